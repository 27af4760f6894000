"""Checks without truth: a still scene gives one answer, whatever the flag, reference or method.

A real photograph has no ground truth, but physics still constrains what a merge of it may
do (``../shared/DESIGN.md``, "Real photographs: checks without truth"). These are
*metamorphic* checks: two merges of the same still bracket that differ only in a flag
(``--deghost``), in the reference frame (a bracket of one rendering) or in the method must
show the same scene.

The comparison is made on blocks, so that noise and half-pixel edges do not count: a block is
the per-channel median of a ``B x B`` tile (:data:`BLOCK`, 16 pixels) of both maps, over the
tiles where both maps are finite and positive. Between two maps ``a`` and ``b``:

* **chroma change** of a block: ``max(|d ln(R/G)|, |d ln(B/G)|)`` with ``d`` the difference
  ``b - a`` (a change of 0.05 is a 5 % shift of a colour ratio; a white balance that differs
  between the two maps shows as a constant, a recolouring of parts of the scene as a tail);
* **luminance change** of a block: ``|ln L_b - ln L_a - k|`` with ``L`` Rec. 709 luminance and
  ``k`` the median of ``ln L_b - ln L_a`` over the blocks (one global scale: a radiance map is
  known up to scale).

:func:`compare_maps` gives their median, p95 and p99 over the blocks (:class:`MapChange`);
the issue's lines read them (``p95 <= 0.03``, ``p99 <= 0.06`` for the chroma change,
``p99 <= 0.06`` for the luminance change, blocks whose luminance is in the darkest 1 % of
either map left out: their colour is the noise of the longest frame).
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from derender.core.colorimetry import luminance

__all__ = ["BLOCK", "DARK_QUANTILE", "MapChange", "block_medians", "compare_maps", "STILL_BRACKETS", "FLAG_METHODS",
           "shared_data_root", "bracket_inputs", "deghost_pair", "flag_invariance", "method_agreement",
           "reference_fidelity", "reference_steps", "STEP_REACH", "STEP_HARD", "FIDELITY_LOW", "FIDELITY_HIGH", "FIDELITY_FLAT", "NEUTRAL_CODES",
           "NEUTRAL_RATIO"]

#: Side of the square tiles (pixels) whose per-channel medians are compared.
BLOCK = 16

#: Blocks darker than this quantile of either map's block luminance are left out of the
#: comparison (their chromaticity is the longest frame's noise, not the scene's colour).
DARK_QUANTILE = 0.01


def block_medians(radiance: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """Per-channel medians of ``block x block`` tiles of an (H, W, 3) map: (H // block, W // block, 3)
    float64 (the last partial rows and columns are left out)."""
    rad = np.asarray(radiance)
    h, w = rad.shape[0] // block, rad.shape[1] // block
    if h == 0 or w == 0:
        raise ValueError(f"a map of {rad.shape[1]}x{rad.shape[0]} has no {block}x{block} block")
    tiles = rad[:h * block, :w * block, :3].reshape(h, block, w, block, 3).swapaxes(1, 2).reshape(h, w, -1, 3)
    return np.median(tiles.astype(np.float64), axis=2)


@dataclass(frozen=True)
class MapChange:
    """How map ``b`` differs from map ``a`` of the same scene, over ``blocks`` blocks (module
    docstring): chroma change median/p95/p99, luminance change median/p95/p99, and ``scale``
    (the global factor ``exp(k)`` of ``b`` against ``a``)."""

    blocks: int
    chroma_median: float
    chroma_p95: float
    chroma_p99: float
    luminance_median: float
    luminance_p95: float
    luminance_p99: float
    scale: float

    def row(self) -> dict[str, float]:
        """JSON-friendly."""
        return asdict(self)


def _change_planes(a: np.ndarray, b: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Per usable block: chroma change, signed luminance log ratio (before the scale), the
    global log scale."""
    ma, mb = block_medians(a, block), block_medians(b, block)
    ok = np.all(np.isfinite(ma) & np.isfinite(mb) & (ma > 0) & (mb > 0), axis=-1)
    la, lb = luminance(ma), luminance(mb)
    if np.count_nonzero(ok) == 0:
        raise ValueError("no block is finite and positive in both maps")
    for lum in (la, lb):
        ok &= lum > np.quantile(lum[ok], DARK_QUANTILE)
    ra, rb = np.log(ma[ok]), np.log(mb[ok])
    d = rb - ra
    chroma = np.maximum(np.abs(d[:, 0] - d[:, 1]), np.abs(d[:, 2] - d[:, 1]))
    dl = np.log(lb[ok]) - np.log(la[ok])
    k = float(np.median(dl))
    return chroma, dl, k


def compare_maps(a: np.ndarray, b: np.ndarray, block: int = BLOCK) -> MapChange:
    """:class:`MapChange` of map ``b`` against map ``a`` (both (H, W, 3), the same scene on the
    same pixel grid)."""
    if np.asarray(a).shape[:2] != np.asarray(b).shape[:2]:
        raise ValueError(f"maps of different sizes: {np.asarray(a).shape[:2]} and {np.asarray(b).shape[:2]}")
    chroma, dl, k = _change_planes(a, b, block)
    lum = np.abs(dl - k)
    q = lambda x, p: float(np.quantile(x, p))   # noqa: E731
    return MapChange(blocks=int(chroma.size), chroma_median=q(chroma, 0.5), chroma_p95=q(chroma, 0.95),
                     chroma_p99=q(chroma, 0.99), luminance_median=q(lum, 0.5), luminance_p95=q(lum, 0.95),
                     luminance_p99=q(lum, 0.99), scale=float(np.exp(k)))


# --- real brackets --------------------------------------------------------------------------

#: The still real brackets of ``../shared/data`` the checks run on: folder, how its times are
#: given, the reference frame (from 1, as the CLI counts) and the alignment. Memorial and
#: Frobisher are on a tripod; the iPhone bracket is handheld (only the monitor's flicker moves).
STILL_BRACKETS: dict[str, dict] = {
    "iphone": {"folder": "iphone6-bracket", "reference": 3, "align": "flow"},
    "memorial": {"folder": "debevec-memorial", "times_file": "memorial.hdr_image_list.txt",
                 "times_file_inverse": True, "reference": 8, "align": "none"},
    "frobisher": {"folder": "colour-hdri-frobisher", "reference": 2, "align": "none"},
}

#: The methods whose maps the flag-invariance check compares.
FLAG_METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint")


def shared_data_root() -> Path:
    """``$DERENDER_SHARED_DATA``, else the ``shared/data`` folder beside the project's checkout
    (where ``../shared/data`` of ``shared/data/README.md`` is), else ``../shared/data``."""
    env = os.environ.get("DERENDER_SHARED_DATA")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for parent in here.parents:
        cand = parent.parent / "shared" / "data"
        if (parent / "pyproject.toml").exists() and cand.is_dir():
            return cand
    return Path.cwd().parent / "shared" / "data"


def bracket_inputs(name: str, root=None, spec: dict | None = None) -> tuple[list, dict]:
    """The image paths and the :func:`derender.hdr.files.merge_files` keywords (times file,
    ``motion``: reference from 0, alignment) of the real bracket ``name`` (``spec``, default
    :data:`STILL_BRACKETS`'s: its folder, times file, reference from 1 and alignment)."""
    from derender.core.errors import InputError
    from derender.engine.motion.run import MotionOptions
    from derender.io.files import expand_image_paths

    spec = STILL_BRACKETS[name] if spec is None else spec
    folder = (shared_data_root() if root is None else Path(root)) / spec["folder"]
    if not folder.is_dir():
        raise InputError(f"real bracket {name!r} not found: {folder} (see shared/data/README.md)")
    paths = expand_image_paths([folder])
    kw: dict = {"motion": MotionOptions(reference=int(spec["reference"]) - 1, align=spec["align"])}
    if "times_file" in spec:
        kw["times_file"] = folder / spec["times_file"]
        kw["times_file_inverse"] = bool(spec.get("times_file_inverse", False))
    return paths, kw


def deghost_pair(paths, method: str, kw: dict):
    """The plain and the ``--deghost`` merge of ``paths`` with ``method`` and the same ``kw``
    (reference, alignment, times), the :class:`MapChange` between them and the fraction of the
    other frames' pixels ghost removal left out."""
    import dataclasses

    from derender.hdr.files import merge_files

    plain = merge_files(paths, method=method, **kw)
    clean = merge_files(paths, method=method, **{**kw, "motion": dataclasses.replace(kw["motion"], deghost=True)})
    change = compare_maps(plain.radiance, clean.radiance)
    rejected = float((clean.info.get("deghost") or {}).get("rejected", 0.0))
    return plain, clean, change, rejected


def flag_invariance(name: str, methods=FLAG_METHODS, root=None, progress=None) -> list[dict]:
    """Per method, :class:`MapChange` of the ``--deghost`` merge of the still real bracket
    ``name`` against the plain merge with the same reference and alignment, with the fraction
    of the other frames' pixels ghost removal left out."""
    paths, kw = bracket_inputs(name, root)
    rows = []
    for m in methods:
        if progress:
            progress(f"{name}: {m}")
        _, _, change, rejected = deghost_pair(paths, m, kw)
        rows.append({"bracket": name, "method": m, "rejected": rejected, **change.row()})
    return rows


def method_agreement(name: str, methods=("debevec", "robertson", "stabilized"), root=None, progress=None) -> list[dict]:
    """Pairs of methods on the still real bracket ``name``: after one scale per channel (the
    median log ratio: each method's map is linear in its own rendering, known up to a
    per-channel factor), the fraction of pixel-channels where the two maps differ by less than
    their combined 95 % interval (``|a - b| < 1.96 sqrt(var_a + var_b)``), and each method's
    median relative standard deviation ``sqrt(var) / value``. Pixels both methods expose
    well (mask 0), positive, finite."""
    from derender.hdr.files import merge_files

    paths, kw = bracket_inputs(name, root)
    res = {}
    for m in methods:
        if progress:
            progress(f"{name}: {m} with its variance")
        res[m] = merge_files(paths, method=m, options={"variance": True}, **kw)
    rows = []
    for i, a in enumerate(methods):
        for b in methods[i + 1:]:
            ra, rb = res[a], res[b]
            ok = (ra.mask == 0) & (rb.mask == 0)
            ok &= np.all((ra.radiance > 0) & (rb.radiance > 0) & np.isfinite(ra.variance) & np.isfinite(rb.variance),
                         axis=-1)
            xa = ra.radiance[ok].astype(np.float64)
            xb = rb.radiance[ok].astype(np.float64)
            va = ra.variance[ok].astype(np.float64)
            vb = rb.variance[ok].astype(np.float64)
            k = np.exp(np.median(np.log(xa) - np.log(xb), axis=0))     # per channel
            xb, vb = xb * k, vb * k * k
            z = np.abs(xa - xb) / np.sqrt(np.maximum(va + vb, 1e-300))
            rows.append({"bracket": name, "pair": f"{a} / {b}", "pixels": int(ok.sum()),
                         "within95": float(np.mean(z < 1.959964)),
                         "rel_sigma_a": float(np.median(np.sqrt(va) / xa)),
                         "rel_sigma_b": float(np.median(np.sqrt(vb) / xb))})
    return rows


#: Reference blocks scored by :func:`reference_fidelity` have every code of their median at
#: least this ...
FIDELITY_LOW = 20

#: ... and at most this ...
FIDELITY_HIGH = 235

#: ... and are smooth: each channel's codes' interdecile range at most this many codes.
FIDELITY_FLAT = 12

#: A reference block is neutral when its median codes are within this many codes of each other.
NEUTRAL_CODES = 3

#: ... and *strictly* neutral (``neutral_strict_p95`` of :func:`reference_fidelity`) when they are also
#: within this log ratio of each other: a 5 % tint in linear light is ``ln(1.05) / 2.2 = 0.022`` in
#: code at a rendering gamma near 2.2. Three codes at codes 20-42 are a 7-15 % code ratio, a 15-33 %
#: tint: on the ping-pong bracket the reference's 16x16 blocks of the player's hair at codes 23-42
#: (B two or three codes above G, the +2 EV frame six to eight codes above G at codes 95-130) pass
#: :data:`NEUTRAL_CODES`, and every frame alone, through Debevec's curve, scores ``neutral_p95``
#: 0.109-0.116 on them (the merge 0.120).
NEUTRAL_RATIO = 0.02


def reference_fidelity(radiance: np.ndarray, reference_codes: np.ndarray, block: int = BLOCK) -> dict:
    """How faithfully a merge shows its reference frame (``--deghost``: the scene at the reference's
    instant), on blocks where the reference is smooth and well exposed (:data:`FIDELITY_LOW` ..
    :data:`FIDELITY_FLAT`):

    * ``neutral_p95``: over the blocks the reference renders neutral (median codes within
      :data:`NEUTRAL_CODES`), the p95 of ``max(|ln(R/G) - m_rg|, |ln(B/G) - m_bg|)`` of the merge,
      ``m`` the medians over those blocks (a method's map is linear in its own rendering, known up
      to a factor per channel): 0.05 is a 5 % tint;
    * ``neutral_strict_p95``: the same over the neutral blocks whose median codes are also within
      :data:`NEUTRAL_RATIO` in log of each other (a reference whose codes say a tint of more than
      about 5 % is not asked to give a neutral merge);
    * ``curve_p95``: after one monotone curve per channel (isotonic regression of the reference's
      block codes on the merge's log block values), the p95 of ``|code - curve|`` (codes).

    Also the block counts (``blocks``, ``neutral_blocks``, ``neutral_strict_blocks``)."""
    from sklearn.isotonic import IsotonicRegression

    rad = block_medians(radiance, block)
    codes = np.asarray(reference_codes)
    h, w = rad.shape[:2]
    tiles = codes[:h * block, :w * block].reshape(h, block, w, block, 3).swapaxes(1, 2).reshape(h, w, -1, 3)
    med = np.median(tiles, axis=2)
    spread = np.quantile(tiles, 0.9, axis=2) - np.quantile(tiles, 0.1, axis=2)
    ok = (np.all((med >= FIDELITY_LOW) & (med <= FIDELITY_HIGH), axis=-1) & np.all(spread <= FIDELITY_FLAT, axis=-1)
          & np.all(rad > 0, axis=-1) & np.all(np.isfinite(rad), axis=-1))
    out = {"blocks": int(ok.sum()), "neutral_blocks": 0, "neutral_p95": float("nan"), "curve_p95": float("nan"),
           "neutral_strict_blocks": 0, "neutral_strict_p95": float("nan")}
    if ok.sum() < 16:
        return out
    lr = np.log(rad[ok])
    resid = []
    for c in range(3):
        iso = IsotonicRegression(increasing=True, out_of_bounds="clip").fit(lr[:, c], med[ok][:, c])
        resid.append(np.abs(med[ok][:, c] - iso.predict(lr[:, c])))
    out["curve_p95"] = float(np.quantile(np.concatenate(resid), 0.95))
    neutral = ok & (np.ptp(med, axis=-1) <= NEUTRAL_CODES)
    strict = neutral & (np.ptp(np.log(np.maximum(med, 1.0)), axis=-1) <= NEUTRAL_RATIO)
    for key, sel in (("neutral", neutral), ("neutral_strict", strict)):
        out[f"{key}_blocks"] = int(sel.sum())
        if sel.sum() >= 8:
            ln = np.log(rad[sel])
            rg, bg = ln[:, 0] - ln[:, 1], ln[:, 2] - ln[:, 1]
            dev = np.maximum(np.abs(rg - np.median(rg)), np.abs(bg - np.median(bg)))
            out[f"{key}_p95"] = float(np.quantile(dev, 0.95))
    return out


#: :func:`reference_steps` compares values this many pixels apart on either side of a pixel ...
STEP_REACH = 3

#: ... and counts a step as hard above this log change (10 %) where the reference is flat.
STEP_HARD = 0.1


def reference_steps(radiance: np.ndarray, reference_codes: np.ndarray, where: np.ndarray | None = None) -> dict:
    """Steps in a ``--deghost`` merge that its reference frame does not show: the hard-edged
    patches and second outlines of a badly masked moving thing (issue 36).

    ``r = ln L - f(Y)``: the merge's log luminance (mean of the channels) less one monotone
    curve ``f`` (isotonic regression) of the reference's mean code ``Y``, on pixels whose ``Y``
    is 12-240 and no channel above 240. ``r`` and ``ln Y`` are smoothed (Gaussian, sigma 2,
    normalised over those pixels); the step at a pixel is the larger of
    ``|r(x + k) - r(x - k)|`` and ``|r(y + k) - r(y - k)|`` (``k`` = :data:`STEP_REACH`), scored
    where the reference's own ``ln Y`` step is at most 0.05 (flat in the reference) and ``where``
    ((H, W) bool, e.g. a box around a moving person; None: everywhere). Returns
    ``pixels`` scored, ``step_p99`` and ``hard`` (the fraction above :data:`STEP_HARD`)."""
    import cv2
    from sklearn.isotonic import IsotonicRegression

    codes = np.asarray(reference_codes)
    lum = np.asarray(radiance, dtype=np.float64).mean(axis=-1)
    y = codes.astype(np.float64).mean(axis=-1)
    ok = (y >= 12) & np.all(codes <= 240, axis=-1) & (lum > 0) & np.isfinite(lum)
    out = {"pixels": 0, "step_p99": float("nan"), "hard": float("nan")}
    if ok.sum() < 1000:
        return out
    ll = np.log(np.where(ok, lum, 1.0))
    sel = np.flatnonzero(ok.ravel())[::17]
    iso = IsotonicRegression(out_of_bounds="clip").fit(y.ravel()[sel], ll.ravel()[sel])
    r = np.where(ok, ll - iso.predict(y.ravel()).reshape(y.shape), 0.0).astype(np.float32)
    wgt = ok.astype(np.float32)
    den = np.maximum(cv2.GaussianBlur(wgt, (0, 0), 2.0), 1e-6)
    rs = cv2.GaussianBlur(r * wgt, (0, 0), 2.0) / den
    ys = cv2.GaussianBlur(np.log(np.maximum(y, 1.0)).astype(np.float32) * wgt, (0, 0), 2.0) / den
    k = STEP_REACH

    def step(a: np.ndarray) -> np.ndarray:
        s = np.zeros_like(a)
        s[:, k:-k] = np.abs(a[:, 2 * k:] - a[:, :-2 * k])
        s[k:-k] = np.maximum(s[k:-k], np.abs(a[2 * k:] - a[:-2 * k]))
        return s

    inner = cv2.erode(ok.astype(np.uint8), np.ones((2 * k + 1, 2 * k + 1), np.uint8)) > 0
    inner[:k] = inner[-k:] = False
    inner[:, :k] = inner[:, -k:] = False
    use = inner & (step(ys) <= 0.05)
    if where is not None:
        use &= np.asarray(where, dtype=bool)
    v = step(rs)[use]
    if v.size < 100:
        return out
    return {"pixels": int(v.size), "step_p99": float(np.quantile(v, 0.99)), "hard": float(np.mean(v > STEP_HARD))}
