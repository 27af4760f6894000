"""The classic merges: Debevec & Malik (1997) and Robertson, Borman & Stevenson (2003).

Both recover one response curve per channel for the whole bracket
(:mod:`derender.response`) and average the per-image radiance estimates on the engine
(:mod:`derender.engine.run`): eq. 6 of Debevec & Malik in the log domain, Robertson's ML
estimate ``sum w t I / sum w t^2`` in the linear domain. Both stream: the calibration
reads the codes of sampled pixels (pass 1), the merge adds one frame at a time (pass 2),
through 256-entry tables (:class:`~derender.engine.plans.TablePlan`).

Colour balance: each channel's curve is known only up to its own offset; the
merges keep ``g_G(128) = 0`` and offset R and B so that neutral colours stay neutral
(:func:`derender.response.curves.balance_channels`: the median log difference between
channels over the near-neutral, well-exposed sampled pixels of every frame, else along
the grey axis), instead of the paper's ``g(128) = 0`` in every channel.

Stacks whose values are not 8-bit codes (16-bit TIFFs) have no table form: they go to
the float reference engine (:func:`derender.engine.float_merge.merge_linear`), which is
also what the table engine is tested against.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from derender.core.errors import InputError
from derender.core.options import check_at_least, check_choice
from derender.core.types import HDRResult, Stack
from derender.engine.float_merge import merge_linear
from derender.engine.motion.run import MotionOptions
from derender.engine.plans import FrameAccess, MethodDefaults, TablePlan
from derender.engine.run import ENGINES
from derender.engine.tables import curve_value_tables, weight_table
from derender.engine.variance import variance_tables
from derender.engine.weights import WEIGHTS, black_codes, floor_weights
from derender.hdr.registry import merge
from derender.response.curves import (
    DEFAULT_SAMPLES,
    DEFAULT_TIE,
    check_usable,
    check_usable_samples,
    cluster_positions,
    histogram_samples,
)

#: Smoothness weight lambda of the Debevec *merge*'s calibration (``merge_debevec``, ``--method
#: debevec``; :func:`~derender.response.debevec1997.calibrate_debevec` itself keeps the
#: response package's :data:`~derender.response.curves.DEFAULT_LAMBDA` = 30). With 2-stop
#: brackets the data constrain ``g`` only between codes one exposure step apart; the shape
#: inside a step is left to the smoothness term, and lambda 30 let it ripple by +-15 % with
#: the period of one step (measured against the true curve on the luminance family's
#: ``camera`` style with a fixed pipeline: exp(g - g_true) 0.84 at code 80, 1.04 at 118, 0.84
#: at 160, 1.12 at 200, seed 1). Spot-calibrated linearity, median abs error / worst decade
#: (``benchmarks/bench_linearity_causes.py``; seeds 0, 1, 2; tuning renderings): lambda 30:
#: gamma 1.8-2.4 % / 1.034, fixed camera style 1.6-6.4 % / 1.106; 60: gamma 1.1-1.3 % /
#: 0.989, fixed camera style 1.0-3.0 % / 1.046; 100: 1.0-1.1 % / 1.010 and 0.9-1.6 % / 1.020;
#: 200: 0.9-1.0 % / 1.021 and 0.8-0.9 % / 1.008. 60, not 100: on the still bracket of
#: ``tests/engine/test_motion_engine.py`` ghost removal's change of the static error, bounded by
#: 5 %, is 2.7 % at 30, 2.2 % at 60 and 9.2, 7.7, 8.0, 11.8 % at 70, 80, 100, 200 (not
#: monotone; the plain merge's own static error falls from 0.273 to 0.257 to 0.244). On the
#: auto-pipeline renderings (``paper``, ``camera``) lambda moves nothing (the frames' own
#: gammas and gains dominate: docs/luminance.md).
MERGE_LAMBDA = 60.0

__all__ = ["MERGE_LAMBDA", "white_weights", "bracket_variance", "DebevecOptions", "RobertsonOptions", "DebevecMethod", "RobertsonMethod",
           "merge_debevec", "merge_robertson", "debevec_stack", "robertson_stack"]


#: The ways a pixel's channels share their weights (the table engine's modes).
CHANNEL_WEIGHTS = ("mean", "min", "independent", "brightest", "min_else_brightest")


@dataclass(frozen=True, kw_only=True)
class DebevecOptions:
    """The options of ``debevec`` (:func:`merge_debevec`), as its engine method, its float-stack
    merge and ``derender merge --option`` read them. Invalid values are refused when the record
    is made.

    Attributes
    ----------
    curves : ResponseCurves, optional
        Skip the calibration and merge with these curves (:class:`~derender.response.curves.ResponseCurves`,
        e.g. a camera profile's).
    lam, n_samples, sampling, seed, tie
        The calibration (:func:`~derender.response.debevec1997.calibrate_debevec`, always with the
        paper's hat weights): smoothness lambda (None: :data:`MERGE_LAMBDA`), number of samples (``"grid"`` samples in
        uniform regions, or ``"histogram"``), the grid's seed, the channel tie (None: the default).
    weight, domain, channel_weights
        The merge's weight (``"gaussian"``, ``"hat"``, ...), averaging domain (``"log"`` or
        ``"linear"``) and how a pixel's channels share weights (``"mean"``, ``"independent"``,
        ``"min"``).
    block_rows : int, optional
        The engine's row blocks.
    engine : {"auto", "table", "reference"}
        ``"auto"`` merges 8-bit stacks on the engine's 256-entry tables (equal to the reference
        to ~1e-6 relative), ``"table"`` insists on it, ``"reference"`` always uses
        :func:`~derender.engine.float_merge.merge_linear`.
    censor : bool
        Codes that stopped following the exposure (a channel saturated below the top code) are
        bounds, not data, in the calibration
        (:func:`~derender.response.debevec1997.censored_observations`); False: the paper's system.
    variance : bool
        Also give the per-pixel variance of the radiance (:mod:`derender.engine.variance`: noise,
        quantisation, frame disagreement, shared model error; 8-bit stacks).
    """

    curves: Any = None
    lam: float | None = None
    n_samples: int | None = None
    sampling: str = "grid"
    seed: int = 0
    weight: str = "gaussian"
    domain: str = "log"
    channel_weights: str = "mean"
    block_rows: int | None = None
    engine: str = "auto"
    tie: float | None = None
    censor: bool = True
    variance: bool = False

    def __post_init__(self) -> None:
        if self.sampling not in ("grid", "histogram"):
            raise InputError(f"unknown sampling method {self.sampling!r}; use 'grid' or 'histogram'")
        if self.n_samples is not None and int(self.n_samples) < 1:
            raise InputError(f"n_samples must be positive, got {self.n_samples}")
        _check_common(self)
        check_choice("domain", self.domain, ("log", "linear"))
        check_choice("channel_weights", self.channel_weights, CHANNEL_WEIGHTS)
        check_at_least("lam", self.lam, 0.0)


@dataclass(frozen=True, kw_only=True)
class RobertsonOptions:
    """The options of ``robertson`` (:func:`merge_robertson`).

    Attributes
    ----------
    curves : ResponseCurves, optional
        Skip the calibration and merge with these curves.
    n_iter, max_pixels, seed, tie
        The calibration: iterations, pixels sampled (seeded), the channel tie (None: the default).
    weight : str
        The calibration's and the merge's level weight.
    censor : bool
        Observations that stopped following the exposure (a channel at the camera's white or
        stuck below it, the rim of a clipped region) are bounds, not data, in the calibration, and codes at or above a channel's white get no weight in the
        merge (:func:`~derender.response.robertson2003.calibration_bounds`); False: every
        observation is data (the former calibration).
    block_rows, engine, variance
        As :class:`DebevecOptions`.
    """

    curves: Any = None
    n_iter: int = 30
    max_pixels: int = 40_000
    weight: str = "gaussian"
    seed: int = 0
    block_rows: int | None = None
    engine: str = "auto"
    tie: float | None = None
    censor: bool = True
    variance: bool = False

    def __post_init__(self) -> None:
        _check_common(self)
        check_at_least("n_iter", self.n_iter, 1)
        check_at_least("max_pixels", self.max_pixels, 1)


def _check_common(opts) -> None:
    """The checks both classic records share (made before any file is read)."""
    check_choice("weight", opts.weight, WEIGHTS, allow_callable=True)
    check_choice("engine", opts.engine, ENGINES)
    check_at_least("block_rows", opts.block_rows, 1)
    check_at_least("tie", opts.tie, 0.0)


class DebevecMethod(MethodDefaults):
    """Debevec & Malik (1997) on the engine: grid (or histogram) samples, Sec. 2.1 curves, eq. 6 tables.

    Grid samples that see a clipped neighbour while unclipped themselves are left out
    (:func:`~derender.response.curves.uniform_samples`).
    """

    name = "debevec"
    sample_cluster = 9          # grid samples come as 3x3 clusters (response.curves.cluster_positions)

    def __init__(self, options: DebevecOptions):
        self.options = options
        self.curves = options.curves
        self.variance = bool(options.variance)
        self.tie = DEFAULT_TIE if options.tie is None else float(options.tie)
        self.lam = MERGE_LAMBDA if options.lam is None else float(options.lam)
        self.n_samples = DEFAULT_SAMPLES if options.n_samples is None else int(options.n_samples)
        self.sampling, self.seed = options.sampling, int(options.seed)
        self.weight, self.domain, self.channel_weights = options.weight, options.domain, options.channel_weights
        self.block_rows = options.block_rows
        self.censor = bool(options.censor)
        self.wants_histograms = self.sampling == "histogram"

    def sample_positions(self, h: int, w: int):
        return cluster_positions(h, w, self.n_samples, self.seed) if self.sampling == "grid" else None

    def plan(self, access: FrameAccess) -> TablePlan:
        from derender.response.curves import uniform_samples
        from derender.response.debevec1997 import calibrate_debevec_from_samples

        samples = (uniform_samples(access.samples, self.n_samples) if self.sampling == "grid"
                   else histogram_samples(access.histograms(), self.n_samples))
        check_usable_samples(samples, access.histograms)
        curves = self.curves
        if curves is None:
            curves = calibrate_debevec_from_samples(samples, access.times, access.histograms, lam=self.lam,
                                                    n_samples=self.n_samples, sampling=self.sampling, seed=self.seed,
                                                    balance=self.sampling == "grid", tie=self.tie,
                                                    censor=self.censor)
        self.fitted = curves
        values = curve_value_tables(curves, access.times, self.domain)
        self.black = black_codes(access.samples, access.times) if access.samples is not None else [0, 0, 0]
        weights = floor_weights(white_weights(weight_table(self.weight), curves), self.black)
        return TablePlan(values=values, weights=weights,
                         channel_weights=self.channel_weights,
                         domain=self.domain, block_rows=self.block_rows,
                         variance=self._variance(values, self.domain, access) if self.variance else None)

    def _variance(self, values, domain: str, access: FrameAccess):
        """The plan's :class:`~derender.engine.variance.VarianceModel`; its ``shared`` term from the
        bracket's curve spread when the curves were fitted here (:func:`bracket_variance`)."""
        return bracket_variance(variance_tables(values, domain, "debevec"), "debevec", self.curves is None,
                                access.samples, access.times, access.histograms, self.seed)

    def finish(self, result: HDRResult, access: FrameAccess) -> None:
        result.info.update({"method": "debevec", "curves": self.fitted, "black_codes": self.black,
                            "weight": self.weight if isinstance(self.weight, str) else "custom"})


