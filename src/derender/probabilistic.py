"""Probabilistic HDR (paper 2, Sec. 3.1, eq. 3): the product of de-rendered Gaussians.

Every exposure i gives, per pixel and channel, a Gaussian over the RAW colour,
``N(mu_i, s_i^2) = model.predict(J_i)``. Scaled to a common target exposure alpha_0
(here exposure time t_0), ``x_0 ~ N(mu_i t_0 / t_i, s_i^2 (t_0 / t_i)^2)``; with independent
exposures the posterior is the normalised product of these Gaussians:

    1 / s_0^2 = sum_i 1 / s_i'^2,     mu_0 = s_0^2 sum_i mu_i' / s_i'^2.

No pixel is thrown away by a threshold: a saturated JPEG value contributes through its
(large) variance. The result is in the model's camera RGB (white balance fixed, as the
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


def _load(model: Any):
    from .derendering import DerenderModel, load_model

    if isinstance(model, (str, os.PathLike)):
        return load_model(model)
    if not isinstance(model, DerenderModel):
        raise InputError("the probabilistic merge needs a de-rendering model (-m MODEL.npz)")
    return model


@register_method("probabilistic")
def merge_probabilistic(stack: Stack, model: Any, target_time: float = 1.0, colour_space: str = "linear_srgb",
                        seed: int = 0) -> HDRResult:
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
    for i in range(stack.n):
        mean, var = model.predict(codes[i])
        scale = float(target_time / stack.times[i])
        v = np.maximum(var.astype(np.float64) * scale * scale, 1e-30)
        p = 1.0 / v
        prec += p
        acc += mean.astype(np.float64) * scale * p
    var0 = 1.0 / prec
    mean0 = acc * var0
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
