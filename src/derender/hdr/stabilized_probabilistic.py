"""``stabilized-probabilistic``: paper 1's stabilised merge weighted by paper 2's de-rendering variances.

Both papers together (paper 1 Algorithm 1; paper 2 Sec. 3.1). The stabilisation (reference,
registration, gamma_j or curves, H_j with RANSAC) is paper 1's
(:mod:`derender.hdr.stabilize`); the merge (Algorithm 1 step 4) weights image j's estimate
``H'_j L_j(z)`` by its trapezoid weight times the inverse *relative* variance of the pixel's
de-rendered RAW colour,

    w_j = w_trap(z_j) / r(z_j),     r(z) = max(mean_c var_c(z) / mean_c(z)^2, 1e-12),

with the model's MAP point and mean squared deviation about it (``model.predict(point="map")``).
Radiance estimated from image j has variance ``r_j L^2``, so for one pixel inverse-variance
weighting reduces to ``1 / r_j``; this replaces paper 1's noise weighting.

The weight depends only on the pixel's 8-bit colour, so on the engine it is one table over
the 2**24 colours (64 MB, :func:`colour_weight_table`), evaluated once per distinct colour of
the bracket and read by the matrix kernel (``MatrixPlan.colour_weights``) with the frames held
as codes: the memory of a stabilised merge plus that table. The float reference engine
(:func:`stabilized_probabilistic_stack`, for homography alignment or saturation below white)
holds per-pixel float64 weights and float images (9 x 24 MP: ~12 GB).

**Variance**. The merge's error has the probabilistic merge's sources (the model's
error shared by the frames that see a colour, the pixels' code noise, the pipeline's spatial
mixing; :mod:`derender.hdr.probabilistic_variance`), with the pipeline changes between frames
corrected by H_j. Its variance is paper 2's posterior's *relative* variance for the same pixel
(the probabilistic merge of the same frames with the shared-error variance), times the
stabilised radiance squared:

    Var L_c = k_stab r_c L_c^2,     r_c = Var_p,c / (L_p,c + s mean_c L_p)^2,

``L_p``, ``Var_p`` the probabilistic merge's radiance and variance, ``s`` its floor share (0.01,
so a channel projected to 0 keeps a finite relative variance); ``k_stab`` (:data:`K_STAB`) chosen
on the tuning families (``docs/uncertainty.md``). It costs a probabilistic merge on the held
frames (measured in the docs); the engine keeps this method's outputs whole (``holds_outputs``)
since the variance needs the merged radiance. Frames aligned by the engine take part only where
valid (the probabilistic pass reads the frames without the stabiliser's shifts).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult, Stack
from derender.engine.motion.run import MotionOptions
from derender.engine.plans import FrameAccess
from derender.hdr.probabilistic import as_model
from derender.hdr.registry import merge
from derender.hdr.stabilize.method import StabilizedMethod, StabilizedOptions

__all__ = [
    "K_STAB",
    "posterior_relative_variance",
    "colour_reliability",
    "colour_weight_table",
    "StabilizedProbabilisticMethod",
    "StabilizedProbabilisticOptions",
    "merge_stabilized_probabilistic",
    "stabilized_probabilistic_stack",
]


#: Scale of the probabilistic posterior's relative variance (tuning families; docs/uncertainty.md).
K_STAB = 1.5


def posterior_relative_variance(model, frames: np.ndarray, times: np.ndarray, threads: int | None = None,
                                valid: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Relative variance (H, W, 3) float64 of paper 2's posterior for held frames (N, H, W, 3) uint8
    sorted by ``times``: the probabilistic merge (shared-error variance) of the same frames,
    ``Var_p / (L_p + 0.01 mean_c L_p)^2`` (module docstring), and its ``variance_sources``."""
    from derender.derendering.base import model_camera_to_srgb
    from derender.engine.gaussian import merge_gaussian_frames
    from derender.hdr.probabilistic import ProbabilisticMethod
    from derender.hdr.registry import method_options

    space = "linear_srgb" if model_camera_to_srgb(model) is not None else "camera_rgb"
    method = ProbabilisticMethod(method_options("probabilistic", {"model": model, "colour_space": space}))
    n, h, w = frames.shape[:3]
    access = FrameAccess(times=np.asarray(times, dtype=np.float64), shape=(h, w), frames=frames, threads=threads,
                         valid=valid, aligned=valid is not None)
    plan = method.plan(access)
    res = merge_gaussian_frames(frames, plan, threads=threads, valid=valid)
    rad = res.radiance.astype(np.float64)
    share = method.shared.floor_share if method.shared is not None else 0.01
    den = rad + share * rad.mean(axis=-1, keepdims=True)
    rel = res.variance.astype(np.float64) / np.maximum(den * den, 1e-300)
    return np.where(np.isfinite(rel), rel, 1e6), res.info.get("variance_sources", {})


