"""Tests for derender.merge: weights, the merge engine, the registry, OpenCV and real-data agreement."""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.colorimetry import luminance
from derender.core.errors import InputError, StackError
from derender.core.types import HDRResult, Stack
from derender.engine.float_merge import merge_linear
from derender.engine.weights import WEIGHTS, weight_gaussian, weight_hat, weight_trapezoid
from derender.evaluation.metrics import psnr_rgbl
from derender.hdr.registry import METHODS, merge, register_method
from derender.response.curves import ResponseCurves

cv2 = pytest.importorskip("cv2")

# --------------------------------------------------------------------------- synthetic stacks
GAMMAS, KNEES = (2.0, 2.2, 2.5), (0.4, 0.5, 0.6)


def _response(x_lin, c):
    """Known per-channel camera response: gamma then a soft shoulder, on clipped exposure."""
    x = np.clip(x_lin, 0.0, 1.0) ** (1.0 / GAMMAS[c])
    return x * (1 + KNEES[c]) / (x + KNEES[c])


def _scene(h, w, seed, decades):
    """Known radiance: a wide log gradient with coloured ripples and flat random patches."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    base = 10 ** (decades * (x - 0.5) + 0.5 * np.sin(6 * y))
    chroma = 0.35 + 0.65 * rng.random(3)
    e = np.stack([base * (0.6 + 0.4 * np.cos(3 * y * (c + 1) + 2 * x)) * chroma[c] for c in range(3)], -1)
    for _ in range(20):
        y0, x0 = rng.integers(0, h - 12), rng.integers(0, w - 12)
        e[y0:y0 + 12, x0:x0 + 12] = 10 ** rng.uniform(-decades / 2, decades / 2) * rng.uniform(0.2, 1, 3)
    return e


def _synthetic(h=160, w=240, seed=1, decades=3.0, step=1.0, n=9, noise=0.002):
    """(radiance, uint8 codes (N,H,W,3), times): radiance scaled so the shortest exposure barely clips."""
    e = _scene(h, w, seed, decades)
    times = 2.0 ** (step * np.arange(n) - step * (n - 1))
    e = e / np.percentile(e, 99.9) / times[0] * 0.9
    rng = np.random.default_rng(seed + 100)
    codes = []
    for t in times:
        x = e * t
        x = x + rng.normal(0.0, 1.0, x.shape) * (noise + 0.01 * np.sqrt(np.maximum(x, 0) * noise))
        y = np.stack([_response(x[..., c], c) for c in range(3)], -1)
        codes.append(np.clip(np.rint(y * 255), 0, 255).astype(np.uint8))
    return e, np.stack(codes), times


def _stack(codes, times):
    return Stack(images=codes.astype(np.float32) / 255.0, times=times)


def _opencv_debevec(codes, times):
    imgs = [np.ascontiguousarray(c[..., ::-1]) for c in codes]
    tt = times.astype(np.float32)
    resp = cv2.createCalibrateDebevec().process(imgs, tt)
    hdr = cv2.createMergeDebevec().process(imgs, tt, resp)[..., ::-1]
    return resp, hdr


# --------------------------------------------------------------------------- weights
def test_weight_functions_shape_and_breakpoints():
    z = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(weight_hat(z), [0, 0.5, 1, 0.5, 0], atol=1e-7)
    # OpenCV 5 / Debevec integer hat min(i, 255 - i) up to scale
    i = np.arange(256)
    np.testing.assert_allclose(weight_hat(i / 255.0), 2 * np.minimum(i, 255 - i) / 255.0, atol=1e-6)
    zt = np.array([0.0, 0.02, 0.07, 0.12, 0.5, 0.88, 0.93, 0.98, 1.0])
    np.testing.assert_allclose(weight_trapezoid(zt), [0, 0, 0.5, 1, 1, 1, 0.5, 0, 0], atol=1e-5)
    g = weight_gaussian(np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(g, [0, 1, 0], atol=1e-6)
    assert set(WEIGHTS) >= {"hat", "trapezoid", "gaussian"}
    with pytest.raises(InputError):
        weight_trapezoid(z, low=0.5, high=0.4)


# --------------------------------------------------------------------------- engine
def test_merge_linear_exact_on_linear_camera_and_saturation_policy():
    rng = np.random.default_rng(0)
    e = 10 ** rng.uniform(-2, 1, (20, 30, 3))
    e[0, 0] = 1e4  # clipped in every exposure
    e[0, 1] = 0.0  # black in every exposure
    e[0, 2, 0] = 1e4  # only the red channel is clipped everywhere
    times = np.array([0.05, 0.2, 0.8])
    lin = np.stack([e * t for t in times])
    images = np.clip(lin, 0, 1).astype(np.float32)  # a linear "camera", clipped at 1
    res = merge_linear(images, times, images, "hat")
    assert isinstance(res, HDRResult) and res.radiance.dtype == np.float32
    assert np.all(np.isfinite(res.radiance))
    ok = (images > 0) & (images < 1)
    well = ok.any(axis=0).all(axis=-1)
    np.testing.assert_allclose(res.radiance[well], e[well], rtol=1e-4)
    # saturation policy
    assert res.mask[0, 0] == HDRResult.MASK_BRIGHT
    np.testing.assert_allclose(res.radiance[0, 0], 1.0 / times[0], rtol=1e-6)  # from the shortest
    assert res.mask[0, 1] == HDRResult.MASK_DARK
    np.testing.assert_allclose(res.radiance[0, 1], images[-1, 0, 1] / times[-1], atol=1e-7)  # from the longest
    assert res.mask[0, 2] == HDRResult.MASK_BRIGHT
    np.testing.assert_allclose(res.radiance[0, 2, 1:], e[0, 2, 1:], rtol=1e-4)  # other channels still merged
    assert res.mask[well & (np.arange(30)[None, :] > 2)].max() == 0
    assert res.info["n_bright"] == 2 and res.info["n_dark"] == 1


def test_merge_linear_callable_blocks_log_domain_and_custom_weights():
    rng = np.random.default_rng(1)
    images = rng.uniform(0, 1, (4, 37, 23, 3)).astype(np.float32)
    times = np.array([0.1, 0.3, 0.9, 2.7])
    lin = images ** 2.2
    ref = merge_linear(lin, times, images, "gaussian")
    call = merge_linear(lambda j, z: z ** 2.2, times, images, "gaussian", block_rows=1)
    np.testing.assert_array_equal(ref.mask, call.mask)
    np.testing.assert_allclose(call.radiance, ref.radiance, rtol=1e-6)
    # independent per-pixel formula (linear and log domain, per-image factors)
    w = weight_gaussian(images).astype(np.float64) * (times ** 2)[:, None, None, None]
    v = lin / times[:, None, None, None]
    expected = (w * v).sum(0) / w.sum(0)
    got = merge_linear(lin, times, images, "gaussian", image_weights=times ** 2).radiance
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    wl = weight_hat(images).astype(np.float64)
    expected_log = np.exp((wl * np.log(v)).sum(0) / wl.sum(0))
    got_log = merge_linear(np.log(lin), times, images, "hat", domain="log", log_input=True, block_rows=5).radiance
    np.testing.assert_allclose(got_log, expected_log, rtol=1e-5)
    # weight_fn returning one weight per pixel; 'min' channel combination
    one = merge_linear(lin, times, images, weight_fn=lambda j, z: np.ones(z.shape[:2], np.float32))
    np.testing.assert_allclose(one.radiance, v.mean(0), rtol=1e-5)
    wmin = weight_hat(images).min(axis=-1, keepdims=True).astype(np.float64)
    got_min = merge_linear(lin, times, images, "hat", channel_weights="min").radiance
    ok = wmin.sum(0)[..., 0] > 0
    np.testing.assert_allclose(got_min[ok], ((wmin * v).sum(0) / wmin.sum(0))[ok], rtol=1e-5)


def test_merge_linear_never_returns_nan():
    images = np.random.default_rng(2).uniform(0, 1, (3, 8, 8, 3)).astype(np.float32)
    lin = images.copy()
    lin[1, 2, 3] = np.nan
    lin[2, 4, 4] = np.inf
    res = merge_linear(lin, [1.0, 2.0, 4.0], images)
    assert np.all(np.isfinite(res.radiance))
    with pytest.raises(InputError):
        merge_linear(lin[:2], [1.0, 2.0, 4.0], images)
    with pytest.raises(InputError):
        merge_linear(lin, [1.0, -2.0, 4.0], images)
    with pytest.raises(InputError):
        merge_linear(lin, [1.0, 2.0, 4.0], images, domain="cubic")


# --------------------------------------------------------------------------- registry
def test_registry_unknown_method_and_options():
    e, codes, times = _synthetic(40, 60, n=5, step=2.0)
    st = _stack(codes, times)
    with pytest.raises(InputError, match="debevec"):
        merge(st, method="no-such-method")
    with pytest.raises(InputError, match="bogus"):
        merge(st, options={"bogus": 1}, method="debevec")
    with pytest.raises(InputError):
        merge(codes, method="debevec")
    assert {"debevec", "robertson"} <= set(METHODS)

    @register_method("_test_identity")
    def _identity(stack, gain=1.0):
        return merge_linear(stack.images, stack.times, stack.images, "hat", info={"gain": gain})

    try:
        res = merge(st, options={"gain": 2.0}, method="_test_identity")
        assert res.info["gain"] == 2.0
    finally:
        METHODS.pop("_test_identity", None)


def test_all_clipped_stack_raises_stack_error():
    times = np.array([0.1, 1.0])
    white = Stack(images=np.ones((2, 8, 8, 3), np.float32), times=times)
    black = Stack(images=np.zeros((2, 8, 8, 3), np.float32), times=times)
    for st in (white, black):
        for method in ("debevec", "robertson"):
            with pytest.raises(StackError):
                merge(st, method=method)


# --------------------------------------------------------------------------- OpenCV
def test_debevec_merge_equals_opencv_given_the_same_curve():
    e, codes, times = _synthetic(96, 128, n=7)
    resp, hdr = _opencv_debevec(codes, times)
    curves = ResponseCurves(np.log(resp[:, 0, ::-1].astype(np.float64)))
    # OpenCV's MergeDebevec = eq. 6 in the log domain, hat weight min(z, 255 - z) averaged over channels
    ours = merge(_stack(codes, times), options={"curves": curves, "domain": "log", "channel_weights": "mean",
                                                "weight": "hat"}, method="debevec")
    ok = np.isfinite(hdr)
    assert ok.mean() > 0.99
    np.testing.assert_allclose(ours.radiance[ok], hdr[ok], rtol=1e-4)


@pytest.mark.parametrize("seed,step,n", [(1, 1.0, 9), (2, 2.0, 6)])
def test_debevec_calibrate_and_merge_at_least_as_good_as_opencv(seed, step, n):
    e, codes, times = _synthetic(seed=seed, step=step, n=n)
    _, hdr = _opencv_debevec(codes, times)
    hdr = np.nan_to_num(hdr, nan=0.0, posinf=0.0)
    ref = psnr_rgbl(hdr, e)
    ours = psnr_rgbl(merge(_stack(codes, times), method="debevec").radiance, e)
    for k in "RGBL":
        assert ours[k] >= ref[k] - 0.3, (k, ours, ref)


def test_robertson_merge_close_to_truth_and_opencv():
    e, codes, times = _synthetic(120, 180, seed=3, n=7)
    imgs = [np.ascontiguousarray(c[..., ::-1]) for c in codes]
    tt = times.astype(np.float32)
    resp = cv2.createCalibrateRobertson().process(imgs, tt)
    hdr = cv2.createMergeRobertson().process(imgs, tt, resp)[..., ::-1]
    ref = psnr_rgbl(np.nan_to_num(hdr), e)
    res = merge(_stack(codes, times), method="robertson")
    ours = psnr_rgbl(res.radiance, e)
    assert ours["L"] >= ref["L"] - 0.5, (ours, ref)
    assert ours["L"] > 35.0
    assert np.all(np.diff(res.info["curves"].log_inverse, axis=0) >= 0)


# --------------------------------------------------------------------------- real data
@pytest.mark.shared_data
def test_memorial_debevec_agrees_with_debevec_radiance_map(memorial_dir):
    from derender.io.images import read_stack
    from derender.io.rgbe import read_hdr

    paths = sorted(memorial_dir.glob("memorial00*.png"))
    st = read_stack(paths, times_file=memorial_dir / "memorial.hdr_image_list.txt", times_file_inverse=True)
    assert st.n == 16 and np.isclose(st.times[0], 1 / 1024) and np.isclose(st.times[-1], 32.0)
    small = Stack(images=st.images[:, ::2, ::2], times=st.times)
    res = merge(small, method="debevec")
    ref = read_hdr(memorial_dir / "memorial.hdr")[::2, ::2]
    la, lb = luminance(res.radiance), luminance(ref)
    ok = (la > 0) & (lb > 0)
    r = np.corrcoef(np.log(la[ok]), np.log(lb[ok]))[0, 1]
    assert r >= 0.98, r
    assert np.all(np.isfinite(res.radiance))
    assert np.all(np.diff(res.info["curves"].log_inverse, axis=0) >= 0)
