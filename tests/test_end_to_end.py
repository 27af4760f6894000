"""End to end on simulator files: CLI merge/evaluate/diagnose/groundtruth, the demo, and
Debevec against OpenCV's CalibrateDebevec + MergeDebevec on the same JPEGs (issue 3)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run_cli

from derender.camera import bracket_paths, simulate_bracket, write_bracket
from derender.evaluation.metrics import psnr_rgbl
from derender.hdr.registry import merge
from derender.io.exr import read_exr
from derender.io.images import read_image, read_stack


@pytest.fixture(scope="module", params=["fixed", "auto"])
def sim_dir(request, tmp_path_factory):
    d = tmp_path_factory.mktemp(f"sim-{request.param}")
    write_bracket(simulate_bracket(size=(192, 128), exposures=7, pipeline=request.param, seed=4), d)
    return d


def _opencv_debevec(stack) -> np.ndarray:
    import cv2

    imgs = [np.ascontiguousarray(c[..., ::-1]) for c in stack.codes()]
    times = stack.times.astype(np.float32)
    crf = cv2.createCalibrateDebevec().process(imgs, times)
    hdr = cv2.createMergeDebevec().process(imgs, times, crf)[..., ::-1]
    return np.nan_to_num(hdr, nan=0.0, posinf=0.0, neginf=0.0)


def test_debevec_matches_or_beats_opencv_on_simulator(sim_dir):
    stack = read_stack(bracket_paths(sim_dir, "jpeg"))
    truth = read_exr(sim_dir / "truth.exr")
    ours = psnr_rgbl(merge(stack, method="debevec").radiance, truth)
    theirs = psnr_rgbl(_opencv_debevec(stack), truth)
    assert ours["L"] >= theirs["L"] - 0.3, (ours, theirs)


def test_cli_merge_evaluate_diagnose_groundtruth(sim_dir, tmp_path, capsys):
    jpgs = bracket_paths(sim_dir, "jpeg")
    out = tmp_path / "m.exr"
    code, o, e = run_cli(["merge", *jpgs, "-o", out, "--preview", tmp_path / "p.png", "--mask", tmp_path / "k.png",
                          "--plot", tmp_path / "c.png"], capsys)
    assert code == 0, e
    rad = read_exr(out)
    assert rad.shape == (128, 192, 3) and np.all(np.isfinite(rad))
    assert read_image(tmp_path / "p.png")[0].shape == (128, 192, 3)
    code, o, e = run_cli(["evaluate", out, sim_dir / "truth.exr", "--json"], capsys)
    assert code == 0, e
    scores = json.loads(o)
    ref = psnr_rgbl(rad, read_exr(sim_dir / "truth.exr"))
    assert scores["L"] == pytest.approx(ref["L"], abs=1e-3)
    code, o, e = run_cli(["diagnose", *jpgs, "-o", tmp_path / "d.png"], capsys)
    assert code == 0, e
    assert "stops" in o and (tmp_path / "d.png").stat().st_size > 1000
    code, o, e = run_cli(["groundtruth", *bracket_paths(sim_dir, "raw"), "-o", tmp_path / "gt.exr"], capsys)
    assert code == 0, e
    gt = read_exr(tmp_path / "gt.exr")
    assert psnr_rgbl(gt, read_exr(sim_dir / "truth.exr"))["L"] > 45


def test_cli_merge_user_errors(sim_dir, tmp_path, capsys):
    jpgs = bracket_paths(sim_dir, "jpeg")
    cases = [
        (["merge", jpgs[0], "-o", tmp_path / "a.exr"], "at least two"),
        (["merge", *jpgs[:2], "-o", tmp_path / "a.exr", "--times", "0.1,0.1"], "duplicate"),
        (["merge", *jpgs[:2], "-o", tmp_path / "a.exr", "--times", "0.1"], "exposure time"),
        (["merge", *jpgs[:2], "-o", tmp_path / "a.png"], ".exr"),
        (["merge", *jpgs[:2], "-o", tmp_path / "a.exr", "--method", "magic"], "unknown merge method"),
        (["merge", *jpgs[:2], "-o", jpgs[0].with_suffix(".exr"), "--times", "0.1,0.2",
          "--times-file", tmp_path / "x"], "either"),
        (["merge", tmp_path / "missing.jpg", jpgs[0], "-o", tmp_path / "a.exr"], "no such file"),
        (["groundtruth", jpgs[0], "-o", tmp_path / "g.exr"], "cannot read raw"),
        (["evaluate", tmp_path / "none.exr", sim_dir / "truth.exr"], "no such file"),
    ]
    for args, needle in cases:
        code, o, e = run_cli(args, capsys)
        assert code == 2, (args, e)
        assert "Traceback" not in e and needle.lower() in e.lower(), (args, e)
    # an all-saturated stack is an error, not a black image
    white = [tmp_path / "w0.png", tmp_path / "w1.png"]
    import cv2

    for p in white:
        cv2.imwrite(str(p), np.full((8, 8, 3), 255, np.uint8))
    code, o, e = run_cli(["merge", *white, "-o", tmp_path / "w.exr", "--times", "0.1,0.2"], capsys)
    assert code == 2 and "error:" in e
    assert not (tmp_path / "w.exr").exists()


def test_demo_runs_and_scores(tmp_path, capsys):
    code, o, e = run_cli(["demo", "-o", tmp_path / "demo", "--size", "160x112"], capsys)
    assert code == 0, e
    rows = json.loads((tmp_path / "demo" / "scores.json").read_text())
    names = [r["method"] for r in rows]
    from derender.hdr.registry import METHODS

    assert names[:2] == ["raw-groundtruth (DNG)", "debevec"]   # the ground truth, then the baseline
    assert sorted(names[1:]) == sorted(METHODS)                # "every method" is every method, once
    for r in rows:
        assert all(np.isfinite(r[p]) for p in "RGBL")
        assert r["L"] > 30.0, r                                # against the simulator's exact radiance
    assert next(r for r in rows if r["method"] == "probabilistic")["calibration_seconds"] > 0
    assert (tmp_path / "demo" / "model-gp.npz").is_file()
    assert "calibrated" in e
    assert (tmp_path / "demo" / "merge-debevec.exr").is_file()
