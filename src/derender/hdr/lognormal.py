"""Moments of censored Gaussians and log-normals: the probabilistic merge's shared helpers (paper 2, Sec. 3.1).

The probabilistic merge (:mod:`derender.hdr.probabilistic`, eq. 3) and its shared-error
variance (:mod:`derender.hdr.probabilistic_variance`) both censor the merged Gaussian at the
saturated channels' bound and turn log-space moments ``(m, v)`` into raw moments of the
log-normal, ``E = exp(m + v/2)``, ``Var = (exp(v) - 1) exp(2m + v)``. This leaf module holds
what they share, so that neither imports the other:

* a Gaussian ``N(mean, var)`` truncated below at ``mean + alpha sd`` has mean
  ``mean + sd lambda`` and variance ``var (1 + alpha lambda - lambda^2)``, with
  ``lambda = phi(alpha) / (1 - Phi(alpha))`` (:func:`truncnorm_moments`);
* :func:`truncate_below` (linear domain) and :func:`truncate_below_log` (log domain) apply it
  per pixel and channel with the merge's rules for conflicts and missing evidence;
* :data:`MAX_LOG` and :data:`MAX_V` cap ``|m|`` and ``v`` so that ``exp`` stays finite.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MAX_LOG", "MAX_V", "truncnorm_moments", "truncate_below", "truncate_below_log"]

#: Cap on ``|log raw|`` of the log-space product (keeps ``exp`` finite).
MAX_LOG = 80.0
#: Cap on the log variance of the product.
MAX_V = 60.0


def truncnorm_moments(mean, var, sd, alpha):
    """Mean and variance of N(mean, var) truncated below at ``mean + alpha sd``."""
    from scipy.special import ndtr

    tail = np.maximum(1.0 - ndtr(alpha), 1e-300)
    lam = np.exp(-0.5 * alpha * alpha) / np.sqrt(2 * np.pi) / tail
    return mean + sd * lam, var * np.maximum(1.0 + alpha * lam - lam * lam, 1e-6)


def truncate_below(mean: np.ndarray, var: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Moments of N(mean, var) truncated to [bound, inf) (bound <= 0: none): the linear-domain
    censoring of :mod:`derender.hdr.probabilistic`. A bound more than 3 sigma above the mean
    (conflict) gives the bound, with variance at least ``bound^2``; no evidence (var inf) gives
    0 with a huge variance."""
    out_m = mean.copy()
    out_v = var.copy()
    active = bound > 0
    finite = np.isfinite(var)
    sd = np.sqrt(np.where(finite, var, 1.0))
    alpha = np.where(finite, (bound - mean) / np.maximum(sd, 1e-300), np.inf)
    ok = active & finite & (alpha < 3.0)
    if ok.any():
        out_m[ok], out_v[ok] = truncnorm_moments(mean[ok], var[ok], sd[ok], alpha[ok])
    conflict = active & ~ok
    out_m[conflict] = bound[conflict]
    out_v[conflict] = np.maximum(np.where(finite[conflict], var[conflict], 0.0), bound[conflict] ** 2)
    nothing = ~np.isfinite(out_v)
    out_m[nothing] = 0.0
    out_v[nothing] = np.finfo(np.float32).max / 8
    return out_m, out_v


def truncate_below_log(mean: np.ndarray, var: np.ndarray, bound: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Log-space moments of N(mean, var) truncated to [bound, inf) (bound -inf: none; var inf: no evidence).

    A bound more than 3 sigma above the mean (conflict) is dropped: the Gaussian evidence
    stands. A bound without Gaussian evidence gives the bound with log variance 1.
    """
    out_m = mean.copy()
    out_v = var.copy()
    active = np.isfinite(bound)
    finite = np.isfinite(var)
    sd = np.sqrt(np.where(finite, var, 1.0))
    with np.errstate(invalid="ignore"):
        alpha = np.where(active & finite, (bound - np.where(finite, mean, 0.0)) / np.maximum(sd, 1e-300), np.inf)
    # a bound more than 8 sigma below the mean changes it by < 1e-14 sigma: skip the work
    ok = active & finite & (alpha < 3.0) & (alpha > -8.0)
    if ok.any():
        out_m[ok], out_v[ok] = truncnorm_moments(mean[ok], var[ok], sd[ok], alpha[ok])
    only_bound = active & ~finite
    out_m[only_bound] = bound[only_bound] - 0.5   # mean exp(m + v/2) = exp(bound): the bound itself
    out_v[only_bound] = 1.0
    nothing = ~np.isfinite(out_v) | ~np.isfinite(out_m)
    out_m[nothing] = -MAX_LOG   # no evidence at all (cannot happen with censoring; keeps outputs finite)
    out_v[nothing] = 1.0
    return out_m, out_v
