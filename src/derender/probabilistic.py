"""Probabilistic HDR (paper 2, Sec. 3.1, eq. 3): the product of de-rendered Gaussians.

Every exposure i gives, per pixel and channel, a Gaussian over the RAW colour,
``N(mu_i, s_i^2) = model.predict(J_i)``. Scaled to a common target exposure alpha_0
(here exposure time t_0), ``x_0 ~ N(mu_i t_0 / t_i, s_i^2 (t_0 / t_i)^2)``; with independent
exposures the posterior is the normalised product of these Gaussians:

    1 / s_0^2 = sum_i 1 / s_i'^2,     mu_0 = s_0^2 sum_i mu_i' / s_i'^2.

No pixel is thrown away by a threshold: a saturated JPEG value contributes through its
(large) variance (``censor=False``, the paper's eq. 3 literally).

Beyond the paper (``censor=True``, default): a JPEG colour with a channel at 255 only says
the RAW colour is *at least* what the calibration saw for that code; a Gaussian centred on
the training data's conditional mean, scaled by t_0 / t_i, claims far too much for a
light source brighter than anything in the calibration (a clipped long exposure would
pull the estimate down with a tiny variance). Such observations are treated as censored:
each gives a lower bound ``B_i = q_0.023(x | J_i) t_0 / t_i`` (the GP's 2.3 % quantile,
``exp(mu - 2 sigma)`` in its log space); the Gaussians of the unclipped observations are
multiplied as in eq. 3, and the product is truncated below at ``B = max_i B_i``
(truncated-normal moments). When the bound contradicts the unclipped evidence by more
than 3 sigma, or no exposure is unclipped, the estimate is ``B`` with a variance of ``B^2``
(at least 100 % relative uncertainty): high exactly where all exposures clip. The result is in the model's camera RGB (white balance fixed, as the
calibration pairs); with the camera's white balance and colour matrix stored in the model
(``derender calibrate`` from ``chart-pairs`` files stores them) it is converted to linear
sRGB, the variance propagated through the same 3x3 map (diagonal of ``A S A^T``).
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from .errors import InputError
from .merge import register_method
from .stack import HDRResult, Stack

__all__ = ["merge_probabilistic", "product_of_gaussians", "model_camera_to_srgb"]


def model_camera_to_srgb(model) -> np.ndarray | None:
    """``A = camera_to_srgb @ diag(wb)`` from the model's metadata, or None when absent."""
    meta = getattr(model, "metadata", {}) or {}
    m = meta.get("camera_to_srgb")
    wb = meta.get("wb")
    if m is None or wb is None:
        return None
    m = np.asarray(m, dtype=np.float64).reshape(3, 3)
    wb = np.asarray(wb, dtype=np.float64).reshape(3)
    return m * wb[None, :]


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