def bracket_variance(model, method: str, fitted: bool, samples, times, hists_fn, seed: int):
    """``model`` (:class:`~derender.engine.variance.VarianceModel`) with its ``shared`` term measured
    on the bracket when ``fitted`` (the method fitted its curves on this bracket): from its grid
    samples ``samples`` (N, 9 M, 3) (the codes at
    :func:`~derender.response.curves.cluster_positions` or Robertson's clusters; ``times``,
    ``hists_fn()`` its code histograms), :func:`~derender.engine.variance.measured_shared` of
    :func:`~derender.response.debevec1997.bracket_curve_sd` (Debevec's merge's calibration,
    ``seed``); with given curves (a profile, ``curves=``) the bracket says nothing about their
    shape and the priors stay."""
    from derender.engine.variance import measured_shared
    from derender.response.debevec1997 import bracket_curve_sd

    if not fitted or samples is None:
        return model
    spread = bracket_curve_sd(samples, times, hists_fn, lam=MERGE_LAMBDA, tie=DEFAULT_TIE, seed=seed)
    return measured_shared(model, method, spread)


def white_weights(weights: np.ndarray, curves) -> np.ndarray:
    """The merge's (256, 3) weight table with no weight at or above each channel's white code, where
    the calibration found one (``curves.params["white_codes"]``,
    :func:`~derender.response.debevec1997.white_codes`: a camera that saturates at 250-254, or
    noise added after clipping): those codes are clipped, as 255 is, so the saturation policy and
    ghost removal read them as bounds, not as values."""
    white = getattr(curves, "params", {}).get("white_codes")
    if not white:
        return weights
    out = np.array(weights, dtype=np.float32, copy=True)
    for c, zw in enumerate(white):
        out[int(zw):, c] = 0.0
    return np.ascontiguousarray(out)


