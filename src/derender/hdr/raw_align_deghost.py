"""Alignment and ghost removal on the mosaic for the ``raw`` method (:func:`derender.hdr.raw.merge_raw`).

:func:`raw_motion` (a :class:`~derender.engine.motion.run.MotionOptions` given as ``motion=``)
works on the mosaic. Alignment: the engine's chained MTB registration
(:func:`derender.engine.motion.align.chain_transforms`) on a grey rendering of each frame (2x2
blocks, gamma 1/2.2) gives even-photosite shifts, each refined to a fraction of a photosite
against its neighbour towards the reference and chained (:mod:`derender.raw.register`). When
every shift is whole and even the frames are shifted (the CFA phase kept) and merged on the
mosaic; otherwise every frame's colours are resampled at the reference's photosites and merged
per colour (:func:`derender.raw.register.merge_shifted`), with the noise model fitted on the
frame pairs whose relative shift is whole and even (:func:`derender.raw.noise.estimate_noise_shifted`:
no resampling, no residual misregistration), else on the smooth photosites of the frames
rounded to even shifts (``_flat_photosites``: elsewhere their differences hold the
misregistration's error). Ghost removal by the Poisson-Gaussian noise model
between each frame and the reference: per photosite ``z = (d_j / e_j - d_r / e_r) /
sqrt(v_j / e_j^2 + v_r / e_r^2)`` (``v`` eq. 1 of :mod:`derender.raw.noise` at the reference's
value), its mean over a 5x5 window against the engine's threshold
(:data:`derender.engine.motion.deghost.GHOST_THRESHOLD`); a censored sample is inconsistent
when the other frame puts the value more than 3 sigma below its saturation level; for a
resampled bracket ``z`` compares 2x2-window sums instead (``_reject_ghosts``; at a shift
not whole and even the windows see the scene through other colour filters, and the
reference's own change across that offset, :func:`derender.raw.window_ghost_test.phase_offset_difference`,
is allowed for in the variance); beside
saturation a frame longer than the reference is tested per photosite with 10 % of the value
allowed for the resampling's error, and where a photosite's resampled sample is left untested
(its support partly saturated) a longer frame is tested colour by colour in the merge
(:func:`derender.raw.colour_ghost_test.colour_ghosts`) and a shorter one is left out; the per-photosite
``z`` and the window sums are compiled (:mod:`derender.raw.register_kernels`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import RawFrame
from derender.engine.motion.run import MotionOptions

__all__ = ["raw_motion"]


#: A censored sample is inconsistent with the other frame when that frame's value lies more
#: than this many sigma below the saturation level (ghost removal on RAW frames).
_CENSOR_SIGMA = 3.0

#: Relative error of a resampled colour (the demosaic's, at the shifted photosite) allowed for
#: in the per-photosite ghost test beside saturation (ghost removal on resampled RAW frames;
#: measured on the simulator's ``paper`` family).
_RESAMPLE_ERROR = 0.1


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
    :func:`derender.hdr.raw.merge_raw`: ``(frames, valid, info)``, the frames in the order given (aligned
    copies), per frame where it takes part, and what was done (``reference``, ``shifts``
    (dy, dx) photosites, ``rejected`` fraction per frame, ``variance_factor`` (N, 2, 2) per
    frame and CFA phase for the resampled frames, ``noise`` the
    :class:`~derender.raw.noise.NoiseModel` the merge is to use)."""
    from derender.raw.mosaic import setting_factors

    frames = list(frames)
    n = len(frames)
    align = motion.align_for("none")
    if align not in ("none", "translation"):
        raise InputError(f"--align {align} is not available on RAW frames; use --align translation (MTB)")
    times = np.array([(f.exposure_time or 1.0) for f in frames]) * setting_factors(frames)
    ref = _raw_reference(frames, motion.reference)
    valid = [np.ones(np.asarray(f.mosaic).shape, bool) for f in frames]
    shifts: list = [(0, 0)] * n
    factors = np.ones((n, 2, 2))
    noise = None
    pairs: list = []
    given_frames = list(frames)
    if align == "translation" and n > 1:
        frames, shifts, factors, noise, pairs = _align_mosaics(frames, times, ref, valid, (gain, read_noise))
    resampled = any(not (float(a).is_integer() and float(b).is_integer() and int(a) % 2 == 0 and int(b) % 2 == 0)
                    for a, b in shifts)
    rejected = [0.0] * n
    kept = [np.ones(np.asarray(f.mosaic).shape, bool) for f in frames]
    untested = None
    if motion.deghost and n > 1:
        if noise is None:
            noise = _bracket_noise(frames, times, (gain, read_noise))
        untested = [np.zeros(np.asarray(f.mosaic).shape, bool) for f in frames] if resampled else None
        rejected = _reject_ghosts(frames, times, ref, valid, threshold=motion.ghost_threshold, noise=noise,
                                  factors=factors, kept=kept,
                                  shifted=(given_frames, shifts, untested) if resampled else None)
    info = {"reference": ref, "align": align, "shifts": shifts, "deghost": bool(motion.deghost),
            "rejected": rejected, "variance_factor": factors, "noise": noise, "pairs": pairs,
            "resampled": resampled, "kept": kept, "untested": untested}
    return frames, valid, info


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


