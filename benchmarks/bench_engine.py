"""pytest-benchmark micro-benchmarks of the 8-bit table engine (not part of the test suite).

    /tmp/venv/bin/pytest benchmarks/bench_engine.py --benchmark-only -p no:cacheprovider

Times, on one 3000x2000 frame: decoding (imagecodecs vs OpenCV), one exposure added to
the table engine (float64 / float32 accumulators), the reference engine's per-exposure
work (``merge_linear`` on a 2-frame stack, halved) and the EXR writer vs OpenEXR's.
"""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("pytest_benchmark")

from runner import generate_bench_bracket  # noqa: E402  (after the skips: pytest-benchmark is optional)

from derender.engine.tables import TableMerge, weight_table  # noqa: E402
from derender.io.exr import write_exr_fast  # noqa: E402
from derender.io.images import read_codes  # noqa: E402

SIZE = (3000, 2000)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    paths = generate_bench_bracket(tmp_path_factory.mktemp("b"), SIZE, 3, sim_width=384)
    return paths, [read_codes(p) for p in paths]


def test_decode_imagecodecs(benchmark, frames):
    benchmark(read_codes, frames[0][1])


def test_decode_opencv(benchmark, frames):
    benchmark(cv2.imread, str(frames[0][1]))


@pytest.mark.parametrize("acc", ["float64", "float32"])
def test_table_engine_add_one_frame(benchmark, frames, acc):
    codes = frames[1]
    eng = TableMerge(codes[0].shape[:2], accumulator=acc)
    vt = np.linspace(-5, 5, 256 * 3, dtype=np.float32).reshape(256, 3)
    wt = weight_table("gaussian")
    benchmark(eng.add, codes[1], vt, wt)
    eng.close()


def test_reference_engine_two_frames(benchmark, frames):
    from derender.engine.float_merge import merge_linear

    imgs = np.stack(frames[1][:2]).astype(np.float32) / 255
    benchmark.pedantic(merge_linear, args=(lambda j, z: np.log(np.maximum(z, 1e-3)), [0.01, 0.04], imgs, "gaussian"),
                       kwargs={"log_input": True, "domain": "log", "channel_weights": "mean"}, rounds=1)


def test_write_exr_fast(benchmark, frames, tmp_path):
    img = np.exp(frames[1][1].astype(np.float32) / 40.0)
    benchmark(write_exr_fast, tmp_path / "a.exr", img)


def test_write_exr_openexr(benchmark, frames, tmp_path):
    from derender.io.exr import write_exr

    img = np.exp(frames[1][1].astype(np.float32) / 40.0)
    benchmark.pedantic(write_exr, args=(tmp_path / "b.exr", img), rounds=1)
