"""RAW frames: LibRaw (``rawpy``) for camera RAW files, DNG tags read with ``tifffile``.

:func:`read_raw` returns a :class:`~derender.core.types.RawFrame`: the Bayer mosaic
(uint16), CFA pattern, black and white level, as-shot white balance, the DNG
``ColorMatrix`` (XYZ -> camera), the exposure time and, when the DNG has one, its
``NoiseProfile`` (``extra["noise_profile"]``: ``(S, O)`` of ``Var[x] = S x + O``). The
as-shot white balance is the DNG's ``AsShotNeutral``, else LibRaw's camera multipliers; a file
that states neither gets ones and ``extra["as_shot_wb_missing"] = True`` (the RAW merge then
balances its demosaic by a grey-world estimate, :func:`derender.raw.optimal.white_balances`). RAW
*development* (merging, white balance, demosaicing, colour) is :mod:`derender.raw`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import RawFrame, validate_times
from derender.io.exif import read_exposure_time

__all__ = [
    "read_raw",
    "read_raw_stack",
    "read_raw_exposure",
    "read_raw_bracket",
]


# --------------------------------------------------------------------------- RAW
def _dng_tags(path: Path) -> dict:
    """Colour tags of a DNG read directly (LibRaw does not expose ColorMatrix1 for all DNGs)."""
    import tifffile

    tags: dict = {}
    try:
        with tifffile.TiffFile(path) as tif:
            for page in tif.pages:
                for tag in page.tags.values():
                    if tag.name in ("ColorMatrix1", "ColorMatrix2", "AsShotNeutral", "CalibrationIlluminant1",
                                    "CalibrationIlluminant2", "ExposureTime", "Make", "Model", "UniqueCameraModel",
                                    "NoiseProfile", "FNumber", "ISOSpeedRatings", "SensitivityType"):
                        tags.setdefault(tag.name, tag.value)
                exif = page.tags.get("ExifTag")
                if exif is not None and isinstance(exif.value, dict):
                    for name in ("ExposureTime", "FNumber", "ISOSpeedRatings", "SensitivityType"):
                        if name in exif.value:
                            tags.setdefault(name, exif.value[name])
                break
    except Exception:  # noqa: BLE001
        return {}
    return tags


def _rationals(values) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size % 2 == 0 and v.size >= 2:
        num, den = v[0::2], v[1::2]
        if np.all(den != 0):
            return num / den
    return v


def read_raw(path: str | os.PathLike) -> RawFrame:
    """Read a RAW/DNG file with rawpy (LibRaw): mosaic, CFA, levels, WB, colour matrix, time.

    Parameters
    ----------
    path : path-like
        A camera RAW file (DNG, CR2, NEF, ARW, ... whatever LibRaw reads) with a Bayer sensor.

    Returns
    -------
    RawFrame
        The visible mosaic (uint16), its CFA pattern, black and white levels, as-shot white
        balance, XYZ-to-camera matrix, exposure time and camera make and model.

    Raises
    ------
    InputError
        A missing file, one LibRaw cannot read, or a sensor that is not a 2x2 Bayer mosaic.

    Examples
    --------
    A 32x32 DNG (LibRaw reads nothing smaller) written by :func:`derender.camera.dng.write_dng`:

    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> from derender.camera.dng import write_dng
    >>> mosaic = np.full((32, 32), 1000, np.uint16)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = write_dng(os.path.join(folder, "frame.dng"), mosaic, cfa_pattern="RGGB",
    ...                      black_level=64, white_level=4095, xyz_to_camera=np.eye(3),
    ...                      as_shot_neutral=np.array([0.5, 1.0, 0.8]), exposure_time=0.01,
    ...                      make="Sim", model="Cam", bits=12)
    ...     frame = derender.read_raw(path)
    >>> frame.mosaic.shape, frame.cfa_pattern, frame.white_level, frame.exposure_time
    ((32, 32), 'RGGB', 4095.0, 0.01)
    >>> frame.as_shot_wb.round(2).tolist(), (frame.make, frame.model)
    ([2.0, 1.0, 1.25], ('Sim', 'Cam'))
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    lib = _libraw_fields(path)
    tags = _dng_tags(path) if path.suffix.lower() == ".dng" else {}
    wb = _as_shot_wb(tags, lib["wb4"])
    extra = _extra(path, tags)
    if wb is None:
        wb = np.ones(3)
        extra["as_shot_wb_missing"] = True
    return RawFrame(
        mosaic=lib["mosaic"],
        cfa_pattern=lib["cfa"],
        black_level=lib["black"],
        white_level=lib["white"],
        as_shot_wb=wb,
        xyz_to_camera=_xyz_to_camera(tags, lib["xyz_cam"], lib["cmat"]),
        exposure_time=_exposure_time(path, tags, lib["shutter"]),
        path=str(path),
        make=str(tags.get("Make", "")).strip("\x00 "),
        model=str(tags.get("Model", tags.get("UniqueCameraModel", ""))).strip("\x00 "),
        extra=extra,
    )


