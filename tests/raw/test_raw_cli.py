"""``derender merge`` and ``derender groundtruth`` on RAW brackets (simulated DNG files with exact truth)."""

import numpy as np
import pytest
from helpers import run_cli

from derender.camera import simulate_bracket, write_bracket
from derender.evaluation.raw_merge import raw_scores
from derender.io.exr import read_exr


@pytest.fixture(scope="module")
def bracket_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("rawbracket")
    b = simulate_bracket("nikon-d5100", kind="outdoor", size=(96, 64), exposures=4, seed=7, style="simple",
                         pipeline="fixed")
    write_bracket(b, d)
    return d, b


def test_merge_dngs_with_variance(bracket_dir, tmp_path, capsys):
    d, b = bracket_dir
    dngs = sorted((d / "raw").glob("*.dng"))
    code, out, err = run_cli(["merge", *dngs[::-1], "-o", tmp_path / "m.exr", "--variance", tmp_path / "v.exr"],
                             capsys)
    assert code == 0, err
    assert out.startswith("raw: 4 images 96x64") and "estimated from the frame pairs" in out
    rad, var = read_exr(tmp_path / "m.exr"), read_exr(tmp_path / "v.exr")
    assert rad.shape == var.shape == (64, 96, 3) and np.all(np.isfinite(rad)) and rad.min() >= 0
    # the same as the in-memory merge, and ahead of paper 1's ground truth on the scene (truth.exr)
    from derender.io.raw import read_raw_stack
    from derender.raw.optimal import raw_merge

    mem = raw_merge(read_raw_stack(dngs))
    np.testing.assert_allclose(rad, mem.radiance, rtol=1e-6)
    truth = read_exr(d / "truth.exr")
    code, _, err = run_cli(["groundtruth", *dngs, "-o", tmp_path / "p1.exr", "--method", "paper1"], capsys)
    assert code == 0, err
    code, _, err = run_cli(["groundtruth", *dngs, "-o", tmp_path / "gt.exr"], capsys)
    assert code == 0, err
    np.testing.assert_array_equal(read_exr(tmp_path / "gt.exr"), rad)       # groundtruth's default is the merge
    ours = raw_scores(rad, truth, mem.mask)
    theirs = raw_scores(read_exr(tmp_path / "p1.exr"), truth, mem.mask)
    assert ours["median"] < theirs["median"] and ours["dark_decade"] < theirs["dark_decade"]
    # a folder (the bracket's, whose raw/ subfolder holds the DNGs) with --method raw
    code, out, err = run_cli(["merge", d / "raw", "-o", tmp_path / "f.exr", "--method", "raw",
                              "-O", "output_space=camera_rgb"], capsys)
    assert code == 0, err
    assert read_exr(tmp_path / "f.exr").shape == (64, 96, 3)


def test_raw_bad_input_is_one_error_line(bracket_dir, tmp_path, capsys):
    d, _ = bracket_dir
    dngs = sorted((d / "raw").glob("*.dng"))
    jpgs = sorted((d / "jpeg").glob("*.jpg"))
    other = tmp_path / "other"
    write_bracket(simulate_bracket("sigma-sd-merrill", kind="outdoor", size=(96, 64), exposures=2, seed=1,
                                   style="simple", pipeline="fixed"), other)
    cases = [
        (["merge", dngs[0], jpgs[1], "-o", tmp_path / "a.exr"], "mixes raw and rendered"),
        (["merge", dngs[0], other / "raw" / "01.dng", "-o", tmp_path / "a.exr"], "mixes cameras"),
        (["merge", *dngs, "-o", tmp_path / "a.exr", "--method", "debevec"], "--method raw"),
        (["merge", *jpgs, "-o", tmp_path / "a.exr", "--method", "raw"], "merges raw files"),
        (["merge", *dngs, "-o", tmp_path / "a.exr", "--align", "translation"], "not available on raw"),
        (["merge", *dngs, "-o", tmp_path / "a.exr", "--deghost"], "not available on raw"),
        (["merge", *dngs, "-o", tmp_path / "a.exr", "-O", "estimator=paper1", "--variance", tmp_path / "v.exr"],
         "no variance"),
        (["merge", *dngs, "-o", tmp_path / "a.exr", "-O", "gain=2"], "both gain and read_noise"),
        (["groundtruth", *dngs, "-o", tmp_path / "a.exr", "--method", "eq11"], "--method"),
    ]
    for args, needle in cases:
        code, out, err = run_cli(args, capsys)
        assert code == 2, (args, err)
        assert "Traceback" not in err and needle.lower() in err.lower(), (args, err)
        assert err.count("error:") == 1
        assert not (tmp_path / "a.exr").exists() and not (tmp_path / "v.exr").exists()