class RobertsonMethod(MethodDefaults):
    """Robertson et al. (2003) on the engine: grid samples, iterative curves, the ML merge in tables."""

    name = "robertson"
    sample_cluster = 9          # each grid pixel with its 8 neighbours (response.robertson2003.robertson_positions)

    def __init__(self, options: RobertsonOptions):
        self.options = options
        self.variance = bool(options.variance)
        self.tie = DEFAULT_TIE if options.tie is None else float(options.tie)
        self.curves, self.n_iter, self.max_pixels = options.curves, int(options.n_iter), int(options.max_pixels)
        self.weight, self.seed, self.block_rows = options.weight, int(options.seed), options.block_rows
        self.censor = bool(options.censor)

    def sample_positions(self, h: int, w: int):
        from derender.response.robertson2003 import robertson_positions

        return robertson_positions(h, w, self.max_pixels, self.seed)

    def plan(self, access: FrameAccess) -> TablePlan:
        from derender.response.robertson2003 import robertson_clusters, robertson_from_samples

        check_usable_samples(access.samples, access.histograms)
        curves = self.curves
        if curves is None:
            z, rim = robertson_clusters(access.samples)
            curves = robertson_from_samples(z, access.times, n_iter=self.n_iter, max_pixels=self.max_pixels,
                                            weight=self.weight, tie=self.tie, censor=self.censor, rim=rim)
        self.fitted = curves
        values = curve_value_tables(curves, access.times, "linear")
        self.black = black_codes(access.samples, access.times)
        return TablePlan(values=values, weights=floor_weights(robertson_weight_table(curves, self.weight), self.black),
                         channel_weights=ROBERTSON_CHANNEL_WEIGHTS, domain="linear",
                         variance=bracket_variance(variance_tables(values, "linear", "robertson"), "robertson",
                                                   self.curves is None, access.samples, access.times,
                                                   access.histograms, self.seed) if self.variance else None)

    def finish(self, result: HDRResult, access: FrameAccess) -> None:
        result.info.update({"method": "robertson", "curves": self.fitted, "black_codes": self.black,
                            "weight": self.weight if isinstance(self.weight, str) else "custom"})


