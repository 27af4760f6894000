"""benchmarks/runner.py: the side-by-side merge benchmark and its peak-memory measurement."""

from __future__ import annotations

import sys

import numpy as np

from derender.io.exr import read_exr


def test_run_bench_small(tmp_path):
    from runner import format_bench, run_bench

    res = run_bench(size=(96, 64), frames=3, workdir=tmp_path, entries=["opencv", "colour-hdri", "derender-debevec"])
    runs = res["runs"]
    assert runs["opencv"]["status"] == "ok", runs["opencv"]
    assert runs["derender-debevec"]["status"] == "ok", runs["derender-debevec"]
    assert runs["colour-hdri"]["status"] in ("ok", "skipped")
    assert runs["derender-debevec"]["peak_rss_mb"] > 10 and runs["opencv"]["wall_s"] > 0
    assert "derender-debevec / opencv" in res["ratios"]
    assert "| derender-debevec | ok |" in format_bench(res)
    out = read_exr(tmp_path / "outputs" / "derender-debevec-3.exr")
    assert out.shape == (64, 96, 3) and np.all(np.isfinite(out))


def test_peak_rss_is_the_childs_own_not_the_runners():
    """A forked child's wait4 ru_maxrss starts from the parent's RSS (issue 15); the wrapper reads the
    child's own VmHWM: a child that allocates 1000 MB (1e9 bytes, the unit of the RSS target) reports
    >= 1000 MB (in MiB, the unit mixed in before, it would be 954 + the interpreter), a child printing 1
    reports far less than this (bloated) runner process."""
    from runner import _run_measured

    ballast = np.ones(40_000_000)                 # 320 MB in the runner
    big = _run_measured([sys.executable, "-c", "import numpy as np; a = np.ones(125_000_000); print(a.sum())"])
    small = _run_measured([sys.executable, "-c", "print(1)"])
    del ballast
    assert big["returncode"] == 0 and big["stdout"].strip() == "125000000.0"
    assert big["peak_rss_source"] == small["peak_rss_source"] == "VmHWM (child)"
    assert 1000 <= big["peak_rss_mb"] < 1100
    assert small["peak_rss_mb"] < 60
    assert "__DERENDER_PEAK_RSS_KB__" not in big["stderr"]