def _libraw_fields(path: Path) -> dict:
    """What LibRaw reads of a 2x2 Bayer file: mosaic, CFA, black per CFA position, white,
    camera WB, its XYZ->camera and sRGB->camera matrices, shutter (errors: one InputError)."""
    import rawpy

    try:
        with rawpy.imread(str(path)) as raw:
            mosaic = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            desc = raw.color_desc.decode("ascii", "replace")
            pattern = np.asarray(raw.raw_pattern)
            if raw.num_colors != 3 or pattern.shape != (2, 2) or mosaic.ndim != 2:
                raise InputError(f"{path}: only 2x2 Bayer RAW files are supported")
            cfa = "".join(desc[int(c)] for c in pattern.reshape(-1)).replace("g", "G")
            out = {"mosaic": mosaic, "cfa": cfa,
                   "black": np.asarray(raw.black_level_per_channel, dtype=np.float64)[pattern],
                   "white": float(raw.white_level),
                   "wb4": np.asarray(raw.camera_whitebalance, dtype=np.float64),
                   "xyz_cam": np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3, :3],
                   "cmat": np.asarray(raw.color_matrix, dtype=np.float64)[:3, :3],
                   "shutter": float(raw.other.shutter_speed) if hasattr(raw, "other") else 0.0}
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - LibRaw raises many types
        raise InputError(f"cannot read RAW file {path}: {type(exc).__name__}: {exc}".rstrip(": ")) from None
    if set(cfa) != {"R", "G", "B"}:
        raise InputError(f"{path}: unsupported CFA pattern {cfa}")
    return out


def _as_shot_wb(tags: dict, wb4: np.ndarray) -> np.ndarray | None:
    """White balance multipliers as R, G, B with G = 1: the DNG's AsShotNeutral, else LibRaw's
    camera multipliers; None when the file states neither (positive)."""
    if "AsShotNeutral" in tags:
        neutral = _rationals(tags["AsShotNeutral"])[:3]
        if np.all(neutral > 0):
            return neutral[1] / neutral
    g = wb4[1] if wb4[1] > 0 else 1.0
    wb = np.array([wb4[0], g, wb4[2]]) / g
    return wb if np.all(wb > 0) else None


def _xyz_to_camera(tags: dict, xyz_cam: np.ndarray, cmat: np.ndarray) -> np.ndarray | None:
    """XYZ -> camera (DNG ColorMatrix semantics): ColorMatrix1, else LibRaw's, else from its
    sRGB -> camera matrix, else None."""
    if "ColorMatrix1" in tags:
        return _rationals(tags["ColorMatrix1"])[:9].reshape(3, 3)
    if np.any(xyz_cam != 0):
        return xyz_cam
    if np.any(cmat != 0) and abs(np.linalg.det(cmat)) > 1e-9:
        from derender.core.colorimetry import LINEAR_SRGB_TO_XYZ

        return np.linalg.inv(LINEAR_SRGB_TO_XYZ @ cmat)
    return None


def _exposure_time(path: Path, tags: dict, shutter: float) -> float | None:
    """The DNG's ExposureTime, else LibRaw's shutter (1.0 is its 'unknown'), else the EXIF reader's."""
    if "ExposureTime" in tags:
        v = _rationals(tags["ExposureTime"])
        if v.size and v[0] > 0:
            return float(v[0])
    if shutter > 0 and shutter != 1.0:
        return shutter
    return read_exposure_time(path)


