"""Exposure times and camera metadata: EXIF tags, ``--times`` strings and times files.

Exposure times are seconds (floats). ``parse_times`` accepts ``1/30,1/8,0.5`` style lists;
``read_times_file`` reads ``name time`` lines (``inverse=True`` for lists of ``1/t`` such
as Debevec's Memorial ``hdr_image_list.txt``); ``file_times`` picks the source for a list
of files (explicit times, else a times file, else EXIF ``ExposureTime``).
"""

from __future__ import annotations

import os
import re
from fractions import Fraction
from pathlib import Path
from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import validate_times
from derender.io.files import RAW_SUFFIXES, check_input_file, resolve_path

__all__ = [
    "read_exif",
    "read_exposure_time",
    "parse_times",
    "read_times_file",
    "file_times",
    "exposure_factors",
]


def _ratio_to_float(value) -> float | None:
    try:
        if hasattr(value, "num") and hasattr(value, "den"):
            return float(value.num) / float(value.den) if value.den else None
        if hasattr(value, "numerator") and hasattr(value, "denominator"):
            return float(value.numerator) / float(value.denominator) if value.denominator else None
        return float(Fraction(str(value)))
    except (ValueError, ZeroDivisionError, TypeError):
        return None


def read_exif(path: str | os.PathLike) -> dict:
    """EXIF fields we use: ``ExposureTime`` (s), ``Make``, ``Model``, ``Lens``, ``ISO``, ``FNumber``,
    and what the ISO speed means: ``SensitivityType`` (EXIF 2.3, an int) and the ``SOS``
    (``StandardOutputSensitivity``), ``REI`` (``RecommendedExposureIndex``) and ``ISOSpeed`` tags.

    Missing fields are absent from the dict; unreadable EXIF gives an empty dict. An
    ``ExposureTime`` that is present but not a positive number is reported as
    ``ExposureTimeInvalid`` (its text), not as a time.
    """
    info: dict = {}
    try:
        import logging

        import exifread

        logging.getLogger("exifread").setLevel(logging.ERROR)   # "PNG file does not have exif data." etc.

        with open(path, "rb") as fh:
            tags = exifread.process_file(fh, details=False)
        mapping = {
            "EXIF ExposureTime": "ExposureTime",
            "Image ExposureTime": "ExposureTime",
            "EXIF FNumber": "FNumber",
            "Image FNumber": "FNumber",             # TIFF/EP and DNG files may keep them in IFD0
            "EXIF ISOSpeedRatings": "ISO",
            "Image ISOSpeedRatings": "ISO",
            "Image Make": "Make",
            "Image Model": "Model",
            "EXIF LensModel": "Lens",
            "EXIF SensitivityType": "SensitivityType",
            "EXIF StandardOutputSensitivity": "SOS",
            "EXIF RecommendedExposureIndex": "REI",
            "EXIF ISOSpeed": "ISOSpeed",
        }
        for key, name in mapping.items():
            if key in tags and name not in info:
                val = tags[key]
                if name in ("Make", "Model", "Lens"):
                    info[name] = str(val.printable).strip().strip("\x00")
                elif name == "SensitivityType":
                    v = _ratio_to_float(val.values[0] if getattr(val, "values", None) else val)
                    if v is not None and v == int(v) and 0 <= v <= 7:
                        info[name] = int(v)
                else:
                    v = _ratio_to_float(val.values[0] if getattr(val, "values", None) else val)
                    if v is not None and np.isfinite(v) and v > 0:
                        info[name] = v
                    elif name == "ExposureTime":
                        info["ExposureTimeInvalid"] = (f"{v:g}" if v is not None
                                                       else str(getattr(val, "printable", val)).strip("(), "))
    except Exception:  # noqa: BLE001 - any EXIF parser failure means "no EXIF"
        pass
    if "ExposureTime" not in info:
        try:
            from derender.io.headers import pillow_image

            with pillow_image().open(path) as im:
                exif = im.getexif()
                sub = exif.get_ifd(0x8769) if exif else {}
                for src in (sub, exif):
                    if src and 0x829A in src:
                        v = _ratio_to_float(src[0x829A])
                        if v is not None and np.isfinite(v) and v > 0:
                            info["ExposureTime"] = v
                            break
                for tag, name in ((0x829D, "FNumber"), (0x8827, "ISO"), (0x8831, "SOS"), (0x8832, "REI"),
                                  (0x8833, "ISOSpeed")):
                    if name not in info and sub and tag in sub:
                        raw = sub[tag][0] if isinstance(sub[tag], tuple) else sub[tag]
                        v = _ratio_to_float(raw)
                        if v is not None and np.isfinite(v) and v > 0:
                            info[name] = v
                if sub and 0x8830 in sub and "SensitivityType" not in info:
                    kind = sub[0x8830][0] if isinstance(sub[0x8830], tuple) else sub[0x8830]
                    if isinstance(kind, int) and 0 <= kind <= 7:
                        info["SensitivityType"] = kind
                if exif:
                    info.setdefault("Make", str(exif.get(0x010F, "")).strip("\x00 ") or None)
                    info.setdefault("Model", str(exif.get(0x0110, "")).strip("\x00 ") or None)
                    if sub and 0xA434 in sub:
                        info.setdefault("Lens", str(sub[0xA434]).strip("\x00 ") or None)
        except Exception:  # noqa: BLE001
            pass
    return {k: v for k, v in info.items() if v is not None}


