"""Error measures of de-rendering predictions against true raw colours (paper 2, Table 1).

* :func:`~derender.derendering.model_selection.relative_rmse` -- ``sqrt(mean_i ||x_hat_i - x_i||^2 / ||x_i||^2)``, the measure of
  paper 2 Table 1; :func:`rmse` and :func:`median_relative_error` alongside;
  :func:`max_colour_share` -- the largest share one colour has of its sum of squares.
* :func:`code_floor_errors` -- the lower bound on the relative RMSE of *any* function of
  the 8-bit code (the ``floor`` row of ``derender experiment derender-table``).
* :func:`~derender.derendering.model_selection.interval_coverage` -- calibration of the
  predictive variance: the fraction of truths inside the central Gaussian interval
  ``mean +- z sqrt(var)``.

:func:`~derender.derendering.model_selection.relative_rmse` and ``interval_coverage`` live in
:mod:`derender.derendering.model_selection` (``derender calibrate --method auto`` scores with
them, and ``derendering`` may not import ``evaluation``); they are re-exported here.
"""

from __future__ import annotations

import numpy as np

from derender.core.errors import InputError
from derender.derendering.model_selection import (  # noqa: F401 (relative_rmse, interval_coverage re-exported)
    interval_coverage,
    pair_arrays,
    relative_rmse,
)

__all__ = [
    "max_colour_share",
    "rmse",
    "median_relative_error",
    "code_floor_errors",
    "fit_and_predict",
]


def max_colour_share(pred, truth) -> float:
    """Largest share one colour has of the squared relative error ``sum_i ||x_hat_i - x_i||^2 / ||x_i||^2``
    (colours with ``||x_i|| > 0``; 0 when the error is 0). A share near 1 means one colour decides
    :func:`~derender.derendering.model_selection.relative_rmse` (an extrapolated colour with a
    predictive mean far above its truth can hold most of a family's squared error)."""
    p, t = pair_arrays(pred, truth)
    n2 = (t * t).sum(1)
    ok = n2 > 0
    e = ((p[ok] - t[ok]) ** 2).sum(1) / n2[ok]
    tot = float(e.sum())
    return float(e.max() / tot) if tot > 0 else 0.0


def rmse(pred, truth) -> float:
    """sqrt(mean_i ||x_hat_i - x_i||^2): RMS Euclidean error per colour vector."""
    p, t = pair_arrays(pred, truth)
    return float(np.sqrt(np.mean(((p - t) ** 2).sum(1))))


def median_relative_error(pred, truth) -> float:
    """median_i ||x_hat_i - x_i|| / ||x_i|| over colours with ||x_i|| > 0."""
    p, t = pair_arrays(pred, truth)
    n = np.sqrt((t * t).sum(1))
    ok = n > 0
    return float(np.median(np.sqrt(((p[ok] - t[ok]) ** 2).sum(1)) / n[ok]))


def code_floor_errors(codes, truth) -> np.ndarray:
    """Per-colour squared relative errors of the best possible function of the 8-bit code.

    Colours sharing a code get the one point ``v = sum_i x_i/|x_i|^2 / sum_i 1/|x_i|^2``
    minimising ``sum_i ||v - x_i||^2 / ||x_i||^2`` over them, fitted to ``truth`` itself; so
    ``sqrt(mean(errors))`` is a lower bound on the :func:`relative_rmse` that *any* model
    predicting from the code alone (GP, polynomial, RBF, a look-up table) can reach on these
    colours. It is far from zero where rendering is one-to-many: clipped (255) channels and
    near-black codes. Colours with ``||x|| = 0`` are left out (as in :func:`relative_rmse`).
    """
    c = np.asarray(codes)
    t = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    c = c.reshape(-1, 3)
    if c.shape != t.shape:
        raise InputError(f"codes and truth shapes differ: {np.shape(codes)} vs {np.shape(truth)}")
    n2 = (t * t).sum(1)
    ok = n2 > 0
    c, t, n2 = c[ok], t[ok], n2[ok]
    if t.shape[0] == 0:
        return np.zeros(0)
    _, inv = np.unique(np.rint(c).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    w = 1.0 / n2
    k = int(inv.max()) + 1
    wsum = np.bincount(inv, w, k)
    v = np.stack([np.bincount(inv, t[:, ch] * w, k) for ch in range(3)], axis=1) / wsum[:, None]
    return ((v[inv] - t) ** 2).sum(1) * w


def fit_and_predict(method: str, jpeg_train: np.ndarray, raw_train: np.ndarray, jpeg_test: np.ndarray,
                    raw_test: np.ndarray, seed: int = 0) -> dict:
    """Fit a de-rendering model and predict held-out colours, as every de-rendering table does.

    Returns ``model``, ``fit_seconds``, the predictive ``mean`` and ``var`` (for the 95 %
    ``coverage``, per channel) and ``point``, the MAP estimate scored by the tables (paper 2,
    Sec. 4.1)."""
    import time

    from derender.derendering.base import fit_model

    t0 = time.perf_counter()
    model = fit_model(method, jpeg_train, raw_train, seed=seed)
    fit_s = time.perf_counter() - t0
    mean, var = model.predict(jpeg_test)
    point, _ = model.predict(jpeg_test, point="map")
    return {"model": model, "fit_seconds": fit_s, "mean": mean, "var": var,
            "coverage": interval_coverage(mean, var, raw_test), "point": point}
