"""merge_files / ``derender merge``: the input contract on exposure times (issue 15, item 3)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli

from derender.core.errors import InputError
from derender.core.types import check_brightness_order
from derender.engine.options import EngineOptions


def test_brightness_order_accepts_brackets_and_clipped_ends():
    t = [1 / 100, 1 / 25, 1 / 6, 0.7, 3.0]
    check_brightness_order(t, [1.0, 20.0, 80.0, 200.0, 254.5])          # black and clipped ends ignored
    check_brightness_order(t[::-1], [254.5, 200.0, 80.0, 20.0, 1.0])    # order of the lists is free
    check_brightness_order([0.1, 0.2], [100.0, 99.0])                   # within 2 codes: noise
    check_brightness_order([0.1, 0.2, 0.4], [50.0, 48.0, 120.0])         # one small dip among rises


def test_brightness_order_refuses_inverted_times_with_a_hint():
    with pytest.raises(InputError, match=r"a.jpg \(0.25 s\) is brighter than b.jpg .*did you mean"):
        check_brightness_order([0.25, 0.5, 1.0], [150.0, 100.0, 40.0], ["a.jpg", "b.jpg", "c.jpg"],
                               "did you mean --times-inverse?")
    with pytest.raises(InputError, match="image 0"):
        check_brightness_order([1.0, 2.0], [200.0, 20.0])


def test_cli_refuses_memorial_list_without_times_inverse(memorial_dir, tmp_path, capsys):
    pngs = sorted(memorial_dir.glob("memorial00*.png"))[::3]
    lst = memorial_dir / "memorial.hdr_image_list.txt"
    for method in ("debevec", "stabilized"):
        out = tmp_path / f"{method}.exr"
        code, o, e = run_cli(["merge", *pngs, "--times-file", lst, "-o", out, "--method", method], capsys)
        assert code == 2, (o, e)
        lines = [ln for ln in (o + e).splitlines() if ln.strip()]
        assert lines[-1].startswith("error: exposure times contradict the images") and "--times-inverse" in lines[-1]
        assert "Traceback" not in o + e and not out.exists()
    code, o, e = run_cli(["merge", *pngs, "--times-file", lst, "--times-inverse", "-o", tmp_path / "ok.exr"], capsys)
    assert code == 0, e


def test_cli_refuses_times_in_the_wrong_order(tmp_path, capsys):
    from derender.camera import bracket_paths, simulate_bracket, write_bracket

    write_bracket(simulate_bracket(size=(64, 48), exposures=3, pipeline="auto", seed=2), tmp_path / "b")
    jpgs = bracket_paths(tmp_path / "b", "jpeg")
    rng = np.random.default_rng(0)
    for method in ("debevec", "robertson", "stabilized"):
        code, o, e = run_cli(["merge", *jpgs, "--times", "8,1,1/8", "-o", tmp_path / "x.exr", "--method", method,
                              "--seed", int(rng.integers(10))], capsys)
        assert code == 2 and "check the order of the times" in o + e, (method, o, e)
        assert not (tmp_path / "x.exr").exists()


def test_options_that_need_each_other(tmp_path, capsys):
    from derender.camera import bracket_paths, simulate_bracket, write_bracket

    write_bracket(simulate_bracket(size=(48, 32), exposures=3, pipeline="fixed", seed=1), tmp_path / "b")
    jpgs = bracket_paths(tmp_path / "b", "jpeg")
    code, o, e = run_cli(["merge", *jpgs, "--times-inverse", "-o", tmp_path / "x.exr"], capsys)
    assert code == 2 and "--times-inverse applies to a --times-file" in o + e
    for method in ("stabilized-probabilistic", "probabilistic"):
        code, o, e = run_cli(["merge", *jpgs, "-o", tmp_path / "x.exr", "--method", method], capsys)
        assert code == 2 and "needs option(s) model (-m MODEL.npz)" in o + e, (method, o, e)
    assert not (tmp_path / "x.exr").exists()
    from derender.core.types import Stack
    from derender.hdr.registry import merge

    with pytest.raises(InputError, match="needs option"):
        merge(Stack(images=np.zeros((2, 4, 4, 3), np.float32), times=[0.1, 0.2]), "probabilistic")


def test_clipped_count_is_the_same_for_every_method_and_engine_path(tmp_path):
    """'px clipped even in the shortest exposure' is counted once, by the engine, from the codes:
    every method and every engine path (streamed in two passes, held, compiled) reports the
    count of the shortest frame's pixels with a channel at 255 (issue 24 item 7: the summary said
    0, 9528 and 3221 for one bracket)."""
    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.engine.frames import clipped_pixels
    from derender.hdr.files import merge_files
    from derender.io.images import read_codes

    write_bracket(simulate_bracket(size=(96, 64), exposures=4, pipeline="auto", seed=12, peak_percentile=95.0),
                  tmp_path / "b")
    paths = bracket_paths(tmp_path / "b", "jpeg")
    want = clipped_pixels(read_codes(paths[0]))
    assert want > 0
    counts = {m: merge_files(paths, method=m).info["n_clipped"] for m in ("debevec", "robertson", "stabilized")}
    counts["debevec two-pass"] = merge_files(paths, method="debevec",
                                             engine=EngineOptions(keep_frames=1)).info["n_clipped"]
    assert set(counts.values()) == {want}, counts
