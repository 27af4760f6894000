"""``derender calibrate --method auto`` (:mod:`derender.derendering.model_selection`, issue 27).

The choice is checked on synthetic renderings whose answer is known: one exactly in the
polynomial baseline's family (3x3 map then a per-channel curve: poly must win) and one that
mixes channels *after* the tone curve (a saturation boost on encoded values, which no
per-channel curve can undo: poly must lose).
"""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.errors import InputError
from derender.derendering.base import load_model
from derender.derendering.model_selection import (
    MIN_FOLD_TEST,
    cv_folds,
    fit_auto,
    fit_calibration,
    interval_coverage,
    relative_rmse,
    select_model,
)

SMALL = {"gp": dict(max_cluster_points=300, opt_points=150, table_size=28), "rbf": dict(table_size=24)}


def _srgb(v):
    v = np.clip(v, 0, 1)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def _poly_family_pairs(n=3000, seed=3):
    """In-gamut, unclipped colours over 6 stops rendered as sRGB(C x): poly's forward model exactly."""
    rng = np.random.default_rng(seed)
    C = np.array([[0.8, 0.15, 0.05], [0.1, 0.8, 0.1], [0.05, 0.15, 0.8]])
    raw = rng.uniform(0.05, 1.0, (n, 3)) * 2.0 ** rng.uniform(-6, 0, (n, 1))
    return np.round(255 * _srgb(raw @ C.T)).astype(np.uint8), raw


def _encoded_mix_pairs(n=3000, seed=4):
    """A saturation boost applied to the *encoded* values, D sRGB(x): not separable after any 3x3 map."""
    rng = np.random.default_rng(seed)
    D = np.array([[1.4, -0.3, -0.1], [-0.2, 1.4, -0.2], [-0.1, -0.3, 1.4]])
    raw = rng.dirichlet([6.0, 6.0, 6.0], n) * 1.5 * 2.0 ** rng.uniform(-6, 0, (n, 1))
    return np.round(255 * np.clip(_srgb(raw) @ D.T, 0, 1)).astype(np.uint8), raw


# ---------------------------------------------------------------------------- metric
def test_relative_rmse_is_the_evaluation_measure_and_exact():
    from derender.evaluation import derendering_metrics as ev

    assert ev.relative_rmse is relative_rmse and ev.interval_coverage is interval_coverage
    x = np.random.default_rng(0).uniform(0.1, 1, (50, 3))
    assert relative_rmse(1.1 * x, x) == pytest.approx(0.1, rel=1e-12)
    e = np.zeros_like(x)
    e[:, 0] = 0.3 * np.linalg.norm(x, axis=1)          # ||err|| / ||x|| = 0.3 for half, 0 for the rest
    e[25:] = 0
    assert relative_rmse(x + e, x) == pytest.approx(np.sqrt(0.5 * 0.09), rel=1e-12)


# ---------------------------------------------------------------------------- folds
def test_illuminant_folds_keep_every_illuminant_whole_and_balance_the_folds():
    groups = np.repeat(np.arange(16), 140 * 3)
    groups = groups[np.random.default_rng(1).permutation(groups.size)]
    fold, scheme, n_groups = cv_folds(groups.size, groups=groups, n_folds=4, seed=0)
    assert scheme == "illuminant" and n_groups == 16
    for g in range(16):
        assert np.unique(fold[groups == g]).size == 1            # whole
    assert sorted(np.bincount(fold).tolist()) == [1680] * 4       # 4 illuminants per fold
    assert sorted(np.unique(groups[fold == 0]).tolist()) != sorted(np.unique(groups[fold == 1]).tolist())
    again, _, _ = cv_folds(groups.size, groups=groups, n_folds=4, seed=0)
    other, _, _ = cv_folds(groups.size, groups=groups, n_folds=4, seed=1)
    np.testing.assert_array_equal(fold, again)
    assert not np.array_equal(fold, other)
    # unequal illuminants still go whole, and the folds stay within one illuminant of each other
    groups = np.repeat(np.arange(7), [400, 300, 300, 200, 200, 100, 100])
    fold, _, _ = cv_folds(groups.size, groups=groups, n_folds=3, seed=2)
    assert all(np.unique(fold[groups == g]).size == 1 for g in range(7))
    assert np.ptp(np.bincount(fold)) <= 400
    # fewer illuminants than folds: leave one illuminant out
    fold, scheme, n_groups = cv_folds(300, groups=np.repeat([5, 9, 11], 100), n_folds=4)
    assert scheme == "illuminant" and n_groups == 3 and fold.max() == 2


def test_random_folds_when_the_pairs_record_no_illuminant():
    for groups in (None, np.zeros(1001, int)):                 # load_pairs' default: all zeros
        fold, scheme, n_groups = cv_folds(1001, groups=groups, n_folds=4, seed=0)
        assert scheme == "random" and n_groups == 0
        assert sorted(np.bincount(fold).tolist()) == [250, 250, 250, 251]
    a, _, _ = cv_folds(1001, n_folds=4, seed=0)
    b, _, _ = cv_folds(1001, n_folds=4, seed=3)
    assert not np.array_equal(a, b)


