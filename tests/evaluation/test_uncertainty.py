"""Coverage of a variance against the truth, on cases whose answer is known exactly."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli
from scipy.stats import norm


def _case(sigma_scale: float = 1.0, seed: int = 0, shape=(120, 160)):
    """An HDR truth over 4 decades, a result = truth / 3 (unknown scale) + Gaussian noise of a
    known, pixel-varying sd, and the variance the method would report (true sd x ``sigma_scale``)."""
    rng = np.random.default_rng(seed)
    g = np.exp(rng.uniform(np.log(0.01), np.log(100.0), shape))[..., None] * rng.uniform(0.5, 1.5, (*shape, 3))
    sd = 0.05 * (g / 3.0) + 1e-4                     # 5 % relative noise plus a floor, in result units
    r = g / 3.0 + rng.normal(size=g.shape) * sd
    r = np.maximum(r, 1e-6)
    return r.astype(np.float32), ((sd * sigma_scale) ** 2).astype(np.float32), g.astype(np.float32)


def test_calibrated_gaussian_errors_give_nominal_coverage():
    from derender.evaluation.uncertainty import COVERAGE_LEVELS, coverage_scores

    r, v, g = _case()
    d = coverage_scores(r, v, g, fit="scale")
    n = d["n"]
    assert n == r.size and d["n_unscored"] == 0
    for p in COVERAGE_LEVELS:
        se = np.sqrt(p * (1 - p) / n)                # binomial sampling error of the share
        assert abs(d["coverage"][p] - p) < 4 * se + 2e-3, (p, d["coverage"][p])
    assert d["median_abs_z"] == pytest.approx(norm.ppf(0.75), abs=0.02)
    assert np.allclose(d["matrix"], 3.0 * np.eye(3), rtol=0.01)    # the unknown scale is found


def test_tail_share_split_into_edge_and_flat_pixels():
    """Known answer: a truth with a vertical step (the edge pixels are the two columns beside
    it) and Gaussian errors of the reported sd, except that the edge pixels' sd is 4x the
    reported one: |z| > 3 in 2 (1 - Phi(3)) = 0.0027 of flat pixel-channels and in
    2 (1 - Phi(0.75)) = 0.453 of edge ones."""
    from derender.evaluation.uncertainty import coverage_scores, edge_pixels

    rng = np.random.default_rng(3)
    h, w = 200, 200
    g = np.full((h, w, 3), 0.2)
    g[:, w // 2:] = 20.0
    g *= np.linspace(1.0, 1.2, w)[None, :, None]      # a gentle ramp: flat pixels have a gradient too
    edge = edge_pixels(g, share=0.01)
    assert edge.sum() == 2 * h and edge[:, w // 2 - 1:w // 2 + 1].all()
    sd = 0.05 * g
    err = rng.normal(size=g.shape) * sd
    err[edge] *= 4.0
    d = coverage_scores((g + err).astype(np.float32), (sd ** 2).astype(np.float32), g.astype(np.float32), fit="none")
    n_flat = 3 * int((~edge_pixels(g)).sum())
    assert d["tail3_flat"] == pytest.approx(2 * norm.sf(3.0), abs=4 * np.sqrt(0.0027 / n_flat) + 1e-3)
    share_edge = 2 * h / (h * w) / 0.10            # the edge set is the top 10 %: 2 of 20 columns are the step
    expect_edge = share_edge * 2 * norm.sf(0.75) + (1 - share_edge) * 2 * norm.sf(3.0)
    assert d["tail3_edge"] == pytest.approx(expect_edge, abs=0.02)
    assert d["tail3"] == pytest.approx(0.1 * d["tail3_edge"] + 0.9 * d["tail3_flat"], abs=2e-3)


def test_variance_too_small_is_caught():
    from derender.evaluation.uncertainty import coverage_scores

    r, v, g = _case(sigma_scale=0.5)
    d = coverage_scores(r, v, g, fit="matrix")
    assert d["coverage"][0.95] == pytest.approx(2 * norm.cdf(0.5 * norm.ppf(0.975)) - 1, abs=0.01)   # 0.675
    assert d["median_abs_z"] == pytest.approx(2 * norm.ppf(0.75), abs=0.04)


def test_evaluate_cli_prints_coverage_and_splits_clipped_pixels(tmp_path, capsys):
    import json

    from helpers import write_png_codes

    from derender.io.exr import write_exr

    r, v, g = _case(shape=(60, 80))
    v[:10] = 0.0                                   # no usable variance there
    mask = np.zeros((60, 80, 3), np.uint8)
    mask[50:] = 128                                # "over-exposed everywhere" rows
    for name, arr in (("r", r), ("v", v), ("g", g)):
        write_exr(tmp_path / f"{name}.exr", arr)
    write_png_codes(tmp_path / "m.png", mask)
    code, out, err = run_cli(["evaluate", tmp_path / "r.exr", "--truth", tmp_path / "g.exr", "--variance",
                              tmp_path / "v.exr", "--mask", tmp_path / "m.png", "--json"], capsys)
    assert code == 0, err
    d = json.loads(out)["coverage"]
    assert set(d) == {"all", "clipped", "measured"}
    assert d["all"]["n_unscored"] == 10 * 80 * 3 and d["clipped"]["n"] == 10 * 80 * 3
    assert abs(d["all"]["coverage"]["0.95"] - 0.95) < 0.02
    code, out, err = run_cli(["evaluate", tmp_path / "r.exr", "--truth", tmp_path / "g.exr", "--variance",
                              tmp_path / "v.exr"], capsys)
    assert code == 0 and "median |z|" in out and "without a usable variance" in out
    code, out, err = run_cli(["evaluate", tmp_path / "r.exr", "--truth", tmp_path / "g.exr", "--mask",
                              tmp_path / "m.png"], capsys)
    assert code == 2 and err.startswith("error:") and "--variance" in err


def test_uncertainty_experiment_rows():
    from derender.evaluation.uncertainty import uncertainty_experiment

    rows = uncertainty_experiment(families=("camera",), size=(96, 64), exposures=4,
                                  methods=("debevec", "probabilistic"), n_train=800)
    by = {r["method"]: r for r in rows}
    d = by["debevec"]       # the classic merges give a variance too (engine/variance.py)
    assert d["gives_variance"] and 0.0 <= d["cov50"] <= d["cov95"] <= 1.0 and d["median_abs_z"] > 0
    p = by["probabilistic"]
    assert p["gives_variance"] and not p["held_out"]
    assert 0.0 <= p["cov50"] <= p["cov80"] <= p["cov95"] <= p["cov99"] <= 1.0 and p["median_abs_z"] > 0
