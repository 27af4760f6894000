"""The gallery of real brackets: every method, plain against ``--deghost``, and the consistency table.

:func:`build_gallery` merges the real brackets of ``../shared/data`` (:data:`GALLERY`) with
every method of :data:`~derender.evaluation.consistency.FLAG_METHODS`, with and without ghost
removal, and writes small JPEG crops of the tone-mapped maps at the trouble spots (the iPhone's
flickering monitor, the sculpture garden's facade, the ping-pong player), side by side, plus the
still brackets' flag-invariance table (:func:`derender.evaluation.consistency.flag_invariance`,
the table ``tests/evaluation/test_consistency.py`` checks) and, on the motion brackets, how
faithfully the ``--deghost`` map shows the reference frame
(:func:`derender.evaluation.consistency.reference_fidelity`), as a Markdown page fragment. The
documentation build runs it (``docs/conf.py``); without the data the page says so.

Both maps of a pair are tone-mapped together (Reinhard 2002 on the two crops side by side, the
``--deghost`` map brought to the plain map's global scale first), so a change of colour or
brightness between them is the merge's, not the tone mapping's.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from derender.evaluation.consistency import (
    FLAG_METHODS,
    STILL_BRACKETS,
    bracket_inputs,
    deghost_pair,
    reference_fidelity,
    shared_data_root,
)

__all__ = ["GALLERY", "THUMB_WIDTH", "build_gallery", "source_key"]

#: Width (pixels) of each crop in the gallery.
THUMB_WIDTH = 240

#: The brackets of the gallery: how to merge them (as :data:`~derender.evaluation.consistency.STILL_BRACKETS`)
#: and the crop ``(top, left, height, width)`` of the (oriented) map shown, None for all of it.
GALLERY: dict[str, dict] = {
    "iphone": {**STILL_BRACKETS["iphone"], "crop": (2300, 300, 800, 800),
               "note": "handheld (--align flow: the skyline and the room shift apart); the monitor flickers (PWM bands in the short frames)"},
    "memorial": {**STILL_BRACKETS["memorial"], "crop": None, "note": "tripod, one film"},
    "frobisher": {**STILL_BRACKETS["frobisher"], "crop": None, "note": "tripod"},
    "pingpong": {"folder": "motion-pingpong", "reference": 2, "align": "translation", "crop": (0, 480, 1080, 960),
                 "note": "handheld, a person swinging a paddle"},
    "sculpture": {"folder": "motion-sculpture-garden", "times_file": "times.txt", "reference": 3, "align": "none",
                  "crop": None, "note": "tripod, pedestrians; the facade"},
}


def _crop(radiance: np.ndarray, crop) -> np.ndarray:
    if crop is None:
        return radiance
    y, x, h, w = crop
    return radiance[y:y + h, x:x + w]


def _pair_thumbnails(plain: np.ndarray, clean: np.ndarray, scale: float, crop) -> tuple[np.ndarray, np.ndarray]:
    """8-bit sRGB crops of the two maps, tone-mapped together, each :data:`THUMB_WIDTH` wide."""
    import cv2

    from derender.io.preview import encode_srgb8, reinhard_photographic

    a = _crop(plain, crop)
    b = _crop(clean, crop) / np.float32(scale)
    both = encode_srgb8(reinhard_photographic(np.hstack([a, b])))
    w = a.shape[1]
    out = []
    for img in (both[:, :w], both[:, w:]):
        h = max(1, int(round(img.shape[0] * THUMB_WIDTH / img.shape[1])))
        out.append(cv2.resize(np.ascontiguousarray(img), (THUMB_WIDTH, h), interpolation=cv2.INTER_AREA))
    return out[0], out[1]


def _write_jpeg(path: Path, rgb8: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85]):
        raise OSError(f"could not write {path}")


def _fmt(x: float) -> str:
    return f"{x:.3f}"


def source_key(methods=FLAG_METHODS) -> str:
    """A digest of derender's source files, the gallery's brackets and ``methods``: a gallery
    built with the same key shows what the code would show now."""
    import hashlib

    h = hashlib.sha256(json.dumps([GALLERY, list(methods)], sort_keys=True, default=str).encode())
    pkg = Path(__file__).resolve().parents[1]
    for f in sorted(pkg.rglob("*.py")):
        h.update(str(f.relative_to(pkg)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def build_gallery(out_dir: str | Path, root: str | Path | None = None, methods=FLAG_METHODS,
                  progress: Callable[[str], None] | None = None) -> tuple[Path, list[dict]]:
    """Merge every gallery bracket with every method, plain and with ``--deghost``; write the crops
    (``gallery/<bracket>-<method>-plain.jpg`` and ``-deghost.jpg``), the rows and the
    :func:`source_key` (``gallery/consistency.json``) and the page fragment ``gallery.md`` into
    ``out_dir``. Returns the fragment's path and the rows (one per bracket and method:
    :class:`~derender.evaluation.consistency.MapChange` fields, ``rejected``, ``still``).
    Brackets whose folder is absent are listed as missing. A gallery already in ``out_dir``
    with the same source key and data folder is kept as it is (the tests build it, the
    documentation build then reads it)."""
    out_dir = Path(out_dir)
    img_dir = out_dir / "gallery"
    img_dir.mkdir(parents=True, exist_ok=True)
    root = shared_data_root() if root is None else Path(root)
    key = source_key(methods)
    frag = out_dir / "gallery.md"
    cache = img_dir / "consistency.json"
    if cache.exists() and frag.exists():
        try:
            old = json.loads(cache.read_text())
        except ValueError:
            old = {}
        if isinstance(old, dict) and old.get("key") == key and old.get("root") == str(root):
            return frag, old["rows"]
    rows: list[dict] = []
    lines: list[str] = []
    for name, spec in GALLERY.items():
        if not (root / spec["folder"]).is_dir():
            lines += [f"## {name}", "", f"*{root / spec['folder']} is absent on the machine that built these pages.*", ""]
            continue
        paths, kw = bracket_inputs(name, root, spec)
        still = name in STILL_BRACKETS
        last = "luminance p99" if still else "fidelity: neutral p95 / curve p95"
        lines += [f"## {name}: {spec['note']}", "", f"| method | plain | `--deghost` | left out | chroma p95 / p99 | {last} |",
                  "| --- | --- | --- | ---: | ---: | ---: |"]
        ref_codes = None
        if not still:
            from derender.io.images import read_codes

            ref_codes = read_codes(paths[kw["motion"].reference])
        for m in methods:
            if progress:
                progress(f"gallery: {name} {m}")
            plain, clean, change, rejected = deghost_pair(paths, m, kw)
            row = {"bracket": name, "method": m, "still": still, "rejected": rejected, **change.row()}
            if not still:
                fid = reference_fidelity(clean.radiance, ref_codes)
                row.update({f"fidelity_{k}": v for k, v in fid.items()})
                cell = f"{_fmt(fid['neutral_p95'])} / {fid['curve_p95']:.1f}"
            else:
                cell = _fmt(change.luminance_p99)
            rows.append(row)
            ta, tb = _pair_thumbnails(plain.radiance, clean.radiance, change.scale, spec["crop"])
            for tag, img in (("plain", ta), ("deghost", tb)):
                _write_jpeg(img_dir / f"{name}-{m}-{tag}.jpg", img)
            lines.append(f"| {m} | ![{name} {m}](gallery/{name}-{m}-plain.jpg) | "
                         f"![{name} {m} deghost](gallery/{name}-{m}-deghost.jpg) | {100 * rejected:.1f} % | "
                         f"{_fmt(change.chroma_p95)} / {_fmt(change.chroma_p99)} | {cell} |")
        lines.append("")
    frag.write_text("\n".join(lines) + "\n")
    cache.write_text(json.dumps({"key": key, "root": str(root), "rows": rows}, indent=2) + "\n")
    return frag, rows
