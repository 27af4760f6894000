"""The ``raw`` merge method: RAW brackets (DNG, CR2, CR3, NEF, ARW, RAF, ...) on ``derender merge``.

The estimator is :func:`derender.raw.optimal.raw_merge` (censored Poisson-Gaussian maximum
likelihood on the mosaic, gain and read noise from the bracket, demosaiced once, with a
per-pixel variance); ``estimator="paper1"`` keeps paper 1's eq. 11 (binary weights,
:func:`derender.raw.groundtruth.raw_ground_truth`, no variance). :func:`merge_raw` is the
method's merge function (frames in memory), :func:`merge_raw_files` the path ``derender merge``
takes for RAW files (:func:`derender.hdr.files.merge_files` hands them over).

The RAW method runs outside the engine for now: the engine's plans look up 8-bit codes.
Motion (:func:`raw_motion`, a :class:`~derender.engine.motion.run.MotionOptions` given as
``motion=``) is done on the mosaic: alignment by even-photosite shifts (the CFA phase kept)
found by the engine's chained MTB registration (:func:`derender.engine.motion.align.chain_transforms`)
on a grey rendering of each frame (2x2 blocks, gamma 1/2.2), and ghost removal by the Poisson-Gaussian noise model
between each frame and the reference: per photosite ``z = (d_j / e_j - d_r / e_r) /
sqrt(v_j / e_j^2 + v_r / e_r^2)`` (``v`` eq. 1 of :mod:`derender.raw.noise` at the reference's
value), its mean over a 5x5 window against the engine's threshold
(:data:`derender.engine.motion.deghost.GHOST_THRESHOLD`); a censored sample is inconsistent
when the other frame puts the value more than 3 sigma below its saturation level. ``--spot``,
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
    """

    estimator: str = "optimal"
    output_space: str = "linear_srgb"
    gain: float | None = None
    read_noise: float | None = None
    demosaic: str = "malvar2004"
    variance: bool = False

    def __post_init__(self) -> None:
        """Every value checked when the record is made, before any file is read."""
        from derender.raw.mosaic import demosaic_name
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
    if motion is not None and motion.needs_motion_run():
        if o.estimator != "optimal":
            raise InputError("motion (--reference, --align, --deghost) works with estimator optimal on RAW frames")
        frames, valid, motion_info = raw_motion(frames, motion, gain=o.gain, read_noise=o.read_noise)
    if o.estimator == "optimal":
        res = raw_merge(frames, output_space=o.output_space, gain=o.gain, read_noise=o.read_noise, demosaic=o.demosaic,
                        variance=o.variance, valid=valid)
        if motion_info is not None:
            res.info["raw_motion"] = motion_info
            res.info.update(_summary_fields(motion_info, motion, frames))
            res.ghosts = np.sum([~v for v in valid], axis=0, dtype=np.uint8)   # frames left out per photosite
    else:
        res = _paper1(frames, o.output_space, o.demosaic)
    res.info.update({"method": "raw", "estimator": o.estimator})
    return res


#: A censored sample is inconsistent with the other frame when that frame's value lies more
#: than this many sigma below the saturation level (ghost removal on RAW frames).
_CENSOR_SIGMA = 3.0


