"""Let the user's own pairs pick the de-rendering model (``derender calibrate --method auto``).

Neither paper 2's local GP nor its baselines is best on every camera pipeline, and whoever
calibrates their own camera cannot know which to use. :func:`select_model` scores each
candidate (``gp``, ``poly``, ``rbf``) by k-fold cross-validation on the calibration pairs
and :func:`fit_auto` refits the winner on all of them.

Folds (:func:`cv_folds`), paper 2's protocol: when the pairs record the illuminant of
each pair (``derender chart-pairs`` sessions: 140 patches x 16 illuminants x 22
exposures), whole illuminants are held out -- the k folds are groups of illuminants, so a
model is always scored on illuminants it never saw (paper 2's held-out-illuminant split,
Sec. 4.1); otherwise (``--raw/--jpeg`` pairs, pairs files without an ``illuminant``
array) k seeded random folds.

Score, per candidate, pooled over the held-out folds (paper 2 Table 1, the measure of
:mod:`derender.evaluation.derendering_metrics`, which re-exports the two functions below):

* relative RMSE of the point estimate (the MAP for the GP and RBF, paper 2 Sec. 4.1)::

      rel = sqrt( mean_i ||x_hat_i - x_i||^2 / ||x_i||^2 )        (:func:`relative_rmse`)

  over all held-out pairs, and over those outside the sRGB gamut when the pairs say so;
  with ``truth_floor`` > 0 only over held-out pairs whose true colour has
  ``||x|| >= truth_floor * raw_white`` (``raw_white`` the typical raw value of bright
  colours, :func:`~derender.derendering.log_space.estimate_raw_white`). ``derender calibrate``
  sets it to :data:`IMAGE_TRUTH_FLOOR` for ``--raw/--jpeg`` pairs, whose truth is one noisy
  RAW pixel: there dark pixels whose RAW is sensor noise around 0 made the relative RMSE
  4e5 (a simulated 5-frame bracket) and the choice a draw of that noise; chart pairs (averaged
  patches, exact truth) are scored on every pair, as paper 2 does;
* the 95 % coverage of the predictive Gaussian ``mean +- 1.96 sqrt(var)`` per channel
  (:func:`interval_coverage`), reported, not used by the choice.

Rule: the candidate with the lowest pooled relative RMSE (all colours) wins; scores are
compared at 3 significant digits, and a tie goes to the candidate listed
first in ``methods`` (default order gp, poly, rbf: the GP is the one whose variance is
fitted per colour). A candidate whose fit fails on a fold (:class:`InputError`) is shown
as failed and never chosen.

Cost. Each candidate is fitted k times, on a seeded subsample of ``cv_train`` pairs of
the other folds (default 2000), and scored on up to ``max_test`` pairs of its held-out
fold. Measured on a ``derender chart-pairs`` session (nikon-d5100, 49,280 pairs, camera
family) the choice and the ranking are the same with 2000 as with the 5000 pairs of the
final fit, in about half the time (docs/paper2.md, "choosing the model").
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "pair_arrays",
    "relative_rmse",
    "interval_coverage",
    "SELECTION_METHODS",
    "DEFAULT_FOLDS",
    "DEFAULT_CV_TRAIN",
    "MIN_FOLD_TEST",
    "MIN_FOLD_TRAIN",
    "IMAGE_TRUTH_FLOOR",
    "SELECTION_RULE",
    "cv_folds",
    "ModelSelection",
    "select_model",
    "fit_calibration",
    "fit_auto",
]

#: Candidates of ``--method auto``, in tie-breaking order.
SELECTION_METHODS = ("gp", "poly", "rbf")
#: Number of cross-validation folds (groups of illuminants, or random folds).
DEFAULT_FOLDS = 4
#: Training pairs per fold fit (a seeded subsample of the other folds); bounds the time.
DEFAULT_CV_TRAIN = 2000
#: Fewest held-out pairs a fold may have.
MIN_FOLD_TEST = 10
#: Fewest training pairs (outside the fold) a fold may have (every model's minimum).
MIN_FOLD_TRAIN = 20
#: ``truth_floor`` for pairs read from RAW/JPEG images: held-out pixels darker than 1e-3 of the
#: raw white (10 stops; the 8-bit sRGB code's first step is 3e-4) are left out of the score.
IMAGE_TRUTH_FLOOR = 1e-3
#: The choice rule, stored with the table in the model file.
SELECTION_RULE = ("lowest pooled held-out relative RMSE of the point estimate (all colours), compared at 3 "
                  "significant digits; ties go to the first of the candidates' order")


# ============================================================================ metrics (paper 2, Table 1)
def pair_arrays(pred, truth) -> tuple[np.ndarray, np.ndarray]:
    """Predicted and true colours as (N, 3) float64 arrays of one shape (an :class:`InputError` otherwise)."""
    p = np.asarray(pred, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    if p.shape != t.shape:
        raise InputError(f"prediction and truth shapes differ: {np.shape(pred)} vs {np.shape(truth)}")
    return p, t


def relative_rmse(pred, truth) -> float:
    """sqrt(mean_i ||x_hat_i - x_i||^2 / ||x_i||^2) over colours with ||x_i|| > 0 (paper 2, Table 1).

    Parameters
    ----------
    pred : array_like
        (..., 3) predicted linear colours (e.g. a de-rendering model's mean).
    truth : array_like
        (..., 3) true linear colours, the same shape.

    Returns
    -------
    float
        The relative RMSE (0: perfect); colours whose truth is black are left out.

    Raises
    ------
    InputError
        Arrays of different shapes.

    Examples
    --------
    A prediction 10 % too bright everywhere (the black colour does not count):

    >>> import numpy as np
    >>> import derender
    >>> truth = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]])
    >>> round(derender.relative_rmse(1.1 * truth, truth), 6)
    0.1
    """
    p, t = pair_arrays(pred, truth)
    n2 = (t * t).sum(1)
    ok = n2 > 0
    return float(np.sqrt(np.mean(((p[ok] - t[ok]) ** 2).sum(1) / n2[ok])))


def interval_coverage(mean, var, truth, level: float = 0.95) -> np.ndarray:
    """Per-channel fraction of truths inside the central Gaussian interval mean +- z sqrt(var).

    ``z`` is the standard normal quantile of ``0.5 + level / 2`` (1.96 for 95 %); a
    calibrated predictive variance covers ``level`` of the truths.

    Parameters
    ----------
    mean, var : array_like
        (..., 3) predicted means and variances (e.g. :meth:`DerenderModel.predict
        <derender.derendering.base.DerenderModel.predict>`).
    truth : array_like
        (..., 3) true values, the shape of ``mean``.
    level : float
        The interval's probability, in (0, 1).

    Returns
    -------
    numpy.ndarray
        (3,) float64, the fraction of each channel's truths inside the interval.

    Raises
    ------
    InputError
        ``level`` outside (0, 1), or arrays of different shapes.

    Examples
    --------
    Standard normal truths against the prediction N(0, 1): about 95 % inside.

    >>> import numpy as np
    >>> import derender
    >>> truth = np.random.default_rng(0).normal(size=(1000, 3))
    >>> derender.interval_coverage(np.zeros((1000, 3)), np.ones((1000, 3)), truth).round(2).tolist()
    [0.95, 0.96, 0.96]
    """
    if not 0 < level < 1:
        raise InputError("level must be in (0, 1)")
    m, t = pair_arrays(mean, truth)
    v = np.asarray(var, dtype=np.float64).reshape(-1, 3)
    if v.shape != m.shape:
        raise InputError("variance shape differs from mean shape")
    from scipy.special import ndtri

    z = float(ndtri(0.5 + level / 2))
    return np.mean(np.abs(t - m) <= z * np.sqrt(np.maximum(v, 0.0)), axis=0)


# ============================================================================ folds
def cv_folds(n_pairs: int, *, groups=None, n_folds: int = DEFAULT_FOLDS, seed: int = 0
             ) -> tuple[np.ndarray, str, int]:
    """Fold index (N,) int of every pair, the scheme (``"illuminant"`` or ``"random"``) and the group count.

    With ``groups`` (per-pair illuminant index) holding at least 2 distinct values, every
    group goes whole into one fold: groups in a seeded random order, each to the fold with
    the fewest pairs so far (so 16 illuminants of equal size make 4 folds of 4); with fewer
    groups than ``n_folds``, one fold per group. Otherwise ``n_folds`` seeded random folds
    of equal size (+-1). Raises :class:`InputError` when a fold would hold fewer than
    :data:`MIN_FOLD_TEST` pairs or leave fewer than :data:`MIN_FOLD_TRAIN` outside it.
    """
    n = int(n_pairs)
    if int(n_folds) < 2:
        raise InputError(f"cross-validation needs at least 2 folds, got {n_folds}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 27]))
    g = None if groups is None else np.asarray(groups).reshape(-1)
    if g is not None and g.shape[0] != n:
        raise InputError(f"{g.shape[0]} illuminant labels for {n} pairs")
    uniq, inv = (np.unique(g, return_inverse=True) if g is not None else (np.zeros(0), None))
    if g is not None and uniq.shape[0] >= 2:
        k = min(int(n_folds), int(uniq.shape[0]))
        counts = np.bincount(inv.reshape(-1), minlength=uniq.shape[0])
        fold_of_group = np.empty(uniq.shape[0], dtype=np.int64)
        sizes = np.zeros(k, dtype=np.int64)
        for grp in rng.permutation(uniq.shape[0]):
            f = int(np.argmin(sizes))            # fewest pairs so far; ties: lowest fold index
            fold_of_group[grp] = f
            sizes[f] += counts[grp]
        fold = fold_of_group[inv.reshape(-1)]
        scheme, n_groups = "illuminant", int(uniq.shape[0])
    else:
        k = int(n_folds)
        fold = np.empty(n, dtype=np.int64)
        fold[rng.permutation(n)] = np.arange(n) % k
        scheme, n_groups = "random", 0
    sizes = np.bincount(fold, minlength=k)
    if sizes.min() < MIN_FOLD_TEST or n - sizes.max() < MIN_FOLD_TRAIN:
        raise InputError(f"{n} pairs are too few for {k}-fold cross-validation"
                         f"{' by illuminant' if scheme == 'illuminant' else ''} (every fold needs at least "
                         f"{MIN_FOLD_TEST} held-out pairs and {MIN_FOLD_TRAIN} pairs outside it; smallest fold "
                         f"{int(sizes.min())}); give more pairs or a --method")
    return fold, scheme, n_groups


# ============================================================================ selection
@dataclass
class ModelSelection:
    """Result of :func:`select_model`: one row per candidate, the chosen method and the folds.

    ``rows``: dicts with ``method``, ``n_scored`` (held-out pairs in the score),
    ``rel_rmse_all``, ``rel_rmse_oog`` (None without out-of-gamut labels or colours),
    ``rel_rmse_folds`` (per fold), ``coverage95`` (R, G, B), ``coverage95_mean``,
    ``fit_seconds`` (sum over folds), ``error`` (None, or why a fit failed) and ``chosen``.
    """

    chosen: str
    rows: list[dict]
    scheme: str            # "illuminant" or "random"
    n_folds: int
    n_groups: int          # distinct illuminants (0 for random folds)
    n_pairs: int
    cv_train: int
    seed: int
    truth_floor: float = 0.0
    seconds: float = 0.0

    def as_metadata(self) -> dict:
        """The JSON-ready table stored in the model file (``metadata["model_selection"]``)."""
        return {"chosen": self.chosen, "rule": SELECTION_RULE, "rows": [dict(r) for r in self.rows],
                "folds": {"scheme": self.scheme, "n_folds": self.n_folds, "n_groups": self.n_groups,
                          "n_pairs": self.n_pairs, "cv_train": self.cv_train, "seed": self.seed,
                          "truth_floor": self.truth_floor},
                "seconds": round(self.seconds, 3)}

    def describe_folds(self) -> str:
        """``"4 folds of whole illuminants (16 illuminants)"`` or ``"4 random folds"``."""
        if self.scheme == "illuminant":
            return f"{self.n_folds} folds of whole illuminants ({self.n_groups} illuminants)"
        return f"{self.n_folds} random folds"


def _sig3(v: float) -> float:
    return float(f"{v:.3g}") if np.isfinite(v) else float("inf")


def select_model(jpeg, raw, *, groups=None, out_of_gamut=None, methods: Sequence[str] = SELECTION_METHODS,
                 n_folds: int = DEFAULT_FOLDS, cv_train: int = DEFAULT_CV_TRAIN, max_test: int = 20_000,
                 seed: int = 0, truth_floor: float = 0.0, options: Mapping[str, dict] | None = None,
                 progress: Callable[[int, int, str], None] | None = None) -> ModelSelection:
    """Cross-validate each of ``methods`` on the pairs and choose one (see the module doc).

    ``jpeg`` (N,3) codes and ``raw`` (N,3) camera RGB as for
    :func:`~derender.derendering.base.fit_model`; ``groups`` the per-pair illuminant (folds
    of whole illuminants) or None (random folds); ``out_of_gamut`` (N,) bool for the
    out-of-gamut column; ``truth_floor`` the score's lower bound on ``||x||`` relative to the raw
    white (0: every pair); ``options`` extra keywords per method; ``progress(done, total,
    label)`` after each fit. Deterministic for a given ``seed``.
    """
    from derender.derendering.base import check_pairs
    from derender.derendering.log_space import estimate_raw_white

    jf, rf = check_pairs(jpeg, raw)
    codes = np.rint(jf).astype(np.uint8)
    methods = list(methods)
    oog = _check_selection(methods, jf.shape[0], cv_train=cv_train, max_test=max_test,
                           out_of_gamut=out_of_gamut, truth_floor=truth_floor)
    scored = np.linalg.norm(rf, axis=1) >= float(truth_floor) * estimate_raw_white(jf, rf)
    scored &= np.linalg.norm(rf, axis=1) > 0
    n = jf.shape[0]
    fold, scheme, n_groups = cv_folds(n, groups=groups, n_folds=n_folds, seed=seed)
    k = int(fold.max()) + 1
    splits = _cv_splits(fold, scored, cv_train=cv_train, max_test=max_test, seed=seed)
    opts = {m: dict((options or {}).get(m, {})) for m in methods}
    total, done = k * len(methods), 0
    t_start = time.perf_counter()

    def tick(label: str, steps: int = 1) -> None:
        nonlocal done
        done += steps
        if progress is not None:
            progress(done, total, label)

    rows = [_cross_validate(m, splits, codes, rf, oog=oog, options=opts[m], seed=seed, tick=tick) for m in methods]
    ok = [i for i, r in enumerate(rows) if r["error"] is None and np.isfinite(r["rel_rmse_all"])]
    if not ok:
        raise InputError("no candidate model could be fitted on the cross-validation folds: "
                         + "; ".join(f"{r['method']}: {r['error']}" for r in rows))
    best = min(ok, key=lambda i: (_sig3(rows[i]["rel_rmse_all"]), i))
    rows[best]["chosen"] = True
    return ModelSelection(chosen=rows[best]["method"], rows=rows, scheme=scheme, n_folds=k, n_groups=n_groups,
                          n_pairs=n, cv_train=int(cv_train), seed=int(seed), truth_floor=float(truth_floor),
                          seconds=time.perf_counter() - t_start)


def _check_selection(methods: list, n: int, *, cv_train: int, max_test: int, out_of_gamut, truth_floor: float):
    """Refuse unknown methods and too small subsamples (:class:`InputError`); the out-of-gamut flags of
    the ``n`` pairs as a bool array, or None."""
    from derender.derendering.base import MODEL_TYPES

    if not methods:
        raise InputError("no candidate methods to choose from")
    for m in methods:
        if m not in MODEL_TYPES:
            raise InputError(f"unknown de-rendering method '{m}' (choose from {', '.join(MODEL_TYPES)})")
    if int(cv_train) < MIN_FOLD_TRAIN:
        raise InputError(f"the cross-validation training subsample must be at least {MIN_FOLD_TRAIN} pairs")
    if int(max_test) < MIN_FOLD_TEST:
        raise InputError(f"max_test must be at least {MIN_FOLD_TEST}")
    oog = None
    if out_of_gamut is not None:
        oog = np.asarray(out_of_gamut, dtype=bool).reshape(-1)
        if oog.shape[0] != n:
            raise InputError(f"{oog.shape[0]} out-of-gamut flags for {n} pairs")
    if not (np.isfinite(truth_floor) and 0 <= truth_floor < 1):
        raise InputError(f"truth_floor must be in [0, 1), got {truth_floor}")
    return oog


def _cv_splits(fold: np.ndarray, scored: np.ndarray, *, cv_train: int, max_test: int, seed: int) -> list:
    """Per fold ``(train, test)`` pair indices: at most ``cv_train`` of the other folds' pairs and
    ``max_test`` of the fold's scored ones (random subsamples, sorted)."""
    k = int(fold.max()) + 1
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 27, 1]))
    splits = []
    for f in range(k):
        pool = np.flatnonzero(fold != f)
        test = np.flatnonzero(fold == f)
        tr = np.sort(rng.choice(pool, size=int(cv_train), replace=False)) if pool.size > cv_train else pool
        te = np.sort(rng.choice(test, size=int(max_test), replace=False)) if test.size > max_test else test
        te = te[scored[te]]
        if te.size < MIN_FOLD_TEST:
            raise InputError(f"fold {f + 1} has {te.size} held-out pairs above the truth floor (needs "
                             f"{MIN_FOLD_TEST}); give more or brighter pairs")
        splits.append((tr, te))
    return splits


