"""Tests for derender.evaluate: the HDR PSNR protocol of DESIGN.md."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from derender.core.errors import InputError
from derender.core.types import HDRResult
from derender.evaluation.metrics import PSNR_CAP, fit_scale, psnr_rgbl


def _reference_psnr(result, truth, remap):
    """Independent re-implementation: plain Python float loops, closed-form scale."""
    h, w, _ = truth.shape
    planes = {}
    for c, name in enumerate("RGB"):
        planes[name] = ([float(result[y, x, c]) for y in range(h) for x in range(w)],
                        [float(truth[y, x, c]) for y in range(h) for x in range(w)])

    def lum(img, y, x):
        return 0.2126 * float(img[y, x, 0]) + 0.7152 * float(img[y, x, 1]) + 0.0722 * float(img[y, x, 2])

    planes["L"] = ([lum(result, y, x) for y in range(h) for x in range(w)],
                   [lum(truth, y, x) for y in range(h) for x in range(w)])
    out = {}
    for name, (r, g) in planes.items():
        if remap == "lstsq":
            k = sum(a * b for a, b in zip(r, g)) / sum(a * a for a in r)
            rr = [k * a for a in r]
        else:
            lo, hi, glo, ghi = min(r), max(r), min(g), max(g)
            rr = [(a - lo) / (hi - lo) * (ghi - glo) + glo for a in r]
        mse = sum((a - b) ** 2 for a, b in zip(rr, g)) / len(g)
        out[name] = 10 * math.log10(max(g) ** 2 / mse)
    return out


@pytest.mark.parametrize("remap", ["lstsq", "minmax"])
def test_psnr_rgbl_matches_independent_implementation(remap):
    rng = np.random.default_rng(0)
    truth = (10 ** rng.uniform(-2, 2, (17, 13, 3))).astype(np.float32)
    result = (truth * 3.7 * np.exp(rng.normal(0, 0.1, truth.shape))).astype(np.float32)
    got = psnr_rgbl(result, truth, remap=remap)
    ref = _reference_psnr(result, truth, remap)
    assert set(got) == {"R", "G", "B", "L"}
    for k in "RGBL":
        assert abs(got[k] - ref[k]) < 0.01, (k, got[k], ref[k])
        assert isinstance(got[k], float)


def test_closed_form_values_and_scale():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 4, (10, 20, 3))
    noise = np.where(rng.random(truth.shape) < 0.5, 0.01, -0.01)
    noise -= noise.mean(axis=(0, 1))  # zero-mean per channel
    # result = truth / 5 + noise / 5 -> best scale close to 5; MSE known in closed form after the exact scale
    result = (truth + noise) / 5.0
    k = fit_scale(result[..., 0], truth[..., 0])
    r, g = result[..., 0].ravel(), truth[..., 0].ravel()
    assert np.isclose(k, r @ g / (r @ r))
    mse = np.mean((k * r - g) ** 2)
    assert np.isclose(psnr_rgbl(result, truth)["R"], 10 * np.log10(g.max() ** 2 / mse))
    # a perfect result (up to scale) is capped, finite, JSON-safe
    perfect = psnr_rgbl(truth, truth)
    assert all(v == PSNR_CAP for v in perfect.values())
    assert all(v > 120 for v in psnr_rgbl(truth * 0.01, truth).values())
    perfect_mm = psnr_rgbl(truth * 2 + 1, truth, remap="minmax")
    assert all(v > 100 for v in perfect_mm.values())
    json.dumps(perfect, allow_nan=False)
    # the scale does not matter for lstsq, it does for nothing else
    a = psnr_rgbl(result, truth)
    b = psnr_rgbl(result * 1000, truth)
    for kk in "RGBL":
        assert abs(a[kk] - b[kk]) < 1e-6


def test_luminance_scaled_separately_and_mask():
    rng = np.random.default_rng(2)
    truth = rng.uniform(0.1, 1, (8, 8, 3))
    # each channel off by a different scale: R, G, B perfect after per-channel scaling, L is not
    result = truth * np.array([1.0, 2.0, 0.5])
    scores = psnr_rgbl(result, truth)
    assert min(scores["R"], scores["G"], scores["B"]) > 120
    assert scores["L"] < 60
    bad = result.copy()
    bad[0, 0] = 50.0
    mask = np.ones((8, 8), bool)
    mask[0, 0] = False
    assert psnr_rgbl(bad, truth)["R"] < 40
    assert psnr_rgbl(bad, truth, mask=mask)["R"] > 120
    hdr = HDRResult(radiance=result.astype(np.float32), mask=np.zeros((8, 8), np.uint8))
    assert psnr_rgbl(hdr, truth)["G"] > 120


def test_input_errors():
    a = np.ones((4, 4, 3))
    with pytest.raises(InputError):
        psnr_rgbl(a, np.ones((4, 5, 3)))
    with pytest.raises(InputError):
        psnr_rgbl(np.ones((4, 4)), np.ones((4, 4)))
    nan = a.copy()
    nan[1, 1, 1] = np.nan
    with pytest.raises(InputError):
        psnr_rgbl(nan, a)
    with pytest.raises(InputError):
        psnr_rgbl(a, nan)
    with pytest.raises(InputError):
        psnr_rgbl(a, a, remap="quantile")
    with pytest.raises(InputError):
        psnr_rgbl(a, a, mask=np.zeros((4, 4), np.uint8))  # HDRResult masks are not evaluation masks
    with pytest.raises(InputError):
        psnr_rgbl(a, np.zeros((4, 4, 3)))  # PSNR undefined without a positive peak


# --------------------------------------------------------------------------- issue 18: every pixel counts
def _hdr_truth(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.exp(rng.normal(0.0, 2.0, size=(40, 50, 3)))          # five decades of radiance


def test_relative_errors_are_zero_under_the_fitted_transform():
    from derender.evaluation.metrics import log_psnr, relative_errors

    g = _hdr_truth()
    a = np.array([[1.2, 0.1, -0.05], [0.05, 0.9, 0.1], [0.0, -0.1, 1.4]])
    r = g @ np.linalg.inv(a).T                                        # r = A^-1 g: a 3x3 rendering change
    rel = relative_errors(r, g, fit="matrix")
    assert rel["median"] < 1e-12 and rel["p90"] < 1e-12
    np.testing.assert_allclose(rel["matrix"], a, atol=1e-10)
    assert relative_errors(3.7 * g, g, fit="scale")["p90"] < 1e-12
    assert relative_errors(r, g, fit="scale")["median"] > 0.01        # one scale cannot undo a matrix
    assert log_psnr(5.0 * g, g) == 200.0


def test_relative_errors_median_and_p90_of_known_errors():
    """Every pixel off by a known factor 1 + f: with no fit the median and 90th percentile are
    those of |f|; the trimmed scale fit reads them back for the scale it found."""
    from derender.evaluation.metrics import relative_errors

    g = _hdr_truth(1)
    f = np.linspace(-0.2, 0.2, g.shape[0] * g.shape[1]).reshape(g.shape[:2])   # pixel factors 1 + f
    r = g * (1.0 + f)[..., None]
    none = relative_errors(r, g, fit="none")
    assert none["median"] == pytest.approx(np.median(np.abs(f)), rel=1e-9)
    assert none["p90"] == pytest.approx(np.percentile(np.abs(f), 90), rel=1e-9)
    assert 0.099 < none["median"] < 0.101 and 0.179 < none["p90"] < 0.181
    rel = relative_errors(r, g, fit="scale")
    k = rel["matrix"][0][0]
    e = np.abs(k * (1 + f) - 1).ravel()
    assert rel["median"] == pytest.approx(np.median(e), rel=1e-9)
    assert rel["p90"] == pytest.approx(np.percentile(e, 90), rel=1e-9)
    assert rel["median"] <= none["median"] + 1e-12


def test_relative_errors_fit_ignores_a_minority_of_wild_pixels():
    """70 % of the pixels are an exact colour transform of the truth, 30 % are wild (colour
    fringes, noise): the trimmed fit recovers the transform (median 0), while the plain
    weighted least squares, a squared loss, is pulled off by the wild pixels."""
    from derender.evaluation.metrics import fit_colour_matrix, relative_errors

    rng = np.random.default_rng(3)
    g = _hdr_truth(4)
    m_true = np.array([[0.9, 0.1, 0.0], [0.05, 1.1, -0.05], [0.0, 0.2, 0.7]])
    r = g @ np.linalg.inv(m_true).T
    wild = rng.random(g.shape[:2]) < 0.3
    r[wild] *= rng.uniform(0.05, 20.0, size=(int(wild.sum()), 3))
    rel = relative_errors(r, g, fit="matrix")
    assert rel["median"] < 1e-9
    assert np.allclose(rel["matrix"], m_true, atol=1e-9)
    rp, gp = r.reshape(-1, 3), g.reshape(-1, 3)
    n2 = np.sum(gp * gp, axis=1)
    m_ls = fit_colour_matrix(rp, gp, 1.0 / n2)
    e_ls = np.sqrt(np.sum((rp @ m_ls.T - gp) ** 2, axis=1) / n2)
    assert np.median(e_ls) > 0.05


def test_log_psnr_sees_the_shadows_that_psnr_misses():
    """A 20 % error in the darkest half of an HDR image barely moves PSNR L, but log-PSNR drops."""
    from derender.evaluation.metrics import hdr_scores

    g = _hdr_truth(2)
    lum = g @ np.array([0.2126, 0.7152, 0.0722])
    dark = lum < np.median(lum)
    r = g.copy()
    r[dark] *= 1.2
    s = hdr_scores(r, g)
    assert s["L"] > 60.0                           # the highlights dominate the squared error
    assert s["log_psnr_L"] < 45.0
    assert s["rel_median"] > 0.05 and s["rel_fit"] == "matrix"
    perfect = hdr_scores(g, g)
    assert perfect["log_psnr_L"] == 200.0 and perfect["rel_p90"] < 1e-12


def test_evaluate_cli_json_has_the_new_metrics(tmp_path, capsys):
    import json

    from helpers import run_cli

    from derender.io.exr import write_exr

    g = _hdr_truth(3).astype(np.float32)
    write_exr(tmp_path / "g.exr", g)
    write_exr(tmp_path / "r.exr", (g * 2.0).astype(np.float32))
    code, out, err = run_cli(["evaluate", tmp_path / "r.exr", tmp_path / "g.exr", "--json"], capsys)
    assert code == 0, err
    d = json.loads(out)
    assert set(d) >= {"R", "G", "B", "L", "rel_median", "rel_p90", "rel_fit", "log_psnr_L"}
    assert d["rel_p90"] < 1e-5 and d["L"] > 100
    code, out, err = run_cli(["evaluate", tmp_path / "r.exr", tmp_path / "g.exr", "--fit", "nope"], capsys)
    assert code == 2 and "error:" in out + err


def test_evaluate_names_the_truth(tmp_path, capsys):
    """The scores are asymmetric, so the truth is named (``--truth``) and echoed; giving it
    twice or not at all is an error."""
    from helpers import run_cli

    from derender.io.exr import write_exr

    g = _hdr_truth(3).astype(np.float32)
    r = (g * np.array([1.0, 1.1, 0.9], np.float32)).astype(np.float32)
    write_exr(tmp_path / "g.exr", g)
    write_exr(tmp_path / "r.exr", r)
    code, out_opt, err = run_cli(["evaluate", tmp_path / "r.exr", "--truth", tmp_path / "g.exr"], capsys)
    assert code == 0, err
    assert out_opt.splitlines()[0] == f"{tmp_path / 'r.exr'} scored against the truth {tmp_path / 'g.exr'}"
    code, out_pos, err = run_cli(["evaluate", tmp_path / "r.exr", tmp_path / "g.exr"], capsys)
    assert code == 0 and out_pos == out_opt
    code, out_swapped, err = run_cli(["evaluate", tmp_path / "g.exr", "--truth", tmp_path / "r.exr"], capsys)
    assert code == 0 and out_swapped.splitlines()[1:] != out_opt.splitlines()[1:]   # asymmetric, and now visible
    for args in (["evaluate", tmp_path / "r.exr"],
                 ["evaluate", tmp_path / "r.exr", tmp_path / "g.exr", "--truth", tmp_path / "g.exr"]):
        code, out, err = run_cli(args, capsys)
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 2 and len(lines) == 1 and "--truth" in lines[0]