def _truncate_below(mean: np.ndarray, var: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Moments of N(mean, var) truncated to [bound, inf); see the module doc for conflicts."""
    from scipy.special import ndtr

    out_m = mean.copy()
    out_v = var.copy()
    active = bound > 0
    finite = np.isfinite(var)
    sd = np.sqrt(np.where(finite, var, 1.0))
    alpha = np.where(finite, (bound - mean) / np.maximum(sd, 1e-300), np.inf)
    ok = active & finite & (alpha < 3.0)
    if ok.any():
        a = alpha[ok]
        tail = np.maximum(1.0 - ndtr(a), 1e-300)
        lam = np.exp(-0.5 * a * a) / np.sqrt(2 * np.pi) / tail
        out_m[ok] = mean[ok] + sd[ok] * lam
        out_v[ok] = var[ok] * np.maximum(1.0 + a * lam - lam * lam, 1e-6)
    conflict = active & ~ok
    out_m[conflict] = bound[conflict]
    out_v[conflict] = np.maximum(np.where(finite[conflict], var[conflict], 0.0), bound[conflict] ** 2)
    nothing = ~np.isfinite(out_v)
    out_m[nothing] = 0.0
    out_v[nothing] = np.finfo(np.float32).max / 8
    return out_m, out_v


def _load(model: Any):
    from .derendering import DerenderModel, load_model

    if isinstance(model, (str, os.PathLike)):
        return load_model(model)
    if not isinstance(model, DerenderModel):
        raise InputError("the probabilistic merge needs a de-rendering model (-m MODEL.npz)")
    return model


@register_method("probabilistic")
def merge_probabilistic(stack: Stack, model: Any, target_time: float = 1.0, colour_space: str = "linear_srgb",
                        censor: bool = True, seed: int = 0) -> HDRResult:
    """Probabilistic HDR merge (paper 2 eq. 3) with a de-rendering model; returns mean and variance.

    ``target_time`` is alpha_0 in seconds (the result is radiance x t_0); ``colour_space``
    is ``"linear_srgb"`` (needs the model's camera metadata) or ``"camera_rgb"``.
    ``seed`` is unused (the merge is deterministic) and accepted for a uniform interface.
    """
    model = _load(model)
    if stack.bit_depth == 16:
        raise InputError("de-rendering models take 8-bit images; this stack is 16-bit")
    if not (np.isfinite(target_time) and target_time > 0):
        raise InputError("target_time must be a positive number of seconds")
    a = None
    if colour_space == "linear_srgb":
        a = model_camera_to_srgb(model)
        if a is None:
            raise InputError("the model has no camera colour metadata (camera_to_srgb, wb); "
                             "use colour_space='camera_rgb' or calibrate from chart-pairs files")
    elif colour_space != "camera_rgb":
        raise InputError(f"colour_space must be 'linear_srgb' or 'camera_rgb', got {colour_space!r}")
    t0 = time.perf_counter()
    codes = stack.codes()
    h, w = stack.shape
    prec = np.zeros((h, w, 3), dtype=np.float64)
    acc = np.zeros((h, w, 3), dtype=np.float64)
    bound = np.zeros((h, w, 3), dtype=np.float64)
    for i in range(stack.n):
        mean, var = model.predict(codes[i])
        scale = float(target_time / stack.times[i])
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
        mean0, var0 = _truncate_below(mean0, var0, bound)
    if a is not None:
        mean0 = mean0 @ a.T
        var0 = var0 @ (a * a).T
    # saturation mask (information only: no pixel is discarded)
    sat_short = np.any(codes[0] >= 255, axis=-1)
    dark_long = np.all(codes[-1] <= 0, axis=-1)
    mask = np.zeros((h, w), dtype=np.uint8)
    mask[sat_short] = HDRResult.MASK_BRIGHT
    mask[dark_long & ~sat_short] = HDRResult.MASK_DARK
    big = np.finfo(np.float32).max / 4
    radiance = np.nan_to_num(mean0, nan=0.0, posinf=big, neginf=-big).astype(np.float32)
    variance = np.nan_to_num(np.clip(var0, 0, big), nan=big, posinf=big).astype(np.float32)
    return HDRResult(radiance=radiance, mask=mask, variance=variance,
                     info={"method": "probabilistic", "colour_space": colour_space, "target_time": target_time,
                           "model": getattr(model, "method", "?"), "merge_seconds": time.perf_counter() - t0})


@register_method("stabilized-probabilistic")
def merge_stabilized_probabilistic(stack: Stack, model: Any, reference: int | None = None, align: str = "mtb",
                                   seed: int = 0) -> HDRResult:
    """Both papers together: paper 1's stabilised merge weighted by paper 2's de-rendering variances.

    The stabilisation (reference, registration, gamma_j, H_j) is paper 1's; each image's
    weight is its trapezoid weight times the inverse *relative* variance of its pixels'
    de-rendered RAW colours, ``1 / mean_c(var_c / mean_c^2)``. The estimate of radiance
    from image j has variance ``r_j L^2`` for relative variance ``r_j`` and radiance L, so
    for the same pixel inverse-variance weighting reduces to weights ``1 / r_j``; this
    replaces paper 1's plain noise weighting.
    """
    from .stabilize import stabilize, stabilized_merge

    model = _load(model)
    if stack.bit_depth == 16:
        raise InputError("de-rendering models take 8-bit images; this stack is 16-bit")
    t0 = time.perf_counter()
    stab = stabilize(stack, reference=reference, align=align, mode="reference", seed=seed)
    aligned = np.rint(np.clip(stab.alignment.images, 0.0, 1.0) * 255.0).astype(np.uint8)
    weights = np.empty(aligned.shape[:3], dtype=np.float64)
    for j in range(aligned.shape[0]):
        mean, var = model.predict(aligned[j], point="map")
        rel = np.mean(var.astype(np.float64) / np.maximum(mean.astype(np.float64), 1e-12) ** 2, axis=-1)
        weights[j] = 1.0 / np.maximum(rel, 1e-12)
    res = stabilized_merge(stab, noise_weighting=False, pixel_weights=weights)
    res.info.update({"method": "stabilized-probabilistic", "model": getattr(model, "method", "?"),
                     "merge_seconds": time.perf_counter() - t0})
    return res
