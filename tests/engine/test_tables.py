"""derender.fastmerge: the 8-bit table engine, streaming file merge and EXR writer equal the references."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli, write_png_codes

from derender.core.errors import InputError
from derender.core.types import HDRResult, Stack
from derender.engine.float_merge import merge_linear
from derender.engine.options import EngineOptions, OutputOptions
from derender.engine.tables import (
    TableMerge,
    code_values,
    curve_value_tables,
    merge_curves_table,
    stack_codes_exact,
    weight_table,
)
from derender.hdr.classic import _curve_lineariser
from derender.hdr.files import merge_files as merge_files_fast
from derender.hdr.registry import merge
from derender.hdr.stabilize import merge_stabilized_table
from derender.io.exr import read_exr, write_exr_fast
from derender.io.images import read_codes, read_image, read_stack
from derender.response.curves import ResponseCurves
from derender.response.debevec1997 import calibrate_debevec

cv2 = pytest.importorskip("cv2")

RTOL = 1e-5


def _rel(a, b):
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-30)))


def _synthetic_codes(h=48, w=64, n=6, seed=0):
    """Known S-shaped per-channel response on a wide radiance ramp, with pixels clipped in
    every exposure (bright fallback) and black in every exposure (dark fallback)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(-7.0, 7.0, w)[None, :, None] + rng.normal(0, 0.3, (h, 1, 3))
    e = np.exp(x + np.array([0.0, 0.3, -0.4]))
    times = 2.0 ** (2.0 * np.arange(n) - n)
    codes = []
    for t in times:
        y = np.clip(e * t, 0, None) ** (1 / 2.2)
        y = y / (y + 0.6) * 1.6
        codes.append(np.clip(np.rint(y * 255 + rng.normal(0, 0.4, y.shape)), 0, 255).astype(np.uint8))
    codes = np.stack(codes)
    codes[:, :4, :4] = 255    # over-exposed everywhere
    codes[:, -4:, -4:] = 0    # under-exposed everywhere
    return codes, times


def _stack(codes, times):
    return Stack(images=codes.astype(np.float32) * np.float32(1 / 255), times=times)


# --------------------------------------------------------------------------- engine vs merge_linear
@pytest.mark.parametrize("weight,domain,channel_weights,threads", [
    ("gaussian", "log", "mean", 2),
    ("hat", "log", "independent", 1),
    ("trapezoid", "linear", "min", 2),
    ("hat", "linear", "mean", 1),
])
def test_table_engine_equals_merge_linear(weight, domain, channel_weights, threads):
    codes, times = _synthetic_codes()
    st = _stack(codes, times)
    curves = calibrate_debevec(st)
    ref = merge_linear(_curve_lineariser(curves), st.times, st.images, weight, log_input=True,
                       channel_weights=channel_weights, domain=domain)
    res = merge_curves_table(st, curves, weight, domain=domain, channel_weights=channel_weights, threads=threads,
                             block_rows=5)
    assert res.info["engine"] == "table"
    assert _rel(res.radiance, ref.radiance) < RTOL
    np.testing.assert_array_equal(res.mask, ref.mask)
    assert (res.info["n_bright"], res.info["n_dark"]) == (ref.info["n_bright"], ref.info["n_dark"])
    assert ref.info["n_bright"] > 0 and ref.info["n_dark"] > 0  # both fallbacks exercised
    assert np.all(np.isfinite(res.radiance)) and res.radiance.dtype == np.float32


def test_merge_methods_use_table_engine_and_match_reference():
    codes, times = _synthetic_codes(seed=3)
    st = _stack(codes, times)
    for method in ("debevec", "robertson"):
        fast = merge(st, method)
        ref = merge(st, method, options={"engine": "reference"})
        assert fast.info["engine"] == "table" and ref.info["engine"] == "reference"
        assert _rel(fast.radiance, ref.radiance) < RTOL
        np.testing.assert_array_equal(fast.mask, ref.mask)
    # float stacks that are not 8-bit codes keep the reference engine
    st2 = Stack(images=np.clip(st.images + 0.3 / 255, 0, 1), times=times)
    assert merge(st2, "debevec").info["engine"] == "reference"
    with pytest.raises(InputError):
        merge(st2, "debevec", options={"engine": "table"})
    with pytest.raises(InputError):
        merge(st, "debevec", options={"engine": "gpu"})


