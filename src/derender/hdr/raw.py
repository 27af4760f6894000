"""The ``raw`` merge method: RAW brackets (DNG, CR2, CR3, NEF, ARW, RAF, ...) on ``derender merge``.

The estimator is :func:`derender.raw.optimal.raw_merge` (censored Poisson-Gaussian maximum
likelihood on the mosaic, gain and read noise from the bracket, demosaiced once, with a
per-pixel variance); ``estimator="paper1"`` keeps paper 1's eq. 11 (binary weights,
:func:`derender.raw.groundtruth.raw_ground_truth`, no variance). :func:`merge_raw` is the
method's merge function (frames in memory), :func:`merge_raw_files` the path ``derender merge``
takes for RAW files (:func:`derender.hdr.files.merge_files` hands them over).

The RAW method runs outside the engine for now: the engine's plans look up 8-bit codes.
``--reference``, ``--align`` and ``--deghost`` are refused with one error line (in one place,
``_refuse_motion``); ``--spot``,
``--vignetting``, ``--profile`` (its photometric factor and vignetting), ``--view``/``.hdr``
output, ``--preview``, ``--mask`` and ``--report`` act on the merged map as for any method.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult, RawFrame
from derender.engine.motion.run import MotionOptions
from derender.engine.options import EngineOptions, OutputOptions

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
    """Options of the ``raw`` merge method (:func:`merge_raw`).

    Attributes
    ----------
    estimator : {"optimal", "paper1"}
        ``"optimal"`` (:func:`derender.raw.optimal.raw_merge`; ``gain`` in DN per electron and
        ``read_noise`` in DN override the estimates from the frames) or ``"paper1"`` (paper 1's
        eq. 11, binary weights, no variance).
    output_space : {"linear_srgb", "camera_rgb", "xyz"}
        Through the files' own colour matrix and as-shot white balance.
    gain, read_noise : float or None
        The sensor's noise (None: estimated from the frames).
    demosaic : str
        The demosaicking algorithm.
    variance : bool
        Also give the per-pixel variance (``estimator="optimal"``).
    """

    estimator: str = "optimal"
    output_space: str = "linear_srgb"
    gain: float | None = None
    read_noise: float | None = None
    demosaic: str = "malvar2004"
    variance: bool = False

    def __post_init__(self) -> None:
        """Every value checked when the record is made, before any file is read."""
        from derender.raw.optimal import OUTPUT_SPACES

        if self.estimator not in ESTIMATORS:
            raise InputError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {self.estimator!r}")
        if self.output_space not in OUTPUT_SPACES:
            raise InputError(f"output_space must be one of {', '.join(OUTPUT_SPACES)}, got {self.output_space!r}")
        if self.estimator == "paper1" and self.variance:
            raise InputError("estimator paper1 (eq. 11) gives no variance; drop --variance or use estimator optimal")
        if self.estimator == "paper1" and (self.gain is not None or self.read_noise is not None):
            raise InputError("estimator paper1 (eq. 11) has no noise model: drop gain and read_noise")
        if self.estimator == "optimal" and (self.gain is None) != (self.read_noise is None):
            raise InputError("give both gain and read_noise, or neither (then they are estimated from the frames)")


def _refuse_motion(motion: MotionOptions | None) -> None:
    """The RAW method runs outside the engine for now (the engine's plans look up 8-bit codes):
    a reference frame, an alignment or ghost removal is one error line. The one place that
    refuses them (:func:`merge_raw`, :func:`merge_raw_files`)."""
    if motion is None:
        return
    asked = [name for name, on in (("reference", motion.reference is not None),
                                    ("align", motion.align not in (None, "none")), ("deghost", motion.deghost)) if on]
    if asked:
        raise InputError(f"{asked[0]} is not available on RAW brackets yet (the RAW merge runs outside the engine); "
                         "merge without it")


def merge_raw(frames: RawFrame | Sequence[RawFrame], options: RawOptions | Mapping[str, Any] | None = None, *,
              motion: MotionOptions | None = None) -> HDRResult:
    """Noise-optimal merge of RAW frames on the mosaic (censored Poisson-Gaussian ML), demosaiced once, with its variance.

    Parameters
    ----------
    frames : RawFrame or sequence of RawFrame
        The bracket (:func:`derender.io.raw.read_raw_stack`).
    options : RawOptions or mapping, optional
        The method's options (:class:`RawOptions`), or a mapping of them.
    motion : MotionOptions, optional
        Refused for now (the RAW merge runs outside the engine), unless it asks for nothing.

    Returns
    -------
    HDRResult
        Radiance (and its variance) in ``options.output_space``.
    """
    from derender.hdr.registry import method_options
    from derender.raw.optimal import raw_merge

    o = method_options("raw", options)
    _refuse_motion(motion)
    if isinstance(frames, RawFrame):
        frames = [frames]
    if not isinstance(frames, (list, tuple)) or not all(isinstance(f, RawFrame) for f in frames):
        raise InputError("the raw method merges RAW frames (derender.read_raw), not rendered images")
    check_one_camera(frames)
    if o.estimator == "optimal":
        res = raw_merge(frames, output_space=o.output_space, gain=o.gain, read_noise=o.read_noise, demosaic=o.demosaic,
                        variance=o.variance)
    else:
        res = _paper1(frames, o.output_space, o.demosaic)
    res.info.update({"method": "raw", "estimator": o.estimator})
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


def merge_raw_files(paths: Sequence[str | os.PathLike], times: Sequence[float] | None, options: RawOptions,
                    motion: MotionOptions | None = None, output: OutputOptions | None = None,
                    engine: EngineOptions | None = None, *, inputs: Sequence[str | os.PathLike] = ()) -> HDRResult:
    """Read RAW files (LibRaw; black and white level per frame, exposure times from the files
    unless ``times`` are given) and merge them with :func:`merge_raw`; optionally write the
    radiance and its variance to the OpenEXR files of ``output``. A bracket of several frames
    needs every exposure time (the error names the files without one); a single frame without
    one is merged per unit exposure (relative units). The records are
    :func:`derender.hdr.files.merge_files`'s; ``engine``: its ``threads`` (EXR writing)."""
    from derender.engine.outputs import write_outputs
    from derender.io.raw import read_raw_stack

    _refuse_motion(motion)
    out = output or OutputOptions()
    threads = (engine or EngineOptions()).threads
    t0 = time.perf_counter()
    frames = read_raw_stack(paths, times=times)
    if len(frames) == 1 and frames[0].exposure_time is None:
        frames[0].exposure_time = 1.0
        single_note = "no exposure time in the file: radiance per unit exposure (relative units)"
    else:
        single_note = None
    t_read = time.perf_counter() - t0
    res = merge_raw(frames, options)
    res.info["n_clipped"] = int(np.count_nonzero(res.mask == HDRResult.MASK_BRIGHT))
    res.info.update({"engine": "raw", "engine_path": "raw", "read_seconds": t_read,
                     "frames": [Path(f.path).name for f in frames]})
    if single_note:
        res.info["note"] = single_note
    write_outputs(res, out.output, out.variance_output, half=out.half, compression=out.compression,
                  inputs=list(inputs) or list(paths), threads=threads, name="raw")
    return res
