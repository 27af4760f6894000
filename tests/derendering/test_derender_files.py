"""De-rendering from files: calibrate, derender, model library, probabilistic merge, stereo, merge-batch."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli

from derender.camera import bracket_paths, simulate_bracket, write_bracket, write_jpeg
from derender.camera.chart import chart_pairs, save_pairs
from derender.core.types import Stack
from derender.derendering.base import load_model
from derender.engine.options import OutputOptions
from derender.io.exr import read_exr


@pytest.fixture(scope="module")
def pairs_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("pairs")
    return save_pairs(chart_pairs("nikon-d5100", n_illuminants=6, n_exposures=12, seed=0), d / "nikon.npz")


@pytest.fixture(scope="module")
def model_file(pairs_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("models") / "nikon-gp.npz"
    code, _, _ = run_cli(["calibrate", "--pairs", pairs_file, "-o", out, "--method", "gp", "--n-train", "1500"])
    assert code == 0
    return out


def test_calibrate_stores_camera_metadata(model_file):
    m = load_model(model_file)
    assert m.method == "gp"
    assert m.metadata["camera"]["model"] == "NIKON D5100"
    assert np.asarray(m.metadata["camera_to_srgb"]).shape == (3, 3)


def test_derender_image_and_model_library(model_file, tmp_path, capsys):
    b = simulate_bracket(size=(64, 48), exposures=1, pipeline="fixed", wb_preset="D65", seed=1)
    img = write_jpeg(tmp_path / "shot.jpg", b.jpeg_codes[0], float(b.times[0]), "NIKON CORPORATION", "NIKON D5100")
    code, out, err = run_cli(["derender", img, "-m", model_file, "-o", tmp_path / "mean.exr",
                              "--variance", tmp_path / "var.exr"], capsys)
    assert code == 0, err
    mean, var = read_exr(tmp_path / "mean.exr"), read_exr(tmp_path / "var.exr")
    assert mean.shape == (48, 64, 3) and np.all(np.isfinite(mean)) and np.all(var >= 0)
    # the streamed files hold exactly the model's per-pixel prediction (decoded like the CLI does)
    from derender.derendering.apply import check_8bit_rgb

    ref_mean, ref_var = load_model(model_file).predict(check_8bit_rgb(img))
    np.testing.assert_array_equal(mean, ref_mean)
    np.testing.assert_array_equal(var, ref_var)
    code, out, err = run_cli(["derender", img, "-m", model_file, "-o", tmp_path / "zip.exr", "--srgb",
                              "--compression", "zip"], capsys)
    assert code == 0, err
    from derender.derendering.apply import derender_image

    np.testing.assert_array_equal(read_exr(tmp_path / "zip.exr"), derender_image(img, model_file, srgb=True)[0])
    code, out, err = run_cli(["derender", img, "-m", model_file, "-o", img.with_suffix(".exr"),
                              "--variance", img.with_suffix(".exr")], capsys)
    assert code == 2 and "same file" in err
    # a folder of models: the one whose camera matches the EXIF is used
    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "a.npz").write_bytes(model_file.read_bytes())
    code, out, err = run_cli(["derender", img, "-m", lib, "-o", tmp_path / "m2.exr"], capsys)
    assert code == 0 and "matches the image EXIF" in out
    np.testing.assert_array_equal(read_exr(tmp_path / "m2.exr"), mean)
    other = write_jpeg(tmp_path / "other.jpg", b.jpeg_codes[0], 0.01, "Canon", "Canon EOS 5D")
    code, out, err = run_cli(["derender", other, "-m", lib, "-o", tmp_path / "m3.exr"], capsys)
    assert code == 2 and "no model" in err


def test_model_of_another_camera_warns_or_is_refused(model_file, tmp_path, capsys):
    """Model files record their camera; an image whose EXIF names another camera gets a one-line
    warning, and --strict-camera makes it an error that writes nothing."""
    b = simulate_bracket(size=(48, 32), exposures=1, pipeline="fixed", wb_preset="D65", seed=3)
    other = write_jpeg(tmp_path / "other.jpg", b.jpeg_codes[0], 0.01, "Canon", "Canon EOS 5D")
    code, out, err = run_cli(["derender", other, "-m", model_file, "-o", tmp_path / "w.exr"], capsys)
    assert code == 0, err
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and "NIKON D5100" in warnings[0] and "Canon EOS 5D" in warnings[0]
    assert "Canon Canon" not in warnings[0] and "NIKON CORPORATION NIKON" not in warnings[0]   # the make once
    code, out, err = run_cli(["derender", other, "-m", model_file, "-o", tmp_path / "s.exr", "--variance",
                              tmp_path / "sv.exr", "--strict-camera"], capsys)
    assert code == 2 and err.startswith("error:") and "--strict-camera" in err
    assert not (tmp_path / "s.exr").exists() and not (tmp_path / "sv.exr").exists()
    same = write_jpeg(tmp_path / "same.jpg", b.jpeg_codes[0], 0.01, "NIKON CORPORATION", "NIKON D5100")
    code, out, err = run_cli(["derender", same, "-m", model_file, "-o", tmp_path / "n.exr", "--strict-camera"], capsys)
    assert code == 0 and "warning" not in err, err


def test_derender_errors(model_file, tmp_path, capsys):
    import cv2
    import tifffile

    rgba = tmp_path / "a.png"
    cv2.imwrite(str(rgba), np.zeros((8, 8, 4), np.uint8))
    sixteen = tmp_path / "s.tif"
    tifffile.imwrite(sixteen, np.zeros((8, 8, 3), np.uint16))
    bad_model = tmp_path / "bad.npz"
    bad_model.write_bytes(b"not a zip")
    nan_pairs = tmp_path / "nan.npz"
    np.savez(nan_pairs, jpeg=np.zeros((20, 3), np.uint8), raw=np.full((20, 3), np.nan))
    good = tmp_path / "g.png"
    cv2.imwrite(str(good), np.zeros((8, 8, 3), np.uint8))
    cases = [
        (["derender", rgba, "-m", model_file, "-o", tmp_path / "o.exr"], "alpha"),
        (["derender", sixteen, "-m", model_file, "-o", tmp_path / "o.exr"], "16-bit"),
        (["derender", good, "-m", bad_model, "-o", tmp_path / "o.exr"], "model"),
        (["calibrate", "--pairs", nan_pairs, "-o", tmp_path / "m.npz"], "nan"),
        (["calibrate", "-o", tmp_path / "m.npz"], "--pairs"),
    ]
    for args, needle in cases:
        code, out, err = run_cli(args, capsys)
        assert code == 2, (args, err)
        assert needle.lower() in err.lower() and "Traceback" not in err, (args, err)


def test_probabilistic_merge_variance_high_where_everything_clips(model_file, tmp_path, capsys):
    b = simulate_bracket(kind="indoor", size=(96, 64), exposures=5, pipeline="fixed", wb_preset="D65", seed=2)
    write_bracket(b, tmp_path / "br")
    jpgs = bracket_paths(tmp_path / "br", "jpeg")
    code, out, err = run_cli(["merge", *jpgs, "--method", "probabilistic", "-m", model_file, "-o", tmp_path / "p.exr",
                              "--variance", tmp_path / "pv.exr"], capsys)
    assert code == 0, err
    rad, var = read_exr(tmp_path / "p.exr"), read_exr(tmp_path / "pv.exr")
    assert np.all(np.isfinite(rad)) and np.all(np.isfinite(var))
    codes = b.jpeg_codes
    all_clip = np.all(codes.max(-1) >= 255, axis=0)
    rel = var.sum(-1) / np.maximum(rad.sum(-1), 1e-12) ** 2
    assert all_clip.any()
    # issue 29: the measured pixels' variance now counts the shared model error and spatial mixing
    # (median relative variance 0.045, was ~0.005 with eq. 3's); the clipped ones' stays ~0.9
    assert np.median(rel[all_clip]) > 10 * np.median(rel[~all_clip])


def test_probabilistic_censoring_beats_plain_product_on_light_source(model_file):
    from derender.evaluation.metrics import psnr_rgbl
    from derender.hdr.probabilistic import merge_probabilistic

    m = load_model(model_file)
    b = simulate_bracket(kind="outdoor", size=(96, 64), exposures=5, pipeline="fixed", wb_preset="D65", seed=3)
    st = Stack(images=b.jpeg_codes / 255.0, times=b.times)
    scores = {}
    for censor in (False, True):
        r = merge_probabilistic(st, options={"model": m, "colour_space": "camera_rgb", "censor": censor})
        srgb = (r.radiance * b.wb_true) @ b.camera_to_srgb.T
        scores[censor] = psnr_rgbl(srgb, b.truth_linear_srgb)["L"]
    assert scores[True] > scores[False] + 5.0, scores


def test_merge_batch_equals_serial(tmp_path, capsys):
    for i in range(2):
        write_bracket(simulate_bracket(size=(64, 48), exposures=3, pipeline="auto", seed=10 + i), tmp_path / f"s{i}")
    stacks = [tmp_path / "s0", tmp_path / "s1"]
    code, out, err = run_cli(["merge-batch", *stacks, "-o", tmp_path / "serial", "--scheduler", "serial"], capsys)
    assert code == 0, err
    code, out, err = run_cli(["merge-batch", *stacks, "-o", tmp_path / "dask", "--workers", "2"], capsys)
    assert code == 0, err
    for s in ("s0", "s1"):
        np.testing.assert_array_equal(read_exr(tmp_path / "serial" / f"{s}.exr"), read_exr(tmp_path / "dask" / f"{s}.exr"))
    (tmp_path / "bad").mkdir()
    code, out, err = run_cli(["merge-batch", tmp_path / "bad", "-o", tmp_path / "x", "--scheduler", "serial"], capsys)
    assert code == 2 and "at least two images" in out + err


def test_stabilized_probabilistic_runs_and_is_close_to_stabilized(model_file):
    from derender.evaluation.metrics import psnr_rgbl
    from derender.hdr.registry import merge

    b = simulate_bracket(size=(96, 64), exposures=5, pipeline="auto", style="simple", seed=1)
    st = Stack(images=b.jpeg_codes / 255.0, times=b.times)
    both = merge(st, options={"model": load_model(model_file)}, method="stabilized-probabilistic")
    alone = merge(st, method="stabilized")
    assert np.all(np.isfinite(both.radiance))
    s_both = psnr_rgbl(both.radiance, b.truth_linear_srgb)["L"]
    s_alone = psnr_rgbl(alone.radiance, b.truth_linear_srgb)["L"]
    assert abs(s_both - s_alone) < 3.0, (s_both, s_alone)


def test_probabilistic_beats_debevec_on_jpeg_files_and_variance_marks_censored(model_file, tmp_path):
    """Issue 7 acceptance: PSNR L >= Debevec on a simulator bracket (JPEG files); variance high exactly where
    a channel is censored (>= clip_code) in every exposure."""
    from derender.evaluation.metrics import psnr_rgbl
    from derender.hdr.probabilistic import merge_probabilistic
    from derender.hdr.registry import merge
    from derender.io.images import read_stack

    m = load_model(model_file)
    for kind in ("indoor", "night"):
        b = simulate_bracket(kind=kind, size=(96, 64), exposures=5, pipeline="fixed", wb_preset="D65", seed=2)
        write_bracket(b, tmp_path / kind)
        st = read_stack(bracket_paths(tmp_path / kind, "jpeg"))
        deb = psnr_rgbl(merge(st, method="debevec").radiance, b.truth_linear_srgb)["L"]
        r = merge_probabilistic(st, options={"model": m, "colour_space": "camera_rgb"})
        assert np.all(np.isfinite(r.radiance)) and np.all(np.isfinite(r.variance))
        prob = psnr_rgbl((r.radiance * b.wb_true) @ b.camera_to_srgb.T, b.truth_linear_srgb)["L"]
        assert prob >= deb, (kind, prob, deb)
        censored = np.all(st.codes() >= 245, axis=0)
        rel = r.variance / np.maximum(r.radiance, 1e-12) ** 2
        assert censored.any()
        # issue 29: measured channels' relative variance now includes spatial mixing (max 0.79 measured)
        assert rel[censored].min() > 1.0 and rel[~censored].max() < rel[censored].min(), (
            kind, rel[censored].min(), rel[~censored].max())
        again = merge_probabilistic(st, options={"model": m, "colour_space": "camera_rgb"})
        np.testing.assert_array_equal(again.radiance, r.radiance)
        # the files stream band by band (merge_files_fast, as the CLI does) to the same numbers
        from derender.hdr.files import merge_files as merge_files_fast

        streamed = merge_files_fast(bracket_paths(tmp_path / kind, "jpeg"), options={"model": m,
                                                                                     "colour_space": "camera_rgb"}, method="probabilistic")
        assert streamed.info["engine_path"] == "streaming"
        np.testing.assert_array_equal(streamed.radiance, r.radiance)
        np.testing.assert_array_equal(streamed.variance, r.variance)
        np.testing.assert_array_equal(streamed.mask, r.mask)


def test_index_colours_matches_unique():
    from derender.derendering.apply import index_colours, pack_codes

    rng = np.random.default_rng(3)
    codes = rng.integers(0, 256, size=(37, 53, 3)).astype(np.uint8)
    codes[5:20, 7:30] = (255, 0, 17)              # a flat patch: repeated colours
    idx = index_colours(codes, block_rows=8)
    uniq = np.unique(codes.reshape(-1, 3), axis=0)
    np.testing.assert_array_equal(idx.codes, uniq)
    rows = idx.rows(codes)
    np.testing.assert_array_equal(idx.codes[rows], codes.astype(np.int32))
    assert pack_codes(np.array([[1, 2, 3]], np.uint8))[0] == (1 << 16) + (2 << 8) + 3


def test_colour_tables_do_not_depend_on_chunking(model_file):
    """Per-colour tables are computed in chunks (bounded temporaries): chunk size must not matter."""
    from derender.derendering.apply import _colour_tables, index_colours
    from derender.hdr.probabilistic import _log_planes

    m = load_model(model_file)
    codes = np.random.default_rng(5).integers(0, 256, size=(40, 30, 3)).astype(np.uint8)
    idx = index_colours(codes)
    whole = _colour_tables(m, idx, False)
    parts = _colour_tables(m, idx, False, chunk=7)
    np.testing.assert_array_equal(whole[0], parts[0])
    np.testing.assert_array_equal(whole[1], parts[1])
    cols = idx.codes.astype(np.uint8)
    np.testing.assert_array_equal(_log_planes(m, cols, 0.01, 245, True), _log_planes(m, cols, 0.01, 245, True, chunk=7))


class _CurveModel:
    """A log-space model with a known curve: log raw median = log(srgb_decode(code / 255)) per channel."""

    eps = 1e-3

    def predict_log(self, colours):
        u = np.asarray(colours, dtype=np.float64) / 255.0
        lin = np.where(u <= 0.04045, u / 12.92, ((u + 0.055) / 1.055) ** 2.4)
        return np.log(lin + self.eps), np.full(u.shape, 1e-4)


def test_log_slope_matches_the_curve_derivative():
    """The code-noise term's slope d log(raw median) / d code equals the analytic derivative of a known curve."""
    from derender.hdr.probabilistic import _log_slope

    codes = np.array([[60, 128, 200], [100, 30, 240], [20, 180, 90]], dtype=np.uint8)
    got = _log_slope(_CurveModel(), codes, None, step=1)
    u = codes / 255.0
    lin = ((u + 0.055) / 1.055) ** 2.4
    exact = 2.4 / (u + 0.055) / 255.0          # d log(lin) / d code
    np.testing.assert_allclose(got, exact, rtol=2e-3)
    assert np.all(got > 0) and np.all(np.isfinite(lin))