def _cross_validate(m: str, splits: list, codes: np.ndarray, rf: np.ndarray, *, oog: np.ndarray | None,
                    options: dict, seed: int, tick: Callable[..., None]) -> dict:
    """Fit method ``m`` on each fold's training pairs and score it on the held-out ones: the
    selection table's row (an ``error`` instead of scores when a fold's fit fails);
    ``tick(label[, steps])`` after each fit."""
    from derender.derendering.base import fit_model

    k = len(splits)
    point_all, mean_all, var_all, truth_all, oog_all, per_fold = [], [], [], [], [], []
    fit_s, error = 0.0, None
    for f, (tr, te) in enumerate(splits):
        kw = dict(options)
        if m in ("gp", "rbf"):
            kw.setdefault("n_train", max(int(tr.size), MIN_FOLD_TRAIN))
        t0 = time.perf_counter()
        try:
            model = fit_model(m, codes[tr], rf[tr], seed=seed, **kw)
        except (InputError, np.linalg.LinAlgError) as exc:
            error = f"fold {f + 1}: {exc}"
        fit_s += time.perf_counter() - t0
        tick(f"{m} fold {f + 1}/{k}")
        if error is not None:
            tick(f"{m} failed", k - 1 - f)
            break
        point, _ = model.predict(codes[te], point="map")
        mean, var = model.predict(codes[te])
        point_all.append(point)
        mean_all.append(mean)
        var_all.append(var)
        truth_all.append(rf[te])
        per_fold.append(relative_rmse(point, rf[te]))
        if oog is not None:
            oog_all.append(oog[te])
    row = {"method": m, "rel_rmse_all": None, "rel_rmse_oog": None, "rel_rmse_folds": None,
           "coverage95": None, "coverage95_mean": None, "fit_seconds": round(fit_s, 3),
           "n_scored": int(sum(te.size for _, te in splits)), "error": error, "chosen": False}
    if error is None:
        p, x = np.concatenate(point_all), np.concatenate(truth_all)
        cov = interval_coverage(np.concatenate(mean_all), np.concatenate(var_all), x)
        row.update(rel_rmse_all=relative_rmse(p, x), rel_rmse_folds=[float(v) for v in per_fold],
                   coverage95=[float(c) for c in cov], coverage95_mean=float(np.mean(cov)))
        if oog is not None:
            o = np.concatenate(oog_all)
            if o.any():
                row["rel_rmse_oog"] = relative_rmse(p[o], x[o])
    return row


