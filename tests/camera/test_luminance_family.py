"""The luminance-truth family: absolute cd/m2, EXIF t/N/ISO consistent with the exposures, grey card, falloff."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run_cli


def test_truth_is_absolute_luminance_over_five_decades():
    """The truth's luminance in cd/m2 is 120 (w . truth) (ISO 12232: a neutral of luminance L
    reaches white at L t S / N^2 = 120). Checked from the sensor itself: in the noise-free
    RAW, a grey-card photosite's green value (white-balance multiplier 1) is L e / 120 of white
    for e = t S / N^2, whatever the aperture and ISO."""
    from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2

    b = simulate_luminance(mode="aperture-iso", render="gamma", size=(96, 64), exposures=7, seed=3, noise=False)
    lum = truth_luminance_cd_m2(b.truth_linear_srgb)
    lp = b.params["luminance"]
    assert lp["luminance_range_cd_m2"][0] < 1.0 and lp["luminance_range_cd_m2"][1] > 3e5
    for lo in (1.0, 10.0, 100.0, 1e3, 1e4, 1e5):      # every decade is populated
        assert np.count_nonzero((lum >= lo) & (lum < 10 * lo)) > 50, lo
    x, y, w, h = lp["spot"]
    assert lp["spot_cd_m2"] == pytest.approx(float(lum[y:y + h, x:x + w].mean()), rel=1e-9)
    assert 50 < lp["spot_cd_m2"] < 1000
    e = np.array(lp["exif_times"]) * np.array(lp["isos"]) / np.array(lp["fnumbers"]) ** 2
    np.testing.assert_allclose(b.times, e, rtol=1e-12)
    cam = b.camera
    gy, gx = y + h // 2, x + w // 2
    gy, gx = gy - gy % 2, gx - gx % 2 + 1                 # RGGB: (even, odd) is a green photosite
    j = int(np.argmin(np.abs(np.log(lum[gy, gx] * e / 120.0 / 0.4))))     # the frame nearest 40 % of white
    raw = (b.mosaics[j, gy, gx] - cam.black_level) / (cam.white_level - cam.black_level)
    assert raw == pytest.approx(lum[gy, gx] * e[j] / 120.0, rel=0.03)


def test_exif_written_and_consistent(tmp_path, capsys):
    """``derender simulate --luminance aperture-iso`` writes EXIF ExposureTime, FNumber and ISO
    that derender reads back, which vary across the bracket, and whose t S / N^2 are the
    simulator's exposures; the time-only bracket keeps f/16 and ISO 100. scene.json gives the
    ready --spot, and a merge with it reads the spot's luminance."""
    from derender.camera import bracket_paths
    from derender.io.exif import read_exif

    code, out, err = run_cli(["simulate", tmp_path / "a", "--luminance", "aperture-iso", "--render", "gamma",
                              "--size", "96x64", "-n", "5", "--seed", "1"], capsys)
    assert code == 0, err
    params = json.loads((tmp_path / "a" / "scene.json").read_text())
    lp = params["luminance"]
    exifs = [read_exif(p) for p in bracket_paths(tmp_path / "a", "jpeg")]
    assert [e["FNumber"] for e in exifs] == pytest.approx(lp["fnumbers"])
    assert [e["ISO"] for e in exifs] == lp["isos"]
    assert [e["ExposureTime"] for e in exifs] == pytest.approx(lp["exif_times"], rel=1e-6)
    assert len(set(lp["fnumbers"])) > 1 and len(set(lp["isos"])) > 1
    e = [x["ExposureTime"] * x["ISO"] / x["FNumber"] ** 2 for x in exifs]
    np.testing.assert_allclose(e, params["times"], rtol=1e-5)
    assert lp["role"] == "tuning" and lp["spot_option"] in out
    code, _, err = run_cli(["simulate", tmp_path / "t", "--luminance", "time", "--render", "dslr-lut",
                            "--size", "96x64", "-n", "3"], capsys)
    assert code == 0, err
    lt = json.loads((tmp_path / "t" / "scene.json").read_text())["luminance"]
    assert set(lt["fnumbers"]) == {16.0} and set(lt["isos"]) == {100} and lt["role"] == "held-out"
    from derender.io.exr import read_exr
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    code, _, err = run_cli(["merge", *bracket_paths(tmp_path / "a", "jpeg"), "-o", tmp_path / "m.exr",
                            "--spot", lp["spot_option"]], capsys)
    assert code == 0, err
    x, y, w, h = lp["spot"]
    got = luminance_cd_m2(read_exr(tmp_path / "m.exr"), SRGB_PRIMARIES)[y:y + h, x:x + w].mean()
    assert got == pytest.approx(lp["spot_cd_m2"], rel=1e-3)


def test_falloff_and_flat_field():
    """The lens falloff multiplies the sensor signal (corner = the given transmission) but not the
    truth; the flat field is uniform in truth."""
    from derender.camera.luminance import radial_falloff, simulate_luminance

    v = radial_falloff((64, 48), 0.55)
    assert v[0, 0] == pytest.approx(0.55) and v[-1, -1] == pytest.approx(0.55) and v.max() <= 1.0
    a = simulate_luminance(mode="flat-field", size=(64, 48), exposures=3, noise=False)
    b = simulate_luminance(mode="flat-field", size=(64, 48), exposures=3, noise=False, falloff=0.55)
    np.testing.assert_array_equal(a.truth_linear_srgb, b.truth_linear_srgb)
    t = a.truth_linear_srgb
    assert float(t.std() / t.mean()) < 1e-3
    ra = a.mosaics[1].astype(float) - a.camera.black_level
    rb = b.mosaics[1].astype(float) - b.camera.black_level
    assert rb[2, 3] / ra[2, 3] == pytest.approx(v[2, 3], rel=0.02)
    assert rb[24, 33] / ra[24, 33] == pytest.approx(v[24, 33], rel=0.02)
    assert b.params["luminance"]["falloff_corner"] == 0.55


def test_bad_options(tmp_path, capsys):
    for args, needle in ((["--luminance", "sideways"], "--luminance"), (["--lens-falloff", "0.5"], "--luminance"),
                         (["--luminance", "time", "--lens-falloff", "1.5"], "corner"),
                         (["--luminance", "time", "--render", "simple", "-n", "1"], "--exposures")):
        code, _, err = run_cli(["simulate", tmp_path / "x", "--size", "64x48", *args], capsys)
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], (args, err)
    assert not (tmp_path / "x").exists()