def test_value_and_weight_tables_match_pointwise_functions():
    codes, times = _synthetic_codes()
    curves = calibrate_debevec(_stack(codes, times))
    v = curve_value_tables(curves, times, "log")
    z = np.repeat(code_values()[:, None], 3, axis=1)
    np.testing.assert_allclose(v[2], curves.log_linearise(z) - np.log(times[2]), rtol=1e-6)
    from derender.engine.weights import weight_gaussian

    np.testing.assert_array_equal(weight_table("gaussian"), weight_gaussian(z))
    assert stack_codes_exact(_stack(codes, times).images).tobytes() == codes.tobytes()


def test_matrix_and_brightest_modes_equal_merge_linear():
    """Channel-mixing path (stabilised merge): per-image gamma table, 3x3 matrix, brightest-channel weight, mask."""
    codes, times = _synthetic_codes(n=4, seed=5)
    rng = np.random.default_rng(1)
    gammas = [2.0, 2.2, 2.4, 2.1]
    mats = [np.eye(3) + 0.1 * rng.normal(size=(3, 3)) for _ in gammas]
    valid = rng.random((4,) + codes.shape[1:3]) > 0.1
    z = code_values()
    zimg = codes.astype(np.float32) * np.float32(1 / 255)
    lin = np.stack([(zimg[j] ** np.float32(g)) @ mats[j].T.astype(np.float32) for j, g in enumerate(gammas)])
    zmax = np.repeat(zimg.max(axis=-1, keepdims=True), 3, axis=-1)
    wt = weight_table("trapezoid")
    ref = merge_linear(lin, times, zmax, "trapezoid", channel_weights="min", domain="linear", block_rows=codes.shape[1],
                       weight_fn=lambda j, blk: wt[:, 0][np.rint(blk[..., 0] * 255).astype(int)] * valid[j])
    with TableMerge(codes.shape[1:3], channel_weights="brightest", domain="linear", threads=2, block_rows=3) as eng:
        tabs = [np.repeat((z ** np.float32(g))[:, None], 3, axis=1) for g in gammas]
        for j in range(4):
            eng.add(codes[j], tabs[j], wt, matrix=mats[j] / times[j], pixel_weights=valid[j])
        res = eng.finish((codes[0], tabs[0], mats[0] / times[0]), (codes[3], tabs[3], mats[3] / times[3]))
    scale = np.abs(ref.radiance).max(axis=2, keepdims=True)
    assert np.max(np.abs(res.radiance - ref.radiance) / np.maximum(scale, 1e-30)) < RTOL
    np.testing.assert_array_equal(res.mask, ref.mask)