def test_code_noise_makes_merged_variances_less_over_confident(model_file):
    """Against simulator truth: per-pixel code noise through the curve brings the merged log-space
    z-scores of the true RAW towards N(0, 1) (measured, 5000-pair D5100 GP: median |z| 7-10 -> 3-4;
    the exposures' de-rendering errors are correlated, so the product stays over-confident)."""
    from derender.hdr.probabilistic import merge_probabilistic

    m = load_model(model_file)
    b = simulate_bracket(kind="outdoor", size=(96, 64), exposures=5, pipeline="fixed", wb_preset="D65", seed=2)
    st = Stack(images=b.jpeg_codes / 255.0, times=b.times)
    tcam = (b.truth_linear_srgb.astype(np.float64) @ np.linalg.inv(b.camera_to_srgb).T) / b.wb_true
    ok = ~np.all(b.jpeg_codes >= 245, axis=0) & (tcam > 1e-3)
    med_z = {}
    for cn in (0.0, 2.0):
        # eq. 3's variance: what the code noise alone changes (issue 29's shared-error variance adds
        # terms that dominate it; tests/hdr/test_probabilistic_variance.py checks that one)
        r = merge_probabilistic(st, options={"model": m, "colour_space": "camera_rgb", "code_noise": cn,
                                             "variance_model": "independent"})
        lv = np.log1p(r.variance / np.maximum(r.radiance, 1e-12) ** 2)
        z = (np.log(tcam) - np.log(np.maximum(r.radiance, 1e-12)) + 0.5 * lv) / np.sqrt(lv)
        med_z[cn] = float(np.median(np.abs(z[ok])))
    assert med_z[2.0] < 0.6 * med_z[0.0], med_z


