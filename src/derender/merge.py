"""The HDR merge engine shared by every method, weight functions and the method registry.

Every merge method turns each exposure ``j`` into values proportional to
``exposure = radiance * t_j`` (its *linearisation*) and hands them to
:func:`merge_linear`, which forms the weighted average of the per-image radiance
estimates ``lin_j / t_j`` (Debevec & Malik 1997, eq. 6, in the linear or the log
domain) and applies the saturation policy of ``DESIGN.md``.

Methods register themselves with :func:`register_method`; :func:`merge` dispatches
by name. This module registers ``"debevec"`` (Debevec & Malik 1997) and
``"robertson"`` (Robertson, Borman & Stevenson 2003).
"""

from __future__ import annotations

import importlib
import inspect
import time
from typing import Any, Callable

import numpy as np

from .errors import InputError
from .stack import HDRResult, Stack

__all__ = [
    "weight_hat",
    "weight_trapezoid",
    "weight_gaussian",
    "WEIGHTS",
    "get_weight",
    "merge_linear",
    "MERGE_METHODS",
    "register_method",
    "merge",
    "merge_debevec",
    "merge_robertson",
]

_F32_MAX = float(np.finfo(np.float32).max)


# --------------------------------------------------------------------------- weights
def weight_hat(z: np.ndarray) -> np.ndarray:
    """Debevec & Malik (1997) hat ``w(z) = 1 - |2z - 1|`` on normalised codes ``z`` in [0, 1].

    Zero at 0 and 1 (black and clipped codes never count), 1 at mid-grey. It is the
    paper's ``z - Zmin`` / ``Zmax - z`` rescaled to a peak of 1 (the scale cancels).
    """
    z = np.clip(np.asarray(z, dtype=np.float32), 0.0, 1.0)
    return (1.0 - np.abs(2.0 * z - 1.0)).astype(np.float32)


def weight_trapezoid(z: np.ndarray, low: float = 0.02, high: float = 0.98, ramp: float = 0.1) -> np.ndarray:
    """Trapezoid weight: 0 for ``z <= low`` and ``z >= high``, linear ramps of width ``ramp``, plateau 1.

    ``w = 0`` on [0, low] (noise floor / crushed blacks), rises linearly to 1 at
    ``low + ramp``, stays 1 up to ``high - ramp``, falls to 0 at ``high`` and is 0 on
    [high, 1] (clipped). Paper 1 (Sec. 3, last step) averages with "a trapezoidal
    function discarding saturated and noisy pixels" from its ref. [2] (Bertalmio,
    *Image Processing for Cinema*, 2014); the paper gives no breakpoints, so the
    defaults (2/98 % of full scale, 10 % ramps) are ours.
    """
    if not (0.0 <= low < high <= 1.0) or ramp <= 0 or low + 2 * ramp > high + 1e-12:
        raise InputError(f"trapezoid weight needs 0 <= low < low+2*ramp <= high <= 1, got low={low}, high={high}, ramp={ramp}")
    z = np.asarray(z, dtype=np.float32)
    up = (z - low) / ramp
    down = (high - z) / ramp
    return np.clip(np.minimum(up, down), 0.0, 1.0).astype(np.float32)


_E4 = float(np.exp(-4.0))


def weight_gaussian(z: np.ndarray) -> np.ndarray:
    """Robertson et al. (2003) Gaussian-like weight ``exp(-16 (z - 1/2)^2)``, shifted and scaled to 0 at the ends.

    ``w(z) = (exp(-16 (z - 0.5)^2) - e^-4) / (1 - e^-4)``: 1 at mid-grey, exactly 0 at
    0 and 1 (the same shifted form as OpenCV's ``RobertsonWeights``).
    """
    z = np.clip(np.asarray(z, dtype=np.float32), 0.0, 1.0)
    return ((np.exp(-16.0 * (z - 0.5) ** 2) - _E4) / (1.0 - _E4)).astype(np.float32)


#: Weight functions on normalised code values in [0, 1], by name.
WEIGHTS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "hat": weight_hat,
    "trapezoid": weight_trapezoid,
    "gaussian": weight_gaussian,
}


