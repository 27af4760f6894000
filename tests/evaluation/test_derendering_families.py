"""De-rendering models on chart sessions rendered by the pipeline families (issue 16 item 3)."""

from __future__ import annotations

import numpy as np

from derender.camera.chart import chart_pairs
from derender.evaluation.derendering_families import derender_families


def test_chart_pairs_family_differs_and_is_deterministic():
    kw = dict(n_illuminants=2, n_exposures=6, seed=3)
    cam = chart_pairs("nikon-d5100", **kw)
    a = chart_pairs("nikon-d5100", family="dslr-lut", **kw)
    b = chart_pairs("nikon-d5100", family="dslr-lut", **kw)
    assert a.family == "dslr-lut" and cam.family is None
    np.testing.assert_array_equal(a.jpeg, b.jpeg)
    np.testing.assert_array_equal(a.raw, cam.raw)          # the truth does not depend on the JPEG engine
    assert np.mean(np.any(a.jpeg != cam.jpeg, axis=1)) > 0.5
    c = chart_pairs("nikon-d5100", family="dslr-lut", n_illuminants=2, n_exposures=6, seed=4)
    assert np.any(c.jpeg != a.jpeg)
    # the tuning families keep the old fixed pipelines byte for byte
    np.testing.assert_array_equal(chart_pairs("nikon-d5100", family="camera", **kw).jpeg, cam.jpeg)
    np.testing.assert_array_equal(chart_pairs("nikon-d5100", family="paper", **kw).jpeg,
                                  chart_pairs("nikon-d5100", style="simple", **kw).jpeg)


def test_derender_families_rows_are_finite():
    rows = derender_families(["camera", "dslr-lut"], methods=("poly",), n_train=600, n_illuminants=5,
                             n_exposures=8)
    assert {(r["family"], r["split"]) for r in rows} == {
        (f, s) for f in ("camera", "dslr-lut") for s in ("random", "held-out illuminants")}
    assert {r["role"] for r in rows if r["family"] == "dslr-lut"} == {"held out"}
    assert {r["role"] for r in rows if r["family"] == "camera"} == {"tuning"}
    assert {r["method"] for r in rows} == {"poly", "floor"}
    for r in rows:
        assert np.isfinite(r["rel_rmse_all"]) and r["n_test"] > 0
        if r["method"] == "floor":
            assert r["rel_rmse_all"] <= next(q["rel_rmse_all"] for q in rows if q["method"] == "poly"
                                             and (q["family"], q["split"]) == (r["family"], r["split"])) + 1e-12
            continue
        assert r["n_train"] == 600
        assert np.isfinite(r["rel_rmse_all"]) and np.isfinite(r["rel_rmse_clipped"])
        assert np.all(np.isfinite(r["coverage95"]))
        assert 0 < r["max_colour_share"] <= 1 and 0 < r["max_colour_share_mean"] <= 1
        assert np.isfinite(r["rel_rmse_mean"])