def test_stabilized_table_equals_stabilized_merge():
    """Per-image curves + 3x3 matrices + min-else-brightest weights (+ noise weighting), fallbacks included."""
    import derender.hdr.stabilize as stabilize
    from derender.camera import simulate_bracket

    b = simulate_bracket(size=(96, 64), exposures=5, seed=4, stops=1.0)
    st = Stack(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
    stab = stabilize.stabilize(st)
    ones = np.ones(st.images.shape[:3])       # pixel weights force the reference engine (merge_linear)
    for nw in (True, False):
        ref = stabilize.stabilized_merge(stab, noise_weighting=nw, pixel_weights=ones)
        assert ref.info.get("engine") != "table"
        res = merge_stabilized_table(stab, noise_weighting=nw)
        assert res is not None
        scale = np.abs(ref.radiance).max(axis=2, keepdims=True)
        assert np.max(np.abs(res.radiance - ref.radiance) / np.maximum(scale, 1e-30)) < RTOL
        np.testing.assert_array_equal(res.mask, ref.mask)
    assert ref.info["n_dark"] > 0


# --------------------------------------------------------------------------- files
@pytest.fixture(scope="module")
def jpeg_bracket(tmp_path_factory):
    from derender.camera import simulate_bracket, write_jpeg

    d = tmp_path_factory.mktemp("bracket")
    b = simulate_bracket(size=(128, 80), exposures=6, seed=2)
    paths = [write_jpeg(d / f"{j:02d}.jpg", b.jpeg_codes[j], t, "Sim", "Cam") for j, t in enumerate(b.times)]
    return paths[::-1]  # unsorted on purpose


@pytest.mark.parametrize("keep_frames,threads", [(1, 2), (6, 1)])
def test_streaming_merge_equals_reference(jpeg_bracket, tmp_path, keep_frames, threads):
    ref = merge(read_stack(jpeg_bracket), "debevec", options={"engine": "reference"})
    out = tmp_path / "m.exr"
    res = merge_files_fast(jpeg_bracket, output=OutputOptions(output=out),
                           engine=EngineOptions(keep_frames=keep_frames, threads=threads))
    assert res.info["engine_path"] == "streaming"
    assert res.info["streaming"]["decodes"] == 12 - min(keep_frames, 6)
    np.testing.assert_array_equal(res.info["curves"].log_inverse, ref.info["curves"].log_inverse)
    assert _rel(res.radiance, ref.radiance) < RTOL
    np.testing.assert_array_equal(res.mask, ref.mask)
    np.testing.assert_array_equal(read_exr(out), res.radiance)


def test_streaming_bytes_do_not_depend_on_threads_or_memory(jpeg_bracket, tmp_path):
    """Same bytes (radiance and EXR file) for any thread count and frame budget (batch runs = serial runs)."""
    outs = []
    for i, (threads, keep) in enumerate([(1, 1), (3, 6)]):
        res = merge_files_fast(jpeg_bracket, output=OutputOptions(output=tmp_path / f"{i}.exr"),
                               engine=EngineOptions(threads=threads, keep_frames=keep))
        outs.append((np.ascontiguousarray(res.radiance).tobytes(), (tmp_path / f"{i}.exr").read_bytes()))
    assert outs[0] == outs[1]


def test_streaming_options_and_fallbacks(jpeg_bracket, tmp_path):
    st = read_stack(jpeg_bracket)
    res = merge_files_fast(jpeg_bracket, options={"sampling": "histogram", "seed": 3, "weight": "hat",
                                                  "channel_weights": "independent"})
    ref = merge(st, "debevec", options={"sampling": "histogram", "seed": 3, "weight": "hat",
                                        "channel_weights": "independent", "engine": "reference"})
    assert _rel(res.radiance, ref.radiance) < RTOL
    # Robertson streams on the engine too (issue 14: every method on the one engine), same numbers as in memory
    rob = merge_files_fast(jpeg_bracket, method="robertson")
    assert rob.info["engine_path"] == "streaming"
    np.testing.assert_array_equal(rob.radiance, merge(st, "robertson").radiance)
    # the reference engine requested: read_stack + merge
    ref_path = merge_files_fast(jpeg_bracket, options={"engine": "reference"}, method="debevec")
    assert ref_path.info["engine_path"] == "stack"
    # 16-bit files fall back to the in-memory path
    rng = np.random.default_rng(0)
    p16 = []
    for j, t in enumerate((0.01, 0.04, 0.16)):
        img = np.clip(rng.integers(1000, 60000, (24, 32, 3)) * (j + 1) // 3, 0, 65535).astype(np.uint16)
        p16.append(write_png_codes(tmp_path / f"h{j}.png", img))
    r16 = merge_files_fast(p16, times=[0.01, 0.04, 0.16])
    assert r16.info["engine_path"] == "stack"
    with pytest.raises(InputError, match="unknown merge method"):
        merge_files_fast(jpeg_bracket, method="nope")
    with pytest.raises(InputError, match="does not accept"):
        merge_files_fast(jpeg_bracket, options={"lambda_": 3})
    with pytest.raises(InputError, match="differ in size"):
        other = write_png_codes(tmp_path / "small.png", np.zeros((8, 8, 3), np.uint8))
        merge_files_fast([jpeg_bracket[0], other], times=[0.1, 0.2])


def test_streaming_memory_does_not_grow_with_frames(tmp_path):
    """tracemalloc peak (NumPy buffers) for 8 frames stays within 1.3x of 4 frames."""
    import tracemalloc

    from derender.camera import write_jpeg

    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), (320, 240), interpolation=cv2.INTER_CUBIC)
    paths = []
    for j in range(8):
        img = np.clip(base.astype(np.float32) * 2.0 ** (j - 4), 0, 255).astype(np.uint8)
        paths.append(write_jpeg(tmp_path / f"{j}.jpg", img, 0.01 * 2.0 ** j, "A", "B"))
    peaks = []
    for n in (4, 8):
        tracemalloc.start()
        merge_files_fast(paths[:n], engine=EngineOptions(keep_frames=1, threads=2))
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    frame = 320 * 240 * 3
    assert peaks[1] < 1.3 * peaks[0], peaks
    assert peaks[1] < 8 * 4 * frame  # less than the float32 stack of 8 frames


