"""Compiled (numba) negative log marginal likelihood of the local GP's ARD-SE kernel.

:func:`gp_nll` is ``_gp_nll`` of :mod:`derender.derendering.heteroscedastic_gp` (R&W eqs. 2.30, 5.8/5.9) with the
element-wise work fused: one pass builds the kernel matrix straight from the inputs (no per-dimension
squared-distance matrices), LAPACK factorises it in place (Fortran order, no copies), and one pass over
the lower triangle of ``(K + S)^-1`` accumulates the five gradient terms (no symmetrised inverse,
no ``alpha alpha^T`` matrix). Measured on a 500-point cluster (one BLAS thread): 8.7 ms per evaluation
with the NumPy version, of which LAPACK (potrf + potrs + potri) is 3.5 ms. The kernels release the
GIL, so the calibration's thread pool runs two ML searches at once. Float64 throughout.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["gp_nll"]


@njit(cache=True, nogil=True)
def _gram(X, inv_l2, sf2, diag, Kf, K):  # pragma: no cover - compiled
    """Kf = sf2 exp(-0.5 sum_d (x_id - x_jd)^2 inv_l2_d) (full, symmetric); K = Kf + diag(diag)."""
    n, d = X.shape
    for i in range(n):
        Kf[i, i] = sf2
        K[i, i] = sf2 + diag[i]
        for j in range(i):
            s = 0.0
            for k in range(d):
                t = X[i, k] - X[j, k]
                s += t * t * inv_l2[k]
            v = sf2 * math.exp(-0.5 * s)
            Kf[i, j] = v
            Kf[j, i] = v
            K[i, j] = v
            K[j, i] = v


@njit(cache=True, nogil=True)
def _grad(X, Kf, Ki, a, r, g):  # pragma: no cover - compiled
    """Accumulate sum_ij W_ij Kf_ij D_k,ij (k < d), sum_ij W_ij Kf_ij and sum_i W_ii r_i into g,
    W = a a^T - Ki, from the lower triangle of Ki (Fortran order, column j contiguous)."""
    n, d = X.shape
    for k in range(d + 2):
        g[k] = 0.0
    for j in range(n):
        wjj = a[j] * a[j] - Ki[j, j]
        g[d] += wjj * Kf[j, j]
        g[d + 1] += wjj * r[j]
        for i in range(j + 1, n):
            wk = 2.0 * (a[i] * a[j] - Ki[i, j]) * Kf[j, i]
            g[d] += wk
            for k in range(d):
                t = X[i, k] - X[j, k]
                g[k] += wk * t * t


def gp_nll(theta: np.ndarray, X: np.ndarray, y: np.ndarray, r: np.ndarray | None = None,
           work: dict | None = None) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood and gradient; same contract as ``local_gp._gp_nll`` but
    taking the inputs ``X`` (n, d) instead of squared distances. ``work``: optional dict reused for
    the (n, n) buffers between calls of one ML search."""
    from scipy.linalg import lapack

    X = np.ascontiguousarray(X, dtype=np.float64)
    n, d = X.shape
    inv_l2 = np.exp(-2.0 * theta[:d])
    sf2 = math.exp(2.0 * theta[d])
    sn2 = math.exp(2.0 * theta[d + 1])
    rr = np.ones(n) if r is None else np.asarray(r, dtype=np.float64)
    if work is None:
        work = {}
    if work.get("n") != n:
        work.update(n=n, Kf=np.empty((n, n)), K=np.empty((n, n)))
    Kf, K = work["Kf"], work["K"]
    _gram(X, inv_l2, sf2, sn2 * rr + 1e-8 * sf2, Kf, K)
    L, info = lapack.dpotrf(K.T, lower=1, clean=1, overwrite_a=1)   # K symmetric: K.T is Fortran-ordered
    if info != 0:
        return 1e25, np.zeros_like(theta)
    alpha, _ = lapack.dpotrs(L, y, lower=1)
    logdet_half = float(np.log(np.diag(L)).sum())
    Ki, info = lapack.dpotri(L, lower=1, overwrite_c=1)             # in place: L is not needed again
    if info != 0:
        return 1e25, np.zeros_like(theta)
    nll = 0.5 * float(y @ alpha) + logdet_half + 0.5 * n * math.log(2 * math.pi)
    s = np.empty(d + 2)
    _grad(X, Kf, Ki, alpha, rr, s)
    g = np.empty_like(theta)
    g[:d] = -0.5 * inv_l2 * s[:d]
    g[d] = -s[d]
    g[d + 1] = -sn2 * s[d + 1]
    return nll, g
