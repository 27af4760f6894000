"""The ``raw`` merge method: RAW brackets (DNG, CR2, CR3, NEF, ARW, RAF, ...) on ``derender merge``.

The estimator is :func:`derender.raw.optimal.raw_merge` (censored Poisson-Gaussian maximum
likelihood on the mosaic, gain and read noise from the bracket, demosaiced once, with a
per-pixel variance); ``estimator="paper1"`` keeps paper 1's eq. 11 (binary weights,
:func:`derender.raw.groundtruth.raw_ground_truth`, no variance). :func:`merge_raw` is the
method's merge function (frames in memory), :func:`merge_raw_files` the path ``derender merge``
takes for RAW files (:func:`derender.hdr.files.merge_files` hands them over).

The RAW method runs outside the engine for now: the engine's plans look up 8-bit codes.
``--reference``, ``--align`` and ``--deghost`` are refused with one error line; ``--spot``,
``--vignetting``, ``--profile`` (its photometric factor and vignetting), ``--view``/``.hdr``
output, ``--preview``, ``--mask`` and ``--report`` act on the merged map as for any method.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult, RawFrame

__all__ = [
    "ESTIMATORS",
    "RawOptions",
    "merge_raw",
    "check_one_camera",
    "merge_raw_files",
]

#: The RAW method's estimators: the noise-optimal merge and paper 1's eq. 11.
ESTIMATORS = ("optimal", "paper1")


@dataclass(frozen=True, kw_only=True)
class RawOptions:
    """Options of the ``raw`` merge method (the keywords of :func:`merge_raw`)."""

    estimator: str = "optimal"
    output_space: str = "linear_srgb"
    gain: float | None = None
    read_noise: float | None = None
    demosaic: str = "malvar2004"
    variance: bool = False


def merge_raw(frames: RawFrame | Sequence[RawFrame], *, estimator: str = "optimal", output_space: str = "linear_srgb",
              gain: float | None = None, read_noise: float | None = None, demosaic: str = "malvar2004",
              variance: bool = False) -> HDRResult:
    """Noise-optimal merge of RAW frames on the mosaic (censored Poisson-Gaussian ML), demosaiced once, with its variance.

    ``estimator``: ``"optimal"`` (:func:`derender.raw.optimal.raw_merge`; ``gain`` in DN per
    electron and ``read_noise`` in DN override the estimates from the frames) or ``"paper1"``
    (paper 1's eq. 11, binary weights, no variance). ``output_space``: ``linear_srgb``,
    ``camera_rgb`` or ``xyz``, through the files' own colour matrix and as-shot white balance.
    """
    from derender.raw.optimal import OUTPUT_SPACES, raw_merge

    if estimator not in ESTIMATORS:
        raise InputError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {estimator!r}")
    if output_space not in OUTPUT_SPACES:
        raise InputError(f"output_space must be one of {', '.join(OUTPUT_SPACES)}, got {output_space!r}")
    if isinstance(frames, RawFrame):
        frames = [frames]
    if not isinstance(frames, (list, tuple)) or not all(isinstance(f, RawFrame) for f in frames):
        raise InputError("the raw method merges RAW frames (derender.read_raw), not rendered images")
    check_one_camera(frames)
    if estimator == "optimal":
        res = raw_merge(frames, output_space=output_space, gain=gain, read_noise=read_noise, demosaic=demosaic,
                        variance=variance)
    else:
        if variance:
            raise InputError("estimator paper1 (eq. 11) gives no variance; drop --variance or use estimator optimal")
        if gain is not None or read_noise is not None:
            raise InputError("estimator paper1 (eq. 11) has no noise model: drop gain and read_noise")
        res = _paper1(frames, output_space, demosaic)
    res.info.update({"method": "raw", "estimator": estimator})
    return res


def _paper1(frames: Sequence[RawFrame], output_space: str, demosaic: str) -> HDRResult:
    from derender.core.colorimetry import LINEAR_SRGB_TO_XYZ
    from derender.raw.groundtruth import raw_ground_truth, raw_to_camera_rgb

    if output_space == "camera_rgb":
        return raw_to_camera_rgb(frames, demosaic=demosaic)
    res = raw_ground_truth(frames, demosaic=demosaic)
    if output_space == "xyz":
        h, w, _ = res.radiance.shape
        xyz = res.radiance.reshape(-1, 3).astype(np.float64) @ LINEAR_SRGB_TO_XYZ.T
        res.radiance = np.ascontiguousarray(np.maximum(xyz, 0.0).reshape(h, w, 3), dtype=np.float32)
        res.info["colour_space"] = "xyz"
    return res


def check_one_camera(frames: Sequence[RawFrame]) -> None:
    """One camera, one sensor layout: make and model, size and CFA pattern alike (else one error)."""
    def name(f: RawFrame) -> str:
        return Path(f.path).name if f.path else "a frame"

    first = frames[0]
    for f in frames[1:]:
        if (f.make, f.model) != (first.make, first.model) and (f.make or f.model) and (first.make or first.model):
            raise InputError(f"the bracket mixes cameras: {name(first)} is {first.make} {first.model}, "
                             f"{name(f)} is {f.make} {f.model}".replace("  ", " "))
        if np.asarray(f.mosaic).shape != np.asarray(first.mosaic).shape:
            raise InputError(f"the bracket mixes sensor sizes: {name(first)} is {np.asarray(first.mosaic).shape}, "
                             f"{name(f)} is {np.asarray(f.mosaic).shape}")
        if f.cfa_pattern.upper() != first.cfa_pattern.upper():
            raise InputError(f"the bracket mixes CFA patterns: {name(first)} {first.cfa_pattern}, "
                             f"{name(f)} {f.cfa_pattern}")


def merge_raw_files(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None, *,
                    output: str | os.PathLike | None = None, variance_output: str | os.PathLike | None = None,
                    half: bool = False, compression: str = "zip", inputs: Sequence[str | os.PathLike] = (),
                    threads: int | None = None, **options: Any) -> HDRResult:
    """Read RAW files (LibRaw; black and white level per frame, exposure times from the files
    unless ``times`` are given) and merge them with :func:`merge_raw`; optionally write the
    radiance and its variance (OpenEXR). A bracket of several frames needs every exposure time
    (the error names the files without one); a single frame without one is merged per unit
    exposure (relative units)."""
    from derender.engine.run import write_outputs
    from derender.io.raw import read_raw_bracket
    from derender.raw.mosaic import setting_factors

    t0 = time.perf_counter()
    frames = read_raw_bracket(paths, times=times, threads=threads)
    if len(frames) > 1:            # t S / N^2 relative to the first frame given, then sorted by it
        for f, k in zip(frames, setting_factors(frames)):
            f.extra = {**(f.extra or {}), "exposure_factor": float(k)}
        frames.sort(key=lambda f: f.exposure_time * f.extra["exposure_factor"])
    if len(frames) == 1 and frames[0].exposure_time is None:
        frames[0].exposure_time = 1.0
        single_note = "no exposure time in the file: radiance per unit exposure (relative units)"
    else:
        single_note = None
    t_read = time.perf_counter() - t0
    res = merge_raw(frames, **options)
    res.info["n_clipped"] = int(np.count_nonzero(res.mask == HDRResult.MASK_BRIGHT))
    res.info.update({"engine": "raw", "engine_path": "raw", "read_seconds": t_read,
                     "frames": [Path(f.path).name for f in frames]})
    if single_note:
        res.info["note"] = single_note
    write_outputs(res, output, variance_output, half=half,
                  compression=compression, inputs=list(inputs) or list(paths), threads=threads, name="raw")
    return res
