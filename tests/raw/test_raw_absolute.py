"""``--absolute exif`` on RAW brackets: the nominal factor from f-number and ISO against the
luminance family's exact cd/m2 (the simulator's sensor is exposed by ISO 12232's saturation
speed, docs/raw.md)."""

import numpy as np
import pytest
from helpers import run_cli

from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2
from derender.core.errors import InputError
from derender.photometry.calibration import RAW_SATURATION_EXPOSURE, raw_exif_factor
from derender.photometry.illuminance import luminance_cd_m2


@pytest.fixture(scope="module")
def luminance_dngs(tmp_path_factory):
    from derender.camera import write_bracket

    d = tmp_path_factory.mktemp("rawlum")
    b = simulate_luminance(mode="time", size=(96, 64), exposures=8, seed=0)
    write_bracket(b, d)
    return d, b


def test_raw_exif_factor_formula():
    # ISO 12232: white at H_sat = 78 / S lx s, H = 0.65 L t / N^2; per second, on 179 w.m
    cal = raw_exif_factor([(8.0, 200), (8.0, 200)], rating="saturation")
    assert cal.factor == pytest.approx(120.0 * 64 / (179.0 * 200))
    assert RAW_SATURATION_EXPOSURE == pytest.approx(120.0)
    assert cal.uncertainty == pytest.approx(0.15, abs=0.01)
    assert raw_exif_factor([(8.0, 200)]).uncertainty == pytest.approx(0.44, abs=0.01)   # unstated rating: +-1 EV
    with pytest.raises(InputError, match="vary the f-number or ISO"):
        raw_exif_factor([(8.0, 200), (8.0, 400)])
    with pytest.raises(InputError, match="positive f-number"):
        raw_exif_factor([(0.0, 200)])


def test_merge_raw_absolute_exif_matches_the_truth(luminance_dngs, tmp_path, capsys):
    from derender.io.exr import read_exr, read_exr_attributes

    d, b = luminance_dngs
    out = tmp_path / "abs.exr"
    code, _, err = run_cli(["merge", d / "raw", "-o", out, "--absolute", "exif"], capsys)
    assert code == 0, err
    assert "nominal from EXIF" in err and "RAW white level" in err
    assert "ISO 12232 saturation speed" in err and "uncertainty 15 %" in err   # the DNGs say SensitivityType 3
    assert "exif nominal" in read_exr_attributes(out)["derender:photometry"]
    lum = luminance_cd_m2(read_exr(out).astype(np.float64))
    truth = truth_luminance_cd_m2(b.truth_linear_srgb)
    ok = truth > 0
    ratio = lum[ok] / truth[ok]
    assert abs(np.median(ratio) - 1.0) < 0.02
    for lo in (1.0, 10.0, 100.0, 1e3, 1e4, 1e5):          # every decade with pixels, 1 .. 1e6 cd/m2
        sel = (truth[ok] >= lo) & (truth[ok] < 10 * lo)
        if sel.sum() >= 50:
            assert abs(np.median(ratio[sel]) - 1.0) < 0.03, lo


def test_raw_absolute_exif_needs_fnumber_and_iso(tmp_path, capsys):
    import os

    from derender.camera.dng import write_dng

    signal = np.linspace(0.02, 2.0, 32 * 32).reshape(32, 32)
    paths = [write_dng(os.path.join(tmp_path, f"{i}.dng"),
                       np.round(64 + np.clip(signal * t / 0.04, 0, 1) * 4031).astype(np.uint16),
                       cfa_pattern="RGGB", black_level=64, white_level=4095, xyz_to_camera=np.eye(3),
                       as_shot_neutral=np.ones(3), exposure_time=t, make="Sim", model="Cam", bits=12, iso=100)
             for i, t in enumerate((0.01, 0.04))]
    before = [p.read_bytes() for p in paths]
    code, out, err = run_cli(["merge", *paths, "-o", tmp_path / "x.exr", "--absolute", "exif"], capsys)
    assert code == 2 and not (tmp_path / "x.exr").exists()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "0.dng has no FNumber" in lines[0], err
    assert [p.read_bytes() for p in paths] == before
