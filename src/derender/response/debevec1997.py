"""Response recovery of Debevec & Malik (1997), "Recovering High Dynamic Range Radiance Maps from Photographs".

Sec. 2.1, eq. 3: minimise ``sum_ij {w(Z_ij) [g(Z_ij) - ln E_i - ln t_j]}^2 + lambda sum_z
[w(z) g''(z)]^2`` over the curve ``g = ln f^-1`` and the log irradiances of sampled
pixels, one channel at a time, with ``g(128) = 0``; solved as a sparse least-squares
system. Hat weights, lambda 30 and 256 grid samples by default; a curve that is not
monotonic is made so (isotonic regression).

Grid samples that see a clipped neighbour while unclipped themselves are left out
(:func:`~derender.response.curves.uniform_samples`): pixels at the rim of a window or a lamp,
whose codes stop following the exposure once their clipped neighbour leaks into them through
demosaicing and chroma noise reduction, bent the curve's top end (docs/results-luminance.md).

The bound-aware top (``censor=True``, what :func:`derender.hdr.classic.merge_debevec` uses; the
paper's system is ``censor=False``): an observation ``Z_ij`` whose code has stopped following the
exposure is a *bound* (``ln E_i + ln t_j >= g(Z_ij)``), not a data row of eq. 3. Which they are:

* :func:`censored_observations`: with the frames in order of exposure, an upper-half code that
  rises by at most one code in the next longer frame, and every longer frame's code of that
  pixel (a camera whose white is below 255, a colour clipped in the sensor before the 3x3 matrix,
  noise added after clipping);
* then up to :data:`CENSOR_ROUNDS` rounds of a residual test (:func:`_residual_censor`): an
  upper-half code more than ``max(CENSOR_RESIDUAL, CENSOR_SPREAD * s)`` below the mean of at
  least two other well-exposed, mutually agreeing observations of its pixel (``s``: the frames'
  own disagreement on lower-half codes);
* :func:`white_codes`: per channel, the code from which on most observations are censored; the
  merge gives codes at or above it no weight (clipped, as 255 is).

Why: those codes gave the curve's top its data, and the least-squares curve followed them (4x at
code 250 on the luminance family's gamma camera), and which of them the grid happened to keep
moved the whole curve: the evalglare illuminance of one bracket read -6.3 .. +12.1 % over sample
grids (docs/results-luminance.md, "The top of Debevec's curve").
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
    uniform_samples,
)

__all__ = [
    "calibrate_debevec_from_samples",
    "bootstrap_curve_sd",
    "bracket_curve_sd",
    "BOOTSTRAP_REPLICATES",
    "solve_debevec",
    "solve_debevec_tied",
    "debevec_system",
    "solve_dense",
    "calibrate_debevec",
    "censored_observations",
    "white_codes",
    "CENSOR_RESIDUAL",
    "CENSOR_ROUNDS",
    "CENSOR_SPREAD",
]

#: A kept observation in the upper half of the codes whose log exposure falls this far (natural
#: log) below its pixel's estimate from the other frames is censored (:func:`_residual_censor`).
CENSOR_RESIDUAL = 0.3
#: Rounds of the residual test (each solves the system again; they stop when nothing changes).
CENSOR_ROUNDS = 3


def calibrate_debevec_from_samples(samples: np.ndarray, times: np.ndarray, hists_fn: Callable[[], np.ndarray], *,
                                   lam: float = DEFAULT_LAMBDA, n_samples: int = DEFAULT_SAMPLES,
                                   sampling: str = "grid", seed: int = 0, balance: bool = False,
                                   tie: float = 0.0, censor: bool = False) -> ResponseCurves:
    """:func:`calibrate_debevec` (hat weights, monotonic) from pre-drawn samples (N, P, 3).

    ``hists_fn()`` gives the per-image code histograms (N, 3, 256), read only when some channel
    has no usable code among the samples (histogram samples are then added). ``balance``:
    offset R and B so that neutral colours stay neutral
    (:func:`~derender.response.curves.balance_channels` on ``samples``; needs grid samples:
    every channel of a sample from the same pixel). ``tie``: weight of the channel tie of
    :func:`solve_debevec_tied` (0: channels solved independently, the paper). ``censor``: codes
    that stopped following the exposure are bounds, not data (:func:`censored_observations`, then
    up to :data:`CENSOR_ROUNDS` rounds of a residual test; module docstring).
    """
    return _calibrate(samples, times, lambda: histogram_samples(hists_fn(), n_samples), lam=lam,
                      n_samples=n_samples, sampling=sampling, seed=seed, weights="hat", n_levels=N_CODES,
                      monotonic=True, balance=balance, tie=tie, censor=censor)


#: Refits of :func:`bootstrap_curve_sd` (each one Debevec solve on resampled samples).
BOOTSTRAP_REPLICATES = 8


def bootstrap_curve_sd(pool: np.ndarray, times: np.ndarray, hists_fn: Callable[[], np.ndarray], *, n: int,
                       replicates: int = BOOTSTRAP_REPLICATES, seed: int = 0, **calibrate) -> float:
    """How tightly the bracket's own samples pin the shape of the curve (a bootstrap over the
    calibration samples): the median, over the channels and the codes some sample shows with
    weight (``0 < z < 255``), of the standard deviation of ``g(z)`` (ln, so a relative sd of the
    radiance) over ``replicates`` refits of :func:`calibrate_debevec_from_samples`
    (``**calibrate``: its keywords), each on ``n`` samples drawn with replacement from ``pool``
    (N, M, 3), every usable grid sample of the bracket (``numpy.random.default_rng(seed)``: the
    same answer on every machine). Each refit's curve is taken relative to its mean over the
    codes shown (``g`` is known up to a constant per channel: a scale of the radiance).

    Many frames close in exposure (Debevec's Memorial: 16 at 1 EV) pin the curve to ~0.01; a
    7-frame bracket whose rendering changes between frames leaves 0.03-0.06 (the simulator's
    families; docs/uncertainty.md)."""
    z = np.asarray(pool)
    m = z.shape[1]
    rng = np.random.default_rng(int(seed))
    shown = np.zeros((N_CODES, 3), dtype=bool)
    for c in range(3):
        zc = z[:, :, c].ravel().astype(np.int64)
        shown[np.unique(zc[(zc > 0) & (zc < N_CODES - 1)]), c] = True
    if m < 2 or not shown.any():
        return 0.0
    gs = []
    for _ in range(int(replicates)):
        idx = np.sort(rng.integers(0, m, size=int(n)))
        g = np.asarray(calibrate_debevec_from_samples(z[:, idx], times, hists_fn, **calibrate).log_inverse,
                       dtype=np.float64)
        for c in range(3):
            if shown[:, c].any():
                g[:, c] -= g[shown[:, c], c].mean()
        gs.append(g)
    sd = np.std(np.asarray(gs), axis=0)
    return float(np.median(sd[shown]))


def bracket_curve_sd(cluster_codes: np.ndarray, times: np.ndarray, hists_fn: Callable[[], np.ndarray], *,
                     lam: float, tie: float, seed: int = 0, replicates: int = BOOTSTRAP_REPLICATES) -> float:
    """:func:`bootstrap_curve_sd` of a bracket: the pool is every usable grid sample of
    ``cluster_codes`` (N, 9 M, 3), the codes at :func:`~derender.response.curves.cluster_positions`
    (or Robertson's clusters; :func:`~derender.response.curves.uniform_samples` with no limit),
    each refit the merge's own calibration on :data:`~derender.response.curves.DEFAULT_SAMPLES`
    of them (grid, channels balanced, bound-aware top, ``lam``, ``tie``). One number per
    bracket, whichever method merges it (:mod:`derender.engine.variance`, the ``shared`` term)."""
    pool = uniform_samples(cluster_codes, np.iinfo(np.int32).max)
    return bootstrap_curve_sd(pool, times, hists_fn, n=DEFAULT_SAMPLES, replicates=replicates, seed=seed, lam=lam,
                              n_samples=DEFAULT_SAMPLES, sampling="grid", balance=True, tie=tie, censor=True)


def censored_observations(codes: np.ndarray, log_times: np.ndarray, n_levels: int = N_CODES) -> np.ndarray:
    """Which observations of one channel are data and which are censored bounds: (N, P) bool, True = data.

    ``codes`` (N, P) of P pixels in N frames. With the frames in order of exposure, a pixel's
    code in the upper half that does not rise by more than one code in the next longer frame has
    stopped following the exposure: the
    camera's channel has saturated there, below the top code (a colour clipped before the 3x3
    matrix, a camera whose white is 250, noise added after clipping). That observation and
    every longer frame's are bounds (the exposure is *at least* what the code says), not data.
    """
    z = np.asarray(codes, dtype=np.int64)
    order = np.argsort(np.asarray(log_times, dtype=np.float64).reshape(-1), kind="stable")
    zs = z[order]
    mid = n_levels // 2
    stuck = (zs[:-1] >= mid) & (zs[1:] <= zs[:-1] + 1)
    cens = np.logical_or.accumulate(np.concatenate([stuck, np.zeros((1, z.shape[1]), bool)]), axis=0)
    keep = np.empty_like(cens)
    keep[order] = ~cens
    return keep


#: Fewest observations (with a longer frame after them) at or above a code for :func:`white_codes` to judge it.
WHITE_MIN_COUNT = 8
#: Share of censored observations at or above a code that makes it the channel's white.
WHITE_SHARE = 0.5


def white_codes(codes: list[np.ndarray], keep: list[np.ndarray], log_times: np.ndarray,
                n_levels: int = N_CODES) -> list[int]:
    """Per channel, the code ``z_w`` from which on the bracket's frames stop following the
    exposure: the camera's white for that channel. Going down from the top code, every code
    seen at least :data:`WHITE_MIN_COUNT` times (in frames with a longer one after them: the
    longest frame's codes cannot show that they stopped) whose observations are censored
    (:func:`censored_observations` and the residual test) at least :data:`WHITE_SHARE` of the
    time extends the white down to it; the first such code censored less often ends the search
    (codes seen fewer times are passed over). ``n_levels - 1`` when no code qualifies; never
    below the upper quarter of the codes."""
    order = np.argsort(np.asarray(log_times, dtype=np.float64).reshape(-1), kind="stable")
    last = order[-1]
    out = []
    for zc, kc in zip(codes, keep):
        z = np.delete(np.asarray(zc, dtype=np.int64), last, axis=0).ravel()
        cens = ~np.delete(np.asarray(kc, dtype=bool), last, axis=0).ravel()
        tot = np.bincount(z, minlength=n_levels)
        bad = np.bincount(z[cens], minlength=n_levels)
        white = n_levels - 1
        for zz in range(n_levels - 2, (3 * n_levels) // 4 - 1, -1):
            if tot[zz] < WHITE_MIN_COUNT:
                continue
            if bad[zz] < WHITE_SHARE * tot[zz]:
                break
            white = zz
        out.append(int(white))
    return out


#: Hat weight from which an observation is well exposed enough to support the residual test.
SUPPORT_WEIGHT = 0.25
#: The residual test's threshold is at least this many times the frames' own disagreement (robust
#: sd of the lower-half residuals): brackets whose frames disagree anyway (an auto pipeline) censor less.
CENSOR_SPREAD = 6.0


def _residual_censor(g: np.ndarray, codes: list[np.ndarray], keep: list[np.ndarray], log_t: np.ndarray,
                     weights: Any, n_levels: int) -> int:
    """Censor (in ``keep``, in place) the upper-half observations whose log exposure ``g(z) - ln t``
    falls more than :data:`CENSOR_RESIDUAL` below the mean of at least two other kept, well-exposed
    (hat weight >= :data:`SUPPORT_WEIGHT`) observations of the same pixel that agree with each other
    within that threshold: a code held down by saturation that still rises with the exposure, which
    :func:`censored_observations` cannot see (a channel mixed by the 3x3 matrix from a clipped
    sensor channel, or the longest frame). Without that support (brackets whose steps leave one
    well-exposed frame per pixel) nothing is censored. The threshold is at least
    :data:`CENSOR_SPREAD` times the frames' own disagreement (the robust sd of the same residual on
    lower-half codes, where nothing saturates): on an auto pipeline, whose frames disagree by 0.2-0.7
    in ln there, the test then censors almost nothing. Returns how many were censored."""
    wl = level_weights(weights, n_levels)
    n_new = 0
    for c, zc in enumerate(codes):
        z = np.asarray(zc, dtype=np.int64)
        le = g[z, c] - log_t[:, None]
        good = keep[c] & (wl[z] >= SUPPORT_WEIGHT)
        cand = keep[c] & (z >= n_levels // 2)
        stats = []
        for j in range(z.shape[0]):
            oth = good.copy()
            oth[j] = False
            n = oth.sum(axis=0)
            lo = np.where(oth, le, np.inf).min(axis=0)
            hi = np.where(oth, le, -np.inf).max(axis=0)
            mean = np.where(oth, le, 0.0).sum(axis=0) / np.maximum(n, 1)
            stats.append((n, hi - lo, le[j] - mean))
        # the frames' own disagreement where nothing saturates: lower-half, well-exposed, supported
        low = [st[2][good[j] & (z[j] < n_levels // 2) & (st[0] >= 2)] for j, st in enumerate(stats)]
        low = np.concatenate(low) if low else np.zeros(0)
        spread = 1.4826 * float(np.median(np.abs(low - np.median(low)))) if low.size >= 16 else 0.0
        thr = max(CENSOR_RESIDUAL, CENSOR_SPREAD * spread)
        bad = np.zeros_like(cand)
        for j, (n, rng_, res) in enumerate(stats):
            bad[j] = cand[j] & (n >= 2) & (rng_ <= thr) & (res < -thr)
        keep[c] &= ~bad
        n_new += int(bad.sum())
    return n_new


def _calibrate(samples: np.ndarray, times: np.ndarray, extra_fn: Callable[[], np.ndarray], *, lam: float,
               n_samples: int, sampling: str, seed: int, weights: Any, n_levels: int, monotonic: bool,
               balance: bool, tie: float, censor: bool = False) -> ResponseCurves:
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
    keep = [censored_observations(zc, log_t, n_levels) for zc in per_channel] if censor else None
    g = solve_debevec_tied(per_channel, log_t, lam=lam, weights=weights, n_levels=n_levels, tie=tie, keep=keep)
    rounds = 0
    if censor:
        while rounds < CENSOR_ROUNDS and _residual_censor(g, per_channel, keep, log_t, weights, n_levels):
            rounds += 1
            g = solve_debevec_tied(per_channel, log_t, lam=lam, weights=weights, n_levels=n_levels, tie=tie, keep=keep)
    fixed = [bool(np.any(np.diff(g[:, c]) < 0)) for c in range(3)]
    if monotonic:
        g = make_monotonic(g)
    params = {"lambda": float(lam), "n_samples": int(n_samples), "sampling": sampling, "seed": int(seed),
              "weights": weights if isinstance(weights, str) else "custom", "monotonic_fixed": fixed,
              "tie": float(tie)}
    if censor:
        params["censored"] = [int((~k).sum()) for k in keep]
        params["censor_rounds"] = rounds
        params["white_codes"] = white_codes(per_channel, keep, log_t, n_levels)
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
                    n_levels: int, keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The reduced normal equations ``(S, rhs)`` of :func:`solve_debevec` for one channel."""
    z = np.asarray(codes).astype(np.int64)
    b = np.asarray(log_times, dtype=np.float64).reshape(-1)
    schur, m, w2, dinv = debevec_system(z, lam, weights, n_levels, keep)
    b_g = np.bincount(z.ravel(), weights=(w2 * b[:, None]).ravel(), minlength=n_levels)
    b_e = -(w2 * b[:, None]).sum(axis=0)
    return schur, b_g - m @ (dinv * b_e)


def solve_debevec_tied(codes: list[np.ndarray], log_times: np.ndarray, lam: float = DEFAULT_LAMBDA,
                       weights: Any = None, n_levels: int = 256, tie: float = DEFAULT_TIE,
                       keep: list[np.ndarray] | None = None) -> np.ndarray:
    """The three channels' curves of :func:`solve_debevec` in one system, tied.

    ``codes``: per channel an (N_img, P_c) array. Each channel keeps its own data rows,
    smoothness and ``g_c(mid) = 0``; added is ``tie * sum_{c < c'} sum_z [Delta (g_c - g_c')(z)]^2``
    (:func:`~derender.response.curves.solve_tied`): the curves may differ by an offset (the
    white balance, set afterwards by :func:`~derender.response.curves.balance_channels`) but
    their difference pays for changing with the code. Debevec & Malik solve each channel
    alone; where a channel has few samples (the ends of the range, a channel the scene
    hardly exposes) its curve then bends on its own, and grey pixels rendered with equal
    codes come out tinted at some levels and not at others. ``tie = 0``: the paper's
    independent channels. ``keep``: per channel an (N_img, P_c) bool mask of the observations
    that have a data row (None: all). Returns ``g`` (n_levels, 3).
    """
    blocks, rhs = [], []
    for c, zc in enumerate(codes):
        z = np.asarray(zc)
        if z.ndim != 2:
            raise InputError(f"codes must be (N_img, P), got {z.shape}")
        if z.size and (z.min() < 0 or z.max() >= n_levels):
            raise InputError(f"codes must lie in [0, {n_levels - 1}]")
        a, r = _debevec_normal(z, log_times, lam, weights, n_levels, None if keep is None else keep[c])
        blocks.append(a)
        rhs.append(r)
    return solve_tied(blocks, rhs, tie)


def debevec_system(codes: np.ndarray, lam: float, weights: Any = "hat", n_levels: int = 256,
                   keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Debevec & Malik's normal equations for one channel with the diagonal ``ln E`` block
    eliminated (:func:`solve_debevec`): ``codes`` (N, P) integer, data rows weighted by
    ``w(Z)``, ``g(mid) = 0`` with weight 1, smoothness ``lam w(z) g''(z)``. Returns ``(S, M, w2,
    dinv)``: the Schur complement ``S`` (n_levels, n_levels), the coupling ``M[z, p] = -sum_j
    w2[j, p] [Z_jp = z]``, the squared weights ``w2`` (N, P) and ``dinv`` (P,), 1 / the ``ln E``
    block's diagonal (0 for samples with no weight). For log exposures ``b`` the right-hand
    side is ``b_g - M @ (dinv * b_e)`` with ``b_g[z] = sum w2 b_j [Z = z]``, ``b_e = -w2.T b``:
    one factorisation serves every ``b`` (:func:`derender.hdr.stabilize.filmic` re-estimates
    exposures with it). ``keep`` (N, P) bool: observations without it get no data row (censored
    bounds, :func:`censored_observations`)."""
    z = np.asarray(codes, dtype=np.int64)
    p = z.shape[1]
    wl = level_weights(weights, n_levels)
    w2 = wl[z] ** 2  # (N, P) squared data-row weights
    if keep is not None:
        w2 = np.where(np.asarray(keep, dtype=bool), w2, 0.0)
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
                      monotonic: bool = True, balance: bool = False, tie: float = 0.0,
                      censor: bool = False) -> ResponseCurves:
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

    Parameters
    ----------
    stack : Stack
        The bracket (8- or 16-bit images in [0, 1] and their exposure times).
    lam : float
        Weight of the smoothness term (the paper's lambda), non-negative.
    n_samples : int
        Pixels sampled for the system.
    sampling : str
        ``"grid"``, ``"random"`` or ``"histogram"`` (:func:`sample_pixels`).
    seed : int
        Seeds the sampling.
    weights : str or callable
        The weight of a code (``"hat"``: the paper's triangle).
    n_levels : int
        Codes per channel (256 for 8-bit images).
    monotonic : bool
        Replace a non-monotonic solution by its isotonic fit.
    balance : bool
        Offset R and B so that neutral colours stay neutral.
    tie : float
        Weight of the channel tie (:func:`solve_debevec_tied`; 0: the paper).
    censor : bool
        Codes that stopped following the exposure are bounds, not data (the bound-aware top of
        the module docstring; False: the paper's system).

    Returns
    -------
    ResponseCurves
        ``log_inverse`` (n_levels, 3) ``g = ln f^-1``, ``method`` ``"debevec"`` and ``params``.

    Raises
    ------
    InputError
        A negative or non-finite ``lam``, or a bracket without usable codes.

    Examples
    --------
    A gamma-2.2 camera: the recovered ``g`` rises by 2.2 natural-log units per unit of ``ln z``:

    >>> import numpy as np
    >>> import derender
    >>> radiance = np.geomspace(0.01, 1.0, 32 * 32).reshape(32, 32, 1).repeat(3, axis=2)   # 100:1
    >>> times = np.array([0.25, 1.0, 4.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> stack = derender.Stack((codes / 255).astype(np.float32), times)
    >>> curves = derender.calibrate_debevec(stack)
    >>> g = curves.log_inverse[:, 1]
    >>> slope = (g[200] - g[50]) / (np.log(200) - np.log(50))
    >>> curves.log_inverse.shape, bool(np.all(np.diff(g) >= 0)), round(float(slope), 1)
    ((256, 3), True, 2.2)
    """
    stack = as_stack(stack)
    if lam < 0 or not np.isfinite(lam):
        raise InputError(f"lambda must be a non-negative number, got {lam}")
    check_usable(stack, n_levels)
    samples = sample_pixels(stack, n_samples=n_samples, method=sampling, seed=seed, n_levels=n_levels)
    return _calibrate(samples, stack.times,
                      lambda: sample_pixels(stack, n_samples=n_samples, method="histogram", n_levels=n_levels),
                      lam=lam, n_samples=n_samples, sampling=sampling, seed=seed, weights=weights, n_levels=n_levels,
                      monotonic=monotonic, balance=balance, tie=tie, censor=censor)