def _coarse_shifts(frames: list[RawFrame], times: np.ndarray, ref: int) -> tuple[np.ndarray, np.ndarray]:
    """Even-photosite shifts (N, 2) in the order given: the engine's chained MTB registration
    (:func:`derender.engine.motion.align.chain_transforms`, the one the JPEG methods use:
    neighbours in exposure, thresholds at percentiles both frames expose well, chained towards
    the reference) on grey renderings of the 2x2 blocks, each frame at its own exposure (a shift
    of one block is two photosites); and the exposure order."""
    from derender.engine.motion.align import chain_transforms, transforms_to_shifts

    order = np.argsort(times, kind="stable")
    transforms, _ = chain_transforms([_grey8(frames[i]) for i in order], "translation",
                                     int(np.flatnonzero(order == ref)[0]))
    blocks = transforms_to_shifts(transforms)              # (dy, dx) in 2x2 blocks, exposure order
    out = np.zeros((len(frames), 2), np.int64)
    out[order] = 2 * blocks
    return out, order


def _even(shift: np.ndarray) -> tuple[int, int]:
    """The nearest even whole shift (the CFA phase kept)."""
    return int(2 * np.rint(shift[0] / 2)), int(2 * np.rint(shift[1] / 2))


def _shown(shift) -> tuple:
    """A shift as reported: whole photosites as ints, else to 0.01 photosite."""
    return tuple(int(v) if float(v).is_integer() else round(float(v), 2) for v in shift)