def test_compiled_log_tables_match_numpy(model_file):
    """The compiled per-colour tables (engine.kernels.log_tables_rows) are _log_tables' values
    (up to libm's exp/log against NumPy's), in both layouts; with and without censoring and code noise."""
    from derender.derendering.apply import index_colours
    from derender.hdr.probabilistic import _compiled_tables, _log_planes, _log_tables

    m = load_model(model_file)
    codes = np.random.default_rng(6).integers(0, 256, size=(60, 50, 3)).astype(np.uint8)
    codes[:5] = 255
    codes[5:10, :, 1] = 250
    codes[10:12] = 0
    cols = np.ascontiguousarray(index_colours(codes).codes, dtype=np.uint8)
    assert _compiled_tables(m, cols) is not None
    for censor, noise, per_channel in ((True, 2.0, True), (False, 0.0, True), (True, 0.0, False)):
        ref = np.concatenate([a.T for a in _log_tables(m, cols, 0.01, 245, censor, per_channel, noise)])
        got = _log_planes(m, cols, 0.01, 245, censor, per_channel=per_channel, code_noise=noise, threads=2, chunk=100)
        np.testing.assert_array_equal(np.isneginf(got), np.isneginf(ref))
        fin = np.isfinite(ref)
        np.testing.assert_allclose(got[fin], ref[fin], rtol=1e-12, atol=0)
        table = _log_planes(m, cols, 0.01, 245, censor, per_channel=per_channel, code_noise=noise, colour_major=True)
        assert table.shape == (cols.shape[0], 8) and table.ctypes.data % 64 == 0
        from derender.engine.plans import GaussianPlan

        derived = GaussianPlan(planes=None, table=table, index=None, log_scales=np.zeros(1), moments=None,
                               mask=None).rows_planes()
        np.testing.assert_array_equal(derived, got)


