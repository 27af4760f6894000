"""Absolute luminance from a spot reading: the calibrated map against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli

from derender.evaluation.linearity import smoothest_window as _smoothest_window


@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_spot_calibrated_luminance_matches_the_absolute_truth(tmp_path, capsys, method):
    """The truth in cd/m2 is the simulator's radiance times an arbitrary 317.0; the meter reads
    its mean luminance over a smooth 8x8 patch. After --spot the patch reads the meter, and
    the map's luminance on the other smooth pixels (where demosaicing keeps the truth) matches
    the absolute truth: median ratio 0.971 / 0.975 and median absolute error 0.038 / 0.043
    (debevec with its merge's lambda 60; 0.974 / 0.054 at lambda 30)
    (debevec / stabilized, 168 smooth pixels; seed 7, 192x128, fixed pipeline, camera style); the bounds leave room for the method's own error
    but not for a wrong factor (179, the primaries' weights, the exposure)."""
    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.io.exr import read_exr
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    write_bracket(simulate_bracket(size=(192, 128), exposures=7, pipeline="fixed", seed=7), tmp_path / "b")
    truth_abs = read_exr(tmp_path / "b" / "truth.exr").astype(np.float64) * 317.0
    lum_true = luminance_cd_m2(truth_abs, SRGB_PRIMARIES)
    x, y = _smoothest_window(lum_true)
    nits = float(lum_true[y:y + 8, x:x + 8].mean())
    code, _, err = run_cli(["merge", *bracket_paths(tmp_path / "b", "jpeg"), "-o", tmp_path / "m.exr",
                            "--method", method, "--spot", f"{x},{y},8,8={nits:.6f}"], capsys)
    assert code == 0, err and "photometric factor" in err
    lum = luminance_cd_m2(read_exr(tmp_path / "m.exr"), SRGB_PRIMARIES)
    assert lum[y:y + 8, x:x + 8].mean() == pytest.approx(nits, rel=1e-4)
    from derender.evaluation.families import smooth_mask

    ok = (lum_true > 1e-3 * lum_true.max()) & smooth_mask(truth_abs)
    ok[y:y + 8, x:x + 8] = False
    ratio = lum[ok] / lum_true[ok]
    assert abs(np.median(ratio) - 1.0) < 0.06
    assert np.median(np.abs(ratio - 1.0)) < 0.08


def test_spot_errors(tmp_path, capsys):
    from derender.camera import bracket_paths, simulate_bracket, write_bracket

    write_bracket(simulate_bracket(size=(64, 48), exposures=3, pipeline="fixed", seed=8), tmp_path / "b")
    ins = bracket_paths(tmp_path / "b", "jpeg")
    for spot, needle in (("60,40,10,10=100", "outside"), ("1,2,3=4", "X,Y,W,H=NITS"), ("1,2,3,4=0", "positive")):
        code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "o.exr", "--spot", spot], capsys)
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], err
    assert not (tmp_path / "o.exr").exists()
