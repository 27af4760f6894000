"""The curve model's shape tie (:data:`derender.hdr.stabilize.filmic.CURVE_SHAPE_TIE`), against exact truth.

A bracket rendered through one tone curve for every channel: equal codes are equal radiance in every
channel, at every code. On three frames two stops apart (pingpong's spacing, issue 36 item 5) samples
that do not follow the exposure (a thing that moves, residual misregistration) bend each independent
channel curve in its own way, and equal codes then give a ratio R/G that swings with the code
(pingpong: 0.90-1.20 with ``--deghost``)."""

from __future__ import annotations

import numpy as np
import pytest


def _bracket(seed: int, move: bool, h: int = 240, w: int = 320):
    """Three frames (1/1000, 1/250, 1/60 s, scaled) of a smooth coloured scene over several decades, each
    channel rendered by the same S-shaped curve, 1-code Gaussian noise; ``move``: a patch 4x brighter at a
    different place in every frame (a thing that moves, not masked)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    amp = rng.normal(size=8)
    waves = np.stack([np.sin((k + 1) * 3 * xx + rng.uniform(0, 6)) * np.cos((k % 3 + 1) * 2 * yy) for k in range(8)])
    lum = np.exp(np.tensordot(amp, waves, 1) * 1.2)
    chroma = np.exp(0.3 * np.stack([np.sin(5 * xx + c) + np.cos(4 * yy + 2 * c) for c in range(3)], -1))
    rad = lum[..., None] * chroma
    rad /= np.median(rad)
    times = np.array([1 / 1000, 1 / 250, 1 / 60]) * 60

    def tone(x):
        return x ** (1 / 2.2) / (x ** (1 / 2.2) + 0.35) * 1.35

    frames = []
    for j, t in enumerate(times):
        r = rad * t
        if move:
            r = r.copy()
            r[40 + 50 * j:100 + 50 * j, 100:180] *= 4.0
        frames.append(np.clip(np.rint(255 * np.clip(tone(r), 0, 1) + rng.normal(0, 1.0, r.shape)), 0, 255))
    return np.stack(frames).astype(np.uint8), times


def _neutral_swing(frames, times, shape_tie=None) -> float:
    """Largest ``|ln(R/G)(z) - median|`` or ``|ln(B/G)(z) - median|`` of the fitted curves over the codes
    16-239 where every channel has data (at least 20 codes of the frames, every 4th pixel, within 4 levels):
    where a channel has none, its curve is the smoothness term's extrapolation."""
    from derender.hdr.stabilize.filmic import unclipped_debevec

    cur = unclipped_debevec(lambda j, ys, xs: frames[j][ys, xs], frames.shape[0], frames.shape[1:3], times,
                            shape_tie=shape_tie)
    count = np.stack([np.bincount(frames[:, ::4, ::4, c].ravel(), minlength=256) for c in range(3)], axis=1)
    ok = np.convolve(count.min(axis=1), np.ones(9), "same") >= 20
    ok[:16] = ok[240:] = False
    d = cur.log_inverse[ok] - cur.log_inverse[ok][:, 1:2]
    return float(np.abs(d - np.median(d, axis=0)).max())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_equal_codes_stay_neutral_on_a_three_frame_bracket(seed):
    """Truth: R/G and B/G of equal codes are constant. With a thing that moves (not masked), independent
    channel curves (``shape_tie=0``, the default) each absorb it in their own way: measured swing 0.257 /
    0.224 / 0.200 (seeds 0-2); with the shape tie (``shape_tie=1``, red and blue held to green's shape)
    0.019 / 0.020 / 0.015. The still bracket: 0.043 / 0.037 / 0.203 -> 0.002 / 0.004 / 0.009."""
    frames, times = _bracket(seed, True)
    assert _neutral_swing(frames, times, shape_tie=1.0) <= 0.05
    assert _neutral_swing(frames, times, shape_tie=0.0) >= 0.15      # what the tie removes
    frames, times = _bracket(seed, False)
    assert _neutral_swing(frames, times, shape_tie=1.0) <= 0.02