# ============================================================================ fitting
def fit_calibration(method: str, jpeg, raw, *, n_train: int = 5000, seed: int = 0, **kw):
    """Fit ``method`` as ``derender calibrate --method METHOD`` does: a seeded random subset of
    ``n_train`` pairs (``np.random.default_rng(seed).choice``), the GP told ``n_train``."""
    from derender.derendering.base import fit_model

    if int(n_train) < 10:
        raise InputError("--n-train must be at least 10")
    jp, rw = np.asarray(jpeg), np.asarray(raw)
    if jp.ndim == 2 and jp.shape[0] > n_train and rw.shape[:1] == jp.shape[:1]:
        sel = np.random.default_rng(seed).choice(jp.shape[0], size=int(n_train), replace=False)
        jp, rw = jp[sel], rw[sel]
    if method == "gp":
        kw.setdefault("n_train", int(n_train))
    return fit_model(method, jp, rw, seed=seed, **kw)


def fit_auto(jpeg, raw, *, n_train: int = 5000, seed: int = 0, groups=None, out_of_gamut=None,
             methods: Sequence[str] = SELECTION_METHODS, n_folds: int = DEFAULT_FOLDS,
             cv_train: int = DEFAULT_CV_TRAIN, truth_floor: float = 0.0, options: Mapping[str, dict] | None = None,
             progress: Callable[[int, int, str], None] | None = None):
    """``derender calibrate --method auto``: :func:`select_model`, then :func:`fit_calibration` of the
    winner on all pairs; returns ``(model, selection)``, the table in
    ``model.metadata["model_selection"]``. The model is the one ``--method <winner>`` fits
    (same subset, same seed). The cross-validation fits use ``min(cv_train, n_train)`` pairs."""
    last = [0]

    def fold_progress(done: int, total: int, label: str) -> None:   # one step more: the final fit
        last[0] = total
        if progress is not None:
            progress(done, total + 1, label)

    sel = select_model(jpeg, raw, groups=groups, out_of_gamut=out_of_gamut, methods=methods, n_folds=n_folds,
                       cv_train=min(int(cv_train), int(n_train)), seed=seed, truth_floor=truth_floor, options=options,
                       progress=fold_progress)
    if progress is not None:
        progress(last[0], last[0] + 1, f"{sel.chosen} on all pairs")
    model = fit_calibration(sel.chosen, jpeg, raw, n_train=n_train, seed=seed,
                            **dict((options or {}).get(sel.chosen, {})))
    model.metadata["model_selection"] = sel.as_metadata()
    if progress is not None:
        progress(last[0] + 1, last[0] + 1, f"{sel.chosen} fitted")
    return model, sel
