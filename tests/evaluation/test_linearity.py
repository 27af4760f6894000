"""Linearity over 5 decades (issue 28): spot-calibrated maps against the absolute truth, and evalglare."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from helpers import run_cli


@pytest.fixture(scope="module")
def gamma_rows():
    from derender.evaluation.linearity import linearity_experiment

    return linearity_experiment(renders=["gamma"], modes=["time"], seeds=[0], n_train=1500)


@pytest.mark.parametrize("method", ["debevec", "robertson", "stabilized", "stabilized-joint", "probabilistic"])
def test_linearity_bound_on_the_tuning_family(gamma_rows, method):
    """Issue 28's done-when line on the luminance family's fixed gamma-2.2 camera (a tuning
    rendering), 192x128, 9 frames 2 stops apart, seed 0: after the spot on the grey card,
    median abs error <= 3 %, p90 <= 10 % and every decade's median ratio within +-5 %.
    Measured: debevec 0.9 % / 2.3 % (decades 0.994 .. 1.007; 1.1 % / 2.7 % before the bound-aware top
    of its curve; with the merge's former lambda 30
    1.8 % / 3.7 %, and before its samples left out the rims of clipped sources 9.2 % / 19.6 %),
    stabilized 1.9 % / 3.0 %, probabilistic 0.8 % / 2.4 %."""
    row = next(r for r in gamma_rows if r["method"] == method)
    assert row["role"] == "tuning"
    assert all(c > 300 for c in row["counts"]), row["counts"]
    assert row["median_abs"] <= 0.03, row
    assert row["p90_abs"] <= 0.10, row
    assert np.all(np.abs(np.asarray(row["decades"]) - 1.0) <= 0.05), row["decades"]


def test_linearity_scores_detect_a_nonlinear_map():
    """The score is not blind: the truth itself scores 0, and the truth bent by a power 0.98
    (2 % per decade) misses the decade bound at the ends."""
    from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2
    from derender.evaluation.linearity import linearity_scores

    b = simulate_luminance(size=(96, 64), exposures=3, noise=False)
    lt = truth_luminance_cd_m2(b.truth_linear_srgb)
    card = b.params["luminance"]["spot"]
    exact = linearity_scores(b.truth_linear_srgb * 7.0, lt, card)
    assert exact["median_abs"] < 1e-4 and np.allclose(exact["decades"], 1.0, atol=1e-4)
    bent = linearity_scores(np.power(b.truth_linear_srgb.astype(np.float64), 0.98), lt, card)
    assert abs(bent["decades"][0] - 1.0) > 0.05 or abs(bent["decades"][-1] - 1.0) > 0.05


def test_experiment_linearity_cli(tmp_path, capsys):
    code, out, err = run_cli(["experiment", "linearity", "--renders", "gamma", "--methods", "debevec",
                              "--size", "96x64", "--exposures", "7", "--json", tmp_path / "r.json"], capsys)
    assert code == 0, err
    assert "| gamma | tuning | time | debevec |" in out
    code, _, err = run_cli(["experiment", "linearity", "--renders", "nope"], capsys)
    assert code == 2 and err.strip().startswith("error:") and "--renders" in err


def _evalglare_ev(path) -> float:
    from radiance_tools import radiance_bin

    run = subprocess.run([str(radiance_bin("evalglare")), "-V", str(path)], capture_output=True, text=True)
    return float(run.stdout.split()[0])


@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_evalglare_on_our_map_matches_the_truth(tmp_path, method):
    """The family framed as a 180-degree circular fisheye (160x160, gamma-2.2 camera, seed 0),
    merged, scaled on the grey card and written with ``VIEW= -vta -vh 180 -vv 180``: Radiance's
    ``evalglare -V`` on our map within 5 % of ``evalglare -V`` on the truth map with the same
    header. Measured: truth 41112 lx, debevec 40817 (-0.7 %; -1.3 % before the bound-aware top of its
    curve, 40735 with its former lambda 30), stabilized 41498 (+0.9 %). The spread debevec really
    has is that of its grid samples: :func:`test_evalglare_debevec_over_the_sample_grid`."""
    from derender.evaluation.linearity import FISHEYE_VIEW, fisheye_maps
    from derender.io.rgbe import write_hdr

    maps = fisheye_maps([method])
    for name, img in maps.items():
        write_hdr(tmp_path / f"{name}.hdr", img, view=FISHEYE_VIEW)
    truth = _evalglare_ev(tmp_path / "truth.hdr")
    ours = _evalglare_ev(tmp_path / f"{method}.hdr")
    assert truth > 1e4
    assert ours == pytest.approx(truth, rel=0.05)


def test_evalglare_debevec_over_the_sample_grid(tmp_path):
    """Issue 37 item 8: the same code gave Ev -6.2 % on another machine and -1.3 % here. The cause
    measured: which grid samples the calibration keeps. :func:`~derender.response.curves.uniform_samples`
    spreads the kept clusters evenly, so one cluster more or less (one neighbour's code crossing 250)
    shifts every later pick; the paper's system, whose top codes took their data from samples that
    had stopped following the exposure, then moved the curve by up to 4x at code 250. Measured,
    dropping one of 30 random candidate clusters: -6.31 .. -1.14 % (the other machine's -6.2 % is
    one of them); grid seeds 0-9: -2.5 .. +12.1 %. With the bound-aware top
    (:func:`~derender.response.debevec1997.censored_observations`): one cluster dropped -1.65 ..
    -0.52 %, grid seeds 0-9 -2.23 .. +2.29 %. Here: grid seeds 0-7 within 3 % of the truth."""
    from derender.camera.luminance import SATURATION_EXPOSURE, simulate_luminance
    from derender.core.types import Stack
    from derender.evaluation.linearity import FISHEYE_VIEW
    from derender.hdr.registry import merge
    from derender.io.rgbe import SRGB_PRIMARIES, write_hdr
    from derender.photometry.calibration import Spot, spot_factor

    b = simulate_luminance(render="gamma", size=(160, 160), exposures=9, seed=0, fisheye=True)
    lum = b.params["luminance"]
    spot = Spot(*lum["spot"], lum["spot_cd_m2"])
    write_hdr(tmp_path / "truth.hdr", b.truth_linear_srgb.astype(np.float64) * (SATURATION_EXPOSURE / 179.0),
              view=FISHEYE_VIEW)
    truth = _evalglare_ev(tmp_path / "truth.hdr")
    stack = Stack(images=b.jpeg_codes.astype(np.float32) / np.float32(255), times=b.times)
    errs = []
    for seed in range(8):
        res = merge(stack, "debevec", options={"seed": seed})
        k = spot_factor(res.radiance, spot, SRGB_PRIMARIES, mask=res.mask).factor
        write_hdr(tmp_path / "m.hdr", np.asarray(res.radiance, np.float64) * k, view=FISHEYE_VIEW)
        errs.append(_evalglare_ev(tmp_path / "m.hdr") / truth - 1.0)
    assert np.all(np.abs(errs) <= 0.03), np.round(errs, 4)


def _pvalue_or_skip() -> str:
    from derender.evaluation.linearity import radiance_program

    exe = radiance_program("pvalue")
    if exe is None:
        pytest.skip("Radiance's pvalue is absent (neither on PATH nor in the pyradiance wheel, a test dependency)")
    return exe


@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_linearity_read_back_through_radiance_pvalue(tmp_path, method):
    """Issue 28's done-when: the --spot scores computed from the written ``.hdr`` read back by
    Radiance's ``pvalue -h -H -o -d`` equal the array's within one RGBE step (2^-8 relative) on
    every figure (gamma-2.2 camera, tuning, 192x128, 9 frames, seed 0; EXPOSURE=0.01 so that ``-o``
    matters). The read-back pixels also carry Radiance's own luminance: ``179 pvalue -b`` (its
    0.265 R + 0.670 G + 0.065 B) equals 179 (CIE_rf, CIE_gf, CIE_bf) . RGB of the read-back RGB
    (the rounded 0.265/0.670/0.065 differ by up to 0.4 % on blue pixels)."""
    from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2
    from derender.core.types import Stack
    from derender.evaluation.families import smooth_mask
    from derender.evaluation.linearity import linearity_scores, pvalue_rgb
    from derender.hdr.registry import merge_seeded
    from derender.io.rgbe import write_hdr

    exe = _pvalue_or_skip()
    b = simulate_luminance(render="gamma", seed=0)
    stack = Stack(images=b.jpeg_codes.astype(np.float32) / 255, times=b.times)
    lt, smooth = truth_luminance_cd_m2(b.truth_linear_srgb), smooth_mask(b.truth_linear_srgb)
    card = b.params["luminance"]["spot"]
    res = merge_seeded(stack, method, 0)
    arr = linearity_scores(res.radiance, lt, card, score_mask=smooth, merge_mask=res.mask)
    back = linearity_scores(res.radiance, lt, card, score_mask=smooth, merge_mask=res.mask, readback="pvalue",
                            hdr_exposure=0.01)
    step = 2.0 ** -8
    assert back["readback"] == "pvalue" and back["n"] == arr["n"]
    assert back["median_abs"] == pytest.approx(arr["median_abs"], abs=step)
    assert back["p90_abs"] == pytest.approx(arr["p90_abs"], abs=step)
    assert back["factor"] == pytest.approx(arr["factor"], rel=step)
    np.testing.assert_allclose(back["decades"], arr["decades"], rtol=step)
    # the bound is met on the file too (the line, read back)
    assert back["median_abs"] <= 0.03 and back["p90_abs"] <= 0.10
    assert np.all(np.abs(np.asarray(back["decades"]) - 1.0) <= 0.05), back["decades"]
    # Radiance's own luminance of the same file
    write_hdr(tmp_path / "m.hdr", np.asarray(res.radiance, np.float64) * arr["factor"], exposure=0.01)
    rgb = pvalue_rgb(tmp_path / "m.hdr")
    run = subprocess.run([exe, "-h", "-H", "-o", "-d", "-b", str(tmp_path / "m.hdr")], capture_output=True, text=True,
                         check=True)
    bright = np.array(run.stdout.split(), dtype=np.float64).reshape(rgb.shape[:2])
    cie = np.array([0.265074126, 0.670114631, 0.064811243])   # Radiance's CIE_rf, CIE_gf, CIE_bf (color.h)
    np.testing.assert_allclose(179.0 * bright, 179.0 * rgb @ cie, rtol=2e-3, atol=1e-3)


def test_readback_path_fails_cleanly_without_pvalue(monkeypatch, capsys):
    """``--readback`` with another word, or with no pvalue to be found: one error line, exit 2."""
    import derender.evaluation.linearity as lin

    code, _, err = run_cli(["experiment", "linearity", "--renders", "gamma", "--readback", "exr"], capsys)
    assert code == 2 and err.strip().startswith("error:") and "--readback" in err
    monkeypatch.setattr(lin, "radiance_program", lambda name: None)
    code, _, err = run_cli(["experiment", "linearity", "--renders", "gamma", "--readback", "pvalue"], capsys)
    assert code == 2 and err.strip().startswith("error:") and "pvalue" in err and len(err.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def spacing_rows_held_out():
    """Every 8-bit method on the Fujifilm X-T3 (``rawtoaces-spectral``; no method was looked at on
    it while choosing), 1.5 EV (12 frames), scenes 0 and 1, white 255, plain merges."""
    from conftest import require_shared

    from derender.evaluation.linearity import SPACING_METHODS, spacing_rows

    require_shared("rawtoaces-spectral")
    return list(spacing_rows(["fujifilm-x-t3"], [1.5], [0, 1], ["255"], SPACING_METHODS, (False,)))


@pytest.mark.parametrize("method", ["debevec", "robertson", "stabilized", "stabilized-joint"])
def test_luminance_does_not_depend_on_the_bracket(spacing_rows_held_out, method):
    """Issue 36's line "luminance that does not depend on the bracket" on a camera not tuned on:
    the luminance family's fixed gamma-2.2 rendering (a tuning rendering), Fujifilm X-T3, 1.5 EV,
    both scenes; with ``--spot`` on the grey card against the simulator's exact luminance, the
    median abs error <= 3 % and every decade's median ratio within +-5 %. The full grid (4 cameras,
    1 / 1.5 / 2 EV, whites 255 and 250-254, ``--deghost``) is in docs/results-luminance.md
    (``benchmarks/bench_luminance_spacing.py``). Measured (seeds 0 / 1; median, worst decade): debevec
    0.9 % / 0.9 %, 1.011 / 1.009; robertson 0.6 % / 0.8 %, 1.007 / 1.016 (1.1 % / 1.4 %, 0.966 / 0.958
    before its calibration's bounds); stabilized and stabilized-joint 0.6 % / 0.6 %, 0.994 / 1.003
    (before their level and scale followed the times: 2.6 % / 2.6 %, 1.039 / 1.042, a tilt measured
    on the results page). At 2 EV robertson and the stabilised merges missed on this camera before
    those changes (the two tests below)."""
    rows = [r for r in spacing_rows_held_out if r["method"] == method]
    assert len(rows) == 2
    for r in rows:
        assert r["frames"] == 12 and all(c > 300 for c in r["counts"]), r["counts"]
        assert r["median_abs"] <= 0.03, (r["seed"], r["median_abs"])
        assert np.all(np.abs(np.asarray(r["decades"]) - 1.0) <= 0.05), (r["seed"], r["decades"])


def test_stabilised_luminance_follows_the_times_at_2_ev():
    """The stabilised merges on a 2-EV bracket of the fixed gamma-2.2 rendering (Fujifilm X-T3, not
    looked at while choosing; 9 frames, scene 1, white 255), where both missed issue 36's line before
    (stabilized 1.9 %, a decade at 1.050; stabilized-joint 3.0 %, 1.063: the gammas' level read
    from pair gains extrapolated to white, 0.7 % high, and the shortest frames' matrices). The pairs'
    gains read at their own colours follow the times (``gamma_level``), so the level comes from them
    and the matrices' scale from the times (:func:`derender.hdr.stabilize.colour_model.anchor_to_times`):
    measured 1.4 % / 0.7 %, worst decades 1.025 / 1.014. The line (median <= 3 %, every decade
    within +-5 %) is asserted; which level was taken is tested in ``tests/hdr/test_stabilize_families.py``."""
    from conftest import require_shared

    from derender.evaluation.linearity import spacing_rows

    require_shared("rawtoaces-spectral")
    rows = list(spacing_rows(["fujifilm-x-t3"], [2.0], [1], ["255"], ["stabilized", "stabilized-joint"], (False,)))
    assert len(rows) == 2
    for r in rows:
        assert r["frames"] == 9 and all(c > 300 for c in r["counts"]), r["counts"]
        assert r["median_abs"] <= 0.03, (r["method"], r["median_abs"])
        assert np.all(np.abs(np.asarray(r["decades"]) - 1.0) <= 0.05), (r["method"], r["decades"])


def test_robertson_has_no_two_stop_ripple_on_a_held_out_camera():
    """Issue 36's line for ``robertson`` where it missed: 2 EV (9 frames), on the Fujifilm X-T3
    (``rawtoaces-spectral``; held out: not looked at while choosing), scene 1, white drawn in
    250..254, the luminance family's fixed gamma-2.2 rendering. With ``--spot`` on the grey card,
    the median abs error <= 3 % and every decade within +-5 %; and the curve itself, green channel
    relative to code 128, within +-5 % of the true gamma 2.2 over codes 96-224 (where the 2-stop
    ripple was) with the white found below 255. Before the calibration's bounds
    (:func:`derender.response.robertson2003.calibration_bounds`) this bracket read 4.4 %, worst
    decade 0.932 (the test failed at its median, 4.38 %), the curve 1.000-1.257 of the gamma over
    codes 96-224; now 1.5 %, worst decade 0.981, the curve 0.994-1.045 and the white 250."""
    import math

    from conftest import require_shared

    from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2
    from derender.core.types import Stack
    from derender.evaluation.families import smooth_mask
    from derender.evaluation.linearity import linearity_scores, saturate_below
    from derender.hdr.registry import merge_seeded

    require_shared("rawtoaces-spectral")
    n = int(math.ceil(16 / 2.0)) + 1
    b = simulate_luminance(render="gamma", size=(192, 128), exposures=n, stops=2.0, seed=1, camera="fujifilm-x-t3")
    codes = saturate_below(b.jpeg_codes, 1)
    res = merge_seeded(Stack(images=codes.astype(np.float32) * np.float32(1 / 255), times=b.times), "robertson", 0)
    sc = linearity_scores(res.radiance, truth_luminance_cd_m2(b.truth_linear_srgb), b.params["luminance"]["spot"],
                          score_mask=smooth_mask(b.truth_linear_srgb), merge_mask=res.mask)
    assert all(c > 300 for c in sc["counts"]), sc["counts"]
    assert sc["median_abs"] <= 0.03, sc["median_abs"]
    assert np.all(np.abs(np.asarray(sc["decades"]) - 1.0) <= 0.05), sc["decades"]
    curves = res.info["curves"]
    z = np.arange(96, 225)
    g = curves.log_inverse[:, 1]
    ratio = np.exp(g[z] - g[128] - 2.2 * np.log(z / 128.0))
    assert np.all(np.abs(ratio - 1.0) <= 0.05), (z[np.argmax(np.abs(ratio - 1.0))], ratio.min(), ratio.max())
    assert all(250 <= w < 255 for w in curves.params["white_codes"]), curves.params["white_codes"]
