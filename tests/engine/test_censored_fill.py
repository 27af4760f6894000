"""The censored fill (:mod:`derender.engine.motion.censored_fill`, issue 36 item 5): where ghost removal
left only clipped frames, the merge no longer returns the clip value as if measured.

Oracles: the simulator's exact truth (a moving object hides the only unclipped view of a bright
region); for the fill itself, a constant scene (any interpolation of a constant is that constant)
and the pixels it must not touch (bit for bit); for the lamp, the still twin (no ghosts, nothing
filled).
"""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.types import Stack
from derender.engine.motion.censored_fill import CENSOR_CODE, censored_fill, hidden_views
from derender.engine.motion.run import MotionOptions

LUMA = np.array([0.2126, 0.7152, 0.0722])


def _frames(h=40, w=48):
    """Three frames: the reference (1) and the long frame (2) clipped on a bright disc, the short
    frame (0) measures it but shows a dark object on the disc's middle (rejected there)."""
    yy, xx = np.mgrid[:h, :w]
    bright = (yy - 20) ** 2 + (xx - 24) ** 2 <= 14 ** 2
    hole = (yy - 20) ** 2 + (xx - 24) ** 2 <= 6 ** 2
    frames = np.full((3, h, w, 3), 120, np.uint8)
    frames[1][bright] = 253
    frames[2][bright] = 255
    frames[2][~bright] = 200
    frames[0][bright] = 90
    frames[0][hole] = 10                       # the object
    rejected = np.zeros((3, h, w), bool)
    rejected[0] = hole
    return frames, rejected, bright, hole


def test_fill_reads_the_measured_clipped_scene_and_touches_nothing_else():
    """A constant radiance where the short frame measures the clipped disc: the hidden middle is
    filled with that constant (per channel), above the bound; every other pixel keeps its bits;
    the variance covers the lift and never falls below the merge's own."""
    frames, rejected, bright, hole = _frames()
    h, w = hole.shape
    radiance = np.full((h, w, 3), 0.5, np.float32)
    radiance[bright] = np.array([3.0, 2.5, 2.0], np.float32)      # measured by the short frame
    radiance[hole] = 1.0                                            # the reference's bound
    variance = np.full_like(radiance, 1e-4)
    before_r, before_v = radiance.copy(), variance.copy()
    valid = (~rejected).view(np.uint8)
    hidden = hidden_views(frames, rejected)
    info = censored_fill(radiance, variance, frames, valid, hidden, 1)
    assert info["region_pixels"] == int(hole.sum()) == info["filled_pixels"]
    np.testing.assert_array_equal(radiance[~hole], before_r[~hole])
    np.testing.assert_array_equal(variance[~hole], before_v[~hole])
    np.testing.assert_allclose(radiance[hole], np.broadcast_to([3.0, 2.5, 2.0], (int(hole.sum()), 3)), rtol=1e-5)
    lift = np.log(radiance[hole] / before_r[hole])
    sig2 = np.log1p(variance[hole] / radiance[hole].astype(np.float64) ** 2)
    assert np.all(sig2 >= lift ** 2 * (1 - 1e-5)) and np.all(variance[hole] >= before_v[hole])


def test_fill_keeps_the_bound_and_the_measured_channels():
    """Data below the bound (a camera whose other frame reads lower) leave the bound; a channel
    that a kept frame measures is not touched; nothing to do without rejected views."""
    frames, rejected, bright, hole = _frames()
    h, w = hole.shape
    radiance = np.full((h, w, 3), 0.5, np.float32)
    radiance[bright] = 0.8                     # the data, below the hole's bound
    radiance[hole] = 1.0
    frames[2][hole, 2] = 100                   # the long frame (kept) measures blue in the hole
    frames[1][hole, 2] = 40
    before = radiance.copy()
    valid = (~rejected).view(np.uint8)
    censored_fill(radiance, None, frames, valid, hidden_views(frames, rejected), 1)
    np.testing.assert_array_equal(radiance, before)
    assert hidden_views(frames, np.zeros_like(rejected)) is None
    assert censored_fill(radiance, None, frames, None, None, 1) is None
    assert CENSOR_CODE == 250


