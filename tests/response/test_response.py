"""Tests for derender.response: Debevec/Robertson response recovery, sampling, monotonicity, errors."""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.errors import InputError, StackError
from derender.core.types import Stack
from derender.response.curves import ResponseCurves, isotonic_increasing, plot_response, sample_pixels
from derender.response.debevec1997 import calibrate_debevec, solve_debevec
from derender.response.robertson2003 import calibrate_robertson

GAMMAS, KNEES = (2.0, 2.2, 2.5), (0.4, 0.5, 0.6)


def _response(x_lin, c):
    """Known per-channel response: gamma then a soft shoulder."""
    x = np.clip(x_lin, 0.0, 1.0) ** (1.0 / GAMMAS[c])
    return x * (1 + KNEES[c]) / (x + KNEES[c])


def _inverse_response(y, c):
    """Exact inverse of :func:`_response` (y in (0, 1))."""
    x = y * KNEES[c] / (1 + KNEES[c] - y)
    return x ** GAMMAS[c]


def _synthetic(h=120, w=160, seed=1, n=9, step=1.0, noise=2e-4, bits=8):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    base = 10 ** (3.0 * (x - 0.5) + 0.5 * np.sin(6 * y))
    e = np.stack([base * (0.6 + 0.4 * np.cos(3 * y * (c + 1) + 2 * x)) for c in range(3)], -1)
    times = 2.0 ** (step * np.arange(n) - step * (n - 1))
    e = e / e.max() / times[0] * 0.9
    scale = 2**bits - 1
    imgs = []
    for t in times:
        xe = e * t + rng.normal(0, noise, e.shape)
        yv = np.stack([_response(xe[..., c], c) for c in range(3)], -1)
        imgs.append(np.clip(np.rint(yv * scale), 0, scale) / scale)
    return e, Stack(images=np.stack(imgs).astype(np.float32), times=times, bit_depth=bits if bits == 16 else 8)


