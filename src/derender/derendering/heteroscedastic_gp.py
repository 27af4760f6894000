"""One cluster's channel GP for the local GP of paper 2: maximum-likelihood fit with a
most-likely heteroscedastic noise GP.

The GP has an ARD squared-exponential kernel plus noise,
``k(a, b) = sf^2 exp(-0.5 sum_d (a_d - b_d)^2 / l_d^2) + sn^2 r(a) [a = b]``
(:func:`se_kernel`), its hyper-parameters ``theta = [log l_1..l_d, log sf, log sn]`` by maximum
marginal likelihood: L-BFGS-B on the negative log marginal likelihood and its gradient
(Rasmussen & Williams eqs. 2.30, 5.8/5.9; ``_gp_nll``, compiled as
:func:`derender.derendering.gp_kernels.gp_nll` for the search). With heteroscedastic noise
(Kersting et al. 2007), the leave-one-out residuals ``loo_i`` of a first homoscedastic fit
(R&W eq. 5.12: ``loo_i = [K^-1 z]_i / [K^-1]_ii``) give the targets
``l_i = log(loo_i^2) - E[log chi^2_1]`` of a noise GP with the known noise variance
``Var[log chi^2_1] = pi^2/2`` (:func:`noise_gp_weights`); ``r = exp(g)``, ``g`` the noise GP's
mean, shapes the noise of a refit (:func:`fit_channel`). How the fitted GPs predict, clustered
and capped, is :class:`derender.derendering.local_gp.LocalGPModel`.
"""

from __future__ import annotations

import numpy as np

from derender.core.errors import ModelFileError

__all__ = [
    "se_kernel",
    "noise_gp_weights",
    "fit_channel",
]

_ELL_MIN = 0.004                        # smallest SE length-scale (in GP input units)
_LOG_CHI2_MEAN = -1.2703628454614782   # E[log chi^2_1] = digamma(1/2) + log 2
_LOG_CHI2_VAR = np.pi ** 2 / 2          # Var[log chi^2_1] = trigamma(1/2)
#: L-BFGS-B relative tolerance on the negative log marginal likelihood (scipy's default 2.2e-9
#: took 18 % more evaluations for NLL changes below 0.004 nats on the S90 chart clusters).
_ML_FTOL = 1e-6
#: Points of the first (homoscedastic) ML search of a heteroscedastic fit: it only seeds the
#: leave-one-out residuals and the warm-started refit on ``opt_points`` (measured on the S90 and
#: D5100 charts: relative RMSE within 0.002 of the search on all 500 points, ~1 s less CPU). Measured
#: further: the subsample moved a few extrapolated colours' variances (simulated drift family, held-out illuminants:
#: one clipped colour 33 codes from the training codes had a predictive mean 6.8x / 15.7x / 9.0x / 7.2x /
#: 9.0x its truth with 200 / 250 / 300 / 400 / all points); with the latent-variance cap below the
#: families' relative RMSE (MAP) moves by <= 0.8 % over those sizes (tests/derendering/test_gp_extrapolation.py).
_FIRST_POINTS = 250


def _sq_dists(X: np.ndarray) -> list[np.ndarray]:
    return [np.ascontiguousarray((X[:, None, d] - X[None, :, d]) ** 2) for d in range(X.shape[1])]


def se_kernel(A: np.ndarray, B: np.ndarray, log_ell: np.ndarray, log_sf: float) -> np.ndarray:
    """Squared-exponential ARD kernel sf^2 exp(-0.5 sum_d (a_d - b_d)^2 / l_d^2)."""
    s = np.exp(-np.asarray(log_ell))
    a, b = A * s, B * s
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
    np.maximum(d2, 0.0, out=d2)
    d2 *= -0.5
    K = np.exp(d2, out=d2)
    K *= np.exp(2.0 * log_sf)
    return K


