"""The float reference engine: the weighted average of per-image radiance estimates, pixel by pixel.

:func:`merge_linear` forms ``sum_j w_j (lin_j / t_j) / sum_j w_j`` (Debevec & Malik 1997,
eq. 6, in the linear or the log domain) on float images and applies the saturation
policy of the design notes (a pixel no image exposes well takes its value from the
shortest or the longest exposure, and the mask says so).

It is the oracle the table engine (:mod:`derender.engine.tables`) is tested against to
1e-5, and the path for stacks that have no 8-bit table form (16-bit TIFFs, sub-pixel
warped frames): a 65536-entry table per channel would not fit OpenCV's 8-bit ``LUT``.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult
from derender.engine.weights import F32_MAX, get_weight

__all__ = [
    "merge_linear",
]


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


def _checked_inputs(images, times, linear, domain: str, channel_weights: str, image_weights):
    """:func:`merge_linear`'s inputs checked: ``(images, times, linear array or None, image weights)``."""
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise InputError(f"images must have shape (N, H, W, 3), got {images.shape}")
    n = images.shape[0]
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
        return images, t, lin_arr, np.ones(n)
    iw = np.asarray(image_weights, dtype=np.float64).reshape(-1)
    if iw.size != n or not np.all(np.isfinite(iw)) or np.any(iw < 0):
        raise InputError("image_weights must be N finite non-negative numbers")
    return images, t, lin_arr, iw


def _frame_values(j: int, lin: np.ndarray, shape: tuple, t: float, log_t: float, domain: str,
                  log_input: bool) -> np.ndarray:
    """Frame ``j``'s radiance estimates (float64) in the merge's domain from its linearised block."""
    if lin.shape != shape:
        raise ValueError(f"linearisation of image {j} has shape {lin.shape}, expected {shape}")
    if domain == "linear":
        return np.exp(lin.astype(np.float64) - log_t) if log_input else lin.astype(np.float64) * (1.0 / t)
    if log_input:
        return lin.astype(np.float64) - log_t
    lin64 = lin.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(lin64 > 0, np.log(lin64), np.nan) - log_t


def _frame_weights(j: int, zj: np.ndarray, weight_fn, wfun, channel_weights: str) -> np.ndarray:
    """Frame ``j``'s float32 weights of a block (custom ``weight_fn(j, block)`` or the named
    weight), shared between channels as ``channel_weights`` says."""
    if weight_fn is not None:
        wj = np.asarray(weight_fn(j, zj), dtype=np.float32)
        wj = np.where(np.isfinite(wj) & (wj > 0), wj, np.float32(0))
    else:
        wj = np.asarray(wfun(zj), dtype=np.float32)
    if wj.shape not in (zj.shape, zj.shape[:2]):
        raise ValueError(f"weights of image {j} have shape {wj.shape}, expected {zj.shape}")
    return _combine_channels(wj, channel_weights)


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
    times : (N,) array_like
        Exposure times in seconds (positive).
    images : (N, H, W, 3) array
        Rendered values in [0, 1]; they drive the weights and the bright/dark decision of
        the saturation policy.
    weight : str or callable
        A name in :data:`WEIGHTS` or a callable on [0, 1] values.
    image_weights : (N,) array_like, optional
        Per-image factors (e.g. ``t_j**2`` for Robertson's maximum-likelihood estimate).
    weight_fn : callable, optional
        ``weight_fn(j, block) -> (h, W) or (h, W, 3)`` replacing ``weight`` (e.g. inverse
        variances of a probabilistic method).
    channel_weights : str
        ``"independent"`` (each channel its own weight), ``"mean"`` (OpenCV: the mean over
        channels for all three) or ``"min"`` (a pixel counts only where all channels are
        usable; for methods that mix channels).
    domain : str
        ``"linear"``: ``E = sum w lin/t / sum w``; ``"log"``: Debevec's eq. 6,
        ``ln E = sum w (ln lin - ln t) / sum w``.
    log_input : bool
        ``linear`` gives ``ln`` of the linearised values (e.g. ``g(z)`` directly), saving an
        exp/log round trip.
    bright_threshold : float
        The rendered value at or above which a pixel without weight counts as over-exposed
        (Notes).
    block_rows : int, optional
        Rows per block (default: ~256k pixels per block).
    info : dict, optional
        Entries added to the result's ``info``.

    Returns
    -------
    HDRResult
        ``radiance`` (H, W, 3) float32 in the units of ``linear / times``, finite; ``mask``
        (0 merged, 1 bright fallback, 2 dark fallback); ``info`` (``n_bright``, ``n_dark``,
        ``domain``, ...); no variance.

    Raises
    ------
    InputError
        Arrays of inconsistent shapes, times that are not positive, an unknown weight,
        ``channel_weights`` or ``domain``, malformed ``image_weights``.
    ValueError
        A callable ``linear`` or ``weight_fn`` returning a block of the wrong shape.

    Notes
    -----
    Saturation policy (``docs/architecture.md``): where the total weight of a channel is 0, the
    value comes from the shortest exposure if that exposure's value of the channel is
    ``>= bright_threshold`` (over-exposed everywhere), else from the longest
    (under-exposed everywhere); ``mask`` is 1 (bright) or 2 (dark) where any channel
    took a fallback (bright wins). Non-finite linearised values (and, in the log
    domain, values <= 0) get weight 0, as do non-finite or negative custom weights;
    the result is finite float32. Memory: works on blocks of ``block_rows`` rows
    (default: ~256k pixels per block), never on full-size float64 temporaries.

    Examples
    --------
    With the camera's response known (gamma 2.2 here), only the weighted average is left:

    >>> import numpy as np
    >>> import derender
    >>> radiance = np.geomspace(0.01, 1.0, 16 * 16).reshape(16, 16, 1).repeat(3, axis=2)   # 100:1
    >>> times = np.array([0.25, 1.0, 4.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> images = codes / 255
    >>> result = derender.merge_linear(images ** 2.2, times, images)
    >>> result.radiance.dtype, bool(np.allclose(result.radiance, radiance, rtol=0.03))
    (dtype('float32'), True)
    """
    t0 = time.perf_counter()
    images, t, lin_arr, iw = _checked_inputs(images, times, linear, domain, channel_weights, image_weights)
    n, h, w_, _ = images.shape
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
            v = _frame_values(j, np.asarray(lin), zj.shape, t[j], log_t[j], domain, log_input)
            wj = _frame_weights(j, zj, weight_fn, wfun, channel_weights)
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
        radiance[r0:r1] = np.clip(np.nan_to_num(res, nan=0.0), -F32_MAX, F32_MAX)
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