#: How the ML merge of Robertson shares weights between a pixel's channels (see :func:`merge_robertson`):
#: ``"independent"`` measured 0.3 dB PSNR L above ``"mean"`` on 8 simulator brackets.
ROBERTSON_CHANNEL_WEIGHTS = "independent"


def _robertson_level_weights(curves, weight: Any) -> tuple[np.ndarray, np.ndarray]:
    """The ML merge's weights at the curves' levels: ``(levels in [0, 1], (L, 3) weights)``
    (:func:`~derender.response.robertson2003.noise_weights`)."""
    from derender.response.curves import level_weights
    from derender.response.robertson2003 import noise_weights

    w = noise_weights(curves.log_inverse, level_weights(weight, curves.n_levels))
    return np.linspace(0.0, 1.0, curves.n_levels), w


def robertson_weight_table(curves, weight: Any) -> np.ndarray:
    """(256, 3) float32 weights of the ML merge on 8-bit codes: ``noise_weights`` of ``curves`` at the
    codes, none at or above the channels' white codes (:func:`white_weights`)."""
    from derender.engine.tables import code_values

    lv, w = _robertson_level_weights(curves, weight)
    z = code_values().astype(np.float64)
    return white_weights(np.stack([np.interp(z, lv, w[:, c]) for c in range(3)], -1), curves)