def _chol_solve_inv(K: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Cholesky of K (overwritten): returns (L, K^-1 y, K^-1) or None if not positive definite."""
    from scipy.linalg import lapack  # scipy is imported on first fit, not by a prediction

    L, info = lapack.dpotrf(K, lower=1, clean=1, overwrite_a=1)
    if info != 0:
        return None
    alpha, _ = lapack.dpotrs(L, y, lower=1)
    Ki, info = lapack.dpotri(L, lower=1)
    if info != 0:
        return None
    # dpotri fills the lower triangle (the upper one is zero: clean=1 above): symmetrise in place
    Ki += Ki.T
    Ki.flat[:: Ki.shape[0] + 1] *= 0.5
    return L, alpha, Ki


def _gp_nll(theta: np.ndarray, D: list[np.ndarray], y: np.ndarray,
            r: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood of an ARD-SE GP and its gradient (R&W eqs. 2.30, 5.9).

    theta = [log l_1..l_d, log sigma_f, log sigma_n]; noise covariance sigma_n^2 diag(r)
    (r = 1: homoscedastic).
    """
    d = len(D)
    n = y.shape[0]
    inv_l2 = np.exp(-2.0 * theta[:d])
    sf2 = np.exp(2.0 * theta[d])
    sn2 = np.exp(2.0 * theta[d + 1])
    E = D[0] * (-0.5 * inv_l2[0])
    for k in range(1, d):
        E += D[k] * (-0.5 * inv_l2[k])
    Kf = np.exp(E, out=E)
    Kf *= sf2
    K = Kf.copy()
    K.flat[:: n + 1] += sn2 * (1.0 if r is None else r) + 1e-8 * sf2
    out = _chol_solve_inv(K, y)
    if out is None:
        return 1e25, np.zeros_like(theta)
    L, alpha, Ki = out
    nll = 0.5 * float(y @ alpha) + float(np.log(np.diag(L)).sum()) + 0.5 * n * np.log(2 * np.pi)
    W = np.outer(alpha, alpha)
    W -= Ki
    g = np.empty_like(theta)
    WK = W * Kf
    for k in range(d):
        g[k] = -0.5 * inv_l2[k] * float(np.vdot(WK, D[k]))
    g[d] = -float(WK.sum())
    wd = np.diag(W)
    g[d + 1] = -sn2 * float(wd.sum() if r is None else wd @ r)
    return nll, g


def _optimise(X: np.ndarray, y: np.ndarray, r: np.ndarray | None = None,
              th0: np.ndarray | None = None) -> np.ndarray:
    """Maximum-likelihood hyper-parameters (L-BFGS-B, analytic gradient) for a standardised target.

    The objective is the compiled :func:`derender.derendering.gp_kernels.gp_nll` (the same value and
    gradient as :func:`_gp_nll`, element-wise work fused, the GIL released)."""
    from derender.derendering.gp_kernels import gp_nll

    d = X.shape[1]
    if th0 is None:
        ell0 = np.clip(X.std(axis=0), 0.02, 1.0)
        th0 = np.concatenate([np.log(ell0), [0.0, np.log(0.1)]])
    bounds = [(np.log(_ELL_MIN), np.log(20.0))] * d + [(np.log(1e-2), np.log(1e2)), (np.log(1e-4), np.log(3.0))]
    th0 = np.clip(th0, [b[0] for b in bounds], [b[1] for b in bounds])
    from scipy.optimize import minimize

    res = minimize(gp_nll, th0, args=(np.ascontiguousarray(X), np.ascontiguousarray(y), r, {}), jac=True,
                   method="L-BFGS-B", bounds=bounds, options={"maxiter": 200, "ftol": _ML_FTOL})
    return np.asarray(res.x if np.isfinite(res.fun) and res.fun < 1e24 else th0, dtype=np.float64)


def _noise_gp(th: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Input-dependent log noise (most-likely heteroscedastic GP, Kersting et al. 2007).

    ``l_i = log(LOO residual_i^2) - E[log chi^2_1]`` is regressed by a GP with the main
    GP's length-scales (after the refit: the refitted ones) and the known noise variance
    Var[log chi^2_1] = pi^2/2.
    Returns (theta_noise = [log l (3), log sf, log sn, mean, g_min, g_max], l); the last two
    (filled in by the caller) bound the log noise factor at prediction to its range over the
    training colours, so the noise GP cannot extrapolate to absurd variances.
    """
    l = np.log(z + 1e-6 * max(float(np.mean(z)), 1e-300)) - _LOG_CHI2_MEAN
    m = float(np.mean(l))
    sf2 = max(float(np.var(l)) - _LOG_CHI2_VAR, 0.05)
    thn = np.concatenate([th[:3], [0.5 * np.log(sf2), 0.5 * np.log(_LOG_CHI2_VAR), m, 0.0, 0.0]])
    return thn, l


def noise_gp_weights(X: np.ndarray, thn: np.ndarray, l: np.ndarray) -> np.ndarray:
    """Weights ``beta = (K_n + sn_n^2 I)^-1 (l - m)`` of the noise GP (``thn`` as :func:`_noise_gp`
    returns it: kernel ``thn[:3]``, ``thn[3]``, noise ``thn[4]``, mean ``thn[5]``) on its targets ``l``
    at the training inputs ``X``; its log noise factor at ``y`` is ``m + k_n(y, X) beta``."""
    K = se_kernel(X, X, thn[:3], thn[3])
    K.flat[:: X.shape[0] + 1] += np.exp(2 * thn[4])
    from scipy.linalg import lapack  # scipy is imported on first fit, not by a prediction

    L, info = lapack.dpotrf(K, lower=1, clean=1, overwrite_a=1)
    if info != 0:  # pragma: no cover - noise variance pi^2/2 keeps K well conditioned
        raise ModelFileError("noise GP covariance is not positive definite")
    beta, _ = lapack.dpotrs(L, l - thn[5], lower=1)
    return beta


def fit_channel(X: np.ndarray, z: np.ndarray, osel: np.ndarray, hetero: bool) -> tuple[np.ndarray, ...]:
    """Fit one channel GP of one cluster: returns theta (5,), theta_noise (8,), l (n,), and the noise
    GP's weights beta (n,) and noise factors r = exp(g) (n,) at the training colours (what
    :meth:`LocalGPModel._compute_factor` would recompute for the prediction table)."""
    n = X.shape[0]
    Xs = X[osel]
    if hetero and osel.size > _FIRST_POINTS:
        fsel = osel[np.linspace(0, osel.size - 1, _FIRST_POINTS).round().astype(np.intp)]
        th = _optimise(X[fsel], z[fsel])
    else:
        th = _optimise(Xs, z[osel])
    if hetero:
        K = se_kernel(X, X, th[:3], th[3])
        K.flat[:: n + 1] += np.exp(2 * th[4]) + 1e-8 * np.exp(2 * th[3])
        out = _chol_solve_inv(K, z)
        if out is not None:
            _, alpha, Ki = out
            loo = alpha / np.diag(Ki)
            tn, l = _noise_gp(th, loo * loo)
            g = tn[5] + se_kernel(X, X, tn[:3], tn[3]) @ noise_gp_weights(X, tn, l)
            gmed = float(np.median(g))
            r = np.exp(g - gmed)
            th0 = np.concatenate([th[:4], [0.5 * gmed]])
            th = _optimise(Xs, z[osel], r=r[osel], th0=th0)
            tn[:3] = th[:3]    # noise GP shares the refitted length-scales (one kernel matrix at prediction)
            tn[5] -= gmed      # store the noise-GP mean relative to the median, so r = exp(g)
            beta = noise_gp_weights(X, tn, l - gmed)
            gfit = tn[5] + se_kernel(X, X, tn[:3], tn[3]) @ beta
            tn[6], tn[7] = float(gfit.min()), float(gfit.max())
            return th, tn, l - gmed, beta, np.exp(gfit)
    # g == 0: homoscedastic (noise weights 0, factors 1)
    return th, np.array([0.0, 0.0, 0.0, np.log(1e-6), 0.0, 0.0, 0.0, 0.0]), np.zeros(n), np.zeros(n), np.ones(n)


def _fit_local_gp(X: np.ndarray, Z: np.ndarray, osel: np.ndarray, hetero: bool) -> tuple[np.ndarray, np.ndarray,
                                                                                      np.ndarray]:
    """Fit the three channel GPs of one cluster: returns theta (3,5), theta_noise (3,8), l (n,3)."""
    fits = [fit_channel(X, Z[:, ch], osel, hetero)[:3] for ch in range(3)]
    return (np.stack([f[0] for f in fits]), np.stack([f[1] for f in fits]), np.stack([f[2] for f in fits], axis=1))