def test_read_codes_matches_read_image(jpeg_bracket, tmp_path):
    codes = read_codes(jpeg_bracket[0])
    img, depth = read_image(jpeg_bracket[0])
    assert depth == 8 and codes.dtype == np.uint8
    np.testing.assert_array_equal(codes.astype(np.float32) * np.float32(1 / 255), img)
    grey = write_png_codes(tmp_path / "g.png", np.arange(48, dtype=np.uint8).reshape(6, 8))
    np.testing.assert_array_equal(read_codes(grey).astype(np.float32) * np.float32(1 / 255), read_image(grey)[0])
    p16 = write_png_codes(tmp_path / "d.png", np.full((4, 4, 3), 300, np.uint16))
    assert read_codes(p16) is None
    with pytest.raises(InputError):
        read_codes(tmp_path / "missing.jpg")


# --------------------------------------------------------------------------- EXR
@pytest.mark.parametrize("half,compression,probe", [(False, "zip", 16), (False, "zip", 1), (True, "zip", 1),
                                                    (False, "none", 16)])
def test_write_exr_fast_roundtrip(tmp_path, half, compression, probe):
    rng = np.random.default_rng(0)
    h, w = 53, 37  # not a multiple of the 16-line blocks
    img = np.exp(rng.normal(0, 3, (h, w, 3))).astype(np.float32)
    img[:20] = 0.25  # compressible rows: compressed blocks next to stored ones
    img[30, 3] = 1e6  # beyond half range: clipped, not inf
    planar = np.ascontiguousarray(img.transpose(2, 0, 1))
    out = write_exr_fast(tmp_path / "x.exr", planar.transpose(1, 2, 0), half=half, compression=compression,
                         probe=probe, threads=2)
    back = read_exr(out)
    expect = np.clip(img, -65504, 65504).astype(np.float16).astype(np.float32) if half else img
    np.testing.assert_array_equal(back, expect)
    if compression == "zip" and probe == 1 and not half:
        assert out.stat().st_size < img.nbytes  # the flat rows were compressed
    bad = img.copy()
    bad[5, 5, 1] = np.nan
    with pytest.raises(ValueError):
        write_exr_fast(tmp_path / "y.exr", bad)
    assert not (tmp_path / "y.exr").exists()


# --------------------------------------------------------------------------- CLI and benchmark
def test_cli_merge_streams_and_matches_library(jpeg_bracket, tmp_path, capsys):
    out = tmp_path / "cli.exr"
    code, stdout, err = run_cli(["merge", *jpeg_bracket, "-o", out, "--preview", tmp_path / "p.png",
                                 "--mask", tmp_path / "m.png", "--plot", tmp_path / "c.png"], capsys)
    assert code == 0, err
    ref = merge(read_stack(jpeg_bracket), "debevec", options={"engine": "reference"})
    assert _rel(read_exr(out), ref.radiance) < RTOL
    assert "6 images 128x80" in stdout
    assert (tmp_path / "p.png").is_file() and (tmp_path / "m.png").is_file() and (tmp_path / "c.png").is_file()


def test_engine_rejects_bad_inputs():
    with pytest.raises(InputError):
        TableMerge((4, 4), channel_weights="max")
    eng = TableMerge((4, 4), domain="log")
    with pytest.raises(InputError):
        eng.add(np.zeros((4, 4, 3), np.uint16), np.zeros((256, 3)), np.ones((256, 3)))
    with pytest.raises(InputError):
        eng.add(np.zeros((4, 4, 3), np.uint8), np.full((256, 3), np.inf), np.ones((256, 3)))
    with pytest.raises(InputError):
        eng.add(np.zeros((4, 4, 3), np.uint8), np.zeros((256, 3)), np.ones((256, 3)), matrix=np.eye(3))
    with pytest.raises(InputError):
        eng.finish((np.zeros((4, 4, 3), np.uint8), np.zeros((256, 3))), (np.zeros((4, 4, 3), np.uint8), np.zeros((256, 3))))
    assert isinstance(ResponseCurves(np.zeros((256, 3))), ResponseCurves) and HDRResult.MASK_DARK == 2


