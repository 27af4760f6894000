"""Small versions of paper 2's experiments (the full ones: 'derender experiment ...')."""

from __future__ import annotations

import numpy as np
import pytest

from derender.camera.chart import chart_pairs
from derender.derendering.base import fit_model
from derender.evaluation.experiments import (
    JPEG_INTERVALS,
    derender_table,
    format_table,
    photometric_stereo_experiment,
    threshold_sweep,
)


def test_derender_table_small():
    rows = derender_table(["nikon-d5100"], methods=("gp", "poly"), n_train=800, n_illuminants=3, n_exposures=8)
    assert [r["method"] for r in rows] == ["gp", "poly", "floor"]
    for r in rows[:2]:
        assert np.isfinite(r["rel_rmse_all"]) and 0 < r["median_rel"] < 1
        assert all(0.5 < c <= 1 for c in r["coverage95"])
    # the floor (best function of the code, fitted to the test colours) bounds every model from below
    gp, poly, floor = (r["rel_rmse_all"] for r in rows)
    assert 0 < floor < gp < poly
    assert rows[0]["ratio_to_poly"] == gp / poly and rows[2]["ratio_to_poly"] == floor / poly
    text = format_table(rows, [("method", "method", ""), ("rel_rmse_all", "rel", ".3f")])
    assert "| gp |" in text


def test_threshold_sweep_small():
    rows = threshold_sweep(["nikon-d5100"], methods=("gp",), n_train=600, holdouts=[1], n_illuminants=3,
                           n_exposures=8)
    assert len(rows) == len(JPEG_INTERVALS)
    errs = [r["rel_rmse_all"] for r in rows]
    assert all(np.isfinite(errs)) and max(errs) < 0.5
    for r in rows:   # one run: the squared all-colour error is the share-weighted in / out-of-gamut mix
        f = r["share_oog"]
        mix = (1 - f) * r["rel_rmse_in"] ** 2 + (f * r["rel_rmse_oog"] ** 2 if f > 0 else 0.0)
        assert np.isclose(r["rel_rmse_all"] ** 2, mix, rtol=1e-9)
    # nested intervals: patches without any observation inside them can only grow; none at [0, 255]
    nv = [r["no_valid"] for r in rows]
    assert nv[0] == 0 and all(a <= b for a, b in zip(nv, nv[1:]))


@pytest.mark.parametrize("shape", ["sphere"])
def test_photometric_stereo_small_orders_methods(shape):
    pairs = chart_pairs("nikon-d5100", n_illuminants=4, n_exposures=12)
    tr = np.random.default_rng(0).permutation(pairs.jpeg.shape[0])[:1500]
    models = {m: fit_model(m, pairs.jpeg[tr], pairs.raw[tr]) for m in ("gp", "poly")}
    rows = photometric_stereo_experiment("nikon-d5100", n_lights=12, size=48, shapes=(shape,), models=models)
    err = {r["method"]: r["mean_angular_error_deg"] for r in rows}
    assert err["gp (weighted LS)"] < err["gamma 2.2 (LS)"]
    assert err["poly (LS)"] < err["gamma 2.2 (LS)"]


def test_scene_estimate_without_a_valid_observation_uses_the_nearest_one():
    """A patch never inside [lo, hi] in all channels takes its observation with the smallest excursion outside
    the interval (here G = 9 at [10, 205]), not the one closest to mid-grey (which has R clipped at 255)."""
    from derender.evaluation.experiments import _scene_estimates

    class Linear:                     # a known model: raw = code / 255, unit variance
        def predict(self, codes):
            c = np.asarray(codes, dtype=np.float64) / 255.0
            return c, np.ones_like(c)

    jpeg = np.array([[[255, 40, 70]], [[197, 9, 61]], [[120, 3, 30]]], dtype=np.uint8)   # (E=3, P=1, 3)
    t_rel = np.array([4.0, 2.0, 1.0])
    for method in ("gp", "poly"):
        est = _scene_estimates(Linear(), method, jpeg, t_rel, 10, 205)
        np.testing.assert_allclose(est[0], np.array([197, 9, 61]) / 255.0 / 2.0)


def test_scene_estimate_without_a_valid_observation_combines_tied_nearest_ones():
    """Two observations equally far outside [10, 205] (one too bright, one too dark) both count; a
    farther one does not."""
    from derender.evaluation.experiments import _scene_estimates

    class Linear:                     # a known model: raw = code / 255, unit variance
        def predict(self, codes):
            c = np.asarray(codes, dtype=np.float64) / 255.0
            return c, np.ones_like(c)

    jpeg = np.array([[[210, 150, 90]], [[100, 80, 5]], [[40, 30, 2]]], dtype=np.uint8)   # excursions 5, 5, 8
    t_rel = np.array([4.0, 1.0, 0.5])
    v1, v2 = np.array([210, 150, 90]) / 255.0 / 4.0, np.array([100, 80, 5]) / 255.0 / 1.0
    # poly: plain mean; gp: inverse-variance weights, variance 1 / t^2 after scaling to exposure 1
    for method, expect in (("poly", (v1 + v2) / 2.0), ("gp", (16.0 * v1 + 1.0 * v2) / 17.0)):
        est = _scene_estimates(Linear(), method, jpeg, t_rel, 10, 205)
        np.testing.assert_allclose(est[0], expect)