def _extra(path: Path, tags: dict) -> dict:
    """``noise_profile`` (the DNG's ``(S, O)`` of ``Var[x] = S x + O``, x in white-level units),
    ``fnumber`` and ``iso`` when the file states them."""
    extra = {}
    if "NoiseProfile" in tags:
        npf = np.asarray(tags["NoiseProfile"], dtype=np.float64).reshape(-1)
        if npf.size >= 2 and np.all(np.isfinite(npf[:2])) and npf[0] > 0 and npf[1] > 0:
            extra["noise_profile"] = (float(npf[0]), float(npf[1]))
    if path.suffix.lower() == ".dng":
        fn = _rationals(tags["FNumber"]) if "FNumber" in tags else np.zeros(0)
        iso = np.asarray(tags.get("ISOSpeedRatings", []), dtype=np.float64).reshape(-1)
        if fn.size and np.isfinite(fn[0]) and fn[0] > 0:
            extra["fnumber"] = float(fn[0])
        if iso.size and iso[0] > 0:
            extra["iso"] = float(iso[0])
    else:
        from derender.io.exif import read_exif

        ex = read_exif(path)
        for key, name in (("FNumber", "fnumber"), ("ISO", "iso")):
            if ex.get(key):
                extra[name] = float(ex[key])
    return extra