def _robertson_weight_fn(curves, weight: Any) -> Callable[[int, np.ndarray], np.ndarray]:
    """``(j, block) -> weights`` of the ML merge for :func:`merge_linear` (any bit depth; the
    channels share them or not as :data:`ROBERTSON_CHANNEL_WEIGHTS` tells the merge); none at or
    above the channels' white codes (:func:`white_weights`, values binned to the curves' levels)."""
    lv, w = _robertson_level_weights(curves, weight)
    w = white_weights(w, curves)

    def fn(j: int, block: np.ndarray) -> np.ndarray:
        b = np.clip(np.asarray(block, dtype=np.float64), 0.0, 1.0)
        return np.stack([np.interp(b[..., c], lv, w[:, c]) for c in range(3)], -1).astype(np.float32)

    return fn


def _white_weight_fn(weight: Any, white: list[int]) -> Callable[[int, np.ndarray], np.ndarray]:
    """``(j, block) -> weights`` of the named ``weight`` with none at or above each channel's white
    code (:func:`white_weights` for :func:`merge_linear`: values binned to 8-bit codes)."""
    from derender.engine.weights import get_weight

    fn = get_weight(weight)
    wc = np.asarray(white, dtype=np.float32)

    def weights(j: int, block: np.ndarray) -> np.ndarray:
        b = np.clip(np.asarray(block, dtype=np.float32), 0.0, 1.0)
        w = np.asarray(fn(b), dtype=np.float32)
        return np.where(np.rint(b * np.float32(255)) >= wc, np.float32(0), w)

    return weights


def _curve_lineariser(curves) -> Callable[[int, np.ndarray], np.ndarray]:
    """``(j, block) -> g(block)`` (log exposure) for :func:`merge_linear` with ``log_input=True``."""

    def lin(j: int, block: np.ndarray) -> np.ndarray:
        return curves.log_linearise(block)

    return lin


def _reference_merge(stack: Stack, name: str, curves, weight: Any, block_rows: int | None, variance: bool,
                     merge_options: dict) -> HDRResult:
    """A classic merge with ``curves`` on the float reference engine (stacks without 8-bit codes);
    ``merge_options``: :func:`merge_linear`'s ``channel_weights``, ``domain`` and ``weight_fn``."""
    if variance:
        raise InputError(f"{name}: a variance needs 8-bit images (every value a code / 255) on the engine")
    t1 = time.perf_counter()
    white = getattr(curves, "params", {}).get("white_codes")
    if white and merge_options.get("weight_fn") is None:
        merge_options = dict(merge_options, weight_fn=_white_weight_fn(weight, white))
    res = merge_linear(_curve_lineariser(curves), stack.times, stack.images, weight, log_input=True,
                       block_rows=block_rows, channel_weights=merge_options["channel_weights"],
                       domain=merge_options["domain"], weight_fn=merge_options.get("weight_fn"))
    res.info.update({"method": name, "curves": curves, "engine": "reference",
                     "timings": {"merge_s": time.perf_counter() - t1}})
    return res


def debevec_stack(stack: Stack, options: DebevecOptions) -> HDRResult:
    """``debevec`` on the float reference engine (:func:`~derender.engine.float_merge.merge_linear`):
    stacks without 8-bit codes, or ``engine="reference"`` (the registry chooses)."""
    from derender.response.debevec1997 import calibrate_debevec

    o, method = options, DebevecMethod(options)
    check_usable(stack)
    t0 = time.perf_counter()
    curves = o.curves
    if curves is None:
        curves = calibrate_debevec(stack, lam=method.lam, n_samples=method.n_samples, sampling=o.sampling, seed=o.seed,
                                   balance=o.sampling == "grid", tie=method.tie, censor=o.censor)
    t1 = time.perf_counter()
    res = _reference_merge(stack, "debevec", curves, o.weight, o.block_rows, o.variance,
                           {"channel_weights": o.channel_weights, "domain": o.domain})
    res.info["timings"]["calibrate_s"] = t1 - t0
    return res