def _hidden_sky(family: str, seed: int):
    """A simulator still bracket (Nikon D5100, outdoor, 160x120, 7 frames 2 stops apart; frames 4-6,
    the reference the middle one: its brightest region is clipped, the short frame sees it) and the
    same frames with a moving object: a disc (radius 8 px) of the short frame's own darkest texture
    pasted into the short frame over the middle of the reference's largest clipped region, so that
    the only unclipped view of that region's middle shows the object (it has moved on by the
    reference's instant: the truth is the still scene). Returns the stack, the truth, the hidden
    pixels (in the disc, clipped in the reference) and the reference's clipped pixels the short frame
    still measures (beside the disc)."""
    from scipy import ndimage

    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec

    b = simulate_bracket("nikon-d5100", kind="outdoor", size=(160, 120), exposures=7, stops=2.0, seed=seed,
                         family=family, motion=MotionSpec(objects=3, shake=3).still())
    codes, times = b.jpeg_codes[4:7].copy(), b.times[4:7]
    clip = (codes[1] >= CENSOR_CODE).all(-1) & (codes[0] < CENSOR_CODE).all(-1)
    lab, _ = ndimage.label(clip)
    big = lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    dist = ndimage.distance_transform_edt(big)
    cy, cx = np.unravel_index(np.argmax(dist), dist.shape)
    yy, xx = np.mgrid[:120, :160]
    disc = (yy - cy) ** 2 + (xx - cx) ** 2 <= 64
    lum = codes[0].mean(-1)
    dy, dx = np.unravel_index(np.argmin(ndimage.uniform_filter(lum, 17)), lum.shape)
    codes[0][disc] = np.roll(np.roll(codes[0], cy - dy, 0), cx - dx, 1)[disc]
    stack = Stack(images=codes.astype(np.float32) / 255, times=times)
    return stack, b.truth_linear_srgb.astype(np.float64), disc & big, big & ~disc


def _hidden_error(res, truth, hidden, around) -> float:
    """Median |ln| of the luminance against the truth on the hidden pixels, after one scale on the
    clipped pixels the short frame measures."""
    lm, lt = np.asarray(res.radiance, np.float64) @ LUMA, truth @ LUMA
    k = np.median(lt[around] / lm[around])
    return float(np.median(np.abs(np.log(k * lm[hidden] / lt[hidden]))))


@pytest.mark.slow
def test_moving_object_hiding_the_only_unclipped_view():
    """Truth: seeds 0-3 of the tuning families ``paper`` and ``camera``, ``stabilized --deghost``
    (reference the middle frame). Without the fill the hidden pixels get the reference's bound,
    median |ln error| 0.130-0.415 (mean 0.255); with it 0.043-0.235 (mean 0.156), better on 6 of
    8. The fill is not exact: it reads the clipped scene around, which is brighter than the hidden
    middle on some seeds (paper 0 +0.235, camera 2 +0.197 against the bound's 0.178)."""
    import derender as dr

    old, new = [], []
    for family in ("paper", "camera"):
        for seed in range(4):
            stack, truth, hidden, around = _hidden_sky(family, seed)
            m = MotionOptions(reference=1, align="none", deghost=True)
            res = dr.merge(stack, "stabilized", motion=m)
            bound = dr.merge(stack, "stabilized", motion=MotionOptions(reference=1, align="none", deghost=True,
                                                                          censored_fill=False))
            assert res.info["censored_fill"]["filled_pixels"] >= hidden.sum() // 2
            assert np.all(np.isfinite(res.radiance)) and res.radiance.min() >= 0
            # only where the reference is clipped and a frame was left out
            changed = np.any(res.radiance != bound.radiance, axis=-1)
            assert not np.any(changed & ((res.ghosts == 0) | (stack.images[1] < CENSOR_CODE / 255).all(-1)))
            old.append(_hidden_error(bound, truth, hidden, around))
            new.append(_hidden_error(res, truth, hidden, around))
    old, new = np.array(old), np.array(new)
    assert old.mean() >= 0.2 and new.mean() <= 0.18, (old, new)
    assert np.sum(new < old) >= 5, (old, new)


@pytest.mark.parametrize("kind", ["outdoor", "indoor"])
def test_still_twin_lamp_is_kept(kind):
    """Issue 36 "lamps are kept": a still twin whose white is drawn in 250..254 (``camera`` style,
    fixed pipeline, 192x128, 7 frames, seed 1, reference 3): ``debevec --deghost`` gives the
    brightest 1 % of the truth the same values with and without the fill. Outdoor nothing is
    rejected where the reference is clipped, so nothing is filled and the maps are equal; indoor
    the test rejects a few hundred still pixels, which the fill reads but does not raise (their
    data lie at their bound)."""
    import derender as dr
    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec

    b = simulate_bracket("nikon-d5100", kind=kind, size=(192, 128), exposures=7, seed=1, pipeline="fixed",
                         style="camera", motion=MotionSpec(objects=3, shake=3).still())
    white = 250 + np.random.default_rng(1).integers(0, 5, size=b.jpeg_codes.shape)
    stack = Stack(images=np.minimum(b.jpeg_codes, white).astype(np.float32) / 255, times=b.times)
    on = dr.merge(stack, "debevec", motion=MotionOptions(reference=3, align="none", deghost=True))
    off = dr.merge(stack, "debevec", motion=MotionOptions(reference=3, align="none", deghost=True,
                                                          censored_fill=False))
    lt = b.truth_linear_srgb @ LUMA
    top = lt >= np.percentile(lt, 99)
    np.testing.assert_array_equal(on.radiance[top], off.radiance[top])
    if kind == "outdoor":
        np.testing.assert_array_equal(on.radiance, off.radiance)
        assert on.info.get("censored_fill") is None