def read_raw_exposure(path: str | os.PathLike) -> dict:
    """A RAW file's exposure settings without decoding its mosaic: ``fnumber`` and ``iso`` (as
    :func:`read_raw` puts them in ``extra``) and ``sensitivity_type`` (EXIF ``SensitivityType``:
    what the ISO speed means), each only when the file states it.

    Parameters
    ----------
    path : path-like
        A camera RAW file (DNG: its tags; other formats: their EXIF).

    Returns
    -------
    dict
        Some of ``fnumber`` (float), ``iso`` (float), ``sensitivity_type`` (int).

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from derender.camera.dng import write_dng
    >>> from derender.io.raw import read_raw_exposure
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = write_dng(os.path.join(folder, "f.dng"), np.full((32, 32), 900, np.uint16),
    ...                      cfa_pattern="RGGB", black_level=64, white_level=4095, xyz_to_camera=np.eye(3),
    ...                      as_shot_neutral=np.ones(3), exposure_time=0.01, make="Sim", model="Cam",
    ...                      bits=12, fnumber=8.0, iso=200)
    ...     read_raw_exposure(path)
    {'fnumber': 8.0, 'iso': 200.0}
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    if path.suffix.lower() == ".dng":
        tags = _dng_tags(path)
        out = {k: v for k, v in _extra(path, tags).items() if k in ("fnumber", "iso")}
        kind = np.asarray(tags.get("SensitivityType", []), dtype=np.float64).reshape(-1)
    else:
        from derender.io.exif import read_exif

        out = {k: v for k, v in _extra(path, {}).items() if k in ("fnumber", "iso")}
        kind = np.asarray([read_exif(path).get("SensitivityType") or 0], dtype=np.float64)
    if kind.size and kind[0] > 0:
        out["sensitivity_type"] = int(kind[0])
    return out


def _check_fixed_aperture_and_iso(frames: Sequence[RawFrame]) -> None:
    """A RAW bracket's frames must share f-number and ISO: the RAW merges normalise by exposure
    time only, and one noise model (gain, read noise) serves every frame."""
    for key, what in (("fnumber", "f-number"), ("iso", "ISO")):
        values = {f.extra[key] for f in frames if f.extra.get(key)}
        if len(values) > 1:
            raise InputError(f"the RAW frames vary the {what} ({', '.join(f'{v:g}' for v in sorted(values))}); "
                             "RAW brackets are merged by exposure time with one noise model, so vary the time only")


def read_raw_stack(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None) -> list[RawFrame]:
    """Read RAW frames sorted by exposure time (times from the files unless given); the same
    file given twice (also through a symlink), frames of different cameras (EXIF make and
    model) or sizes, several frames without exposure times (the error names the files) and
    frames that vary the f-number or ISO are refused.

    Parameters
    ----------
    paths : sequence of path-like
        The bracket's RAW files, in any order.
    times : sequence of float, optional
        Exposure times in seconds, one per path in the order given (replacing the files').

    Returns
    -------
    list of RawFrame
        The frames (:func:`read_raw`), shortest exposure first.

    Raises
    ------
    InputError
        No files, a file given twice, frames of different cameras or sizes, missing or
        repeated exposure times, frames that vary the f-number or ISO, or a file
        :func:`read_raw` refuses.

    Examples
    --------
    Two exposures of a ramp, given longest first:

    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> from derender.camera.dng import write_dng
    >>> signal = np.linspace(0.02, 2.0, 32 * 32).reshape(32, 32)   # of white, in 0.04 s
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     paths = [write_dng(os.path.join(folder, f"{t}.dng"),
    ...                        np.round(64 + np.clip(signal * t / 0.04, 0, 1) * 4031).astype(np.uint16),
    ...                        cfa_pattern="RGGB", black_level=64, white_level=4095,
    ...                        xyz_to_camera=np.eye(3), as_shot_neutral=np.ones(3), exposure_time=t,
    ...                        make="Sim", model="Cam", bits=12) for t in (0.04, 0.01)]
    ...     frames = derender.read_raw_stack(paths)
    >>> [frame.exposure_time for frame in frames], frames[0].mosaic.shape
    ([0.01, 0.04], (32, 32))
    """
    frames = read_raw_bracket(paths, times=times)
    if len(frames) > 1:
        _check_fixed_aperture_and_iso(frames)
        validate_times([f.exposure_time for f in frames], len(frames))
        frames.sort(key=lambda f: f.exposure_time)
    return frames


def read_raw_bracket(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
                     threads: int | None = None) -> list[RawFrame]:
    """Read RAW frames in the order given, for :func:`derender.raw.optimal.raw_merge`: as
    :func:`read_raw_stack` (the same file twice, different cameras or sizes and several frames
    without exposure times are refused), but frames may vary the f-number and ISO -- the merge
    normalises each by ``t S / N^2`` relative to the first frame given
    (:func:`derender.raw.mosaic.setting_factors`) -- they are not sorted, and they are decoded in
    threads. ``times`` replace
    the files' exposures whole (``extra["exposure_factor"] = 1``: they are ``t S / N^2``).

    Parameters
    ----------
    paths : sequence of path-like
        The bracket's RAW files.
    times : sequence of float, optional
        Exposures, one per path in the order given.
    threads : int, optional
        Files decoded at once (default: the CPU count).

    Returns
    -------
    list of RawFrame
        The frames (:func:`read_raw`), in the order of ``paths``.

    Raises
    ------
    InputError
        As :func:`read_raw_stack`, except for frames varying the f-number or ISO.
    """
    from derender.io.files import check_input_file, resolve_path

    paths = list(paths)
    seen: set = set()
    for p in paths:
        check_input_file(p)
        r = resolve_path(p)
        if r in seen:
            raise InputError(f"the same file is given twice: {p}")
        seen.add(r)
    if not paths:
        raise InputError("no RAW files given")
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max(1, min(len(paths), threads or os.cpu_count() or 1))) as pool:
        frames = list(pool.map(read_raw, paths))          # LibRaw decodes without the GIL
    if times is not None:
        t = validate_times(times, len(frames))
        for f, v in zip(frames, t):
            f.exposure_time = float(v)
            f.extra = {**(f.extra or {}), "exposure_factor": 1.0}
    named = [f for f in frames if f.make or f.model]
    other = next((f for f in named if (f.make, f.model) != (named[0].make, named[0].model)), None)
    if other is not None:
        first = named[0]
        raise InputError(f"the bracket mixes cameras: {Path(first.path).name} is {first.make} {first.model}, "
                         f"{Path(other.path).name} is {other.make} {other.model}")
    shapes = {f.mosaic.shape for f in frames}
    if len(shapes) > 1:
        raise InputError(f"RAW frames differ in size: {sorted(shapes)}")
    if len(frames) > 1:
        missing = [Path(f.path).name for f in frames if f.exposure_time is None]
        if missing:
            raise InputError(f"no exposure time in {', '.join(missing)}; give --times")
    return frames
