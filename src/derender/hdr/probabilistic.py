"""Probabilistic HDR (paper 2, Sec. 3.1, eq. 3): the product of de-rendered Gaussians.

Every exposure i gives, per pixel and channel, a Gaussian over the RAW colour,
``N(mu_i, s_i^2) = model.predict(J_i)``. Scaled to a common target exposure alpha_0
(here exposure time t_0), ``x_0 ~ N(mu_i t_0 / t_i, s_i^2 (t_0 / t_i)^2)``; with independent
exposures the posterior is the normalised product of these Gaussians:

    1 / s_0^2 = sum_i 1 / s_i'^2,     mu_0 = s_0^2 sum_i mu_i' / s_i'^2.

``censor=False`` (``domain="linear"``) is the paper's eq. 3 literally: no pixel is thrown away
by a threshold, a saturated JPEG value contributes through its (large) variance.

Default (``censor=True``, ``domain="log"``), beyond the paper, for log-space models (the GP,
which has ``predict_log``; others fall back to ``domain="linear"``):

* **Log-space product.** The GP's own Gaussian is over ``t = log(raw + eps)``. Each
  exposure gives a Gaussian over ``log x_0``: mean ``log(exp(mu_i) - eps) + log s_i``
  (``s_i = t_0 / t_i``, the log of the scaled predictive median) and variance
  ``s2_i (exp(mu_i) / (exp(mu_i) - eps))^2`` (delta method: a code near black, whose
  median is ~0, gets ~no weight instead of pulling the estimate to ``eps s_i``); eq. 3 is
  applied to these (a product of log-normals) and the product's raw moments
  ``exp(m + v/2)``, ``(exp(v) - 1) exp(2m + v)`` are returned. Raw-space Gaussians (eq. 3
  literally) misdescribe the skewed log-normal predictive.
* **Per-pixel code noise** (``code_noise``, default 2 codes). The GP is fitted to chart
  patches whose JPEG and RAW values are averaged over many pixels, so its variance
  describes the scatter of patch averages; a single scene pixel's code also carries the
  pixel's own noise after the ISP (simulated nikon-d5100, flat fields: per-pixel code sd
  0.4-2.3 codes, largest in the shadows), which the GP never saw (median ``|z|`` of single
  pixels 1.82, 0.67 expected). It is propagated through the de-rendering curve: each
  observation's log variance gets ``(code_noise * d log(raw median_c) / d code_c)^2``,
  the slope by central differences of the model's own log-median over +-2 codes
  (:func:`_log_slope`; on the GP's table six O(1) gathers per distinct colour). Codes
  where the curve is steep (near black, near clipping) are down-weighted, as a Debevec
  hat weight does, but by the model's own curve.
* **Model-error floor.** ``floor`` (log variance, default 0) is added to every
  observation's ``s2_i``. It was 0.01 (10 % relative) to stand in for what the code-noise
  term now models explicitly; with the code noise on, floor 0.01 loses 0.45-0.96 dB mean
  (table below).
* **Joint per-pixel weights.** The measured (uncensored) channels of one observation get
  the same precision ``1 / mean_c(s2_ic + floor)``, so the channels come from the same mix
  of exposures (no chroma from one exposure and luminance from another).
* **Per-channel censoring at ``clip_code`` (default 245).** A channel at code
  ``>= clip_code`` only says the RAW value is *at least* what the calibration saw for that
  code (a Gaussian centred on the training data's conditional mean would pull a light
  source brighter than anything in the calibration down, with a small variance). It
  gives a lower bound ``B = log(exp(mu - k sqrt(s2)) - eps) + log s_i`` (``k`` =
  ``_BOUND_SIGMAS`` = 1, the GP's 16 % quantile; it was 2, 2.3 %: table below) instead
  of a Gaussian; the other channels of that colour still count. 245, not 255: JPEG compression turns a clipped 255 into 249-254 (a lamp seen clipped in
  every exposure then "measured" at 7x its brightness too low, -10 to -17 dB on JPEG
  files); 250 was still fragile (night, JPEG files: 26.9 dB). The product is truncated
  below at the largest bound (truncated-normal moments, in log space). A bound more than
  3 sigma above the measured evidence is dropped: the GP's quantile for a clipped colour
  reflects how bright the calibration's clipped colours were, not the clipping level (a
  255 after a 7x longer exposure gave bounds ~1.5x above a well-exposed measurement;
  keeping the bound there put 1000+ ordinary sky pixels at relative variance > 0.5).
  A channel censored in every exposure gets the bound as its mean with log variance 1
  (relative variance e - 1 = 172 %): the variance map is high exactly where all exposures
  clip (measured, 192x128 brackets below: relative variance 1.72 on every channel
  censored in all exposures, <= 0.17 on every other channel with a code < 245 somewhere).

``domain="linear", censor=True`` is the previous default (raw-space product, a colour with
any channel at 255 censored as a whole, bound ``q_0.023 t_0 / t_i``, conflicts -> variance B^2).

Measured (simulated nikon-d5100, GP on 5000 chart pairs (seed 0), ``simulate_bracket(kind,
(192, 128), 7 exposures, pipeline="fixed", wb_preset="D65", seed)``; camera RGB -> linear
sRGB with the scene's white balance; PSNR L in dB, lstsq remap; seeds 2 / 3). "codes":
the simulator's uint8 codes; "JPEG": the same bracket written as JPEG files and read back.

    kind     input  Debevec      eq. 3        linear+censor  default
    indoor   codes  46.0 / 42.8  23.4 / 23.4  38.4 / 39.4    43.8 / 44.9
    outdoor  codes  43.5 / 45.3  23.3 / 23.4  42.7 / 43.2    43.2 / 43.5
    night    codes  43.7 / 42.8  23.3 / 23.4  39.2 / 40.0    43.4 / 44.6
    indoor   JPEG   38.3 / 36.0  23.4 / 23.4  36.0 / 35.7    44.0 / 44.0
    outdoor  JPEG   41.2 / 42.2  23.3 / 23.4  35.9 / 37.3    42.3 / 41.5
    night    JPEG   35.2 / 35.9  23.3 / 23.4  37.5 / 37.9    43.2 / 43.0

The default is at least as good as Debevec in 7 of 12 cases (5 of 6 JPEG-file cases, by
1-8 dB; it loses outdoor seed 3 by 0.7 dB); on the uncompressed codes it loses outdoor
(0.3 / 1.8 dB), indoor seed 2 (2.2 dB) and night seed 2 (0.3 dB).
Ablation (log space, codes, seed 2, before the later changes): whole-colour censoring
instead of per channel 38.2-42.8 (indoor 38.2 vs 43.8); median ``exp(m)`` instead of the
mean 0.5-2 dB worse at night; floor 0 / 0.003 / 0.01 / 0.03 / 0.1: best 0.01-0.03 (0.1
loses 1 dB outdoor seed 3). Excluding pixels seen unclipped by a single exposure (the
lamp), the log merge beats Debevec by 2-4 dB; the remaining gap on outdoor is
single-image de-rendering of the lamp's edge pixels (JPEG colours blended by demosaicking
and chroma denoising, e.g. a near-neutral JPEG code for a tungsten-coloured RAW), which no
merge of exposures can correct.

Current defaults (code noise 2, floor 0, bound at 1 sigma, GP fitted on the corrected
chart pairs of :func:`derender.chart.chart_pairs`), measured as probabilistic minus
Debevec PSNR L (dB) on 12 simulated nikon-d5100 brackets (outdoor / indoor / night x
seeds 0-3, ``simulate_bracket(kind, (192, 128), 7 exposures, pipeline="fixed",
wb_preset="D65", seed)``, uint8 codes, camera RGB -> linear sRGB with the scene's white
balance), and on seeds 4-7 (a check only, not used for any choice):

    chart  floor  code_noise  k    seeds 0-3: mean / wins   seeds 4-7: mean / wins
    old    0.01   0           2    +0.03 / 7 of 12          +0.46 / 7 of 12   (previous default)
    fixed  0.01   0           2    -0.48 / 6                -0.16 / 7
    fixed  0.01   2           2    -0.05 / 6                +0.27 / 7
    fixed  0.01   2           1    +0.02 / 7                +0.32 / 8
    fixed  0      2           2    +0.40 / 8                +1.04 / 9
    fixed  0      3           2    +0.44 / 7                +0.98 / 9
    fixed  0      2           1    +0.70 / 8                +1.28 / 9   (default)
    fixed  0      2           0.5  +0.20 / 7                +0.69 / 8
    fixed  0      2           0    -1.08 / 5                -0.54 / 5

With the defaults it loses outdoor seeds 1 / 3 (-0.25 / -0.23 dB) and indoor seeds 0 / 2
(-1.8 / -2.6 dB). PSNR L is set by ~100 lamp pixels (the 100 largest squared errors
carry 93-98 % of the MSE in all four): pixels seen below ``clip_code`` in at most one
exposure, i.e. single-image de-rendering of the lamp and its blended edges, and
channels censored in every exposure, whose estimate is a lower bound.
The table further below is the earlier (old chart, floor 0.01, k 2, no code noise) one.

The result is in the model's camera RGB (white balance fixed, as the calibration
pairs); with the camera's white balance and colour matrix stored in the model
(``derender calibrate`` from ``chart-pairs`` files stores them) it is converted to linear
sRGB, the variance propagated through the same 3x3 map (diagonal of ``A S A^T``).

**Non-negative output**. The product's moments are positive in camera RGB, but
``A`` has negative off-diagonals: a saturated colour's weak channel, or a colour outside the
sRGB gamut, comes out below 0. The mean is projected onto the non-negative orthant where ``A``
is applied (:func:`finite_outputs`, and the engine's compiled pass),

    L_c = max((A m)_c, 0),     var_c = (A S A^T)_cc + min((A m)_c, 0)^2,

the nearest radiance that can exist, with the posterior's mean squared deviation about it as
its variance (as the stabilised kernel projects each frame's estimate). Measured (GP of the
simulated D5100, 49,280 chart pairs; ``derender simulate --size 512x256 --seed 0``, camera
family, indoor scene): 10,888 negative values (the truth itself negative in 5,741 of those
channels) -> 0; PSNR L 45.69 -> 45.73 dB, R 41.15 -> 41.48; ``|z| < 2`` on the projected channels
0.31 -> 0.90. Projecting each exposure's colour before the product instead left 5,143 negative
values (a per-channel weighted geometric mean of in-gamut colours can leave the gamut) and
moved no PSNR. The real iPhone 6 bracket (5,541 negative values with this GP) is handheld and
this merge does not register the frames: 43 % of its negative pixels see a code fall by more than
20 with a longer exposure (4 % of all pixels).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import thread_count
from derender.core.options import check_at_least, check_choice
from derender.core.types import HDRResult, Stack
from derender.derendering.base import model_camera_to_srgb
from derender.engine.frames import ArrayFrames, NotStreamable
from derender.engine.motion.run import MotionOptions
from derender.engine.plans import FrameAccess, GaussianPlan, LogNormalMoments, MethodDefaults, SharedVariance
from derender.engine.run import run
from derender.hdr.lognormal import MAX_LOG, MAX_V, truncate_below, truncate_below_log
from derender.hdr.probabilistic_variance import K_MODEL, K_PIPE, K_SPATIAL
from derender.hdr.registry import merge

__all__ = [
    "CODE_NOISE",
    "product_of_gaussians",
    "as_model",
    "merge_probabilistic",
    "ProbabilisticOptions",
    "probabilistic_engine",
    "probabilistic_stack",
    "saturation_mask",
    "finite_outputs",
    "check_options",
    "ProbabilisticMethod",
    "log_product_moments",
]


_BOUND_SIGMAS = 1.0   # censoring bound: the GP's mu - k sigma quantile (module docstring)


#: Default per-pixel code noise (8-bit code sd) of the log-space product (module docstring).
CODE_NOISE = 2.0      # default per-pixel code noise (8-bit code sd) of the log-space product


def product_of_gaussians(means: list[np.ndarray] | np.ndarray, variances, floor: float = 1e-30
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of the normalised product of independent Gaussians (eq. 3)."""
    prec = None
    acc = None
    for m, v in zip(means, variances):
        p = 1.0 / np.maximum(np.asarray(v, dtype=np.float64), floor)
        prec = p if prec is None else prec + p
        acc = m * p if acc is None else acc + m * p
    var = 1.0 / prec
    return acc * var, var