def robertson_stack(stack: Stack, options: RobertsonOptions) -> HDRResult:
    """``robertson`` on the float reference engine (as :func:`debevec_stack`)."""
    from derender.response.robertson2003 import calibrate_robertson

    o, method = options, RobertsonMethod(options)
    check_usable(stack)
    t0 = time.perf_counter()
    curves = o.curves
    if curves is None:
        curves = calibrate_robertson(stack, n_iter=o.n_iter, max_pixels=o.max_pixels, weight=o.weight, seed=o.seed,
                                     tie=method.tie, censor=o.censor)
    t1 = time.perf_counter()
    res = _reference_merge(stack, "robertson", curves, o.weight, o.block_rows, o.variance,
                           {"weight_fn": _robertson_weight_fn(curves, o.weight),
                            "channel_weights": ROBERTSON_CHANNEL_WEIGHTS, "domain": "linear"})
    res.info["timings"]["calibrate_s"] = t1 - t0
    return res


def merge_debevec(stack: Stack, options: DebevecOptions | Mapping[str, Any] | None = None, *,
                  motion: MotionOptions | None = None) -> HDRResult:
    """Debevec & Malik (1997): recover ``g = ln f^-1`` per channel (Sec. 2.1), merge with eq. 6.

    The merge defaults are eq. 6's log-domain average with a Gaussian weight shared by the
    three channels of a pixel (the mean of the channel weights, as OpenCV's MergeDebevec shares
    them): a camera mixes channels (3x3 matrix), so a clipped or noisy sensor channel spoils the
    other two, and the Gaussian weight trusts the toe and shoulder of the tone curve less than
    the hat does (the measurements behind this choice: ``docs/paper1.md``, "Classic merges").
    ``weight="hat", channel_weights="independent"`` is eq. 6 literally.

    Parameters
    ----------
    stack : Stack
        The bracket (8- or 16-bit images in [0, 1] and their exposure times).
    options : DebevecOptions or mapping, optional
        The method's options (:class:`DebevecOptions`, where each is described), or a mapping
        of them.
    motion : MotionOptions, optional
        Reference frame, alignment, ghost removal (:func:`derender.hdr.registry.merge`).

    Returns
    -------
    HDRResult
        Radiance in the images' own linear RGB, relative units; ``info["curves"]`` the curves.

    References
    ----------
    P. E. Debevec, J. Malik, "Recovering high dynamic range radiance maps from photographs",
    SIGGRAPH 1997, Sec. 2.1 and eq. 6. doi:10.1145/258734.258884
    """
    return merge(stack, "debevec", options, motion=motion)


def merge_robertson(stack: Stack, options: RobertsonOptions | Mapping[str, Any] | None = None, *,
                    motion: MotionOptions | None = None) -> HDRResult:
    """Robertson, Borman & Stevenson (2003), made robust: iterative ``f^-1`` and the ML merge.

    The curve: :func:`derender.response.robertson2003.calibrate_robertson` (leave-one-out,
    log-domain update, monotone and smooth, colour-balanced). The merge is Robertson's
    ``sum w t I / sum w t^2`` with ``w`` the inverse variance of ``I(z)`` under a constant
    code noise, i.e. every frame's ``I(z_j) / t_j`` weighted by ``w(z_j) / g'(z_j)^2``
    (:func:`~derender.response.robertson2003.noise_weights`, the same weights as the
    calibration), each channel with its own weight (the literal ``t^2``-weighted merge lets the
    longest frame's near-clipped codes decide: ``docs/paper1.md``, "Classic merges").

    Parameters
    ----------
    stack : Stack
        The bracket.
    options : RobertsonOptions or mapping, optional
        The method's options (:class:`RobertsonOptions`), or a mapping of them.
    motion : MotionOptions, optional
        As :func:`merge_debevec`.

    Returns
    -------
    HDRResult
        Radiance in the images' own linear RGB, relative units; ``info["curves"]`` the curves.

    References
    ----------
    M. A. Robertson, S. Borman, R. L. Stevenson, "Estimation-theoretic approach to dynamic range
    enhancement using multiple exposures", J. Electronic Imaging 12(2), 2003.
    doi:10.1117/1.1557695
    """
    return merge(stack, "robertson", options, motion=motion)