def test_too_few_pairs_for_the_folds_is_an_input_error():
    with pytest.raises(InputError, match="too few for 4-fold"):
        cv_folds(4 * MIN_FOLD_TEST - 1, n_folds=4)
    with pytest.raises(InputError, match="by illuminant"):       # one tiny illuminant makes a tiny fold
        cv_folds(205, groups=np.repeat([0, 1], [200, 5]), n_folds=4)
    with pytest.raises(InputError, match="at least 2 folds"):
        cv_folds(1000, n_folds=1)
    jpeg, raw = _poly_family_pairs(30)
    with pytest.raises(InputError, match="too few"):
        select_model(jpeg, raw, n_folds=4)


# ---------------------------------------------------------------------------- the choice
def test_auto_picks_poly_on_an_exactly_polynomial_rendering():
    jpeg, raw = _poly_family_pairs()
    sel = select_model(jpeg, raw, cv_train=800, seed=0, options=SMALL)
    s = {r["method"]: r["rel_rmse_all"] for r in sel.rows}
    assert sel.chosen == "poly" and sel.scheme == "random" and sel.n_folds == 4
    assert s["poly"] < 0.7 * min(s["gp"], s["rbf"]), s            # measured 0.013 vs 0.022 (gp), 0.030 (rbf)
    assert [r["chosen"] for r in sel.rows] == [False, True, False]


def test_auto_does_not_pick_poly_when_channels_mix_after_the_curve():
    jpeg, raw = _encoded_mix_pairs()
    groups = np.random.default_rng(0).integers(0, 8, raw.shape[0])
    sel = select_model(jpeg, raw, groups=groups, cv_train=800, seed=0, options=SMALL)
    s = {r["method"]: r["rel_rmse_all"] for r in sel.rows}
    assert sel.scheme == "illuminant" and sel.n_groups == 8
    assert sel.chosen in ("gp", "rbf") and s["poly"] > 2 * s[sel.chosen], s   # measured 0.049 vs 0.014
    for r in sel.rows:
        assert len(r["rel_rmse_folds"]) == 4 and all(0.5 <= c <= 1 for c in r["coverage95"])


def test_ties_go_to_the_first_candidate():
    jpeg, raw = _poly_family_pairs(600)
    sel = select_model(jpeg, raw, methods=["poly", "poly"], seed=0)
    assert sel.rows[0]["rel_rmse_all"] == sel.rows[1]["rel_rmse_all"]
    assert [r["chosen"] for r in sel.rows] == [True, False]


def test_fit_auto_stores_the_table_which_survives_save_and_load(tmp_path):
    jpeg, raw = _encoded_mix_pairs(1500)
    oog = raw[:, 0] > raw[:, 2]                                   # any labelling: the column must follow it
    model, sel = fit_auto(jpeg, raw, n_train=1000, cv_train=500, seed=5, out_of_gamut=oog, options=SMALL)
    assert model.method == sel.chosen
    path = model.save(tmp_path / "auto.npz")
    back = load_model(path)
    table = back.metadata["model_selection"]
    assert table == sel.as_metadata() and table["chosen"] == back.method
    assert table["folds"] == {"scheme": "random", "n_folds": 4, "n_groups": 0, "n_pairs": 1500, "cv_train": 500,
                              "seed": 5, "truth_floor": 0.0}
    assert {r["method"] for r in table["rows"]} == {"gp", "poly", "rbf"}
    assert all(r["rel_rmse_oog"] is not None and r["rel_rmse_oog"] > 0 for r in table["rows"])
    # the winner is exactly the model a direct fit of that method gives (same subset and seed)
    direct = fit_calibration(sel.chosen, jpeg, raw, n_train=1000, seed=5, **SMALL.get(sel.chosen, {}))
    codes = np.random.default_rng(0).integers(0, 256, (500, 3)).astype(np.uint8)
    for a, b in zip(back.predict(codes), direct.predict(codes)):
        np.testing.assert_array_equal(a, b)
    # deterministic with the seed
    _, sel2 = fit_auto(jpeg, raw, n_train=1000, cv_train=500, seed=5, out_of_gamut=oog, options=SMALL)
    assert [r["rel_rmse_all"] for r in sel2.rows] == [r["rel_rmse_all"] for r in sel.rows]


def test_the_truth_floor_leaves_near_black_pairs_out_of_the_score():
    """One-pixel RAW truths near 0 (sensor noise) would dominate the relative RMSE: with the floor
    they do not count, and every scored pair is above it."""
    jpeg, raw = _poly_family_pairs(2000)
    raw = raw.copy()
    raw[:40] = 1e-9                                             # 2 %: black pixels whose RAW is noise
    jpeg = jpeg.copy()
    jpeg[:40] = 3
    plain = select_model(jpeg, raw, methods=["poly"], seed=0)
    floored = select_model(jpeg, raw, methods=["poly"], seed=0, truth_floor=1e-3)
    assert plain.rows[0]["rel_rmse_all"] > 1e3                   # the 40 pixels make it meaningless
    assert floored.rows[0]["rel_rmse_all"] < 0.05 and floored.truth_floor == 1e-3
    assert plain.rows[0]["n_scored"] == 2000 and floored.rows[0]["n_scored"] == 1960
    with pytest.raises(InputError, match="truth_floor"):
        select_model(jpeg, raw, methods=["poly"], truth_floor=-1)