def test_fused_gaussian_pass_matches_the_numpy_moments(model_file):
    """The engine's fused sums-and-moments pass gives the outputs of the NumPy moments on the sums."""
    import dataclasses

    from derender.engine.gaussian import merge_gaussian_frames
    from derender.engine.plans import FrameAccess
    from derender.hdr.probabilistic import ProbabilisticMethod, ProbabilisticOptions

    frames = np.random.default_rng(7).integers(0, 256, size=(3, 40, 37, 3)).astype(np.uint8)
    frames[:, :4] = 255
    frames[:, 4:8, :, 0] = 250
    opts = {"model": load_model(model_file), "target_time": 1.0, "colour_space": "linear_srgb", "censor": True,
            "domain": None, "floor": 0.0, "clip_code": 245, "code_noise": 2.0}
    method = ProbabilisticMethod(ProbabilisticOptions(**opts))
    access = FrameAccess(frames=frames, times=np.array([0.01, 0.04, 0.16]), shape=frames.shape[1:3], threads=2)
    plan = method.plan(access)
    assert plan.table is not None and plan.lognormal is not None
    fused = merge_gaussian_frames(frames, plan, threads=2)
    slow = merge_gaussian_frames(frames, dataclasses.replace(plan, planes=plan.rows_planes(), table=None), threads=2)
    np.testing.assert_allclose(fused.radiance, slow.radiance, rtol=1e-6, atol=0)
    np.testing.assert_allclose(fused.variance, slow.variance, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(fused.mask, slow.mask)


def test_stabilized_probabilistic_engine_equals_the_per_pixel_reference(model_file):
    """Issue 17: ``stabilized-probabilistic`` on the engine (frames held as codes, one per-colour weight
    table) gives the float reference engine's per-pixel-weighted merge, registration shifts included."""
    from derender.hdr.stabilized_probabilistic import (
        StabilizedProbabilisticOptions,
        colour_reliability,
        colour_weight_table,
        merge_stabilized_probabilistic,
        stabilized_probabilistic_stack,
    )

    model = load_model(model_file)
    b = simulate_bracket(size=(96, 64), exposures=5, pipeline="auto", style="simple", seed=2)
    codes = b.jpeg_codes.copy()
    codes[1] = np.roll(codes[1], (2, -3), axis=(0, 1))       # a frame that registration must shift back
    codes[3] = np.roll(codes[3], (-1, 1), axis=(0, 1))
    st = Stack(images=codes / 255.0, times=b.times)
    eng = merge_stabilized_probabilistic(st, options={"model": model})
    ref = stabilized_probabilistic_stack(st, StabilizedProbabilisticOptions(model=model))
    assert eng.info["engine_path"] == "streaming" and ref.info["engine_path"] == "stack"
    assert eng.info["shifts"] == ref.info["shifts"] and any(s != [0, 0] for s in eng.info["shifts"])
    r_eng, r_ref = np.asarray(eng.radiance, np.float64), np.asarray(ref.radiance, np.float64)
    assert np.all(np.isfinite(r_eng)) and r_eng.min() >= 0
    assert np.max(np.abs(r_eng - r_ref)) <= 1e-5 * np.max(r_ref)
    assert np.array_equal(eng.mask, ref.mask)
    # the table holds each present colour's reliability; the weights really change the merge
    table = colour_weight_table(model, codes)
    px = codes.reshape(-1, 3)[::37]
    packed = (px[:, 0].astype(np.int64) << 16) | (px[:, 1].astype(np.int64) << 8) | px[:, 2]
    np.testing.assert_allclose(table[packed], colour_reliability(model, px), rtol=1e-6)
    from derender.hdr.registry import merge

    unweighted = merge(st, options={"noise_weighting": False}, method="stabilized")
    assert np.max(np.abs(np.asarray(unweighted.radiance) - r_eng)) > 1e-3 * np.max(r_ref)


def test_stabilized_probabilistic_files_take_the_engine(model_file, tmp_path, capsys):
    b = simulate_bracket(size=(96, 64), exposures=4, pipeline="auto", style="simple", seed=3)
    write_bracket(b, tmp_path / "b")
    jpgs = bracket_paths(tmp_path / "b", "jpeg")
    from derender.hdr.files import merge_files
    from derender.hdr.stabilized_probabilistic import StabilizedProbabilisticOptions, stabilized_probabilistic_stack
    from derender.io.images import read_stack

    res = merge_files(jpgs, options={"model": str(model_file)}, method="stabilized-probabilistic",
                      output=OutputOptions(output=tmp_path / "sp.exr"))
    assert res.info["engine_path"] == "streaming" and "colour_weights_s" in res.info["timings"]
    ref = stabilized_probabilistic_stack(read_stack(jpgs), StabilizedProbabilisticOptions(model=load_model(model_file)))
    back = read_exr(tmp_path / "sp.exr")
    assert np.max(np.abs(back - ref.radiance)) <= 1e-5 * np.max(ref.radiance)


def test_probabilistic_outputs_written_from_band_buffers_are_the_same_files(model_file, tmp_path, monkeypatch):
    """``hold_outputs=False`` (what ``derender merge`` does without --preview): radiance and variance
    go from the merge's band buffers into the files; same bytes as writing held arrays."""
    from helpers import write_png_codes

    from derender.hdr.files import merge_files

    b = simulate_bracket(size=(100, 175), exposures=4, pipeline="auto", style="simple", seed=4)
    paths = [write_png_codes(tmp_path / f"f{j}.png", np.repeat(np.repeat(b.jpeg_codes[j], 4, axis=0), 4, axis=1))
             for j in range(4)]
    times = [float(t) for t in b.times]
    model = load_model(model_file)
    files = {}
    for hold in (True, False):
        for var in (True, False):
            out, vout = tmp_path / f"m-{hold}-{var}.exr", (tmp_path / f"v-{hold}-{var}.exr" if var else None)
            res = merge_files(paths, times, "probabilistic", options={"model": model},
                              output=OutputOptions(output=out, variance_output=vout, hold_outputs=hold))
            assert res.info["outputs_held"] == hold and (res.variance is None) == (not hold)
            files[hold, var] = out.read_bytes() + (vout.read_bytes() if var else b"")
    assert files[True, True] == files[False, True] and files[True, False] == files[False, False]