@pytest.mark.parametrize("method", ["stabilized", "stabilized-joint"])
def test_streamed_stabilized_equals_reference_engine(tmp_path, method):
    """merge_files_fast streams stabilized brackets (8-bit frames, shifts, sampled fits) to the
    in-memory method's numbers, the reference engine (merge_linear) included."""
    from derender.camera import simulate_bracket, write_jpeg
    from derender.hdr.stabilize import stabilize, stabilized_merge
    from derender.io.images import read_stack

    b = simulate_bracket(size=(160, 112), exposures=6, seed=5, style="camera")
    paths = []
    for j, t in enumerate(b.times):           # a hand-held bracket: frames moved by whole pixels
        codes = np.roll(b.jpeg_codes[j], (j % 3 - 1, 2 - j % 4), axis=(0, 1))
        paths.append(write_jpeg(tmp_path / f"{j:02d}.jpg", codes, float(t), "Sim", "Cam"))
    res = merge_files_fast(paths, options={"seed": 3}, method=method)
    assert res.info["engine_path"] == "streaming"
    stack = read_stack(paths)
    stab = stabilize(stack, mode="joint" if method == "stabilized-joint" else "reference", seed=3)
    assert np.any(np.asarray(stab.alignment.shifts) != 0)
    assert res.info["shifts"] == np.asarray(stab.alignment.shifts).tolist()
    ref = stabilized_merge(stab, pixel_weights=np.ones(stack.images.shape[:3]))
    scale = np.abs(ref.radiance).max(axis=2, keepdims=True)
    assert np.max(np.abs(res.radiance - ref.radiance) / np.maximum(scale, 1e-30)) < RTOL
    np.testing.assert_array_equal(res.mask, ref.mask)


def test_streamed_stabilized_refuses_unusable_stacks(tmp_path):
    """All-white frames: the streaming path raises the same StackError as the in-memory method."""
    from derender.camera import write_jpeg
    from derender.core.errors import StackError
    from derender.hdr.registry import merge
    from derender.io.images import read_stack

    white = np.full((40, 64, 3), 255, np.uint8)
    paths = [write_jpeg(tmp_path / f"{j}.jpg", white, t, "Sim", "Cam") for j, t in enumerate((0.01, 0.04))]
    with pytest.raises(StackError) as streamed:
        merge_files_fast(paths, method="stabilized")
    with pytest.raises(StackError) as in_memory:
        merge(read_stack(paths), "stabilized")
    assert str(streamed.value) == str(in_memory.value)


def test_stabilized_merge_restores_opencv_threads(tmp_path):
    """Bands merge in parallel with OpenCV's own threads off; the user's setting comes back."""
    import cv2

    from derender.camera import simulate_bracket, write_jpeg

    b = simulate_bracket(size=(160, 112), exposures=4, seed=1)
    paths = [write_jpeg(tmp_path / f"{j}.jpg", b.jpeg_codes[j], float(t), "S", "C") for j, t in enumerate(b.times)]
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(3)
        for _ in range(3):
            merge_files_fast(paths, method="stabilized", engine=EngineOptions(threads=2))
            assert cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(before)


@pytest.mark.parametrize("method,opts", [("debevec", {}), ("robertson", {}),
                                         ("debevec", {"channel_weights": "independent"}),
                                         ("debevec", {"domain": "linear"}),
                                         ("debevec", {"domain": "linear", "channel_weights": "independent"}),
                                         ("debevec", {"channel_weights": "min"})])
def test_held_kernel_equals_two_pass_stream(jpeg_bracket, tmp_path, method, opts, monkeypatch):
    """Frames held (decoded once, the compiled table kernel) give the two-pass stream's bytes and mask (issue 17)."""
    import derender.engine.run as engine_run

    monkeypatch.setattr(engine_run, "KERNEL_MIN_PIXEL_FRAMES", 0)     # the kernel even for this small bracket
    held = merge_files_fast(jpeg_bracket, options=opts, method=method,
                            output=OutputOptions(output=tmp_path / "a.exr"), engine=EngineOptions(threads=2))
    two = merge_files_fast(jpeg_bracket, options=opts, method=method, output=OutputOptions(output=tmp_path / "b.exr"),
                           engine=EngineOptions(threads=1, keep_frames=1))
    assert held.info["streaming"]["decodes"] == 6 and two.info["streaming"]["decodes"] == 11
    if opts.get("channel_weights", "mean") in ("mean", "independent"):
        assert held.info["kernel"] == "table_merge_rows"
    np.testing.assert_array_equal(np.ascontiguousarray(held.radiance), np.ascontiguousarray(two.radiance))
    np.testing.assert_array_equal(held.mask, two.mask)
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    monkeypatch.setattr(engine_run, "KERNEL_MIN_PIXEL_FRAMES", 10 ** 12)
    small = merge_files_fast(jpeg_bracket, options=opts, method=method, engine=EngineOptions(threads=2))
    assert "kernel" not in small.info and small.info["streaming"]["decodes"] == 6
    np.testing.assert_array_equal(np.ascontiguousarray(small.radiance), np.ascontiguousarray(two.radiance))
    np.testing.assert_array_equal(small.mask, two.mask)
