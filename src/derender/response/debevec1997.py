"""Response recovery of Debevec & Malik (1997), "Recovering High Dynamic Range Radiance Maps from Photographs".

Sec. 2.1, eq. 3: minimise ``sum_ij {w(Z_ij) [g(Z_ij) - ln E_i - ln t_j]}^2 + lambda sum_z
[w(z) g''(z)]^2`` over the curve ``g = ln f^-1`` and the log irradiances of sampled
pixels, one channel at a time, with ``g(128) = 0``; solved as a sparse least-squares
system. Hat weights, lambda 30 and 256 grid samples by default; a curve that is not
monotonic is made so (isotonic regression).

Grid samples that see a clipped neighbour while unclipped themselves are left out
(:func:`~derender.response.curves.uniform_samples`): pixels at the rim of a window or a lamp,
whose codes stop following the exposure once their clipped neighbour leaks into them through
demosaicing and chroma noise reduction, bent the curve's top end (docs/luminance.md).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import N_CODES
from derender.core.parallel import one_blas_thread
from derender.core.types import Stack
from derender.response.curves import (
    DEFAULT_LAMBDA,
    DEFAULT_SAMPLES,
    DEFAULT_TIE,
    ResponseCurves,
    as_stack,
    balance_channels,
    check_usable,
    histogram_samples,
    level_weights,
    make_monotonic,
    sample_pixels,
    solve_tied,
)

__all__ = [
    "calibrate_debevec_from_samples",
    "solve_debevec",
    "solve_debevec_tied",
    "debevec_system",
    "solve_dense",
    "calibrate_debevec",
]


def calibrate_debevec_from_samples(samples: np.ndarray, times: np.ndarray, hists_fn: Callable[[], np.ndarray], *,
                                   lam: float = DEFAULT_LAMBDA, n_samples: int = DEFAULT_SAMPLES,
                                   sampling: str = "grid", seed: int = 0, balance: bool = False,
                                   tie: float = 0.0) -> ResponseCurves:
    """:func:`calibrate_debevec` (hat weights, monotonic) from pre-drawn samples (N, P, 3).

    ``hists_fn()`` gives the per-image code histograms (N, 3, 256), read only when some channel
    has no usable code among the samples (histogram samples are then added). ``balance``:
    offset R and B so that neutral colours stay neutral
    (:func:`~derender.response.curves.balance_channels` on ``samples``; needs grid samples:
    every channel of a sample from the same pixel). ``tie``: weight of the channel tie of
    :func:`solve_debevec_tied` (0: channels solved independently, the paper).
    """
    return _calibrate(samples, times, lambda: histogram_samples(hists_fn(), n_samples), lam=lam,
                      n_samples=n_samples, sampling=sampling, seed=seed, weights="hat", n_levels=N_CODES,
                      monotonic=True, balance=balance, tie=tie)


def _calibrate(samples: np.ndarray, times: np.ndarray, extra_fn: Callable[[], np.ndarray], *, lam: float,
               n_samples: int, sampling: str, seed: int, weights: Any, n_levels: int, monotonic: bool,
               balance: bool, tie: float) -> ResponseCurves:
    """The one body of :func:`calibrate_debevec` and :func:`calibrate_debevec_from_samples`:
    ``extra_fn()`` gives histogram samples for a channel the samples miss."""
    if lam < 0 or not np.isfinite(lam):
        raise InputError(f"lambda must be a non-negative number, got {lam}")
    log_t = np.log(times)
    per_channel = []
    for c in range(3):
        zc = samples[:, :, c]
        if not np.any((zc > 0) & (zc < n_levels - 1)):
            zc = np.concatenate([zc, extra_fn()[:, :, c]], axis=1)
        per_channel.append(zc)
    g = solve_debevec_tied(per_channel, log_t, lam=lam, weights=weights, n_levels=n_levels, tie=tie)
    fixed = [bool(np.any(np.diff(g[:, c]) < 0)) for c in range(3)]
    if monotonic:
        g = make_monotonic(g)
    params = {"lambda": float(lam), "n_samples": int(n_samples), "sampling": sampling, "seed": int(seed),
              "weights": weights if isinstance(weights, str) else "custom", "monotonic_fixed": fixed,
              "tie": float(tie)}
    if balance:
        g, info = balance_channels(g, samples, mode="grey-axis" if tie > 0 else "neutral")
        params.update(info)
    return ResponseCurves(log_inverse=g, method="debevec", params=params)


def solve_debevec(codes: np.ndarray, log_times: np.ndarray, lam: float = DEFAULT_LAMBDA,
                  weights: Any = None, n_levels: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares response recovery of Debevec & Malik (1997), Sec. 2.1 (their ``gsolve``).

    Minimises ``sum_ij [w(Z_ij) (g(Z_ij) - ln E_i - ln dt_j)]^2
    + sum_z [lam w(z) g''(z)]^2`` subject to ``g(mid) = 0`` (one equation of weight 1,
    ``mid = n_levels // 2``), for one channel. ``codes`` is (N_img, P), ``log_times``
    (N_img,), ``weights`` a name, a callable on [0, 1] (default hat) or an
    (n_levels,) table. Returns ``(g (n_levels,), ln E (P,))``.

    Solved exactly (same minimiser as the dense system) via the normal equations with
    the diagonal ``ln E`` block eliminated (Schur complement): an ``n_levels`` square
    system, fast for any number of samples. Samples with zero weight in every image
    get ``ln E = 0`` (their value is undetermined).
    """
    z = np.asarray(codes)
    if z.ndim != 2:
        raise InputError(f"codes must be (N_img, P), got {z.shape}")
    z = z.astype(np.int64)
    b = np.asarray(log_times, dtype=np.float64).reshape(-1)
    n_img, p = z.shape
    if b.size != n_img:
        raise InputError(f"{b.size} log times for {n_img} images")
    if z.size and (z.min() < 0 or z.max() >= n_levels):
        raise InputError(f"codes must lie in [0, {n_levels - 1}]")
    schur, m, w2, dinv = debevec_system(z, lam, weights, n_levels)
    live = dinv > 0
    b_g = np.bincount(z.ravel(), weights=(w2 * b[:, None]).ravel(), minlength=n_levels)
    b_e = -(w2 * b[:, None]).sum(axis=0)
    g = solve_dense(schur, b_g - m @ (dinv * b_e))
    log_e = np.zeros(p)
    log_e[live] = ((w2 * (g[z] - b[:, None])).sum(axis=0))[live] * dinv[live]
    return g, log_e