def _with_variance(res: HDRResult, rel: np.ndarray, sources: dict) -> None:
    """``res.variance = K_STAB rel L^2`` (float32, finite) and the sources in its info."""
    big = np.finfo(np.float32).max / 4
    lin = res.radiance.astype(np.float64)
    res.variance = np.clip(np.nan_to_num(K_STAB * rel * lin * lin, nan=big, posinf=big), 0.0, big).astype(np.float32)
    res.info["variance_sources"] = dict(sources)
    res.info["variance_model"] = "probabilistic posterior's relative variance x stabilised radiance^2"


def colour_reliability(model, colours: np.ndarray) -> np.ndarray:
    """Inverse relative variance ``1 / max(mean_c(var_c / mean_c^2), 1e-12)`` of the de-rendered
    RAW colour (the MAP point and the mean squared deviation about it) of each uint8 colour
    (M, 3): the per-colour weight of ``stabilized-probabilistic``."""
    mean, var = model.predict(np.ascontiguousarray(colours, dtype=np.uint8), point="map")
    rel = np.mean(var.astype(np.float64) / np.maximum(mean.astype(np.float64), 1e-12) ** 2, axis=-1)
    return 1.0 / np.maximum(rel, 1e-12)


def colour_weight_table(model, frames: np.ndarray, threads: int | None = None) -> np.ndarray:
    """:func:`colour_reliability` of every colour present in the held frames (N, H, W, 3) uint8
    as a (2**24,) float32 table indexed ``R << 16 | G << 8 | B`` (the engine's
    ``MatrixPlan.colour_weights``); absent colours hold 0 and are never read. The model is
    evaluated once per distinct colour (a photograph has 10^5-10^6 of them)."""
    from derender.derendering.apply import ColourIndexBuilder
    from derender.engine.gaussian import mark_colours_held

    builder = ColourIndexBuilder()
    if not mark_colours_held(frames, builder.present, threads):
        for f in frames:
            builder.add(f)
    packed = np.flatnonzero(builder.present)
    del builder
    colours = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.uint8)
    table = np.zeros(1 << 24, dtype=np.float32)     # pages of absent colour ranges stay unmapped
    chunk = 1 << 18                                   # the model's temporaries bounded
    for s in range(0, packed.shape[0], chunk):
        w = colour_reliability(model, colours[s:s + chunk])
        table[packed[s:s + chunk]] = np.clip(w, 1e-30, 1e12).astype(np.float32)
    return table


class StabilizedProbabilisticMethod(StabilizedMethod):
    """``stabilized-probabilistic`` on the engine: paper 1's stabilisation of
    :class:`~derender.hdr.stabilize.method.StabilizedMethod` (every frame held once as 8-bit
    codes, registration shifts, gamma_j / curves, H_j), merged by the matrix kernel with the
    trapezoid weight times the per-colour :func:`colour_reliability` table
    (:func:`colour_weight_table`, ``MatrixPlan.colour_weights``), no noise weighting. The
    in-memory path computed the same weights per pixel as an (N, H, W) float64 array (9 x 24
    MP: 1.7 GB, the whole merge ~12 GB); here they are one 64 MB table."""

    def __init__(self, options: "StabilizedProbabilisticOptions"):
        self.model = as_model(options.model)
        self.wants_variance = bool(options.variance)
        self.holds_outputs = self.wants_variance      # finish() then reads the merged radiance
        # the stabilised merge's own defaults, without noise weighting: the model's variances replace it
        full = StabilizedOptions(seed=options.seed, noise_weighting=False)
        super().__init__("stabilized-probabilistic", full)

    def plan(self, access: FrameAccess):
        plan = super().plan(access)
        t0 = time.perf_counter()
        plan.colour_weights = colour_weight_table(self.model, access.frames, access.threads)
        self.colour_s = time.perf_counter() - t0
        return plan

    def finish(self, result: HDRResult, access: FrameAccess) -> None:
        super().finish(result, access)
        if self.wants_variance and result.radiance is not None and access.frames is not None:
            t0 = time.perf_counter()
            rel, sources = posterior_relative_variance(self.model, access.frames, access.times, access.threads,
                                                       access.valid)
            _with_variance(result, rel, sources)
            result.info.setdefault("timings", {})["variance_s"] = time.perf_counter() - t0
        result.info.update({"model": getattr(self.model, "method", "?"), "noise_weighting": False,
                            "pixel_weights": "inverse relative variance of the model (per colour)"})
        result.info.setdefault("timings", {})["colour_weights_s"] = self.colour_s


