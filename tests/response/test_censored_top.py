"""The bound-aware top of the Debevec merge's response solve (issues 36 item 8, 37 item 8), against the
simulator's exact truth: the luminance family's fixed gamma-2.2 camera (a tuning rendering)."""

from __future__ import annotations

import numpy as np
import pytest

from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2
from derender.core.types import Stack
from derender.engine.motion.run import MotionOptions
from derender.evaluation.families import smooth_mask
from derender.evaluation.linearity import linearity_scores
from derender.hdr.registry import merge
from derender.response.debevec1997 import censored_observations

LUMA = np.array([0.2126, 0.7152, 0.0722])


def _curve_error(curves) -> np.ndarray:
    """``exp(g - g_true)`` per code and channel, 1 at code 128: the simple style renders
    ``code = rint(255 lin^(1 / 2.2))`` per channel, so ``g_true(z) = 2.2 ln z`` up to an offset."""
    z = np.arange(256)
    gt = 2.2 * np.log(np.maximum(z, 0.5))
    e = curves.log_inverse - gt[:, None]
    return np.exp(e - e[128])


def test_curve_top_follows_the_true_gamma():
    """The merge's curve on the fisheye luminance bracket of the evalglare test (160x160, 9 frames 2
    stops apart): within 6 % of the true gamma 2.2 over codes 32..250 for each of the grid's seeds
    0-5. Measured: 0.973-1.051 (the worst near code 160, the 2-stop ripple of the smoothness term,
    not the top); the paper's system (``censor=False``), where codes that stopped rising with the
    exposure are data rows, is off by 1.35-4.0 at the top on every seed (4.0 at code 250 on seed 0;
    1.71 at codes 128-200 on seed 5)."""
    b = simulate_luminance(render="gamma", size=(160, 160), exposures=9, seed=0, fisheye=True)
    stack = Stack(images=b.jpeg_codes.astype(np.float32) / 255, times=b.times)
    for seed in range(6):
        err = _curve_error(merge(stack, "debevec", options={"seed": seed}).info["curves"])[32:251]
        assert np.all(np.abs(err - 1.0) <= 0.06), (seed, err.min(axis=0), err.max(axis=0))
        old = _curve_error(merge(stack, "debevec", options={"seed": seed, "censor": False}).info["curves"])[32:251]
        assert np.abs(old - 1.0).max() > 0.3, seed      # the test can fail: the paper's system misses it


def _saturating(codes: np.ndarray, seed: int) -> np.ndarray:
    """A camera whose white is 250..254, drawn per observation (noise after clipping)."""
    white = 250 + np.random.default_rng(seed).integers(0, 5, size=codes.shape)
    return np.minimum(codes, white).astype(np.uint8)


def _top_and_decades(res, b):
    lt = truth_luminance_cd_m2(b.truth_linear_srgb)
    x, y, w, h = b.params["luminance"]["spot"]
    sc = linearity_scores(res.radiance, lt, [x, y, w, h], score_mask=smooth_mask(b.truth_linear_srgb),
                          merge_mask=res.mask)
    lum = np.asarray(res.radiance, np.float64) @ LUMA
    card = np.median(lum[y:y + h, x:x + w] / lt[y:y + h, x:x + w])
    top = lt >= np.percentile(lt, 99)
    return float(np.median(lum[top] / lt[top]) / card), sc


def test_lamp_kept_on_a_camera_that_saturates_below_255():
    """Issue 36 item 4 and 8 on the luminance family (Nikon D5100, 192x128, 12 frames 1.5 stops apart,
    seed 0) with a white of 250..254: the brightest 1 % of the scene within 3 % of the truth (relative
    to the grey card) with and without ``--deghost``, every decade within +-5 %. Measured: plain 1.000,
    deghost 0.993, decades 0.995-1.005 / 0.996-1.014; the paper's system 0.877 / 0.846 and the decade
    1e3..1e4 at 1.162 with ``--deghost``. The white codes found: 250 in every channel."""
    b = simulate_luminance(render="gamma", exposures=12, stops=1.5, seed=0)
    stack = Stack(images=_saturating(b.jpeg_codes, 0).astype(np.float32) / 255, times=b.times)
    plain = merge(stack, "debevec")
    assert plain.info["curves"].params["white_codes"] == [250, 250, 250]
    for res in (plain, merge(stack, "debevec", motion=MotionOptions(deghost=True))):
        top, sc = _top_and_decades(res, b)
        assert top == pytest.approx(1.0, abs=0.03)
        assert np.all(np.abs(np.asarray(sc["decades"]) - 1.0) <= 0.05), sc["decades"]
        assert sc["median_abs"] <= 0.03
    old_top, _ = _top_and_decades(merge(stack, "debevec", options={"censor": False}), b)
    assert old_top < 0.95                          # the paper's system loses the lamp


def test_censored_observations_rule():
    """Frames given out of order: a pixel's code that stops rising (240 -> 240) is a bound from that
    frame on; one that rises to 255 is not (255 is clipped anyway); dark codes that do not rise are
    data (noise, not saturation)."""
    times = np.log(np.array([4.0, 1.0, 2.0, 8.0]))          # order: 1, 2, 0, 3
    z = np.array([[240, 200, 20, 255],
                  [130, 100, 10, 90],
                  [180, 150, 10, 200],
                  [240, 255, 21, 255]])
    keep = censored_observations(z, times)
    np.testing.assert_array_equal(keep[:, 0], [False, True, True, False])
    assert keep[:, 1].all() and keep[:, 2].all()