def _grey8(frame: RawFrame) -> np.ndarray:
    """A grey rendering of a mosaic for MTB: 2x2 block sums above black, relative to white, to
    8 bit by gamma 1/2.2 (MTB's thresholds are percentiles: the rendering only has to be monotone)."""
    m = np.asarray(frame.mosaic, dtype=np.float32)
    h, w = (m.shape[0] // 2) * 2, (m.shape[1] // 2) * 2
    bl = np.asarray(frame.black_level, dtype=np.float32)
    bl = float(bl.mean())
    s = (m[0:h:2, 0:w:2] + m[1:h:2, 0:w:2] + m[0:h:2, 1:w:2] + m[1:h:2, 1:w:2]) - 4 * bl
    s = np.clip(s / (4 * (float(frame.white_level) - bl)), 0.0, 1.0)
    return np.round(255.0 * s ** (1 / 2.2)).astype(np.uint8)


def _shifted(mosaic: np.ndarray, dy: int, dx: int) -> tuple[np.ndarray, np.ndarray]:
    """``out[y, x] = mosaic[y + dy, x + dx]`` (even shifts keep the CFA phase) and where it is inside."""
    h, w = mosaic.shape
    out = np.empty_like(mosaic)
    inside = np.zeros((h, w), bool)
    ys, xs = slice(max(0, -dy), min(h, h - dy)), slice(max(0, -dx), min(w, w - dx))
    src_y, src_x = slice(ys.start + dy, ys.stop + dy), slice(xs.start + dx, xs.stop + dx)
    out[...] = mosaic
    out[ys, xs] = mosaic[src_y, src_x]
    inside[ys, xs] = True
    return out, inside


def raw_motion(frames: Sequence[RawFrame], motion: MotionOptions, gain: float | None = None,
               read_noise: float | None = None) -> tuple[list[RawFrame], list[np.ndarray], dict]:
    """Reference, alignment and ghost removal on RAW frames (module docstring) for
    :func:`merge_raw`: ``(frames, valid, info)``, the frames in the order given (aligned
    copies), per frame where it takes part, and what was done (``reference``, ``shifts``,
    ``rejected`` fraction per frame)."""
    from derender.raw.mosaic import setting_factors

    frames = list(frames)
    n = len(frames)
    align = motion.align_for("none")
    if align not in ("none", "translation"):
        raise InputError(f"--align {align} is not available on RAW frames; use --align translation (MTB)")
    times = np.array([(f.exposure_time or 1.0) for f in frames]) * setting_factors(frames)
    ref = _raw_reference(frames, motion.reference)
    valid = [np.ones(np.asarray(f.mosaic).shape, bool) for f in frames]
    shifts = [(0, 0)] * n
    if align == "translation" and n > 1:
        frames, shifts = _align_mosaics(frames, times, ref, valid)
    rejected = [0.0] * n
    if motion.deghost and n > 1:
        rejected = _reject_ghosts(frames, times, ref, valid, motion.ghost_threshold, (gain, read_noise))
    info = {"reference": ref, "align": align, "shifts": shifts, "deghost": bool(motion.deghost),
            "rejected": rejected}
    return frames, valid, info


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


def _raw_reference(frames: list[RawFrame], reference: int | None) -> int:
    """The reference frame: ``reference`` (0-based, as given), else the frame with most photosites
    well inside its range (2-90 % of white minus black)."""
    n = len(frames)
    if reference is not None:
        if reference >= n:
            raise InputError(f"reference frame {reference + 1} of {n}: there is no such frame")
        return int(reference)

    def well(f: RawFrame) -> int:
        d = np.asarray(f.mosaic, np.float32) - float(np.mean(f.black_level))
        c = float(f.white_level) - float(np.mean(f.black_level))
        return int(np.count_nonzero((d > 0.02 * c) & (d < 0.9 * c)))

    return int(np.argmax([well(f) for f in frames]))


def _align_mosaics(frames: list[RawFrame], times: np.ndarray, ref: int,
                   valid: list[np.ndarray]) -> tuple[list[RawFrame], list[tuple[int, int]]]:
    """Even-photosite shifts: the engine's chained MTB registration
    (:func:`derender.engine.motion.align.chain_transforms`, the one the JPEG methods use: neighbours
    in exposure, thresholds at percentiles both frames expose well, chained towards the reference)
    on grey renderings of the 2x2 blocks, each frame at its own exposure; a shift of one block is
    two photosites, so the CFA phase is kept. Returns the shifted copies and the shifts; ``valid``
    loses the photosites shifted in from outside."""
    from dataclasses import replace

    from derender.engine.motion.align import chain_transforms, transforms_to_shifts

    order = np.argsort(times, kind="stable")
    transforms, _ = chain_transforms([_grey8(frames[i]) for i in order], "translation",
                                     int(np.flatnonzero(order == ref)[0]))
    blocks = transforms_to_shifts(transforms)              # (dy, dx) in 2x2 blocks, exposure order
    out, shifts = list(frames), [(0, 0)] * len(frames)
    for k, j in enumerate(order):
        dy, dx = 2 * int(blocks[k, 0]), 2 * int(blocks[k, 1])
        if (dy, dx) == (0, 0):
            continue
        shifts[j] = (dy, dx)
        mos, inside = _shifted(np.asarray(frames[j].mosaic), dy, dx)
        valid[j] &= inside
        out[j] = replace(frames[j], mosaic=mos)
    return out, shifts


def _frame_noise(frames: list[RawFrame], times: np.ndarray, given: tuple) -> tuple:
    """Per frame (in the order given): gain, read variance, black-level plane and white level,
    the noise ``given`` as (gain, read noise) or estimated from the frames."""
    from derender.raw.noise import NoiseModel, estimate_noise_frames
    from derender.raw.optimal import compiled_frames

    n = len(frames)
    order = np.argsort(times, kind="stable")
    sorted_frames = [frames[i] for i in order]
    mosaics, black, white = compiled_frames(sorted_frames)
    if given[0] is not None and given[1] is not None:
        noise = NoiseModel(float(given[0]), float(given[1]) ** 2, "given")
    else:
        noise = estimate_noise_frames(mosaics, black, white, times[order],
                                      [(f.extra or {}).get("iso") for f in sorted_frames])
    g_s, s2_s = noise.per_frame(n)
    g, s2 = np.empty(n), np.empty(n)
    g[order], s2[order] = g_s, s2_s
    h, w = np.asarray(frames[0].mosaic).shape
    planes, whites = [None] * n, [0.0] * n
    for k, i in enumerate(order):
        planes[i] = np.tile(black[k], ((h + 1) // 2, (w + 1) // 2))[:h, :w]
        whites[i] = white[k]
    return g, s2, planes, whites


def _reject_ghosts(frames: list[RawFrame], times: np.ndarray, ref: int, valid: list[np.ndarray],
                   threshold: float | None, given: tuple) -> list[float]:
    """Ghost removal by the Poisson-Gaussian model (module docstring): ``valid[j]`` loses where the
    5x5 window mean of ``z^2`` against the reference exceeds the threshold. Returns the fraction
    rejected per frame."""
    from scipy.ndimage import uniform_filter

    from derender.engine.motion.deghost import GHOST_THRESHOLD

    g, s2, planes, whites = _frame_noise(frames, times, given)
    d_r = np.asarray(frames[ref].mosaic, np.float64) - planes[ref]
    sat_r = np.asarray(frames[ref].mosaic) >= whites[ref]
    x_r = np.maximum(d_r / times[ref], 0.0)
    v_r = g[ref] * x_r * times[ref] + s2[ref]
    c_r = whites[ref] - planes[ref]
    thr = float(threshold or GHOST_THRESHOLD)
    rejected = [0.0] * len(frames)
    for j in range(len(frames)):
        if j == ref:
            continue
        d_j = np.asarray(frames[j].mosaic, np.float64) - planes[j]
        sat_j = np.asarray(frames[j].mosaic) >= whites[j]
        v_j = g[j] * x_r * times[j] + s2[j]
        z2 = (d_j / times[j] - d_r / times[ref]) ** 2 / (v_j / times[j] ** 2 + v_r / times[ref] ** 2)
        # a censored sample: inconsistent only where the other frame is clearly below its level
        below_j = x_r * times[j] < whites[j] - planes[j] - _CENSOR_SIGMA * np.sqrt(v_j)
        x_j = np.maximum(d_j / times[j], 0.0)
        below_r = x_j * times[ref] < c_r - _CENSOR_SIGMA * np.sqrt(g[ref] * x_j * times[ref] + s2[ref])
        z2 = np.where(sat_j & sat_r, 0.0, z2)
        z2 = np.where(sat_j & ~sat_r, np.where(below_j, 4.0 * thr, 0.0), z2)
        z2 = np.where(~sat_j & sat_r, np.where(below_r, 4.0 * thr, 0.0), z2)
        bad = uniform_filter(z2, size=5, mode="nearest") > thr
        valid[j] &= ~bad
        rejected[j] = float(np.mean(bad))
    return rejected


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