def _true_g(levels, c, n_levels=256):
    z = np.arange(n_levels) / (n_levels - 1)
    g = np.log(_inverse_response(z[levels], c))
    return g - np.log(_inverse_response(np.array([(n_levels // 2) / (n_levels - 1)]), c))


# --------------------------------------------------------------------------- solver
def test_solve_debevec_equals_dense_gsolve():
    """Our Schur-complement solver against a literal dense transcription of Debevec's gsolve."""
    rng = np.random.default_rng(0)
    n_img, p, n = 5, 40, 256
    z = rng.integers(0, 256, (n_img, p))
    b = np.log(np.array([0.01, 0.04, 0.16, 0.64, 2.56]))
    lam = 7.0
    wz = np.minimum(np.arange(n), 255 - np.arange(n)).astype(float)
    a = np.zeros((n_img * p + n - 1, n + p))
    rhs = np.zeros(a.shape[0])
    k = 0
    for i in range(p):
        for j in range(n_img):
            w = wz[z[j, i]]
            a[k, z[j, i]] = w
            a[k, n + i] = -w
            rhs[k] = w * b[j]
            k += 1
    a[k, 128] = 1
    k += 1
    for i in range(1, n - 1):
        a[k, i - 1:i + 2] = lam * wz[i] * np.array([1, -2, 1])
        k += 1
    sol = np.linalg.lstsq(a, rhs, rcond=None)[0]
    g, log_e = solve_debevec(z, b, lam=lam, weights=wz)
    np.testing.assert_allclose(g, sol[:n], atol=1e-7)
    np.testing.assert_allclose(log_e, sol[n:], atol=1e-7)
    # the table of weights is only used up to scale together with lambda: hat on [0, 1] is the same system
    g2, _ = solve_debevec(z, b, lam=lam, weights="hat")
    np.testing.assert_allclose(g2, g, atol=1e-7)


@pytest.mark.shared_data
def test_histogram_sampling_and_gsolve_match_colour_hdri_reference(frobisher_dir):
    """colour-hdri's regression arrays: g_solve(samples_Grossberg2003(stack)[..., c], log(1/L_avg))."""
    from derender.io.images import read_image

    imgs = np.stack([read_image(frobisher_dir / f"IMG_{k}.jpg")[0] for k in (2600, 2601, 2602)])
    times = np.array([1 / 8, 1.0, 8.0])
    # colour-hdri: B = ln(1 / average_luminance(N=8, t, S=100)) with L = N^2 / t / S * 12.5
    b = np.log(1.0 / (8.0**2 / times / 100.0 * 12.5))
    samples = sample_pixels(imgs, n_samples=1000, method="histogram")
    assert samples.shape == (3, 1000, 3)
    a = np.linspace(0, 1, 256)  # colour-hdri weighting_function_Debevec1997 (domain 0.01 .. 0.99)
    w = np.where(a <= 0.5, a - 0.01, 0.99 - a)
    w = np.maximum(w / w.max(), 0)
    ref = frobisher_dir / "reference"
    for c in range(3):
        g, log_e = solve_debevec(samples[:, :, c], b, lam=30, weights=w)
        np.testing.assert_allclose(g, np.load(ref / f"test_g_solve_g_{c}.npy"), atol=1e-6)
        np.testing.assert_allclose(log_e, np.load(ref / f"test_g_solve_lE_{c}.npy"), atol=1e-6)


# --------------------------------------------------------------------------- calibration
def test_debevec_recovers_known_response():
    _, st = _synthetic(noise=2e-5)
    curves = calibrate_debevec(st)
    assert curves.log_inverse.shape == (256, 3) and curves.method == "debevec"
    assert np.all(curves.log_inverse[128] == 0)
    # below ~code 25 the true g is very steep (gamma 2.5: g' = 2.5 / z) and barely sampled
    levels = np.arange(25, 251)
    for c in range(3):
        err = curves.log_inverse[levels, c] - _true_g(levels, c)
        assert np.max(np.abs(err)) < 0.03, (c, np.max(np.abs(err)))


def test_robertson_recovers_known_response():
    _, st = _synthetic(seed=2, noise=2e-5)
    # channels whose curves differ (GAMMAS, KNEES): the paper's independent channels (tie=0); the tie
    # (issue 27) assumes one shape and moves code 25 by 0.2 here
    curves = calibrate_robertson(st, balance=False, tie=0)  # g(128) = 0 per channel, as _true_g
    assert curves.method == "robertson" and curves.params["iterations"] >= 2
    levels = np.arange(25, 251)
    for c in range(3):
        err = curves.log_inverse[levels, c] - _true_g(levels, c)
        assert np.max(np.abs(err)) < 0.06, (c, np.max(np.abs(err)))
    assert np.all(np.diff(curves.log_inverse, axis=0) >= 0)


def test_curves_are_monotonic_even_when_least_squares_is_not():
    _, st = _synthetic(60, 80, n=4, step=2.0, noise=0.01, seed=3)
    raw = calibrate_debevec(st, lam=0.05, monotonic=False)
    assert np.any(np.diff(raw.log_inverse, axis=0) < 0)  # the unconstrained solution wiggles
    fixed = calibrate_debevec(st, lam=0.05)
    assert np.all(np.diff(fixed.log_inverse, axis=0) >= 0)
    assert any(fixed.params["monotonic_fixed"])
    assert np.all(fixed.log_inverse[128] == 0)
    # isotonic regression is the least-squares monotone fit
    np.testing.assert_allclose(isotonic_increasing([1, 3, 2, 4, 0]), [1, 2.25, 2.25, 2.25, 2.25])
    np.testing.assert_allclose(isotonic_increasing([0, 1, 2]), [0, 1, 2])


@pytest.mark.shared_data
def test_memorial_curves_monotonic(memorial_dir):
    from derender.io.images import read_stack

    st = read_stack(sorted(memorial_dir.glob("memorial00*.png")),
                    times_file=memorial_dir / "memorial.hdr_image_list.txt", times_file_inverse=True)
    for curves in (calibrate_debevec(st), calibrate_robertson(st, max_pixels=10_000)):
        g = curves.log_inverse
        assert np.all(np.diff(g, axis=0) >= 0)
        # Memorial's 16 one-stop exposures span ~ 7-8 stops of film response between codes 30 and 225
        span = (g[225] - g[30]) / np.log(2)
        assert np.all((span > 4) & (span < 12)), span


def test_sixteen_bit_stack_is_binned_and_works():
    e, st16 = _synthetic(60, 80, bits=16, noise=2e-5)
    assert st16.bit_depth == 16
    curves = calibrate_debevec(st16)
    levels = np.arange(25, 251)
    for c in range(3):
        assert np.max(np.abs(curves.log_inverse[levels, c] - _true_g(levels, c))) < 0.03
    lin = curves.linearise(st16.images[3])
    assert lin.dtype == np.float32 and np.all(np.isfinite(lin))


def test_sampling_is_deterministic_and_documented_shapes():
    _, st = _synthetic(60, 80, n=5)
    a = sample_pixels(st, n_samples=50, method="grid", seed=4)
    b = sample_pixels(st, n_samples=50, method="grid", seed=4)
    c = sample_pixels(st, n_samples=50, method="grid", seed=5)
    assert a.shape == (5, 50, 3) and a.dtype == np.int32
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(a, sample_pixels(st.codes(), n_samples=50, method="grid", seed=4))
    h = sample_pixels(st, n_samples=64, method="histogram")
    assert h.shape == (5, 64, 3)
    assert np.all(np.diff(h, axis=1) >= 0)  # quantile matching: codes grow with the quantile
    with pytest.raises(InputError):
        sample_pixels(st, method="magic")


def test_unusable_stacks_raise_stack_error():
    times = np.array([0.01, 0.1, 1.0])
    for value in (0.0, 1.0):
        st = Stack(images=np.full((3, 10, 10, 3), value, np.float32), times=times)
        with pytest.raises(StackError, match="usable"):
            calibrate_debevec(st)
        with pytest.raises(StackError):
            calibrate_robertson(st)
    imgs = np.random.default_rng(0).uniform(0.2, 0.8, (3, 10, 10, 3)).astype(np.float32)
    imgs[..., 2] = 1.0  # blue clipped everywhere
    with pytest.raises(StackError, match="channel B"):
        calibrate_debevec(Stack(images=imgs, times=times))
    with pytest.raises(InputError):
        calibrate_debevec(imgs)


def test_response_curves_interpolation_and_plot(tmp_path):
    g = np.stack([np.linspace(-5, 2, 256)] * 3, -1)
    g -= g[128]
    curves = ResponseCurves(g)
    z = np.array([[0.0, 0.5, 1.0], [128 / 255, 64.5 / 255, 3 / 255]], np.float32)
    np.testing.assert_allclose(curves.log_linearise(z)[1, 0], 0.0, atol=1e-5)
    np.testing.assert_allclose(curves.log_linearise(z)[1, 1], (g[64, 1] + g[65, 1]) / 2, atol=1e-5)
    np.testing.assert_allclose(curves.linearise(z), np.exp(curves.log_linearise(z)), rtol=1e-6)
    with pytest.raises(InputError):
        ResponseCurves(np.full((256, 3), np.nan))
    out = plot_response(curves, tmp_path / "curves.png")
    assert out.stat().st_size > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["curves.png"]