@pytest.mark.parametrize("seed", [0, 1])
def test_the_shape_tie_keeps_greens_curve_and_its_truth(seed):
    """Green carries most of the luminance (Rec. 709 weight 0.72): the tie bends red and blue towards
    green's shape and leaves green's curve as its own samples give it (a tie between all three channels
    moved green too and cost the simulator's ``camera`` family 0.9-1.3 dB outdoors). Truth: every channel
    renders through the same curve, so ``g_G`` is the log inverse of that curve; with the tie it stays
    the untied fit (measured within 1e-11), and red's and blue's curves come to green's shape (range of
    ``g_c - g_G`` over the codes with data, red / blue, moving patch unmasked: untied 0.33 / 0.28 and
    0.43 / 0.34 for seeds 0 / 1, tied 0.027 / 0.004 and 0.029 / 0.021)."""
    from derender.hdr.stabilize.filmic import unclipped_debevec

    frames, times = _bracket(seed, True)

    def fit(k):
        return unclipped_debevec(lambda j, ys, xs: frames[j][ys, xs], 3, frames.shape[1:3], times,
                                 shape_tie=k).log_inverse

    free, tied = fit(0.0), fit(1.0)
    count = np.stack([np.bincount(frames[:, ::4, ::4, c].ravel(), minlength=256) for c in range(3)], axis=1)
    ok = np.convolve(count.min(axis=1), np.ones(9), "same") >= 20
    ok[:16] = ok[240:] = False
    assert np.max(np.abs(tied[ok, 1] - free[ok, 1])) <= 1e-9         # green is the untied fit
    for c in (0, 2):
        d_free = free[ok, c] - free[ok, 1]
        d_tied = tied[ok, c] - tied[ok, 1]
        assert np.ptp(d_tied) <= 0.08 and np.ptp(d_tied) < 0.5 * np.ptp(d_free), (c, np.ptp(d_free), np.ptp(d_tied))


def test_shape_tie_leaves_a_constant_and_a_log_code_multiple_free():
    """The penalty (:func:`derender.hdr.stabilize.filmic._shape_penalty`) is zero on ``a + b ln z`` (a white
    balance, a channel exponent) and positive on a ripple."""
    from derender.hdr.stabilize.filmic import _shape_penalty

    pen = _shape_penalty(256, 60.0, 1.0)
    z = np.arange(256, dtype=np.float64)
    free = 0.3 + 0.2 * np.log(np.maximum(z, 1.0))
    ripple = 0.05 * np.sin(z / 12.0)
    scale = float(ripple @ pen @ ripple)
    assert scale > 0
    assert abs(float(free @ pen @ free)) <= 1e-7 * scale


def test_the_merge_takes_the_shape_tie_as_an_option():
    """``-O shape_tie=K`` of the stabilised merges reaches the curve (the merge's info says which
    weight it used) and changes the merge only through it; a negative weight is refused."""
    import derender as dr
    from derender.core.errors import InputError

    frames, times = _bracket(0, True, h=120, w=160)
    stack = dr.Stack(frames.astype(np.float32) / 255, times)
    plain = dr.merge(stack, "stabilized", {"response": "curve"})
    tied = dr.merge(stack, "stabilized", {"response": "curve", "shape_tie": 1.0})
    assert plain.info["shape_tie"] == 0.0 and tied.info["shape_tie"] == 1.0
    assert not np.array_equal(plain.radiance, tied.radiance)
    g = tied.radiance[..., 1] > 0
    assert np.all(np.isfinite(tied.radiance)) and tied.radiance.min() >= 0 and g.any()
    with pytest.raises(InputError):
        dr.merge(stack, "stabilized", {"response": "curve", "shape_tie": -1.0})