def _align_mosaics(frames: list[RawFrame], times: np.ndarray, ref: int, valid: list[np.ndarray],
                   given: tuple) -> tuple:
    """Sub-photosite alignment (:mod:`derender.raw.register`): the even-photosite MTB shifts
    (:func:`_coarse_shifts`), the noise model on the frames shifted by them (whole even shifts
    are exact), then each frame's translation refined against its neighbour towards the
    reference on the CFA planes (:func:`derender.raw.register.refine_shift`) and chained; each
    frame moved by its shift (:data:`~derender.raw.register.SNAP`-whole even: a copy; else
    :func:`derender.raw.register.resample_mosaic`). Returns the aligned copies, the shifts,
    the variance factors (N, 2, 2), the noise model and the pairs' details; ``valid`` loses the
    photosites that take no part (shifted in from outside, partly saturated support)."""
    from dataclasses import replace

    from derender.raw.register import refine_shift, resample_mosaic, snap_shift

    n = len(frames)
    coarse, order = _coarse_shifts(frames, times, ref)
    blacks = [_black22(f) for f in frames]
    s2 = np.full(n, 4.0) if given[1] is None else np.full(n, float(given[1]) ** 2)   # read noise for the
    # refinement's thresholds only: 2 DN until the noise model is known (it needs the shifts)
    # refine along the chain: each frame against its neighbour nearer the reference
    k_ref = int(np.flatnonzero(order == ref)[0])
    total = {ref: np.zeros(2)}
    pairs = []
    for k in list(range(k_ref - 1, -1, -1)) + list(range(k_ref + 1, n)):
        j, a = int(order[k]), int(order[k + 1] if k < k_ref else order[k - 1])
        start = coarse[j] - coarse[a]
        # the longer exposure is the one interpolated: interpolating the noisier frame lowers its
        # noise between photosites, which pulls the estimate towards half photosites (measured:
        # 0.36 photosite on a tripod bracket's shortest frame)
        lo, hi, sign = (j, a, -1.0) if times[j] < times[a] else (a, j, 1.0)
        s, info = refine_shift(np.asarray(frames[lo].mosaic), np.asarray(frames[hi].mosaic), sign * start,
                               (times[lo], times[hi]), (blacks[lo], blacks[hi]),
                               (float(frames[lo].white_level), float(frames[hi].white_level)),
                               read_sd=float(np.sqrt(max(s2[a], s2[j]))))
        s = sign * s
        total[j] = total[a] + s
        pairs.append({"from": a, "to": j, "shift": _shown(np.round(s, 3)), **info})
    out, shifts, factors = list(frames), [(0, 0)] * n, np.ones((n, 2, 2))
    resampled = False
    for j in range(n):
        sy, sx = snap_shift(total[j])
        if (sy, sx) == (0.0, 0.0):
            continue
        shifts[j] = _shown((sy, sx))
        if float(sy).is_integer() and float(sx).is_integer() and _even((sy, sx)) == (sy, sx):
            mos, inside = _shifted(np.asarray(frames[j].mosaic), int(sy), int(sx))
            valid[j] &= inside
        else:
            mos, ok, factors[j] = resample_mosaic(np.asarray(frames[j].mosaic), (sy, sx), blacks[j],
                                                  float(frames[j].white_level), frames[j].cfa_pattern)
            valid[j] &= ok
            resampled = True
        out[j] = replace(frames[j], mosaic=mos)
    noise = (_shifted_noise(frames, [total[j] for j in range(n)], times, ref, given) if resampled
             else _bracket_noise(out, times, given))
    return out, shifts, factors, noise, pairs


#: A photosite is smooth where, within 3 photosites, no 2x2-window mean differs from its 5x5
#: neighbourhood's by more than this many noise sigma (the noise fit of a shifted bracket).
_FLAT_SIGMA = 3.5