@dataclass(frozen=True, kw_only=True)
class StabilizedProbabilisticOptions:
    """The options of ``stabilized-probabilistic`` (:func:`merge_stabilized_probabilistic`).

    Attributes
    ----------
    model : DerenderModel or path
        A de-rendering model.
    seed : int
        As :func:`~derender.hdr.stabilize.method.stabilize`.
    variance : bool
        Also give the per-pixel variance (paper 2's posterior relative variance times the
        radiance squared, :func:`posterior_relative_variance`; it costs a second, probabilistic
        pass over the frames).
    """

    model: Any
    seed: int = 0
    variance: bool = False


def merge_stabilized_probabilistic(stack: Stack, options: StabilizedProbabilisticOptions | Mapping[str, Any], *,
                                   motion: MotionOptions | None = None) -> HDRResult:
    """Both papers together: paper 1's stabilised merge weighted by paper 2's de-rendering variances.

    The stabilisation (reference, registration, gamma_j, H_j) is paper 1's; each image's
    weight is its trapezoid weight times the inverse *relative* variance of its pixels'
    de-rendered RAW colours, ``1 / mean_c(var_c / mean_c^2)``. The estimate of radiance
    from image j has variance ``r_j L^2`` for relative variance ``r_j`` and radiance L, so
    for the same pixel inverse-variance weighting reduces to weights ``1 / r_j``; this
    replaces paper 1's plain noise weighting.

    8-bit stacks run on the engine (:class:`StabilizedProbabilisticMethod`: the weight is a
    function of the pixel's colour, so one per-colour table replaces the per-pixel weights);
    others (saturation below white) on the float reference engine
    (:func:`stabilized_probabilistic_stack`), the same numbers to 1e-5.

    Parameters
    ----------
    stack : Stack
        An 8-bit bracket.
    options : StabilizedProbabilisticOptions or mapping
        The method's options (``model`` required), or a mapping of them.
    motion : MotionOptions, optional
        Reference frame, alignment, ghost removal (:func:`derender.hdr.registry.merge`).

    Returns
    -------
    HDRResult
        Radiance in the reference frame's linear rendering; with ``variance`` its variance.
    """
    return merge(stack, "stabilized-probabilistic", options, motion=motion)


def stabilized_probabilistic_stack(stack: Stack, options: StabilizedProbabilisticOptions) -> HDRResult:
    """``stabilized-probabilistic`` on the float reference engine (the registry's fallback):
    :func:`stabilize` (paper 1's reference, Ward's MTB) and
    :func:`~derender.hdr.stabilize.method.stabilized_merge` with per-pixel weights (N, H, W)
    float64 (~50 bytes per pixel and frame)."""
    from derender.hdr.stabilize import stabilize, stabilized_merge

    model = as_model(options.model)
    if stack.bit_depth == 16:
        raise InputError("de-rendering models take 8-bit images; this stack is 16-bit")
    t0 = time.perf_counter()
    stab = stabilize(stack, mode="reference", seed=options.seed)
    aligned = np.rint(np.clip(stab.alignment.images, 0.0, 1.0) * 255.0).astype(np.uint8)
    weights = np.empty(aligned.shape[:3], dtype=np.float64)
    for j in range(aligned.shape[0]):
        weights[j] = colour_reliability(model, aligned[j].reshape(-1, 3)).reshape(aligned.shape[1:3])
    res = stabilized_merge(stab, noise_weighting=False, pixel_weights=weights)
    if options.variance:
        rel, sources = posterior_relative_variance(model, stack.codes(), stack.times)
        _with_variance(res, rel, sources)
    res.info.update({"method": "stabilized-probabilistic", "model": getattr(model, "method", "?"),
                     "merge_seconds": time.perf_counter() - t0, "engine_path": "stack"})
    return res
