"""Paper 1's stabilised merge as a method: Algorithm 1 end to end, and its registration as
``"stabilized"`` and ``"stabilized-joint"``.

:func:`stabilize` (or :func:`stabilize_aligned` on registered frames) runs steps 1-4 and
returns a :class:`Stabilization`; :func:`stabilized_merge` is step 4's trapezoid-weighted
average (eq. 10), by default also weighted by each estimate's inverse noise variance.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.options import check_at_least, check_choice
from derender.core.types import HDRResult, Stack
from derender.engine.frames import NotStreamable
from derender.engine.matrix import matrix_output_bytes, merge_matrix_frames, warm_up_kernels
from derender.engine.motion.reference_frame import REF_PIXELS, select_reference
from derender.engine.motion.run import MotionOptions
from derender.engine.plans import FrameAccess, MatrixPlan, MethodDefaults
from derender.engine.tables import code_histograms, code_values, stack_codes_exact, weight_table
from derender.engine.weights import WEIGHTS
from derender.hdr.registry import merge
from derender.hdr.stabilize.blocks import FIT_FLOOR, FIT_HIGH, FIT_LOW, make_blocks
from derender.hdr.stabilize.colour_model import fit_colour_model
from derender.hdr.stabilize.curves import Curve
from derender.hdr.stabilize.exponents import GammaEstimate, estimate_gammas_blocks
from derender.hdr.stabilize.filmic import (
    CURVE_SHAPE_TIE,
    CURVE_TIE,
    SCREEN_TREND,
    curve_model,
    gamma_trend,
    power_law_plausible,
    screen_gamma_trend,
    unclipped_debevec,
)
from derender.hdr.stabilize.frame_views import CodeFrameRows, HeldValid, LazyAlignment, ShiftedFrames
from derender.hdr.stabilize.saturation import HIDDEN_FRACTION, saturation_fraction, saturation_mask
from derender.hdr.stabilize.summary import stabilization_info

__all__ = ["Stabilization", "stabilize", "stabilize_aligned", "stabilized_merge",
           "merge_stabilized", "merge_stabilized_joint", "merge_stabilized_table", "stabilized_plan",
           "StabilizedMethod", "StabilizedOptions", "stabilized_engine", "stabilized_joint_engine", "stabilized_stack",
           "stabilized_joint_stack"]


def stabilized_plan(stab, weight: Any = "trapezoid", noise_weighting: bool = True,
                    shifts: np.ndarray | None = None) -> MatrixPlan:
    """Paper 1, Algorithm 1 step 4 as the engine's :class:`~derender.engine.plans.MatrixPlan`.

    Image ``j`` contributes ``H'_j L_j(z) / t_j`` with the per-channel table
    ``L_j = stab.curves[j].lin`` on the 256 codes and the 3x3 matrix ``H'_j``
    (``H_j t_j / t_ref`` in reference mode, ``K_j`` in joint mode). One weight for all
    channels: the smallest channel weight where some exposure has all channels usable,
    else the weight of the brightest channel; with ``noise_weighting`` times
    ``t_j^2 / mean_c (dL_j/dJ)^2`` (the reference engine also divides by the per-pixel
    maximum over images, a common factor that cancels). :class:`NotStreamable` when there is
    no table form (noise weighting without per-image curves)."""
    times = np.asarray(stab.times, dtype=np.float64)
    n = times.shape[0]
    z3 = np.repeat(code_values()[:, None], 3, axis=1)
    curves = list(getattr(stab, "curves", None) or [])
    values, mats, ivs, iks = [], [], [], []
    t2max = float(np.max(times ** 2))
    for j in range(n):
        if curves:
            lin = np.asarray(curves[j].lin(z3), dtype=np.float64)
        else:  # power law of the gamma estimate (paper 1, eq. 4)
            lin = np.clip(z3.astype(np.float64), 0.0, 1.0) ** float(stab.gammas.gammas[j])
        values.append(lin.astype(np.float32))
        m = np.asarray(stab.matrices[j], dtype=np.float64)
        if stab.mode == "reference":
            m = m * (times[j] / times[stab.reference])
        mats.append(m / times[j])
        if noise_weighting:
            if not curves:
                raise NotStreamable("noise weighting needs per-image curves")
            d2 = np.asarray(curves[j].dlin(z3), dtype=np.float64) ** 2
            ivs.append(d2.astype(np.float32) / np.float32(3.0))
            iks.append(times[j] ** 2 / t2max)          # common 1/t2max keeps float32 in range
    if shifts is None:
        shifts = np.zeros((n, 2), dtype=np.int64)
    return MatrixPlan(values=np.ascontiguousarray(np.stack(values), dtype=np.float32),
                      matrices=np.ascontiguousarray(np.stack(mats), dtype=np.float64),
                      weights=np.ascontiguousarray(weight_table(weight), dtype=np.float32),
                      shifts=np.asarray(shifts, dtype=np.int64),
                      inverse_variance=np.ascontiguousarray(np.stack(ivs), dtype=np.float32) if noise_weighting else None,
                      inverse_variance_k=np.array(iks, dtype=np.float32) if noise_weighting else None)


def _merge_info(stab, weight: Any, noise_weighting: bool) -> dict:
    info = {"weight": weight if isinstance(weight, str) else "custom", "noise_weighting": bool(noise_weighting)}
    info.update(stabilization_info(stab))
    return info


def merge_stabilized_table(stab, weight: Any = "trapezoid", noise_weighting: bool = True,
                           threads: int | None = None, codes: np.ndarray | None = None) -> HDRResult:
    """:func:`stabilized_merge` of an in-memory :class:`Stabilization` on the engine's matrix
    kernel (:func:`~derender.engine.matrix.merge_matrix_frames`): one compiled pass per pixel,
    float32 sums (2e-7 to 4e-7 relative to the float64 reference engine), the registration
    mask applied. ``codes``: the aligned images as 8-bit codes, if already made.
    :class:`NotStreamable` when they are not 8-bit codes (sub-pixel warps) or there is no
    table form (:func:`stabilized_plan`)."""
    al = stab.alignment
    codes = stack_codes_exact(al.images) if codes is None else codes
    if codes is None:
        raise NotStreamable("the aligned images are not 8-bit codes")
    plan = stabilized_plan(stab, weight, noise_weighting)
    valid = getattr(al, "valid", None)
    if valid is not None:
        valid = np.asarray(valid)
        valid = None if valid.all() else np.ascontiguousarray(valid, dtype=np.uint8)
    res = merge_matrix_frames(codes, plan, stab.times, valid=valid, threads=threads)
    res.info.update(_merge_info(stab, weight, noise_weighting))
    return res


class StabilizedMethod(MethodDefaults):
    """Paper 1's stabilised merge on the engine (methods ``"stabilized"`` and ``"stabilized-joint"``).

    Every frame is held once as 8-bit codes (72 MB per 24 MP frame, a quarter of the
    float image the reference path holds); Ward's grey images are made in the decoding
    threads (registration, :func:`derender.engine.motion.align.chain_transforms`); the reference is
    chosen on the codes as :func:`select_reference` does; the gamma / matrix fits read
    only their sampled blocks through :class:`ShiftedFrames`; the Debevec curve (filmic
    cameras) comes from grid samples of the aligned frames; the merge is the engine's
    matrix kernel over all frames through their shifts. Same numbers as
    :func:`stabilize` + :func:`stabilized_merge` on the same codes.
    """

    holds_frames = True
    output_bytes = staticmethod(matrix_output_bytes)
    own_align = "translation"     # registers the frames itself (Ward's MTB) unless the engine did

    def __init__(self, name: str, options: "StabilizedOptions"):
        self.name, self.options = name, options
        self.seed = int(options.seed)
        self.variance = bool(options.variance)
        warm_up_kernels()

    def derive(self):
        from derender.engine.motion.ward2003 import grey8_codes

        return lambda frame, out: grey8_codes(frame, out=out)

    def plan(self, access: FrameAccess) -> MatrixPlan:
        from derender.engine.motion.align import chain_transforms, transforms_to_shifts
        from derender.response.curves import DEFAULT_LAMBDA, DEFAULT_SAMPLES, check_usable_samples, grid_positions
        from derender.response.debevec1997 import calibrate_debevec_from_samples

        opts, seed, frames, t = self.options, self.seed, access.frames, access.times
        n = access.n
        h, w = access.shape
        # response.check_usable: grid samples settle it, unless some channel shows no usable code there
        ys, xs = grid_positions(h, w, DEFAULT_SAMPLES, seed)
        check_usable_samples(np.stack([f[ys, xs] for f in frames]), access.histograms)
        t0 = time.perf_counter()
        if access.aligned:                         # the engine chose the reference and registered the frames
            ref = int(access.reference)
            transforms, ainfo = np.repeat(np.eye(3)[None], n, axis=0), {}
        else:                                      # paper 1's rule on the 8-bit codes, Ward's MTB
            ref = select_reference(frames)
            transforms, ainfo = chain_transforms(access.planes, "translation", ref, seed=seed, threads=access.threads)
            access.release_planes()      # Ward's grey images (N bytes per pixel) are done with
        shifts = transforms_to_shifts(transforms)
        view = ShiftedFrames(frames, shifts)
        valid_view = view.valid_view if access.valid is None else HeldValid(access.valid)
        rows = -(-h * w // REF_PIXELS)     # the gate counts ~REF_PIXELS pixels per frame (every k-th row)
        if saturation_fraction(CodeFrameRows(view, rows), t) > HIDDEN_FRACTION:   # the in-memory path applies the mask
            raise NotStreamable("saturation below white (stabilize.saturation)")
        al = LazyAlignment(images=view, valid=valid_view, transforms=transforms,
                           method="none" if access.aligned else "translation",
                           reference=ref, shifts=shifts, info=ainfo)
        t1 = time.perf_counter()

        def calibrate():
            cur = unclipped_debevec(view.code_pixels, n, (h, w), t, seed=seed,
                                    exposure_rounds=opts.exposure_rounds, exponent_rounds=opts.exponent_rounds,
                                    shape_tie=opts.shape_tie, valid_at=None if access.valid is None else valid_view.pixels)
            if cur is not None:
                return cur
            ys, xs = grid_positions(h, w, DEFAULT_SAMPLES, seed)
            if access.valid is not None:       # only pixels every frame covers and agrees on
                keep = np.all(access.valid[:, ys, xs] != 0, axis=0)
                ys, xs = ys[keep], xs[keep]
            samples = np.stack([view.code_pixels(j, ys, xs) for j in range(n)]).astype(np.int32)

            def aligned_hists() -> np.ndarray:
                return np.stack([code_histograms(np.ascontiguousarray(view.codes(j))) for j in range(n)])

            return calibrate_debevec_from_samples(samples, t, aligned_hists, lam=DEFAULT_LAMBDA,
                                                  n_samples=DEFAULT_SAMPLES, sampling="grid", seed=seed, tie=CURVE_TIE)

        mode = "joint" if self.name == "stabilized-joint" else "reference"
        stab = stabilize_aligned(al, t, mode=mode, response=opts.response, gammas=opts.gammas,
                                 use_times=opts.use_times, path=opts.path, block=opts.block,
                                 max_blocks=opts.max_blocks, ransac_iter=opts.ransac_iter, seed=seed,
                                 calibrate=calibrate, exposure_rounds=opts.exposure_rounds,
                                 exponent_rounds=opts.exponent_rounds, shape_tie=opts.shape_tie)
        self.stab = stab
        self.align_s = t1 - t0
        plan = stabilized_plan(stab, opts.weight, opts.noise_weighting, shifts=shifts)
        if self.variance:
            from derender.engine.variance import SHARED_BOOTSTRAP, matrix_variance_tables

            plan.variance = matrix_variance_tables(plan.values, self.name)
            if self.name in SHARED_BOOTSTRAP:      # the shared term measured on the bracket's grid samples
                from derender.hdr.classic import bracket_variance
                from derender.response.curves import cluster_positions

                cy, cx = cluster_positions(h, w, DEFAULT_SAMPLES, seed)
                clusters = np.stack([view.code_pixels(j, cy, cx) for j in range(n)]).astype(np.int32)
                plan.variance = bracket_variance(plan.variance, self.name, True, clusters, t, access.histograms, seed)
        return plan

    def finish(self, result: HDRResult, access: FrameAccess) -> None:
        result.info.update(_merge_info(self.stab, self.options.weight, self.options.noise_weighting))
        result.info["method"] = self.name
        timings = result.info.setdefault("timings", {})
        timings.update({"align_s": self.align_s, **self.stab.info["timings"]})


# --------------------------------------------------------------------------- driver
@dataclass
class Stabilization:
    """Everything :func:`stabilize` found for a bracket.

    Attributes
    ----------
    mode : str
        ``"reference"`` (paper 1: ``matrices[j] = H_j`` maps image j's linear values onto
        the reference's, exposure ratio included) or ``"joint"`` (``matrices[j] = K_j``
        maps ``L_j / t_j`` into the common average rendering).
    reference : int
        reference image index (also the registration target).
    gammas : GammaEstimate
        display gammas; for the curve model the effective gamma of each image's curve.
    matrices : numpy.ndarray
        (N, 3, 3) H_j or K_j.
    alignment : Alignment
        :class:`derender.engine.motion.align.Alignment` (or :class:`LazyAlignment`).
    times : numpy.ndarray
        (N,) exposure times (s).
    curves : list
        per-image :class:`~derender.hdr.stabilize.curves.Curve` linearisations actually used.
    how : list
        per image, how its matrix was obtained.
    info : dict
        timings and decisions (response model, gamma trend).
    """

    mode: str
    reference: int
    gammas: GammaEstimate
    matrices: np.ndarray
    alignment: Any
    times: np.ndarray
    curves: list = field(default_factory=list)
    how: list = field(default_factory=list)
    info: dict = field(default_factory=dict)

    def linear_exposure(self, j: int) -> np.ndarray:
        """Stabilised image j (eq. 10) scaled to exposure ``radiance * t_j`` for the merge engine,
        float32, projected onto the non-negative orthant as the engine's kernel does
        (:func:`~derender.engine.kernels.stabilized_merge_rows`)."""
        lin = self.curves[j].lin(self.alignment.images[j])
        m = self.matrices[j]
        if self.mode == "reference":
            m = m * (self.times[j] / self.times[self.reference])
        return np.ascontiguousarray(np.maximum(lin @ m.T, 0.0), dtype=np.float32)


def stabilize(stack: Stack, *, reference: int | None = None, align: str = "translation", mode: str = "reference",
              response: str = "auto", gammas: Sequence[float] | None = None, use_times: bool = True,
              path: str = "auto", block: int = 2, max_blocks: int = 20000, low: float = FIT_LOW,
              high: float = FIT_HIGH, floor: float = FIT_FLOOR, ransac_iter: int = 100,
              seed: int = 0, exposure_rounds: int | None = None,
              exponent_rounds: int | None = None, shape_tie: float | None = None) -> Stabilization:
    """Paper 1, Algorithm 1 steps 1-3 (reference, registration, per-image linearisation and
    H_j), or the reference-free joint fit (``mode="joint"``).

    Parameters
    ----------
    stack : Stack
        The bracket.
    reference : int, optional
        The reference frame (index by exposure time); None: the best-exposed (paper 1's rule).
    align : {"translation", "homography", "none"}
        Registration: Ward's median-threshold bitmaps (translation) or features (homography).
    mode : {"reference", "joint"}
        H_j to the reference frame, or all K_j fitted jointly to the bracket's average rendering.
    response : {"auto", "power", "curve"}
        ``"power"``: paper 1's model, a display gamma per image (:func:`estimate_gammas`);
        ``"curve"``: a common non-parametric response (Debevec & Malik) with the per-image H_j
        on top (:func:`curve_model`; tone curves that are not a power law); ``"auto"``: the power
        model unless :func:`power_law_plausible` rejects its gammas (the choice and the gamma
        trend are in ``info``).
    gammas : sequence of float, optional
        Display gammas, one per image: skips the estimation.
    use_times : bool
        False estimates the gammas blind (without the exposure times).
    path, block, max_blocks, low, high, floor
        The fitting path, the block size and number of blocks, and the code range the fits use.
    ransac_iter, seed
        RANSAC iterations of the H_j fits and the seed of every random step.
    exposure_rounds : int, optional
        Curve model: rounds of per-frame exposure offsets re-estimated with the common curve
        (:func:`~derender.hdr.stabilize.filmic.unclipped_debevec`; default
        :data:`~derender.hdr.stabilize.filmic.CURVE_EXPOSURE_ROUNDS`).
    exponent_rounds : int, optional
        Curve model: rounds of per-frame relative exponents (the camera's per-frame display gamma)
        searched with the common curve (:mod:`~derender.hdr.stabilize.frame_exponents`; default
        :data:`~derender.hdr.stabilize.filmic.CURVE_EXPONENT_ROUNDS`).
    shape_tie : float, optional
        Curve model: weight of the tie of red's and blue's curve shapes to green's (equal codes stay
        near neutral; default :data:`~derender.hdr.stabilize.filmic.CURVE_SHAPE_TIE`, off).

    Returns
    -------
    Stabilization
        The aligned frames, per-image linearisations, matrices and ``info``.
    """
    if not isinstance(stack, Stack):
        raise InputError(f"stabilize() needs a Stack, got {type(stack).__name__}")
    _check_modes(mode, response)
    from derender.engine.motion.align import align_images
    from derender.response.curves import check_usable

    check_usable(stack)
    t0 = time.perf_counter()
    images = stack.images
    n = stack.n
    if reference is None:
        ref = select_reference(images)
    else:
        ref = int(reference)
        if not 0 <= ref < n:
            raise InputError(f"reference image {reference} is out of range 0..{n - 1}")
    al = align_images(images, method=align, reference=ref, seed=seed)
    hidden, hidden_frac = saturation_mask(al.images, stack.times)
    if hidden is not None:
        al.valid = al.valid & ~hidden
    t1 = time.perf_counter()
    stab = stabilize_aligned(al, stack.times, mode=mode, response=response, gammas=gammas, use_times=use_times,
                             path=path, block=block, max_blocks=max_blocks, low=low, high=high, floor=floor,
                             ransac_iter=ransac_iter, seed=seed, exposure_rounds=exposure_rounds,
                             exponent_rounds=exponent_rounds, shape_tie=shape_tie)
    stab.info["timings"] = {"align_s": t1 - t0, **stab.info["timings"]}
    stab.info["hidden_saturation"] = {"fraction": hidden_frac, "masked": hidden is not None}
    return stab


def _check_modes(mode: str, response: str) -> None:
    if mode not in ("reference", "joint"):
        raise InputError(f"mode must be 'reference' or 'joint', got {mode!r}")
    if response not in ("auto", "power", "curve"):
        raise InputError(f"response must be 'auto', 'power' or 'curve', got {response!r}")


def stabilize_aligned(al: Any, times: Sequence[float], *, mode: str = "reference", response: str = "auto",
                      gammas: Sequence[float] | None = None, use_times: bool = True, path: str = "auto",
                      block: int = 2, max_blocks: int = 20000, low: float = FIT_LOW, high: float = FIT_HIGH,
                      floor: float = FIT_FLOOR, ransac_iter: int = 100, seed: int = 0,
                      calibrate: Any = None, exposure_rounds: int | None = None,
                      exponent_rounds: int | None = None, shape_tie: float | None = None) -> Stabilization:
    """:func:`stabilize` after registration: linearisations and matrices of the aligned bracket ``al``.

    ``al`` is an :class:`derender.engine.motion.align.Alignment`, or a lazy equivalent with ``images``
    and ``valid`` offering ``shape`` and ``pixels(j, ys, xs)`` (the streaming path of
    :func:`derender.hdr.files.merge_files`, which also passes ``calibrate``, see
    :func:`curve_model`). The reference is ``al.reference``.
    """
    _check_modes(mode, response)
    t1 = time.perf_counter()
    ref = int(al.reference)
    times = np.asarray(times, dtype=np.float64)
    n = times.shape[0]
    blocks = make_blocks(al.images, al.valid, block, max_blocks, seed, times)
    info: dict = {}
    if gammas is not None:
        g = np.asarray(gammas, dtype=np.float64).reshape(-1)
        if g.size != n or not np.all(np.isfinite(g)) or np.any(g <= 0):
            raise InputError(f"gammas must be {n} positive numbers, got {np.asarray(gammas).tolist()}")
        ge = GammaEstimate(gammas=g, method="given")
        curves = [Curve(1.0, gamma=float(v)) for v in g]
    else:
        ge = curves = None
        screened = False
        if response == "auto":
            # quick trend first: clearly filmic brackets skip the full exponent search, whose
            # gammas power_law_plausible would reject anyway
            quick = screen_gamma_trend(blocks, times, low=low, high=high, floor=floor)
            info["screen_trend"] = quick
            screened = abs(quick) > SCREEN_TREND
            if screened:
                info["gamma_trend"] = quick
        if response == "power" or (response == "auto" and not screened):
            ge = estimate_gammas_blocks(blocks, times if use_times else None, low=low, high=high, floor=floor,
                                         max_gap=2, prior_sd=0.1, min_blocks=12, base=2.2, bounds=(1.0, 4.0),
                                         info={"block": block, "max_blocks": max_blocks})
            curves = [Curve(1.0, gamma=float(v)) for v in ge.gammas]
            info["gamma_trend"] = gamma_trend(ge.gammas, times)
            info["response"] = "power"
        if response == "curve" or (response == "auto" and (screened or not power_law_plausible(ge.gammas, times))):
            cc, cinfo = curve_model(blocks, al.images, times, low, high, floor, seed=seed, calibrate=calibrate,
                                    exposure_rounds=exposure_rounds, exponent_rounds=exponent_rounds,
                                    shape_tie=shape_tie)
            if ge is not None:
                cinfo["rejected_power_gammas"] = ge.gammas.tolist()
            ge = GammaEstimate(gammas=np.array([c.effective_gamma for c in cc]), method="curve", info=cinfo)
            curves = cc
            info["response"] = "curve"
            info["shape_tie"] = CURVE_SHAPE_TIE if shape_tie is None else float(shape_tie)
    t2 = time.perf_counter()
    mats, how = fit_colour_model(blocks, curves, ge, times, ref, mode, low=low, high=high, floor=floor, path=path,
                                 seed=seed, ransac_iter=ransac_iter, info=info)
    t3 = time.perf_counter()
    info["timings"] = {"response_s": t2 - t1, "matrices_s": t3 - t2}
    return Stabilization(mode=mode, reference=ref, gammas=ge, matrices=mats, alignment=al, times=times,
                         curves=curves, how=how, info=info)


def stabilized_merge(stab: Stabilization, weight: str = "trapezoid", noise_weighting: bool = True,
                     pixel_weights: np.ndarray | None = None) -> HDRResult:
    """Paper 1, Algorithm 1 step 4: weighted average of the stabilised linear images through
    :func:`derender.engine.float_merge.merge_linear`. H_j mixes channels, so a pixel of image j gets one
    weight for all channels, times its registration mask: the smallest trapezoid weight
    of its three channels (every channel usable), or, for pixels that no image exposes
    well in all channels, the trapezoid of the *brightest* channel. The latter keeps
    saturated and out-of-gamut colours whose weakest channel renders as 0 in every
    exposure (a blue sky behind a window), which would otherwise fall to the saturation
    fallback. The engine's fallback (a pixel without any weight) sees the brightest
    channel, so a pixel clipped everywhere takes the shortest exposure in all channels.
    ``noise_weighting`` (default; beyond the paper's plain trapezoid) multiplies the weight
    by the inverse variance of image j's radiance estimate for equal code noise,
    ``t_j^2 / (dL_j/dJ)^2``: a dark code of a short exposure, inverted through a steep
    curve, otherwise counts as much as a well-exposed one and dominates a linear average
    with its noise. Linear result: the reference's colour rendering, grey-balanced (:mod:`.grey_balance`)
    (``mode="reference"``, radiance per second of the reference's exposure) or the common
    average rendering (``mode="joint"``). ``pixel_weights`` (N, H, W) multiplies the
    weights (normalised per pixel). 8-bit stacks with integer alignment and no
    ``pixel_weights`` take the table path of :func:`merge_stabilized_table` (same result to 1e-5)."""
    from derender.engine.float_merge import merge_linear
    from derender.engine.weights import get_weight

    if pixel_weights is None and (stab.curves or not noise_weighting):     # a table form (stabilized_plan)
        codes = stack_codes_exact(stab.alignment.images)
        if codes is not None:
            return merge_stabilized_table(stab, weight, noise_weighting, codes=codes)

    wfun = get_weight(weight)
    al = stab.alignment
    n, h = al.images.shape[0], al.images.shape[1]
    lin = np.stack([stab.linear_exposure(j) for j in range(n)])
    valid = al.valid.astype(np.float32)
    # per image: all-channel weight (min over channels) and brightest-channel weight
    w_all = np.stack([np.asarray(wfun(al.images[j]), np.float32).min(axis=-1) for j in range(n)]) * valid
    w_max = np.stack([np.asarray(wfun(al.images[j].max(axis=-1)), np.float32) for j in range(n)]) * valid
    use_all = w_all.sum(axis=0) > 0
    wts = np.where(use_all[None], w_all, w_max)
    if noise_weighting:
        # inverse variance of the radiance estimate L_j / t_j for equal code noise:
        # var ~ (dL/dJ)^2 / t_j^2 (mean over channels), normalised per pixel for range
        inv = np.stack([stab.times[j] ** 2 / np.maximum(np.mean(stab.curves[j].dlin(al.images[j]) ** 2, axis=-1),
                                                           1e-30) for j in range(n)])
        inv = inv / np.maximum(inv.max(axis=0, keepdims=True), 1e-300)
        wts = (wts * inv).astype(np.float32)
    if pixel_weights is not None:
        # extra per-image, per-pixel reliability (e.g. inverse relative variance of a de-rendering model)
        pw = np.asarray(pixel_weights, dtype=np.float64)
        if pw.shape != wts.shape or not np.all(np.isfinite(pw)) or np.any(pw < 0):
            raise InputError(f"pixel_weights must be finite, non-negative, shape {wts.shape}")
        pw = pw / np.maximum(pw.max(axis=0, keepdims=True), 1e-300)
        wts = (wts * pw).astype(np.float32)
    # the engine's saturation fallback then sees the brightest channel of each pixel
    zmax = np.repeat(al.images.max(axis=-1, keepdims=True), 3, axis=-1)

    def weight_fn(j: int, block: np.ndarray) -> np.ndarray:
        if block.shape[0] != h:          # cannot happen with block_rows=h; keep the engine honest
            raise RuntimeError("stabilized merge expects the whole image in one block")
        return wts[j]

    info = stabilization_info(stab)
    return merge_linear(lin, stab.times, zmax, weight, weight_fn=weight_fn, channel_weights="min",
                        domain="linear", block_rows=h, info=info)


@dataclass(frozen=True, kw_only=True)
class StabilizedOptions:
    """The options of ``stabilized`` and ``stabilized-joint`` (:func:`merge_stabilized`,
    :func:`merge_stabilized_joint`), as their engine method, their float-stack merge and
    ``derender merge --option`` read them. The reference frame and the registration are the
    engine's (:class:`~derender.engine.motion.run.MotionOptions`; without them the method
    registers the frames itself to paper 1's reference by Ward's MTB).

    Attributes
    ----------
    response, gammas, use_times, path, block, max_blocks, ransac_iter, seed, exposure_rounds
        As :func:`stabilize`.
    exponent_rounds : int, optional
        As :func:`stabilize` (per-frame exponents of the curve model; off by default).
    shape_tie : float, optional
        As :func:`stabilize` (the curve model's tie of red's and blue's shapes to green's; off by
        default: ``-O shape_tie=1`` keeps equal codes neutral on pingpong but turns Memorial orange,
        docs/paper1.md).
    weight : str
        The merge's weight (paper 1: ``"trapezoid"``).
    noise_weighting : bool
        Also weight each frame's estimate by its inverse variance for equal code noise,
        ``t_j^2 / (dL_j/dJ)^2`` (:func:`stabilized_merge`).
    variance : bool
        Also give the per-pixel variance (:mod:`derender.engine.variance`; engine path only).
    """

    response: str = "auto"
    gammas: Sequence[float] | None = None
    use_times: bool = True
    path: str = "auto"
    weight: str = "trapezoid"
    noise_weighting: bool = True
    block: int = 2
    max_blocks: int = 20000
    ransac_iter: int = 100
    seed: int = 0
    exposure_rounds: int | None = None
    exponent_rounds: int | None = None
    shape_tie: float | None = None
    variance: bool = False

    def __post_init__(self) -> None:
        """Every value checked when the record is made, before any file is read."""
        check_choice("response", self.response, ("auto", "power", "curve"))
        check_choice("path", self.path, ("auto", "direct", "chain"))
        check_choice("weight", self.weight, WEIGHTS, allow_callable=True)
        for name in ("block", "max_blocks", "ransac_iter"):
            check_at_least(name, getattr(self, name), 1)
        for name in ("exposure_rounds", "exponent_rounds"):
            check_at_least(name, getattr(self, name), 0)
        if self.gammas is not None and not all(float(g) > 0 for g in self.gammas):
            raise InputError(f"gammas must be positive numbers, got {list(self.gammas)}")
        if self.shape_tie is not None and not (np.isfinite(float(self.shape_tie)) and float(self.shape_tie) >= 0):
            raise InputError(f"shape_tie must be a number >= 0, got {self.shape_tie}")


def stabilized_engine(options: StabilizedOptions) -> StabilizedMethod:
    """The engine form of ``stabilized`` (its registry entry's factory)."""
    return StabilizedMethod("stabilized", options)


def stabilized_joint_engine(options: StabilizedOptions) -> StabilizedMethod:
    """The engine form of ``stabilized-joint`` (its registry entry's factory)."""
    return StabilizedMethod("stabilized-joint", options)


def _stabilized_stack(name: str, stack: Stack, opts: StabilizedOptions) -> HDRResult:
    """Both stabilised merges on the float reference engine: :func:`stabilize` (paper 1's
    reference, Ward's MTB) + :func:`stabilized_merge` (16-bit stacks, saturation below white)."""
    if opts.variance:
        raise InputError(f"{name}: a variance needs 8-bit images and no saturation below white (the engine's "
                         "matrix kernel)")
    t0 = time.perf_counter()
    stab = stabilize(stack, mode="joint" if name == "stabilized-joint" else "reference", response=opts.response,
                     gammas=opts.gammas, use_times=opts.use_times, path=opts.path, block=opts.block,
                     max_blocks=opts.max_blocks, ransac_iter=opts.ransac_iter, seed=opts.seed,
                     exposure_rounds=opts.exposure_rounds, exponent_rounds=opts.exponent_rounds,
                     shape_tie=opts.shape_tie)
    t1 = time.perf_counter()
    res = stabilized_merge(stab, weight=opts.weight, noise_weighting=opts.noise_weighting)
    res.info.update({"method": name, "timings": dict(stab.info["timings"], merge_s=time.perf_counter() - t1,
                                                     total_s=time.perf_counter() - t0)})
    return res


def stabilized_stack(stack: Stack, options: StabilizedOptions) -> HDRResult:
    """``stabilized`` on the float reference engine (the registry's fallback)."""
    return _stabilized_stack("stabilized", stack, options)


def stabilized_joint_stack(stack: Stack, options: StabilizedOptions) -> HDRResult:
    """``stabilized-joint`` on the float reference engine (the registry's fallback)."""
    return _stabilized_stack("stabilized-joint", stack, options)


def merge_stabilized(stack: Stack, options: StabilizedOptions | Mapping[str, Any] | None = None, *,
                     motion: MotionOptions | None = None) -> HDRResult:
    """Pipeline-aware exposure fusion (paper 1, Algorithm 1): reference, registration,
    gamma_j, H_j (RANSAC), trapezoid-weighted merge; result in the reference's rendering.

    8-bit stacks run on the engine (:class:`StabilizedMethod`: the frames registered to paper
    1's reference by Ward's MTB, or by the engine's motion run when ``motion`` asks for a
    reference, another alignment or ghost removal); others (16-bit) on the float reference
    engine (:func:`stabilize` + :func:`stabilized_merge`), the same numbers to 1e-5.
    :func:`merge_stabilized_joint` takes the same options.

    Parameters
    ----------
    stack : Stack
        The bracket.
    options : StabilizedOptions or mapping, optional
        The method's options (:class:`StabilizedOptions`), or a mapping of them.
    motion : MotionOptions, optional
        Reference frame, alignment, ghost removal (:func:`derender.hdr.registry.merge`).

    Returns
    -------
    HDRResult
        Radiance in the reference frame's linear rendering (per second of its exposure);
        ``info``: reference, gammas, matrices, alignment.

    References
    ----------
    Paper 1 (``docs/paper1.md``): Algorithm 1, eqs. 4 and 9-10.
    """
    return merge(stack, "stabilized", options, motion=motion)


def merge_stabilized_joint(stack: Stack, options: StabilizedOptions | Mapping[str, Any] | None = None, *,
                           motion: MotionOptions | None = None) -> HDRResult:
    """Reference-free variant: all K_j fitted jointly to the bracket's average rendering
    (:func:`joint_colour_matrices`); the reference only chooses the registration target.
    Runs on the engine as :func:`merge_stabilized` does."""
    return merge(stack, "stabilized-joint", options, motion=motion)