def _debevec_normal(codes: np.ndarray, log_times: np.ndarray, lam: float, weights: Any,
                    n_levels: int) -> tuple[np.ndarray, np.ndarray]:
    """The reduced normal equations ``(S, rhs)`` of :func:`solve_debevec` for one channel."""
    z = np.asarray(codes).astype(np.int64)
    b = np.asarray(log_times, dtype=np.float64).reshape(-1)
    schur, m, w2, dinv = debevec_system(z, lam, weights, n_levels)
    b_g = np.bincount(z.ravel(), weights=(w2 * b[:, None]).ravel(), minlength=n_levels)
    b_e = -(w2 * b[:, None]).sum(axis=0)
    return schur, b_g - m @ (dinv * b_e)


def solve_debevec_tied(codes: list[np.ndarray], log_times: np.ndarray, lam: float = DEFAULT_LAMBDA,
                       weights: Any = None, n_levels: int = 256, tie: float = DEFAULT_TIE) -> np.ndarray:
    """The three channels' curves of :func:`solve_debevec` in one system, tied.

    ``codes``: per channel an (N_img, P_c) array. Each channel keeps its own data rows,
    smoothness and ``g_c(mid) = 0``; added is ``tie * sum_{c < c'} sum_z [Delta (g_c - g_c')(z)]^2``
    (:func:`~derender.response.curves.solve_tied`): the curves may differ by an offset (the
    white balance, set afterwards by :func:`~derender.response.curves.balance_channels`) but
    their difference pays for changing with the code. Debevec & Malik solve each channel
    alone; where a channel has few samples (the ends of the range, a channel the scene
    hardly exposes) its curve then bends on its own, and grey pixels rendered with equal
    codes come out tinted at some levels and not at others. ``tie = 0``: the paper's
    independent channels. Returns ``g`` (n_levels, 3).
    """
    blocks, rhs = [], []
    for zc in codes:
        z = np.asarray(zc)
        if z.ndim != 2:
            raise InputError(f"codes must be (N_img, P), got {z.shape}")
        if z.size and (z.min() < 0 or z.max() >= n_levels):
            raise InputError(f"codes must lie in [0, {n_levels - 1}]")
        a, r = _debevec_normal(z, log_times, lam, weights, n_levels)
        blocks.append(a)
        rhs.append(r)
    return solve_tied(blocks, rhs, tie)


