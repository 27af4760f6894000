"""The ``raw`` merge method: RAW brackets (DNG, CR2, CR3, NEF, ARW, RAF, ...) on ``derender merge``.

The estimator is :func:`derender.raw.optimal.raw_merge` (censored Poisson-Gaussian maximum
likelihood on the mosaic, gain and read noise from the bracket, demosaiced once, with a
per-pixel variance); ``estimator="paper1"`` keeps paper 1's eq. 11 (binary weights,
:func:`derender.raw.groundtruth.raw_ground_truth`, no variance). :func:`merge_raw` is the
method's merge function (frames in memory), :func:`merge_raw_files` the path ``derender merge``
takes for RAW files (:func:`derender.hdr.files.merge_files` hands them over).

The RAW method runs outside the engine for now: the engine's plans look up 8-bit codes.
Motion (:func:`raw_motion`, a :class:`~derender.engine.motion.run.MotionOptions` given as
``motion=``) is done on the mosaic, in :mod:`derender.hdr.raw_align_deghost` (alignment and ghost
removal; the method's resampled merge is :func:`derender.raw.register.raw_merge_shifted`). ``--spot``,
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
from derender.hdr.raw_align_deghost import raw_motion

__all__ = [
    "ESTIMATORS",
    "RawOptions",
    "merge_raw",
    "raw_motion",
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
        ``malvar2004`` (``malvar``; the default: a linear filter, its variance exact, about
        1 s at 24 MP), ``menon2007`` (``menon``; 0.2-0.6 points closer to the scene in median
        on simulated brackets, its variance exact given its chosen directions plus a
        direction-flip term; about 4x Malvar's time with the variance), ``ahd`` (Hirakawa &
        Parks 2005, dcraw's and LibRaw's; closer still, its variance exact given its chosen
        directions plus a direction-flip term, about 13x Malvar's time; :mod:`derender.raw.ahd`)
        or ``bilinear``
        (:data:`derender.raw.mosaic.DEMOSAIC_METHODS`; docs/results-raw.md).
    variance : bool
        Also give the per-pixel variance (``estimator="optimal"``).
    variance_terms : {"total", "noise"}
        What the variance holds (:data:`derender.raw.interpolation.VARIANCE_TERMS`):
        ``"total"`` (the default; the noise plus the demosaic's interpolation error estimated
        from the mosaic, :mod:`derender.raw.interpolation`: the sigma that holds against the
        scene) or ``"noise"`` (the merge's noise only, exact against the demosaiced true
        mosaic). A bracket resampled at sub-photosite shifts (``--align``) gives the noise only.
    """

    estimator: str = "optimal"
    output_space: str = "linear_srgb"
    gain: float | None = None
    read_noise: float | None = None
    demosaic: str = "malvar2004"
    variance: bool = False
    variance_terms: str = "total"

    def __post_init__(self) -> None:
        """Every value checked when the record is made, before any file is read."""
        from derender.raw.interpolation import VARIANCE_TERMS
        from derender.raw.mosaic import demosaic_name
        from derender.raw.optimal import OUTPUT_SPACES

        if self.estimator not in ESTIMATORS:
            raise InputError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {self.estimator!r}")
        if self.output_space not in OUTPUT_SPACES:
            raise InputError(f"output_space must be one of {', '.join(OUTPUT_SPACES)}, got {self.output_space!r}")
        if self.variance_terms not in VARIANCE_TERMS:
            raise InputError(f"variance_terms must be one of {', '.join(VARIANCE_TERMS)}, got {self.variance_terms!r}")
        if self.estimator == "paper1" and self.variance:
            raise InputError("estimator paper1 (eq. 11) gives no variance; drop --variance or use estimator optimal")
        if self.estimator == "paper1" and (self.gain is not None or self.read_noise is not None):
            raise InputError("estimator paper1 (eq. 11) has no noise model: drop gain and read_noise")
        if self.estimator == "optimal" and (self.gain is None) != (self.read_noise is None):
            raise InputError("give both gain and read_noise, or neither (then they are estimated from the frames)")
        object.__setattr__(self, "demosaic", demosaic_name(self.demosaic))


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
        Reference frame, alignment and ghost removal on the mosaic (:func:`raw_motion`);
        estimator ``optimal`` only.

    Returns
    -------
    HDRResult
        Radiance (and its variance) in ``options.output_space``.
    """
    from derender.hdr.registry import method_options
    from derender.raw.optimal import raw_merge

    o = method_options("raw", options)
    if isinstance(frames, RawFrame):
        frames = [frames]
    if not isinstance(frames, (list, tuple)) or not all(isinstance(f, RawFrame) for f in frames):
        raise InputError("the raw method merges RAW frames (derender.read_raw), not rendered images")
    check_one_camera(frames)
    motion_info = None
    valid = None
    original = list(frames)
    if motion is not None and motion.needs_motion_run():
        if o.estimator != "optimal":
            raise InputError("motion (--reference, --align, --deghost) works with estimator optimal on RAW frames")
        frames, valid, motion_info = raw_motion(frames, motion, gain=o.gain, read_noise=o.read_noise)
    if o.estimator == "optimal":
        extra = {}
        if motion_info is not None and motion_info.get("noise") is not None:
            extra = {"noise": motion_info["noise"], "variance_factor": motion_info["variance_factor"]}
        if motion_info is not None and motion_info["resampled"]:
            # sub-photosite or odd shifts: every frame's colours at the reference's photosites,
            # merged per colour, from the frames as read
            from derender.raw.register import raw_merge_shifted

            frames, valid = original, motion_info["kept"]
            res = raw_merge_shifted(frames, motion_info["shifts"], motion_info["noise"], valid=valid,
                                    output_space=o.output_space, variance=o.variance,
                                    untested=motion_info["untested"], reference=motion_info["reference"],
                                    threshold=float(motion.ghost_threshold or _ghost_threshold()))
        else:
            res = raw_merge(frames, output_space=o.output_space, gain=o.gain, read_noise=o.read_noise,
                            demosaic=o.demosaic, variance=o.variance, valid=valid,
                            variance_terms=o.variance_terms, **extra)
        if motion_info is not None:
            res.info["raw_motion"] = {k: v for k, v in motion_info.items() if k not in ("noise", "kept", "untested")}
            res.info["raw_motion"]["variance_factor"] = np.asarray(motion_info["variance_factor"]).tolist()
            res.info.update(_summary_fields(motion_info, motion, frames))
            res.ghosts = np.sum([~v for v in valid], axis=0, dtype=np.uint8)   # frames left out per photosite
    else:
        res = _paper1(frames, o.output_space, o.demosaic)
    res.info.update({"method": "raw", "estimator": o.estimator})
    return res


def _ghost_threshold() -> float:
    from derender.engine.motion.deghost import GHOST_THRESHOLD

    return float(GHOST_THRESHOLD)


def _summary_fields(motion_info: dict, motion: MotionOptions, frames: Sequence[RawFrame]) -> dict:
    """What :func:`raw_motion` did, in the keys the merge summary reads
    (:func:`derender.hdr.summary.merge_summary_record`, as the engine's motion run writes them):
    the reference as given, the shifts in exposure order, the fraction ghost removal left out."""
    from derender.engine.motion.deghost import GHOST_THRESHOLD
    from derender.raw.mosaic import setting_factors

    times = np.array([(f.exposure_time or 1.0) for f in frames]) * setting_factors(frames)
    order = np.argsort(times, kind="stable")
    out = {"reference_input": int(motion_info["reference"])}
    if motion_info["align"] != "none":
        out["alignment"] = {"align": motion_info["align"], "shifts": [motion_info["shifts"][i] for i in order]}
    if motion_info["deghost"]:
        others = [r for j, r in enumerate(motion_info["rejected"]) if j != motion_info["reference"]]
        out["deghost"] = {"threshold": float(motion.ghost_threshold or GHOST_THRESHOLD),
                          "rejected": float(np.mean(others)) if others else 0.0}
    return out


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
    from derender.io.raw import read_raw_bracket
    from derender.raw.mosaic import setting_factors

    out = output or OutputOptions()
    threads = (engine or EngineOptions()).threads
    t0 = time.perf_counter()
    frames = read_raw_bracket(paths, times=times, threads=threads)
    if len(frames) > 1:            # t S / N^2 relative to the first frame given (motion's reference: as given)
        for f, k in zip(frames, setting_factors(frames)):
            f.extra = {**(f.extra or {}), "exposure_factor": float(k)}
    if len(frames) == 1 and frames[0].exposure_time is None:
        frames[0].exposure_time = 1.0
        single_note = "no exposure time in the file: radiance per unit exposure (relative units)"
    else:
        single_note = None
    t_read = time.perf_counter() - t0
    res = merge_raw(frames, options, motion=motion)
    frames = sorted(frames, key=lambda f: (f.exposure_time or 1.0) * (f.extra or {}).get("exposure_factor", 1.0))
    res.info["n_clipped"] = int(np.count_nonzero(res.mask == HDRResult.MASK_BRIGHT))
    res.info.update({"engine": "raw", "engine_path": "raw", "read_seconds": t_read,
                     "frames": [Path(f.path).name for f in frames]})
    if single_note:
        res.info["note"] = single_note
    write_outputs(res, out.output, out.variance_output, half=out.half, compression=out.compression,
                  inputs=list(inputs) or list(paths), threads=threads, name="raw")
    return res