def read_exposure_time(path: str | os.PathLike) -> float | None:
    """EXIF ``ExposureTime`` of a file in seconds, or None."""
    return read_exif(path).get("ExposureTime")


_NUMBER = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)(?:\s*/\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?))?\s*$")


def _parse_number(text: str, what: str) -> float:
    m = _NUMBER.match(text)
    if not m:
        raise InputError(f"cannot read {what} {text!r}: use numbers like 0.01 or 1/60")
    num = float(m.group(1))
    if m.group(2) is not None:
        den = float(m.group(2))
        if den == 0:
            raise InputError(f"cannot read {what} {text!r}: division by zero")
        num /= den
    return num


def parse_times(text: str) -> list[float]:
    """Parse ``"0.01,0.1,1/30"`` into seconds."""
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    if not parts:
        raise InputError("--times is empty")
    return [_parse_number(p, "exposure time") for p in parts]


def read_times_file(path: str | os.PathLike, inverse: bool = False) -> dict[str, float]:
    """Read ``FILENAME SECONDS`` lines (``#`` comments allowed) into ``{name: seconds}``.

    With ``inverse=True`` the second column is 1/time, as in HDRShop/Debevec image
    lists such as ``memorial.hdr_image_list.txt``.
    """
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise InputError(f"no such times file: {path}")
    check_input_file(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        raise InputError(f"times file is not text: {path}") from None
    out: dict[str, float] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) < 2:
            raise InputError(f"{path}:{lineno}: expected 'FILENAME SECONDS', got {line!r}")
        value = _parse_number(fields[1], f"time on line {lineno} of {path.name}")
        if value <= 0:
            raise InputError(f"{path}:{lineno}: exposure value must be positive")
        name = Path(fields[0]).name
        if name in out:
            raise InputError(f"{path}:{lineno}: {name} listed twice")
        out[name] = 1.0 / value if inverse else value
    if not out:
        raise InputError(f"times file lists no images: {path}")
    return out


def file_times(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
               times_file: str | os.PathLike | None = None, times_file_inverse: bool = False) -> np.ndarray:
    """Exposure times of image files without decoding them, in the order of ``paths``.

    From ``times`` (one per path), else ``times_file`` (matched by file name), else each
    file's EXIF ``ExposureTime``; checks the paths exist, are distinct and not RAW files.
    """
    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise InputError("an exposure stack needs at least two images")
    for p in paths:
        check_input_file(p)
    seen: set[Path] = set()
    for p in paths:
        r = resolve_path(p)
        if r in seen:
            raise InputError(f"the same file is given twice: {p}")
        seen.add(r)
    for p in paths:
        if p.suffix.lower() in RAW_SUFFIXES:
            raise InputError(f"{p} is a RAW file; RAW brackets merge with 'derender merge' (method raw) or "
                             "'derender groundtruth'")
    if times is not None:
        t = [float(x) for x in times]
        if len(t) != len(paths):
            raise InputError(f"{len(t)} exposure time(s) given for {len(paths)} image(s)")
    elif times_file is not None:
        table = read_times_file(times_file, inverse=times_file_inverse)
        missing = [p.name for p in paths if p.name not in table]
        if missing:
            raise InputError(f"times file {times_file} has no entry for: {', '.join(missing)}")
        t = [table[p.name] for p in paths]
    else:
        t, missing, exifs = [], [], []
        for p in paths:
            exif = read_exif(p)
            exifs.append(exif)
            v = exif.get("ExposureTime")
            if v is None and "ExposureTimeInvalid" in exif:
                raise InputError(f"{p.name}: EXIF ExposureTime is {exif['ExposureTimeInvalid']}, not a valid "
                                 "exposure time; give --times or --times-file")
            if v is None:
                missing.append(p.name)
            t.append(v if v is not None else 0.0)
        if missing:
            from derender.io.headers import probe_image

            for p in paths:
                if p.name in missing:
                    _check_readable(probe_image(p, max_megapixels=None))   # the real cause first
            raise InputError(f"no EXIF ExposureTime in {', '.join(missing)}; give --times or --times-file")
        t = [ti * f for ti, f in zip(t, exposure_factors(paths, exifs))]
    source = "--times" if times is not None else f"times file {times_file}" if times_file is not None else "EXIF"
    _check_distinct(paths, t, source)
    return validate_times(t, len(paths))


