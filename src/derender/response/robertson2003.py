"""Response recovery of Robertson, Borman & Stevenson (2003), "Estimation-theoretic approach to dynamic range enhancement using multiple exposures".

Alternates the ML radiance ``E_i = sum_j w_ij t_j I(Z_ij) / sum_j w_ij t_j^2`` and the
response ``I(m) = mean of E_i t_j over the pixels with code m`` until the change falls
below ``tol``, with the Gaussian-like weight ``exp(-16 (z - 1/2)^2)``; normalised so
that ``I(128) = 1`` per channel.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.core.errors import StackError
from derender.core.types import Stack
from derender.response.curves import (
    CHANNELS,
    ResponseCurves,
    as_stack,
    check_usable,
    grid_positions,
    level_weights,
    make_monotonic,
    to_codes,
)

__all__ = [
    "calibrate_robertson",
    "robertson_positions",
    "robertson_from_samples",
]


# --------------------------------------------------------------------------- Robertson
def calibrate_robertson(stack: Stack, n_iter: int = 30, tol: float = 1e-6, max_pixels: int = 40_000,
                        weight: Any = "gaussian", n_levels: int = 256, seed: int = 0) -> ResponseCurves:
    """Iterative response recovery of Robertson, Borman & Stevenson (1999; JEI 2003, Sec. 3).

    Alternates the maximum-likelihood radiance ``E_i = sum_j w_ij t_j I(z_ij) /
    sum_j w_ij t_j^2`` with ``I(m) = mean of t_j E_i over all (i, j) with z_ij = m``,
    normalising ``I(mid) = 1``; starts from the linear ``I(m) = m / mid``; stops after
    ``n_iter`` iterations or when the mean squared change of ``I`` drops below ``tol``.
    Uses at most ``max_pixels`` pixels (a regular grid). Levels never observed are
    interpolated in ``I``; the result is made non-decreasing in ``ln I`` like
    :func:`calibrate_debevec`.
    """
    stack = as_stack(stack)
    check_usable(stack, n_levels)
    n_img, h, w_, _ = stack.images.shape
    ys, xs = robertson_positions(h, w_, max_pixels, seed)
    z = to_codes(stack.images[:, ys, xs, :], n_levels)  # (N, P, 3)
    return robertson_from_samples(z, stack.times, n_iter=n_iter, tol=tol, max_pixels=max_pixels, weight=weight,
                                  n_levels=n_levels)


def robertson_positions(h: int, w: int, max_pixels: int = 40_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The pixels :func:`calibrate_robertson` reads: at most ``max_pixels`` on a regular grid (no border)."""
    return grid_positions(h, w, min(int(max_pixels), h * w), seed, border=0.0)


def robertson_from_samples(z: np.ndarray, times: np.ndarray, n_iter: int = 30, tol: float = 1e-6,
                           max_pixels: int = 40_000, weight: Any = "gaussian", n_levels: int = 256) -> ResponseCurves:
    """:func:`calibrate_robertson` on sampled codes ``z`` (N, P, 3) int of a bracket with ``times`` (s)."""
    times = np.asarray(times, dtype=np.float64)
    wl = level_weights(weight, n_levels)
    t = times[:, None, None]
    wz = wl[z]
    wt = wz * t  # (N, P, 3)
    den = (wz * t * t).sum(axis=0)  # (P, 3), constant over iterations
    live = den > 0
    inv_den = np.where(live, 1.0 / np.where(live, den, 1.0), 0.0)
    flat = (z * 3 + np.arange(3)).ravel()  # level-major index into the (n_levels, 3) table
    live_obs = np.broadcast_to(live, z.shape).ravel().astype(np.float64)
    card = np.bincount(flat, weights=live_obs, minlength=3 * n_levels).reshape(n_levels, 3)
    seen = card > 0
    for c in range(3):
        if not np.any(seen[:, c]):
            raise StackError(f"channel {CHANNELS[c]} has no usable pixel; cannot recover its response")
    mid = n_levels // 2
    inv = np.repeat((np.arange(n_levels, dtype=np.float64) / mid)[:, None], 3, axis=1)
    levels = np.arange(n_levels)
    iters = 0
    for iters in range(1, int(n_iter) + 1):
        e = (wt * inv.ravel()[flat].reshape(z.shape)).sum(axis=0) * inv_den  # (P, 3) ML radiance
        te = (t * e[None]).ravel() * live_obs
        tot = np.bincount(flat, weights=te, minlength=3 * n_levels).reshape(n_levels, 3)
        new = np.empty_like(inv)
        for c in range(3):
            sc = seen[:, c]
            new[:, c] = np.interp(levels, levels[sc], tot[sc, c] / card[sc, c])
            if new[mid, c] <= 0:
                raise StackError(f"channel {CHANNELS[c]}: degenerate response (mid-grey maps to zero)")
            new[:, c] /= new[mid, c]
        change = float(np.mean((new - inv) ** 2))
        inv = new
        if change < tol:
            break
    positive = inv[inv > 0]
    floor = positive.min() * 0.5 if positive.size else 1e-6
    g = np.log(np.maximum(inv, floor))
    # Levels of zero weight (the clipped ends) carry no information in Robertson's update
    # (I(255) is the mean of t E over clipped pixels, i.e. anything above saturation): extend
    # g linearly from the two nearest weighted levels instead, like Debevec's smooth ends.
    nz = np.flatnonzero(wl > 0)
    if nz.size >= 2:
        lo, hi = int(nz[0]), int(nz[-1])
        if lo > 0:
            g[:lo] = g[lo] + (np.arange(lo) - lo)[:, None] * (g[lo + 1] - g[lo])
        if hi < n_levels - 1:
            g[hi + 1:] = g[hi] + (np.arange(hi + 1, n_levels) - hi)[:, None] * (g[hi] - g[hi - 1])
    g = make_monotonic(g)
    return ResponseCurves(log_inverse=g, method="robertson",
                          params={"iterations": iters, "max_pixels": int(max_pixels),
                                  "weight": weight if isinstance(weight, str) else "custom"})