def test_frames_without_exposure_time(bracket_dir, tmp_path, capsys):
    """Several frames without a time: the error names them; one frame: relative units, or --times."""
    import tifffile

    d, _ = bracket_dir
    dngs = sorted((d / "raw").glob("*.dng"))
    stripped = []
    for p in dngs[:2]:
        with tifffile.TiffFile(p) as tif:
            page = tif.pages[0]
            arr = page.asarray()
            tags = [(t.code, t.dtype, t.count, t.value, True) for t in page.tags.values()
                    if t.code in (254, 271, 272, 33421, 33422, 50706, 50707, 50708, 50713, 50714, 50717, 50721, 50728,
                                  50778)]
        q = tmp_path / p.name
        tifffile.imwrite(q, arr, photometric=32803, extratags=[(c, dt if isinstance(dt, str) else dt, n,
                                                               v, w) for c, dt, n, v, w in tags])
        stripped.append(q)
    code, _, err = run_cli(["merge", *stripped, "-o", tmp_path / "a.exr"], capsys)
    assert code == 2 and "no exposure time in 00.dng, 01.dng" in err, err
    code, out, err = run_cli(["merge", *stripped, "-o", tmp_path / "a.exr", "--times", "0.001,0.01"], capsys)
    assert code == 0, err
    (tmp_path / "times.txt").write_text("00.dng 1000\n01.dng 100\n")
    code, out, err = run_cli(["merge", *stripped, "-o", tmp_path / "c.exr", "--times-file", tmp_path / "times.txt",
                              "--times-inverse"], capsys)
    assert code == 0, err
    np.testing.assert_array_equal(read_exr(tmp_path / "c.exr"), read_exr(tmp_path / "a.exr"))
    code, out, err = run_cli(["merge", stripped[0], "-o", tmp_path / "b.exr"], capsys)
    assert code == 0, err
    assert "relative units" in out


def test_a_bracket_varying_aperture_is_refused(tmp_path, capsys):
    from derender.camera.luminance import simulate_luminance

    write_bracket(simulate_luminance(mode="aperture-iso", size=(64, 48), exposures=3, seed=0), tmp_path / "b")
    code, _, err = run_cli(["merge", tmp_path / "b" / "raw", "-o", tmp_path / "a.exr"], capsys)
    assert code == 2 and "vary the f-number" in err, err
    assert not (tmp_path / "a.exr").exists()


def test_vignetting_fitted_on_a_raw_flat_field_and_divided_out(tmp_path, capsys):
    from derender.camera.luminance import simulate_luminance

    write_bracket(simulate_luminance(mode="flat-field", size=(96, 64), exposures=3, seed=0, falloff=0.55),
                  tmp_path / "ff")
    code, out, err = run_cli(["vignetting", tmp_path / "ff" / "raw", "-o", tmp_path / "v.json"], capsys)
    assert code == 0, err
    corner = float(out.split("corner ")[1].split(",")[0])
    assert abs(corner - 0.55) < 0.01                       # measured 0.547
    code, out, err = run_cli(["merge", tmp_path / "ff" / "raw", "-o", tmp_path / "m.exr", "--vignetting",
                              tmp_path / "v.json"], capsys)
    assert code == 0, err
    lum = read_exr(tmp_path / "m.exr").mean(-1)
    assert abs(lum[2:8, 2:8].mean() / lum[28:36, 44:52].mean() - 1) < 0.01     # measured 1.0005