def get_weight(weight: str | Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    """Resolve a weight name from :data:`WEIGHTS` (or pass a callable through)."""
    if callable(weight):
        return weight
    try:
        return WEIGHTS[str(weight)]
    except KeyError:
        raise InputError(f"unknown weight {weight!r}; known: {', '.join(sorted(WEIGHTS))}") from None


# --------------------------------------------------------------------------- engine
def _combine_channels(w: np.ndarray, mode: str) -> np.ndarray:
    if w.ndim == 2:
        return w[:, :, None]
    if mode == "independent":
        return w
    if mode == "mean":
        return w.mean(axis=2, keepdims=True, dtype=np.float32)
    if mode == "min":
        return w.min(axis=2, keepdims=True)
    raise InputError(f"channel_weights must be 'independent', 'mean' or 'min', got {mode!r}")


def merge_linear(
    linear: np.ndarray | Callable[[int, np.ndarray], np.ndarray],
    times: Any,
    images: np.ndarray,
    weight: str | Callable[[np.ndarray], np.ndarray] = "hat",
    *,
    image_weights: Any = None,
    weight_fn: Callable[[int, np.ndarray], np.ndarray] | None = None,
    channel_weights: str = "independent",
    domain: str = "linear",
    log_input: bool = False,
    bright_threshold: float = 0.5,
    block_rows: int | None = None,
    info: dict | None = None,
) -> HDRResult:
    """Weighted merge of linearised exposures into one radiance map (Debevec & Malik 1997, eq. 6).

    Parameters
    ----------
    linear : (N, H, W, 3) array, or callable ``linear(j, block) -> (h, W, 3)``
        Linearised exposure ``j``: values proportional to ``radiance * t_j`` (NOT yet
        divided by the time; pass ``times=np.ones(N)`` if yours already are). A
        callable receives ``images[j, rows]`` (a block of rows of the rendered image)
        and must be *pointwise* (each output pixel depends only on the same input
        pixel), because the engine works on blocks of rows; precompute an array
        otherwise.
    times : (N,) exposure times in seconds (positive).
    images : (N, H, W, 3) rendered values in [0, 1]; they drive the weights and the
        bright/dark decision of the saturation policy.
    weight : name in :data:`WEIGHTS` or callable on [0, 1] values.
    image_weights : optional (N,) per-image factors (e.g. ``t_j**2`` for Robertson's
        maximum-likelihood estimate).
    weight_fn : optional ``weight_fn(j, block) -> (h, W) or (h, W, 3)`` replacing
        ``weight`` (e.g. inverse variances of a probabilistic method).
    channel_weights : ``"independent"`` (each channel its own weight), ``"mean"``
        (OpenCV: the mean over channels for all three) or ``"min"`` (a pixel counts
        only where all channels are usable; for methods that mix channels).
    domain : ``"linear"``: ``E = sum w lin/t / sum w``; ``"log"``: Debevec's eq. 6,
        ``ln E = sum w (ln lin - ln t) / sum w``.
    log_input : ``linear`` gives ``ln`` of the linearised values (e.g. ``g(z)``
        directly), saving an exp/log round trip.

    Saturation policy (``DESIGN.md``): where the total weight of a channel is 0, the
    value comes from the shortest exposure if that exposure's value of the channel is
    ``>= bright_threshold`` (over-exposed everywhere), else from the longest
    (under-exposed everywhere); ``mask`` is 1 (bright) or 2 (dark) where any channel
    took a fallback (bright wins). Non-finite linearised values (and, in the log
    domain, values <= 0) get weight 0, as do non-finite or negative custom weights;
    the result is finite float32. Memory: works on blocks of ``block_rows`` rows
    (default: ~256k pixels per block), never on full-size float64 temporaries.
    """
    t0 = time.perf_counter()
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise InputError(f"images must have shape (N, H, W, 3), got {images.shape}")
    n, h, w_, _ = images.shape
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.size != n:
        raise InputError(f"{t.size} exposure time(s) for {n} image(s)")
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise InputError(f"exposure times must be positive finite seconds, got {t.tolist()}")
    lin_arr = None
    if not callable(linear):
        lin_arr = np.asarray(linear)
        if lin_arr.shape != images.shape:
            raise InputError(f"linear images {lin_arr.shape} do not match images {images.shape}")
    if domain not in ("linear", "log"):
        raise InputError(f"domain must be 'linear' or 'log', got {domain!r}")
    _combine_channels(np.zeros((1, 1, 3), np.float32), channel_weights)  # validate early
    if image_weights is None:
        iw = np.ones(n)
    else:
        iw = np.asarray(image_weights, dtype=np.float64).reshape(-1)
        if iw.size != n or not np.all(np.isfinite(iw)) or np.any(iw < 0):
            raise InputError("image_weights must be N finite non-negative numbers")
    wfun = get_weight(weight) if weight_fn is None else None
    j_short, j_long = int(np.argmin(t)), int(np.argmax(t))
    log_t = np.log(t)
    if block_rows is None:
        block_rows = max(1, (1 << 18) // max(w_, 1))
    block_rows = max(1, int(block_rows))

    radiance = np.empty((h, w_, 3), dtype=np.float32)
    mask = np.zeros((h, w_), dtype=np.uint8)
    n_bright = n_dark = 0
    for r0 in range(0, h, block_rows):
        r1 = min(h, r0 + block_rows)
        num = np.zeros((r1 - r0, w_, 3), dtype=np.float64)
        den = None
        v_short = v_long = None
        for j in range(n):
            zj = images[j, r0:r1]
            lin = linear(j, zj) if lin_arr is None else lin_arr[j, r0:r1]
            lin = np.asarray(lin)
            if lin.shape != zj.shape:
                raise ValueError(f"linearisation of image {j} has shape {lin.shape}, expected {zj.shape}")
            if domain == "linear":
                v = np.exp(lin.astype(np.float64) - log_t[j]) if log_input else lin.astype(np.float64) * (1.0 / t[j])
            elif log_input:
                v = lin.astype(np.float64) - log_t[j]
            else:
                lin64 = lin.astype(np.float64)
                with np.errstate(divide="ignore", invalid="ignore"):
                    v = np.where(lin64 > 0, np.log(lin64), np.nan) - log_t[j]
            if weight_fn is not None:
                wj = np.asarray(weight_fn(j, zj), dtype=np.float32)
                wj = np.where(np.isfinite(wj) & (wj > 0), wj, np.float32(0))
            else:
                wj = np.asarray(wfun(zj), dtype=np.float32)
            if wj.shape not in (zj.shape, zj.shape[:2]):
                raise ValueError(f"weights of image {j} have shape {wj.shape}, expected {zj.shape}")
            wj = _combine_channels(wj, channel_weights)
            bad = ~np.isfinite(v)
            if bad.any():
                v[bad] = 0.0
                wj = np.where(bad, np.float32(0), wj)
            if j == j_short:
                v_short = v
            if j == j_long:
                v_long = v
            wj = wj.astype(np.float64) * iw[j] if iw[j] != 1.0 else wj.astype(np.float64)
            num += wj * v
            den = wj.copy() if den is None else den + wj
        ok = den > 0
        res = num / np.where(ok, den, 1.0)
        if not ok.all():
            none = np.broadcast_to(~ok, res.shape)
            bright = none & (images[j_short, r0:r1] >= bright_threshold)
            dark = none & ~bright
            res = np.where(bright, v_short, np.where(dark, v_long, res))
            bpix = bright.any(axis=2)
            dpix = dark.any(axis=2) & ~bpix
            mask[r0:r1][bpix] = HDRResult.MASK_BRIGHT
            mask[r0:r1][dpix] = HDRResult.MASK_DARK
            n_bright += int(bpix.sum())
            n_dark += int(dpix.sum())
        if domain == "log":
            res = np.exp(np.minimum(res, 88.0))
        radiance[r0:r1] = np.clip(np.nan_to_num(res, nan=0.0), -_F32_MAX, _F32_MAX)
    out_info = {
        "weight": weight if isinstance(weight, str) and weight_fn is None else "custom",
        "domain": domain,
        "channel_weights": channel_weights,
        "n_bright": n_bright,
        "n_dark": n_dark,
        "merge_seconds": time.perf_counter() - t0,
    }
    if info:
        out_info.update(info)
    return HDRResult(radiance=radiance, mask=mask, variance=None, info=out_info)


# --------------------------------------------------------------------------- registry
#: Merge methods by name: ``fn(stack, **options) -> HDRResult``.
MERGE_METHODS: dict[str, Callable[..., HDRResult]] = {}

#: Modules that register further methods when imported; :func:`merge` imports them
#: lazily (missing ones are skipped) so that ``merge(stack, method=...)`` finds them.
_PLUGIN_MODULES = ("derender.stabilize", "derender.stabilized", "derender.derendering", "derender.probabilistic")


def register_method(name: str, gives_variance: bool = False
                    ) -> Callable[[Callable[..., HDRResult]], Callable[..., HDRResult]]:
    """Decorator registering ``fn(stack, **options) -> HDRResult`` under ``name``
    (``gives_variance``: its results carry a per-pixel variance)."""

    def deco(fn: Callable[..., HDRResult]) -> Callable[..., HDRResult]:
        fn.gives_variance = bool(gives_variance)
        MERGE_METHODS[name] = fn
        return fn

    return deco


def _load_plugins() -> None:
    """Import the modules of :data:`_PLUGIN_MODULES` that exist (they register methods)."""
    for mod in _PLUGIN_MODULES:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise


def merge(stack: Stack, method: str = "debevec", **options: Any) -> HDRResult:
    """Merge a :class:`~derender.stack.Stack` into an HDR radiance map with a registered method.

    Unknown methods or options raise :class:`InputError` (listing what is known).
    """
    if not isinstance(stack, Stack):
        raise InputError(f"merge() needs a Stack, got {type(stack).__name__}")
    if method not in MERGE_METHODS:
        _load_plugins()
    fn = MERGE_METHODS.get(method)
    if fn is None:
        raise InputError(f"unknown merge method {method!r}; known: {', '.join(sorted(MERGE_METHODS))}")
    try:
        inspect.signature(fn).bind(stack, **options)
    except TypeError:
        params = [p for p in inspect.signature(fn).parameters][1:]
        bad = [k for k in options if k not in params]
        raise InputError(
            f"merge method {method!r} does not accept option(s) {', '.join(bad) or '?'}; "
            f"accepted: {', '.join(params)}"
        ) from None
    return fn(stack, **options)


def _curve_lineariser(curves) -> Callable[[int, np.ndarray], np.ndarray]:
    """``(j, block) -> g(block)`` (log exposure) for :func:`merge_linear` with ``log_input=True``."""

    def lin(j: int, block: np.ndarray) -> np.ndarray:
        return curves.log_linearise(block)

    return lin


_ENGINES = ("auto", "table", "reference")


def _table_engine(stack: Stack, curves, weight, engine: str, **kw: Any) -> HDRResult | None:
    """Merge with the 8-bit table engine (:mod:`derender.fastmerge`) when ``engine`` allows it.

    ``"auto"``: the table engine when every value of the stack is an 8-bit code / 255
    (same result as :func:`merge_linear` to ~1e-6 relative, several times faster), else
    None (the caller runs :func:`merge_linear`); ``"table"``: the table engine or an
    :class:`InputError`; ``"reference"``: None.
    """
    if engine not in _ENGINES:
        raise InputError(f"engine must be one of {', '.join(_ENGINES)}, got {engine!r}")
    if engine == "reference":
        return None
    from .fastmerge import merge_curves_table

    res = merge_curves_table(stack, curves, weight, **kw)
    if res is None and engine == "table":
        raise InputError("engine='table' needs an 8-bit stack (every value a code / 255)")
    return res


@register_method("debevec")
def merge_debevec(
    stack: Stack,
    curves=None,
    lam: float | None = None,
    n_samples: int | None = None,
    sampling: str = "grid",
    seed: int = 0,
    weight: str = "gaussian",
    domain: str = "log",
    channel_weights: str = "mean",
    block_rows: int | None = None,
    engine: str = "auto",
) -> HDRResult:
    """Debevec & Malik (1997): recover ``g = ln f^-1`` per channel (Sec. 2.1), merge with eq. 6.

    ``curves`` (a :class:`~derender.response.ResponseCurves`) skips the calibration
    (which always uses the paper's hat weights). Merge defaults: eq. 6's log-domain
    average, with a Gaussian weight shared by the three channels of a pixel (the mean of
    the channel weights, as OpenCV's MergeDebevec shares them). ``weight="hat",
    channel_weights="independent"`` is eq. 6 literally. Chosen by measurement (PSNR L vs
    truth on simulator brackets 192x128, 7 exposures, seed 4; log-luminance correlation
    with Debevec's memorial.hdr at half resolution):

    =====================  ==========  =========  ========
    merge                  sim fixed   sim auto   Memorial
    =====================  ==========  =========  ========
    eq. 6 literal (hat)    38.0 dB     34.4 dB    0.985
    hat, shared            39.6 dB     36.8 dB    0.986
    gaussian, shared       41.7 dB     38.7 dB    0.995
    linear domain, hat     41.6 dB     40.5 dB    0.810
    OpenCV Calibrate+Merge 40.5 dB     36.5 dB    0.987
    =====================  ==========  =========  ========

    A camera mixes channels (3x3 matrix), so a clipped or noisy sensor channel spoils the
    other two: shared weights avoid trusting them; the Gaussian weight trusts codes near
    the ends of the range (toe and shoulder of the tone curve) less than the hat does.

    ``engine``: ``"auto"`` merges 8-bit stacks with 256-entry tables
    (:mod:`derender.fastmerge`, equal to the reference to ~1e-6 relative; ``block_rows``
    then does not apply), ``"reference"`` always uses :func:`merge_linear`.
    """
    from .response import DEFAULT_LAMBDA, DEFAULT_SAMPLES, calibrate_debevec, check_usable

    check_usable(stack)
    t0 = time.perf_counter()
    if curves is None:
        curves = calibrate_debevec(
            stack,
            lam=DEFAULT_LAMBDA if lam is None else lam,
            n_samples=DEFAULT_SAMPLES if n_samples is None else n_samples,
            sampling=sampling,
            seed=seed,
        )
    t1 = time.perf_counter()
    res = _table_engine(stack, curves, weight, engine, domain=domain, channel_weights=channel_weights)
    if res is None:
        res = merge_linear(_curve_lineariser(curves), stack.times, stack.images, weight, log_input=True,
                           channel_weights=channel_weights, domain=domain, block_rows=block_rows)
        res.info["engine"] = "reference"
    t2 = time.perf_counter()
    res.info.update({"method": "debevec", "curves": curves,
                     "timings": {"calibrate_s": t1 - t0, "merge_s": t2 - t1}})
    return res


@register_method("robertson")
def merge_robertson(
    stack: Stack,
    curves=None,
    n_iter: int = 30,
    max_pixels: int = 40_000,
    weight: str = "gaussian",
    seed: int = 0,
    block_rows: int | None = None,
    engine: str = "auto",
) -> HDRResult:
    """Robertson, Borman & Stevenson (2003): iterative ``f^-1`` and the ML merge ``sum w t I / sum w t^2``.

    ``engine`` as in :func:`merge_debevec` (8-bit stacks use the table engine by default).
    """
    from .response import calibrate_robertson, check_usable

    check_usable(stack)
    t0 = time.perf_counter()
    if curves is None:
        curves = calibrate_robertson(stack, n_iter=n_iter, max_pixels=max_pixels, weight=weight, seed=seed)
    t1 = time.perf_counter()
    res = _table_engine(stack, curves, weight, engine, domain="linear", channel_weights="independent",
                        image_weights=stack.times ** 2)
    if res is None:
        res = merge_linear(_curve_lineariser(curves), stack.times, stack.images, weight, log_input=True,
                           image_weights=stack.times ** 2, domain="linear", block_rows=block_rows)
        res.info["engine"] = "reference"
    t2 = time.perf_counter()
    res.info.update({"method": "robertson", "curves": curves,
                     "timings": {"calibrate_s": t1 - t0, "merge_s": t2 - t1}})
    return res