def _flat_photosites(frame: RawFrame, noise) -> np.ndarray:
    """(H, W) bool: where the frame has no texture above its noise (``noise`` a
    :class:`~derender.raw.noise.NoiseModel`; an upper bound is enough): the photosites whose
    frame differences hold no misalignment's error, for the noise fit of a shifted bracket."""
    from scipy.ndimage import maximum_filter, uniform_filter

    y = np.asarray(frame.mosaic, np.float64)
    h, w = y.shape
    d = y - np.tile(_black22(frame), ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    box = uniform_filter(d, size=2, mode="nearest")
    sd = np.sqrt(noise.variance(np.maximum(box, 0.0)) / 4.0)
    dev = np.abs(box - uniform_filter(box, size=5, mode="nearest")) / sd
    dev[y >= float(frame.white_level)] = np.inf
    return maximum_filter(dev, size=7, mode="nearest") <= _FLAT_SIGMA


def _shifted_noise(frames: list[RawFrame], shifts: list, times: np.ndarray, ref: int, given: tuple):
    """The noise model of a shifted bracket: on the frame pairs whose relative shift is whole and
    even (``_exact_pair_noise``) when there are any; else the frames moved by their shifts rounded to even
    photosites (exact samples, the CFA phase kept), the fit (:func:`derender.raw.noise.estimate_noise_frames`)
    on the photosites where the reference has no texture above its noise (there a residual shift of
    a photosite changes nothing), found with the reference's own green-pair estimate (an upper
    bound) and again with the bracket's; the green-pair estimate if too few are left."""
    from dataclasses import replace

    from derender.raw.noise import NoiseModel, estimate_noise_single
    from derender.raw.optimal import mosaic_observations

    if given[0] is not None and given[1] is not None:
        return NoiseModel(float(given[0]), float(given[1]) ** 2, "given")
    exact = _exact_pair_noise(frames, shifts, times)
    if exact is not None:
        return exact
    moved = list(frames)
    for j, s in enumerate(shifts):
        dy, dx = _even(s)
        if (dy, dx) != (0, 0):
            moved[j] = replace(frames[j], mosaic=_shifted(np.asarray(frames[j].mosaic), dy, dx)[0])
    d, sat, ceil = mosaic_observations([frames[ref]])
    noise = estimate_noise_single(d[0], sat[0], ceil[0], frames[ref].cfa_pattern)
    for _ in range(2):
        try:
            noise = _bracket_noise(moved, times, given, _flat_photosites(frames[ref], noise))
        except InputError:
            break
    return noise


def _exact_pair_noise(frames: list[RawFrame], shifts: list, times: np.ndarray):
    """:func:`derender.raw.noise.estimate_noise_shifted` on the frames in exposure order (the
    pairs whose relative shift is whole and even), or None (no such pair, ISO varies)."""
    from derender.raw.noise import estimate_noise_shifted
    from derender.raw.optimal import compiled_frames
    from derender.raw.register import SNAP

    if len({(f.extra or {}).get("iso") for f in frames}) > 1:
        return None
    order = np.argsort(times, kind="stable")
    mosaics, black, white = compiled_frames([frames[i] for i in order])
    return estimate_noise_shifted(mosaics, black, white, times[order],
                                  np.array([shifts[i] for i in order], np.float64), SNAP)


def _black22(frame: RawFrame) -> np.ndarray:
    bl = np.asarray(frame.black_level, dtype=np.float64)
    return np.broadcast_to(bl.reshape(-1)[0], (2, 2)).copy() if bl.size == 1 else bl.reshape(2, 2)


def _bracket_noise(frames: list[RawFrame], times: np.ndarray, given: tuple, where: np.ndarray | None = None):
    """The noise model: ``given`` as (gain, read noise), else estimated from the frames
    (:func:`derender.raw.noise.estimate_noise_frames`, frames in exposure order, as the merge
    does), on the photosites ``where`` (None: all; the others are given the white level, which
    the fit leaves out)."""
    from dataclasses import replace

    from derender.raw.noise import NoiseModel, estimate_noise_frames
    from derender.raw.optimal import compiled_frames

    if given[0] is not None and given[1] is not None:
        return NoiseModel(float(given[0]), float(given[1]) ** 2, "given")
    order = np.argsort(times, kind="stable")
    sorted_frames = [frames[i] for i in order]
    if where is not None:
        sorted_frames = [replace(f, mosaic=np.where(where, np.asarray(f.mosaic, np.float64), float(f.white_level)))
                         for f in sorted_frames]
    mosaics, black, white = compiled_frames(sorted_frames)
    return estimate_noise_frames(mosaics, black, white, times[order],
                                 [(f.extra or {}).get("iso") for f in sorted_frames])


def _per_frame_noise(noise, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gain and read variance per frame in the order given (the model's are in exposure order)."""
    n = len(times)
    order = np.argsort(times, kind="stable")
    g_s, s2_s = noise.per_frame(n)
    g, s2 = np.empty(n), np.empty(n)
    g[order], s2[order] = g_s, s2_s
    return g, s2


#: The shifted path's ghost test compares the difference of two frames' 2x2-window sums as the
#: 3x3 mean of the windows (4x4 photosites weighted 1, 2, 2, 1 per axis, / 9): these taps per axis
#: (the 3x3 mean) ...
_WINDOW_MEAN3 = np.ones(3) / 3.0
#: ... its variance, the photosites' weighted by (1, 4, 4, 1) per axis / 81 ...
_WINDOW_VAR4 = np.array([1.0, 4.0, 4.0, 1.0]) / 9.0
#: ... and a window's photosites in the 3x3 mean.
_WINDOW_PAIR3 = np.array([1.0, 2.0, 2.0, 1.0]) / 3.0


def _separable(v: np.ndarray, taps: np.ndarray, taps_x: np.ndarray | None = None) -> np.ndarray:
    """``v`` correlated with ``taps`` along the rows and ``taps_x`` (else ``taps``) along the columns,
    edges repeated (``scipy.ndimage.correlate1d``'s ``nearest``, compiled:
    :func:`derender.raw.register_kernels.correlate_nearest`)."""
    from derender.raw.register_kernels import correlate_nearest

    out = np.empty(np.shape(v))
    tx = taps if taps_x is None else taps_x
    correlate_nearest(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(taps, np.float64),
                      np.ascontiguousarray(tx, np.float64), out)
    return out


def _leave_untested(untested: list, j: int, longer: bool, use: np.ndarray, valid_j: np.ndarray,
                    bad: np.ndarray) -> np.ndarray:
    """Photosites neither ghost test of :func:`_reject_ghosts` could decide (near saturation, the
    resampled sample's support partly saturated), where the merge would take frame ``j``'s
    colours unchecked: a frame longer than the reference (``longer``) is tested there colour by
    colour by the merge (:func:`derender.raw.colour_ghost_test.colour_ghosts`: leaving its
    colours out beside its own saturation cost the static zone 1.22 -> 1.18 on seed 0,
    measured), so ``untested[j]`` records them; a shorter one is left out. Returns ``bad``."""
    if longer:
        untested[j] = ~use & ~valid_j & ~bad
        return bad
    return bad | (~use & ~valid_j)


def _reject_ghosts(frames: list[RawFrame], times: np.ndarray, ref: int, valid: list[np.ndarray], *,
                   threshold: float | None, noise, factors: np.ndarray, kept: list[np.ndarray],
                   shifted: tuple | None = None) -> list[float]:
    """Ghost removal by the Poisson-Gaussian model (module docstring): ``valid[j]`` loses where the
    5x5 window mean of ``z^2`` against the reference exceeds the threshold; a resampled frame's
    variance is its factor per CFA phase times the model's. With ``shifted`` (the frames as read
    and their shifts, a resampled bracket), ``z^2`` compares 2x2-window sums instead
    (:func:`derender.raw.window_ghost_test.shifted_box`, each frame's window at ``p + s``; colours weighed
    alike by :func:`derender.raw.register.phase_scale`), wherever neither window is saturated:
    a window holds one photosite of each colour whatever its phase, so no colour is interpolated
    across (a resampled sample of another colour carries the demosaic's error, which the noise
    model does not describe and which rejected 40-50 % of the static photosites of a handheld
    bracket). ``shifted`` is ``(frames as read, shifts, untested)``: ``untested[j]`` gets the
    photosites of a frame longer than the reference that neither test could decide, for the
    merge's test colour by colour (:func:`derender.raw.colour_ghost_test.colour_ghosts`). Returns the
    fraction rejected per frame; ``kept[j]`` loses the rejected photosites."""
    from scipy.ndimage import uniform_filter

    from derender.engine.motion.deghost import GHOST_THRESHOLD
    from derender.raw.register_kernels import ghost_z2

    g, s2 = _per_frame_noise(noise, times)
    h, w = np.asarray(frames[0].mosaic).shape

    def plane(a22: np.ndarray) -> np.ndarray:
        return np.tile(a22, ((h + 1) // 2, (w + 1) // 2))[:h, :w]

    planes = [plane(_black22(f)) for f in frames]
    whites = [float(f.white_level) for f in frames]
    d_r = np.asarray(frames[ref].mosaic, np.float64) - planes[ref]
    sat_r = np.asarray(frames[ref].mosaic) >= whites[ref]
    x_r = np.maximum(d_r / times[ref], 0.0)
    thr = float(threshold or GHOST_THRESHOLD)
    rejected = [0.0] * len(frames)
    if shifted is not None:
        from derender.raw.register import phase_scale
        from derender.raw.window_ghost_test import phase_offset_difference, shifted_box

        originals, shift_values, untested = shifted
        scale = phase_scale(originals[ref].mosaic, _black22(originals[ref]), whites[ref], times[ref])
        sc2 = plane(scale) ** 2
        smooth = _separable
        mean3, var4, pair3 = _WINDOW_MEAN3, _WINDOW_VAR4, _WINDOW_PAIR3
        vq_r = (g[ref] * x_r * times[ref] + s2[ref]) / times[ref] ** 2 / sc2
        box_r, bsat_r = shifted_box(d_r / times[ref], sat_r, (0, 0), scale)[:2]
        var_r = smooth(vq_r, var4)
    mos_r = np.ascontiguousarray(frames[ref].mosaic)
    everywhere = np.empty((0, 0), np.bool_)
    for j in range(len(frames)):
        if j == ref:
            continue
        # z^2 per photosite (derender.raw.register_kernels.ghost_z2): a censored sample is
        # inconsistent only where the other frame is clearly below its level; on a resampled
        # bracket, for a frame longer than the reference where its resampled sample is measured
        # (support unsaturated: ``valid``), with the resampled colour's error allowed for
        # (``_RESAMPLE_ERROR``; a ghost beside the long frame's saturation went untested), else
        # (neither sample saturated) 0: the window test below decides. Testing the shorter
        # frames so too made the object zone worse (docs/results-raw.md, measured).
        tested = (np.ascontiguousarray(valid[j] & (times[j] > times[ref])) if shifted is not None
                  else everywhere)
        z2 = np.empty((h, w))
        ghost_z2(np.ascontiguousarray(frames[j].mosaic), mos_r, _black22(frames[j]), _black22(frames[ref]),
                 whites[j], whites[ref], float(times[j]), float(times[ref]), float(g[j]), float(s2[j]),
                 float(g[ref]), float(s2[ref]), np.ascontiguousarray(factors[j], np.float64),
                 np.ascontiguousarray(factors[ref], np.float64), _CENSOR_SIGMA, 4.0 * thr,
                 _RESAMPLE_ERROR if shifted is not None else 0.0, tested, z2)
        if shifted is not None:
            o = originals[j]
            d_o = np.asarray(o.mosaic, np.float64) - planes[j]
            box_j, bsat_j, inside, (wy, wx) = shifted_box(d_o / times[j], np.asarray(o.mosaic) >= whites[j],
                                                          shift_values[j], scale)
            vq_j = (g[j] * x_r * times[j] + s2[j]) / times[j] ** 2 / sc2
            # frame j's photosites enter through the window, the 3x3 mean and Keys' weights
            ky, kx = np.convolve(pair3, wy[wy != 0]) ** 2, np.convolve(pair3, wx[wx != 0]) ** 2
            var_j = smooth(vq_j, ky, kx)
            # the windows' colours differ at a shift not whole and even: the scene's change over
            # that offset allowed for (derender.raw.window_ghost_test.phase_offset_difference)
            texture = smooth(phase_offset_difference(box_r, shift_values[j]), mean3) ** 2
            zb = smooth(box_j - box_r, mean3) ** 2 / (var_j + var_r + texture)
            use = inside & (smooth((bsat_j | bsat_r).astype(np.float64), mean3) == 0.0)
            # near saturation (a window holds a saturated photosite) the censored samples' rule
            # and the per-photosite test above
            z2 = np.where(use, zb, z2)
        bad = uniform_filter(z2, size=5, mode="nearest") > thr
        if shifted is not None:
            bad = _leave_untested(untested, j, bool(times[j] > times[ref]), use, valid[j], bad)
        valid[j] &= ~bad
        kept[j] &= ~bad
        rejected[j] = float(np.mean(bad))
    return rejected