def debevec_system(codes: np.ndarray, lam: float, weights: Any = "hat",
                   n_levels: int = 256) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Debevec & Malik's normal equations for one channel with the diagonal ``ln E`` block
    eliminated (:func:`solve_debevec`): ``codes`` (N, P) integer, data rows weighted by
    ``w(Z)``, ``g(mid) = 0`` with weight 1, smoothness ``lam w(z) g''(z)``. Returns ``(S, M, w2,
    dinv)``: the Schur complement ``S`` (n_levels, n_levels), the coupling ``M[z, p] = -sum_j
    w2[j, p] [Z_jp = z]``, the squared weights ``w2`` (N, P) and ``dinv`` (P,), 1 / the ``ln E``
    block's diagonal (0 for samples with no weight). For log exposures ``b`` the right-hand
    side is ``b_g - M @ (dinv * b_e)`` with ``b_g[z] = sum w2 b_j [Z = z]``, ``b_e = -w2.T b``:
    one factorisation serves every ``b`` (:func:`derender.hdr.stabilize.filmic` re-estimates
    exposures with it)."""
    z = np.asarray(codes, dtype=np.int64)
    p = z.shape[1]
    wl = level_weights(weights, n_levels)
    w2 = wl[z] ** 2  # (N, P) squared data-row weights
    d = w2.sum(axis=0)  # diagonal of the ln E block
    # g-g block: data + constraint + smoothness
    a_gg = np.diag(np.bincount(z.ravel(), weights=w2.ravel(), minlength=n_levels))
    mid = n_levels // 2
    a_gg[mid, mid] += 1.0
    k = np.arange(1, n_levels - 1)
    s = (lam * wl[k]) ** 2
    stencil = np.array([1.0, -2.0, 1.0])
    for a in range(3):
        for c in range(3):
            a_gg[k - 1 + a, k - 1 + c] += s * stencil[a] * stencil[c]
    # g-E coupling: M[z, p] = -sum_j w2[j, p] [z_jp = z]
    m = np.zeros((n_levels, p))
    np.add.at(m, (z, np.broadcast_to(np.arange(p), z.shape)), -w2)
    live = d > 0
    dinv = np.zeros(p)
    dinv[live] = 1.0 / d[live]
    with one_blas_thread():      # a 256-square system: threads only wait on a busy machine
        schur = a_gg - (m * dinv) @ m.T
    return schur, m, w2, dinv


def solve_dense(a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``a x = rhs`` for a small dense system (LU on one BLAS thread; least squares where ``a``
    is singular or the solution is not finite)."""
    with one_blas_thread():
        try:
            x = np.linalg.solve(a, rhs)
            if not np.all(np.isfinite(x)):
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            x = np.linalg.lstsq(a, rhs, rcond=None)[0]
    return x


def calibrate_debevec(stack: Stack, *, lam: float = DEFAULT_LAMBDA, n_samples: int = DEFAULT_SAMPLES,
                      sampling: str = "grid", seed: int = 0, weights: Any = "hat", n_levels: int = 256,
                      monotonic: bool = True, balance: bool = False, tie: float = 0.0) -> ResponseCurves:
    """Recover ``g = ln f^-1`` per channel with :func:`solve_debevec` (Debevec & Malik 1997).

    Samples by :func:`sample_pixels`; channels solved independently, each with
    ``g(mid) = 0`` (see the module docstring for what that implies for colour).
    With ``monotonic=True`` a non-monotonic least-squares solution is replaced by its
    isotonic (pool-adjacent-violators) least-squares fit, so ``g`` is non-decreasing;
    ``params["monotonic_fixed"]`` says per channel whether that was needed. If a
    grid sample misses every usable code of a channel, histogram samples are added.

    ``balance=False`` keeps the paper's ``g(mid) = 0`` in every channel (mid-grey codes
    neutral). ``balance=True`` (what :func:`derender.hdr.classic.merge_debevec` uses) then
    offsets R and B by :func:`~derender.response.curves.balance_channels` so that the
    near-neutral, well-exposed sampled pixels of the bracket come out neutral
    (``g_G(mid) = 0`` stays; ``params["channel_offsets"]`` says by how much).
    """
    stack = as_stack(stack)
    if lam < 0 or not np.isfinite(lam):
        raise InputError(f"lambda must be a non-negative number, got {lam}")
    check_usable(stack, n_levels)
    samples = sample_pixels(stack, n_samples=n_samples, method=sampling, seed=seed, n_levels=n_levels)
    return _calibrate(samples, stack.times,
                      lambda: sample_pixels(stack, n_samples=n_samples, method="histogram", n_levels=n_levels),
                      lam=lam, n_samples=n_samples, sampling=sampling, seed=seed, weights=weights, n_levels=n_levels,
                      monotonic=monotonic, balance=balance, tie=tie)