def _check_readable(info) -> None:
    """A file without EXIF times whose header reads but whose data does not (a damaged HEIC,
    AVIF or TIFF): "not a readable image" is its real cause, not the missing times. Only on
    the way to an error: the merge decodes every frame anyway."""
    if info.format in ("jpeg", "png"):
        return                      # their probe checked the data's end; the decoder names damage inside
    from derender.io.headers import pillow_image

    try:
        with pillow_image().open(info.path) as im:
            im.load()
    except Exception as exc:  # noqa: BLE001 - Pillow, libheif and libavif raise assorted types
        raise InputError(f"not a readable image ({str(exc).strip()[:120] or 'corrupt data'}): {info.path}") from None


def _check_distinct(paths: Sequence[Path], t: Sequence[float], source: str) -> None:
    """Refuse two frames with one exposure time, naming the frames (and, for EXIF times, a
    times file beside them: the sculpture-garden bracket's EXIF gives all five frames 1/20 s,
    its ``times.txt`` the real times)."""
    groups: dict[float, list[str]] = {}
    for p, v in zip(paths, t):
        if np.isfinite(v) and v > 0:
            groups.setdefault(float(v), []).append(Path(p).name)
    dups = {v: names for v, names in groups.items() if len(names) > 1}
    if not dups:
        return
    parts = "; ".join(f"{', '.join(names)} all have {_seconds(v)}" for v, names in sorted(dups.items()))
    if source == "EXIF":
        folders = sorted({Path(p).parent for p in paths})
        files = [f / "times.txt" for f in folders if (f / "times.txt").is_file()]
        hint = ("the EXIF times are wrong (a camera or converter that rewrote them); give the real times with "
                + (f"--times-file {files[0]}" if files else "--times-file FILE ('NAME SECONDS' lines)")
                + " or --times")
    else:
        hint = "every exposure needs its own time"
    raise InputError(f"duplicate exposure times from {source}: {parts}; {hint}")


def _seconds(v: float) -> str:
    return f"1/{1 / v:.4g} s" if v < 1 else f"{v:g} s"


def exposure_factors(paths: Sequence[str | os.PathLike], exifs: Sequence[dict]) -> list[float]:
    """Per frame ``(S_j / S_1) (N_1 / N_j)^2`` from EXIF ISO ``S`` and f-number ``N`` (1 for
    a quantity that does not vary; a quantity that varies must be in every frame's EXIF, else
    an :class:`InputError` names the frames without it)."""
    factors = [1.0] * len(exifs)
    for key, power, what in (("ISO", 1.0, "ISO speed"), ("FNumber", -2.0, "f-number")):
        values = [e.get(key) for e in exifs]
        present = [v for v in values if v is not None]
        if len(set(present)) <= 1:
            continue
        lacking = [Path(p).name for p, v in zip(paths, values) if v is None]
        if lacking:
            raise InputError(f"the frames' {what} varies but {', '.join(lacking)} has none in its EXIF; "
                             "give the exposures with --times (t S / N^2, relative)")
        for j, v in enumerate(values):
            factors[j] *= (v / values[0]) ** power
    return factors
