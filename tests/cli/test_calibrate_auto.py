"""``derender calibrate`` defaults to ``--method auto`` (issue 27): the cross-validation table is
printed and stored in the model file, and the model it writes is used like any other
(``derender derender -m`` and ``derender merge -m`` give what the directly fitted model gives)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli

from derender.camera.chart import chart_pairs, save_pairs
from derender.derendering.base import load_model


@pytest.fixture(scope="module")
def pairs_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("pairs")
    return save_pairs(chart_pairs("nikon-d5100", n_illuminants=6, n_exposures=10, seed=0), d / "nikon.npz")


FAST = ["--n-train", "600", "--cv-train", "300"]


def test_calibrate_defaults_to_auto_prints_and_stores_the_table(pairs_file, tmp_path, capsys):
    out = tmp_path / "auto.npz"
    code, stdout, err = run_cli(["calibrate", "--pairs", pairs_file, "-o", out, *FAST], capsys)
    assert code == 0, err
    for needle in ("rel RMSE all", "rel RMSE out-of-gamut", "coverage 95 %", "gp", "poly", "rbf",
                   "4 folds of whole illuminants (6 illuminants)"):
        assert needle in stdout, (needle, stdout)
    model = load_model(out)
    table = model.metadata["model_selection"]
    chosen = table["chosen"]
    assert model.method == chosen and f"auto chose {chosen}" in stdout
    assert table["folds"]["scheme"] == "illuminant" and table["folds"]["n_groups"] == 6
    best = min(table["rows"], key=lambda r: r["rel_rmse_all"])
    assert best["method"] == chosen and f"{best['rel_rmse_all']:.4f}" in stdout
    assert model.metadata["camera"]["model"] == "NIKON D5100"       # calibrate's metadata kept beside the table
    # the chosen model is exactly the one --method <chosen> writes, and loads and derenders like it
    direct = tmp_path / "direct.npz"
    code, stdout2, err = run_cli(["calibrate", "--pairs", pairs_file, "-o", direct, "--method", chosen, *FAST],
                                 capsys)
    assert code == 0, err
    assert "auto chose" not in stdout2 and "model_selection" not in load_model(direct).metadata
    from derender.camera import write_jpeg
    from derender.io.exr import read_exr

    codes = np.random.default_rng(0).integers(0, 256, (24, 32, 3)).astype(np.uint8)
    img = write_jpeg(tmp_path / "shot.jpg", codes, 0.01, "NIKON CORPORATION", "NIKON D5100")
    for m in (out, direct):
        code, _, err = run_cli(["derender", img, "-m", m, "-o", m.with_suffix(".exr")], capsys)
        assert code == 0, err
    np.testing.assert_array_equal(read_exr(out.with_suffix(".exr")), read_exr(direct.with_suffix(".exr")))
    from derender.camera import bracket_paths, simulate_bracket, write_bracket

    b = simulate_bracket(size=(48, 32), exposures=3, pipeline="fixed", wb_preset="D65", seed=2)
    write_bracket(b, tmp_path / "br")
    jpgs = bracket_paths(tmp_path / "br", "jpeg")
    for m in (out, direct):
        code, _, err = run_cli(["merge", *jpgs, "--method", "probabilistic", "-m", m, "-o", m.with_suffix(".hdr.exr"),
                                "--variance", m.with_suffix(".var.exr")], capsys)
        assert code == 0, err
    for suffix in (".hdr.exr", ".var.exr"):
        np.testing.assert_array_equal(read_exr(out.with_suffix(suffix)), read_exr(direct.with_suffix(suffix)))


def test_pairs_without_illuminants_use_random_folds(tmp_path, capsys):
    pr = chart_pairs("nikon-d5100", n_illuminants=2, n_exposures=6, seed=1)
    plain = tmp_path / "plain.npz"
    np.savez(plain, jpeg=pr.jpeg, raw=pr.raw)                   # no 'illuminant' array: as --raw/--jpeg pairs
    out = tmp_path / "m.npz"
    code, stdout, err = run_cli(["calibrate", "--pairs", plain, "-o", out, "--seed", "3", *FAST], capsys)
    assert code == 0, err
    assert "4 random folds" in stdout
    folds = load_model(out).metadata["model_selection"]["folds"]
    assert folds["scheme"] == "random" and folds["seed"] == 3
    assert all(r["rel_rmse_oog"] is None for r in load_model(out).metadata["model_selection"]["rows"])


def test_calibrate_auto_bad_input_is_one_error_line(pairs_file, tmp_path, capsys):
    few = tmp_path / "few.npz"
    pr = chart_pairs("nikon-d5100", n_illuminants=1, n_exposures=2, seed=0)
    np.savez(few, jpeg=pr.jpeg[:30], raw=pr.raw[:30])
    cases = [
        (["calibrate", "--pairs", few, "-o", tmp_path / "a.npz"], "too few for 4-fold"),
        (["calibrate", "--pairs", pairs_file, "-o", tmp_path / "b.npz", "--folds", "1"], "at least 2 folds"),
        (["calibrate", "--pairs", pairs_file, "-o", tmp_path / "c.npz", "--cv-train", "5"], "--cv-train"),
        (["calibrate", "--pairs", pairs_file, "-o", tmp_path / "d.npz", "--method", "best"], "--method"),
    ]
    for args, needle in cases:
        code, stdout, err = run_cli(args, capsys)
        assert code == 2, (args, err)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], (args, err)
        assert not args[4].exists()