def _lower_quantile(model, codes: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """2.3 % quantile of the predictive RAW distribution (exp(mu - 2 sigma) - eps for log-space models)."""
    if hasattr(model, "predict_log"):
        mu, s2 = model.predict_log(codes)
        return np.maximum(np.exp(np.asarray(mu) - 2.0 * np.sqrt(np.maximum(s2, 0.0))) - model.eps, 0.0)
    return np.maximum(np.asarray(mean, dtype=np.float64), 0.0)


def as_model(model: Any):
    """A :class:`~derender.derendering.base.DerenderModel`: ``model`` itself, or loaded from its path."""
    from derender.derendering.base import DerenderModel, load_model

    if isinstance(model, (str, os.PathLike)):
        return load_model(model)
    if not isinstance(model, DerenderModel):
        raise InputError("the probabilistic merge needs a de-rendering model (-m MODEL.npz)")
    return model


@dataclass(frozen=True, kw_only=True)
class ProbabilisticOptions:
    """The options of ``probabilistic`` (:func:`merge_probabilistic`), as its engine method, its
    in-memory merge and ``derender merge --option`` read them.

    Attributes
    ----------
    model : DerenderModel or path
        A de-rendering model (:func:`~derender.derendering.base.fit_model`, ``derender calibrate``).
    target_time : float
        alpha_0 in seconds: the result is radiance x t_0.
    colour_space : {"linear_srgb", "camera_rgb"}
        The output's space (linear sRGB needs the model's camera metadata).
    censor : bool
        Codes at or above ``clip_code`` are censored (a bound, not a value).
    domain : {"log", "linear"} or None
        ``"log"``: the log-space product (per-channel censoring, joint weights, model-error
        ``floor`` in log variance); ``"linear"``: the raw-space product (with ``censor=False``
        eq. 3 literally); None: ``"log"`` with ``censor=True``, eq. 3 with ``censor=False``
        (module docstring).
    floor, clip_code, code_noise
        Model-error floor (log variance), the censoring code, and the per-pixel code standard
        deviation propagated through the model's curve (log space only; 0 = off).
    variance_model : {"shared", "independent"}
        ``"shared"`` keeps the model's error shared across frames and adds the frames' spread
        (pipeline changes) and the spatial-mixing term, weighted by ``k_model``, ``k_pipe`` and
        ``k_spatial`` (:mod:`derender.hdr.probabilistic_variance`); ``"independent"`` is eq. 3's
        ``1 / sum p``. The radiance is the same for both.
    k_model, k_pipe, k_spatial : float
        Those weights.
    """

    model: Any
    target_time: float = 1.0
    colour_space: str = "linear_srgb"
    censor: bool = True
    domain: str | None = None
    floor: float = 0.0
    clip_code: int = 245
    code_noise: float = CODE_NOISE
    variance_model: str = "shared"
    k_model: float = K_MODEL
    k_pipe: float = K_PIPE
    k_spatial: float = K_SPATIAL

    def __post_init__(self) -> None:
        """Every value checked when the record is made, before any file is read."""
        check_choice("colour_space", self.colour_space, ("linear_srgb", "camera_rgb"))
        check_choice("domain", self.domain, (None, "log", "linear"))
        check_choice("variance_model", self.variance_model, ("shared", "independent"))
        if not 1 <= int(self.clip_code) <= 255:
            raise InputError(f"clip_code must be a code 1..255, got {self.clip_code}")
        if not float(self.target_time) > 0:
            raise InputError(f"target_time must be positive seconds, got {self.target_time}")
        for name in ("floor", "code_noise", "k_model", "k_pipe", "k_spatial"):
            check_at_least(name, getattr(self, name), 0.0, optional=False)


def probabilistic_engine(options: ProbabilisticOptions) -> "ProbabilisticMethod":
    """The engine form of :func:`merge_probabilistic` (its registry entry's factory); the
    raw-space product (``domain="linear"``) has none (:class:`NotStreamable`)."""
    method = ProbabilisticMethod(options)
    if method.domain != "log":
        raise NotStreamable("raw-space product")
    return method


def probabilistic_stack(stack: Stack, options: ProbabilisticOptions) -> HDRResult:
    """``probabilistic`` where the engine has no form for it (the registry's fallback): the
    raw-space product of deterministic models in memory (:func:`_product_linear`), or a stack
    whose values are not exactly 8-bit codes rounded to codes and merged on the engine."""
    if stack.bit_depth == 16:
        raise InputError("de-rendering models take 8-bit images; this stack is 16-bit")
    method = ProbabilisticMethod(options)
    codes = stack.codes()
    if method.domain == "log":
        return run(method, ArrayFrames(codes, stack.times))
    t0 = time.perf_counter()
    mean0, var0 = _product_linear(method.model, codes, stack.times, float(options.target_time), options.censor)
    radiance, variance = finite_outputs(mean0, var0, method.camera_to_srgb)
    return HDRResult(radiance=radiance, mask=saturation_mask(codes[0], codes[-1]), variance=variance,
                     info=_info(method.options, "linear", time.perf_counter() - t0))


def merge_probabilistic(stack: Stack, options: ProbabilisticOptions | Mapping[str, Any], *,
                        motion: MotionOptions | None = None) -> HDRResult:
    """Probabilistic HDR merge (paper 2 eq. 3) with a de-rendering model; returns mean and variance.

    Parameters
    ----------
    stack : Stack
        An 8-bit bracket.
    options : ProbabilisticOptions or mapping
        The method's options (:class:`ProbabilisticOptions`, where each is described), or a
        mapping of them; ``model`` (a de-rendering model or its path) is required.
    motion : MotionOptions, optional
        Reference frame, alignment, ghost removal (:func:`derender.hdr.registry.merge`).

    Returns
    -------
    HDRResult
        Radiance and variance (finite, non-negative); ``info["variance_sources"]``. The merge is
        deterministic (it takes no seed).

    References
    ----------
    Y. Xiong, K. Saenko, T. Darrell, T. Zickler, "From pixels to physics: Probabilistic color
    de-rendering", CVPR 2012, eq. 3 (``docs/paper2.md``).
    """
    return merge(stack, "probabilistic", options, motion=motion)


def _info(o: ProbabilisticOptions, domain: str, seconds: float) -> dict:
    return {"method": "probabilistic", "colour_space": o.colour_space, "target_time": o.target_time,
            "domain": domain, "censor": bool(o.censor), "floor": float(o.floor),
            "code_noise": float(o.code_noise) if domain == "log" else 0.0, "model": getattr(o.model, "method", "?"),
            "merge_seconds": seconds}


def saturation_mask(shortest: np.ndarray, longest: np.ndarray) -> np.ndarray:
    """HDRResult mask from the codes of the shortest and longest exposure (information only:
    the probabilistic merge discards no pixel)."""
    # channel by channel: NumPy's any/all over a last axis of 3 is ~10x slower
    sat_short = (shortest[..., 0] >= 255) | (shortest[..., 1] >= 255) | (shortest[..., 2] >= 255)
    dark_long = (longest[..., 0] <= 0) & (longest[..., 1] <= 0) & (longest[..., 2] <= 0)
    mask = np.zeros(shortest.shape[:-1], dtype=np.uint8)
    mask[sat_short] = HDRResult.MASK_BRIGHT
    mask[dark_long & ~sat_short] = HDRResult.MASK_DARK
    return mask


def finite_outputs(mean0: np.ndarray, var0: np.ndarray, a: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Camera RGB moments -> float32 radiance and variance, finite and non-negative by construction.

    Through ``a`` (camera -> linear sRGB) when given, variance by the diagonal of ``A S A^T``.
    The mean is then projected onto the non-negative orthant, ``max(A m, 0)``, the nearest
    radiance that can exist (a saturated colour's weak channel, or a colour outside
    the sRGB gamut, comes out below 0 through the matrix's negative off-diagonals, as in the
    stabilised merges' kernel, :func:`~derender.engine.kernels.stabilized_merge_rows`); a
    projected channel's variance is the posterior's mean squared deviation about the value
    output, ``v + (A m)_c^2``. The compiled :func:`~derender.engine.kernels.gaussian_moments_band`
    computes the same."""
    if a is not None:
        mean0 = mean0 @ a.T
        var0 = var0 @ (a * a).T
    with np.errstate(invalid="ignore", over="ignore"):
        short = np.minimum(mean0, 0.0)                 # below the orthant (NaN stays NaN)
        var0 = var0 + short * short
        mean0 = np.maximum(mean0, 0.0)
    big = np.finfo(np.float32).max / 4
    radiance = np.nan_to_num(np.clip(mean0, 0.0, big), nan=0.0, posinf=big).astype(np.float32)
    variance = np.nan_to_num(np.clip(var0, 0, big), nan=big, posinf=big).astype(np.float32)
    return radiance, variance


def check_options(model, options: ProbabilisticOptions) -> tuple[str, np.ndarray | None]:
    """The validated product domain (``"log"`` or ``"linear"``) and the camera -> linear sRGB
    matrix ``camera_to_srgb`` (None for camera RGB output) of ``options`` with ``model``."""
    o = options
    if not (np.isfinite(o.target_time) and o.target_time > 0):
        raise InputError("target_time must be a positive number of seconds")
    domain = o.domain
    if domain is None:
        domain = "log" if o.censor else "linear"
    if domain not in ("log", "linear"):
        raise InputError(f"domain must be 'log' or 'linear', got {domain!r}")
    if not (np.isfinite(o.floor) and o.floor >= 0):
        raise InputError("floor must be a non-negative log variance")
    if not (np.isfinite(o.code_noise) and 0 <= o.code_noise <= 64):
        raise InputError("code_noise must be a standard deviation in 8-bit codes, 0 .. 64")
    if not 1 <= int(o.clip_code) <= 255:
        raise InputError("clip_code must be in 1..255")
    colour_space = o.colour_space
    camera_to_srgb = None
    if colour_space == "linear_srgb":
        camera_to_srgb = model_camera_to_srgb(model)
        if camera_to_srgb is None:
            raise InputError("the model has no camera colour metadata (camera_to_srgb, wb); "
                             "use colour_space='camera_rgb' or calibrate from chart-pairs files")
    elif colour_space != "camera_rgb":
        raise InputError(f"colour_space must be 'linear_srgb' or 'camera_rgb', got {colour_space!r}")
    if domain == "log" and not hasattr(model, "predict_log"):
        domain = "linear"   # deterministic / raw-space models: eq. 3 in raw space
    return domain, camera_to_srgb


class ProbabilisticMethod(MethodDefaults):
    """Paper 2's probabilistic merge on the engine (log-space product; GP models).

    Every frame is held once as 8-bit codes; every distinct colour of the bracket is
    de-rendered once (:func:`_log_tables` on the union of the frames' colours, in
    chunks; for a GP with its interpolation table the compiled
    :func:`derender.engine.kernels.log_tables_rows`, in threads, as a colour-major table),
    and the engine's Gaussian kernel multiplies the exposures band by band and turns the
    sums into moments in the same pass (:func:`derender.engine.gaussian.merge_gaussian_frames`,
    :func:`derender.engine.kernels.gaussian_moments_band`). Raw-space models
    (deterministic baselines) have no log-space Gaussians: :func:`merge_probabilistic`
    multiplies them in memory (:func:`_product_linear`)."""

    name = "probabilistic"
    holds_frames = True
    warm_up = "gaussian"          # the engine loads its compiled kernel while the frames decode

    def __init__(self, options: ProbabilisticOptions):
        self.model = as_model(options.model)
        self.options = options
        self.domain, self.camera_to_srgb = check_options(self.model, options)
        vm = options.variance_model
        if vm not in ("shared", "independent"):
            raise InputError(f"variance_model must be 'shared' or 'independent', got {vm!r}")
        k_model, k_pipe, k_spatial = float(options.k_model), float(options.k_pipe), float(options.k_spatial)
        if not all(np.isfinite(k) and k >= 0 for k in (k_model, k_pipe, k_spatial)):
            raise InputError("k_model, k_pipe and k_spatial must be non-negative numbers")
        self.shared = SharedVariance(k_model, k_pipe, k_spatial) if vm == "shared" else None

    def plan(self, access: FrameAccess) -> GaussianPlan:
        from derender.derendering.apply import ColourIndexBuilder
        from derender.engine.gaussian import mark_colours_held

        if self.domain != "log":
            raise NotStreamable("raw-space product")
        opts, a = self.options, self.camera_to_srgb
        t0 = time.perf_counter()
        builder = ColourIndexBuilder()
        if not mark_colours_held(access.frames, builder.present, access.threads):   # compiled, in threads
            for f in access.frames:
                builder.add(f)
        index = builder.finish()
        colours = np.ascontiguousarray(index.codes, dtype=np.uint8)
        # compiled tables in the engine's threads, colour-major for the fused pass where the index
        # has a look-up table; NumPy's serial (threads measured no faster under load)
        compiled = _compiled_tables(self.model, colours) is not None
        fused = compiled and getattr(index, "lut", None) is not None
        planes = _log_planes(self.model, colours, float(opts.floor), int(opts.clip_code),
                             opts.censor, code_noise=float(opts.code_noise),
                             threads=access.threads if compiled else 1, colour_major=fused)
        shared = self.shared
        if shared is not None:      # the model's log sd per colour (shared-error variance)
            from derender.hdr.probabilistic_variance import add_spatial, fill_model_sd, shared_log_moments

            planes = fill_model_sd(self.model, colours, planes, float(opts.floor), int(opts.clip_code),
                                   opts.censor, fused, _compiled_tables(self.model, colours) if fused else None,
                                   threads=access.threads)
        censor = bool(opts.censor)
        self.distinct = int(index.packed.shape[0])
        self.t_plan = t0

        def moments(prec: np.ndarray, acc: np.ndarray, bound: np.ndarray, extra=None
                    ) -> tuple[np.ndarray, np.ndarray]:
            if extra is not None:        # shared-error variance, spatial term on the block's output
                mean0, var0, terms = shared_log_moments(prec, acc, bound, extra, censor=censor,
                                                        k_model=shared.k_model, k_pipe=shared.k_pipe,
                                                        max_log=MAX_LOG, max_v=MAX_V)
                rad, var = finite_outputs(mean0, var0, a)
                add_spatial(rad, var, terms, extra[4], shared.k_spatial, shared.floor_share)
                return rad, var
            return finite_outputs(*log_product_moments(prec, acc, bound, censor), a)

        return GaussianPlan(planes=None if fused else planes, table=planes if fused else None, index=index,
                            log_scales=np.array([np.log(opts.target_time / t) for t in access.times]),
                            moments=moments, mask=saturation_mask,
                            lognormal=LogNormalMoments(censor, MAX_LOG, MAX_V, a), shared=shared)

    def finish(self, result: HDRResult, access: FrameAccess) -> None:
        info = _info(self.options, self.domain, time.perf_counter() - self.t_plan)
        info["distinct_colours"] = self.distinct
        info["variance_model"] = "shared" if self.shared is not None else "independent"
        if self.shared is not None:
            info.update(k_model=self.shared.k_model, k_pipe=self.shared.k_pipe, k_spatial=self.shared.k_spatial)
        result.info.update(info)


def _product_linear(model, codes: np.ndarray, times: np.ndarray, target_time: float, censor: bool
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3 in raw space (``censor``: colours with a channel at 255 as lower bounds); camera RGB."""
    n, h, w = codes.shape[:3]
    prec = np.zeros((h, w, 3), dtype=np.float64)
    acc = np.zeros((h, w, 3), dtype=np.float64)
    bound = np.zeros((h, w, 3), dtype=np.float64)
    for i in range(n):
        mean, var = model.predict(codes[i])
        scale = float(target_time / times[i])
        v = np.maximum(var.astype(np.float64) * scale * scale, 1e-30)
        p = 1.0 / v
        if censor:
            clipped = np.any(codes[i] >= 255, axis=-1)
            if clipped.any():
                low = _lower_quantile(model, codes[i][clipped], mean[clipped]) * scale
                bound[clipped] = np.maximum(bound[clipped], low)
                p = np.where(clipped[..., None], 0.0, p)
        prec += p
        acc += mean.astype(np.float64) * scale * p
    with np.errstate(divide="ignore", invalid="ignore"):
        var0 = np.where(prec > 0, 1.0 / prec, np.inf)
        mean0 = np.where(prec > 0, acc * var0, 0.0)
    if censor:
        mean0, var0 = truncate_below(mean0, var0, bound)
    return mean0, var0


def _log_slope(model, colours: np.ndarray, mu: np.ndarray, step: int = 2) -> np.ndarray:
    """``d log(raw median_c) / d code_c`` per channel of (M, 3) uint8 colours: central differences
    of the model's own log-median over +-``step`` codes of that channel (one-sided at 0 / 255);
    float64 (M, 3). On the GP's interpolation table these are O(1) gathers per colour."""
    eps = float(getattr(model, "eps", 0.0))
    c16 = colours.astype(np.int16)
    out = np.empty(colours.shape, dtype=np.float64)
    for ch in range(3):
        ends = []
        for d in (step, -step):
            x = c16.copy()
            x[:, ch] = np.clip(x[:, ch] + d, 0, 255)
            m = model.predict_log(x.astype(np.uint8))[0][:, ch]
            m = np.clip(np.nan_to_num(np.asarray(m, dtype=np.float64), nan=0.0), -MAX_LOG, MAX_LOG)
            ends.append((np.log(np.maximum(np.exp(m) - eps, 1e-30)), x[:, ch]))
        (lu, cu), (ld, cd) = ends
        out[:, ch] = (lu - ld) / np.maximum(cu - cd, 1)
    return out


def _log_tables(model, colours: np.ndarray, floor: float, clip_code: int, censor: bool,
                per_channel: bool = True, code_noise: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What one observation of each colour (uint8 (M, 3)) contributes to the log-space product,
    before its exposure scaling ``log(t_0 / t_i)`` is added (a function of the colour alone,
    so computed once per distinct colour): the log raw median ``log(exp(mu) - eps)``, the
    joint precision of the measured channels (0 where censored) and the censoring lower
    bound (``-inf`` where measured); float64 (M, 3) each. See the module docstring."""
    eps = float(getattr(model, "eps", 0.0))
    tiny = 1e-30
    mu, s2 = model.predict_log(colours)
    mu = np.clip(np.nan_to_num(np.asarray(mu, dtype=np.float64), nan=0.0), -MAX_LOG, MAX_LOG)
    s2 = np.clip(np.nan_to_num(np.asarray(s2, dtype=np.float64), nan=1e6), 1e-12, 1e6)
    # log of the raw median, var by the delta method
    e = np.exp(mu)
    r = np.maximum(e - eps, tiny)
    lg = np.log(r)
    s2l = np.minimum(s2 * (e / r) ** 2, 1e6) + floor
    if code_noise > 0:
        # per-pixel code noise through the de-rendering curve (module docstring)
        s2l = np.minimum(s2l + (code_noise * _log_slope(model, colours, mu)) ** 2, 1e6)
    clipped = np.zeros(colours.shape, dtype=bool)
    low = np.full(colours.shape, -np.inf)
    if censor:
        clipped = colours >= clip_code
        if not per_channel:
            clipped = np.repeat(np.any(clipped, axis=-1, keepdims=True), 3, axis=-1)
        if clipped.any():
            low = np.where(clipped, np.log(np.maximum(np.exp(mu - _BOUND_SIGMAS * np.sqrt(s2)) - eps, tiny)),
                               -np.inf)
    # joint per-pixel weight: one precision for the colour's measured (uncensored) channels
    n_ok = np.sum(~clipped, axis=-1, keepdims=True)
    mean_s2 = np.sum(np.where(clipped, 0.0, s2l), axis=-1, keepdims=True) / np.maximum(n_ok, 1)
    p = np.where(clipped | (n_ok == 0), 0.0, 1.0 / np.maximum(mean_s2, 1e-12))
    return lg, p, low


def log_product_moments(prec: np.ndarray, acc: np.ndarray, bound: np.ndarray, censor: bool
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Raw-space mean and variance (..., 3) of the (censored) log-normal product, camera RGB,
    from the log-space sums of :class:`~derender.engine.gaussian.LogGaussianProduct` (3, ...)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(prec > 0, 1.0 / prec, np.inf)
        m = np.where(prec > 0, acc * v, 0.0)
    if censor:
        m, v = truncate_below_log(m, v, bound)
    m = np.clip(m, -MAX_LOG, MAX_LOG)
    v = np.clip(v, 0.0, MAX_V)
    with np.errstate(over="ignore"):
        mean0 = np.exp(m + 0.5 * v)
        var0 = np.expm1(v) * np.exp(2.0 * m + v)
    return np.moveaxis(mean0, 0, -1), np.moveaxis(var0, 0, -1)


def _compiled_tables(model, colours: np.ndarray) -> tuple | None:
    """The GP's interpolation tables for :func:`derender.engine.kernels.log_tables_rows` (the
    compiled :func:`_log_tables`), or None where that kernel does not apply (other models, exact
    predictions, colours that are not a contiguous (M, 3) uint8 array)."""
    from derender.derendering.local_gp import LocalGPModel

    if (not isinstance(model, LocalGPModel) or type(model).predict_log is not LocalGPModel.predict_log
            or getattr(model, "_table", None) is None or not model.fitted or colours.dtype != np.uint8
            or colours.ndim != 2 or colours.shape[1] != 3 or not colours.flags.c_contiguous):
        return None
    table = model._table
    tabs = table._gb_tables()
    if len(tabs) != 2:
        return None
    return (tabs[0], tabs[1], np.ascontiguousarray(table._lut_lo, dtype=np.int64),
            np.ascontiguousarray(table._lut_w, dtype=np.float32))


def _log_planes(model, colours: np.ndarray, floor: float, clip_code: int, censor: bool,
                *, per_channel: bool = True, chunk: int = 1 << 18, code_noise: float = 0.0,
                threads: int | None = 1, colour_major: bool = False) -> np.ndarray:
    """:func:`_log_tables` as contiguous (9, M) planes ``[lg; p; low]`` for :meth:`_LogProduct.add_rows`,
    computed ``chunk`` colours at a time (72 bytes per colour, temporaries bounded), after the
    first chunk in ``threads`` threads (None: all CPUs). For a GP with an interpolation table the
    compiled :func:`derender.engine.kernels.log_tables_rows` computes them (all chunks in threads);
    ``colour_major`` (compiled only): the (M, 8) table of
    :func:`derender.engine.kernels.gaussian_moments_band` instead, rows 64-byte aligned."""
    compiled = _compiled_tables(model, colours)
    if colour_major:
        if compiled is None:
            raise ValueError("colour-major tables need the compiled kernel (_compiled_tables)")
        m = colours.shape[0]
        raw = np.empty(8 * m + 8, dtype=np.float64)      # rows on 64-byte cache lines
        off = (-raw.ctypes.data % 64) // 8
        planes = raw[off:off + 8 * m].reshape(m, 8)
    else:
        planes = np.empty((9, colours.shape[0]), dtype=np.float64)
    if compiled is not None:
        from derender.engine.kernels import log_tables_rows

        chunk = max(1, min(chunk, -(-colours.shape[0] // max(1, 4 * thread_count(threads)))))
        args = (*compiled, float(getattr(model, "eps", 0.0)), float(floor), int(clip_code), bool(censor),
                bool(per_channel), float(code_noise), 2, _BOUND_SIGMAS, MAX_LOG, planes, bool(colour_major))

    def one(s: int) -> None:
        if compiled is not None:
            log_tables_rows(colours, s, min(s + chunk, colours.shape[0]), *args)
            return
        part = _log_tables(model, colours[s:s + chunk], floor, clip_code, censor, per_channel, code_noise)
        for k, arr in enumerate(part):
            planes[3 * k:3 * k + 3, s:s + chunk] = arr.T

    starts = list(range(0, colours.shape[0], chunk))
    if not starts:
        return planes
    if compiled is None:
        one(starts[0])      # the first chunk alone: the model's lazily built tables are made once
    rest = starts if compiled is not None else starts[1:]
    nthreads = min(thread_count(threads), len(rest))
    if nthreads > 1:        # chunks are independent (disjoint columns): the bytes do not depend on threads
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(nthreads, thread_name_prefix="derender-planes") as ex:
            list(ex.map(one, rest))
    else:
        for s in rest:
            one(s)
    return planes
