"""A bracket's black floor (derender.engine.weights.black_codes, floor_weights), against exact
constructions: a film-like bracket whose codes never go below an offset per channel, and a
digital one whose black is code 0.

Oracle: the construction itself. Codes are ``max(F_c, round(255 (E t)^(1/2.2)))``: a code ``z``
at most ``F_c + 1`` shows ``F_c`` when the exposure is halved (``0.73 (F_c + 1) < F_c`` for
``F_c >= 3``), so it did not fall by more than one code, and ``F_c + 2`` falls to ``F_c`` (by
two): the floor is ``F_c + 1`` exactly.
"""

from __future__ import annotations

import numpy as np
import pytest

import derender as dr
from derender.core.types import Stack
from derender.engine.weights import FLOOR_MIN_CODE, black_codes, floor_weights


def _bracket(floor, n=10, pixels=40_000, seed=0, noise=0.0):
    rng = np.random.default_rng(seed)
    scene = np.exp(rng.uniform(np.log(1e-5), np.log(1.0), size=(pixels, 3)))
    times = 2.0 ** np.arange(n, dtype=np.float64) / 2.0 ** (n - 1)
    codes = np.empty((n, pixels, 3), dtype=np.int64)
    for j, t in enumerate(times):
        x = np.clip(scene * t * np.exp(rng.normal(0, noise, scene.shape)), 0, 1)
        codes[j] = np.maximum(np.asarray(floor)[None, :], np.rint(255 * x ** (1 / 2.2)).astype(np.int64))
    return np.clip(codes, 0, 255), times, scene


def test_a_film_floor_is_found_exactly():
    codes, times, _ = _bracket([13, 17, 15])
    assert black_codes(codes, times) == [14, 18, 16]
    # the samples' order and the frames' order do not matter
    perm = np.random.default_rng(1).permutation(times.size)
    assert black_codes(codes[perm], times[perm]) == [14, 18, 16]


def test_a_digital_black_is_left_as_it_is():
    codes, times, _ = _bracket([0, 0, 0], noise=0.02)
    assert black_codes(codes, times) == [0, 0, 0]
    # a floor below FLOOR_MIN_CODE (crushed blacks) is not one either
    codes, times, _ = _bracket([FLOOR_MIN_CODE - 3] * 3)
    assert black_codes(codes, times) == [0, 0, 0]


def test_floor_weights_zero_the_floor_and_nothing_else():
    w = np.tile(np.linspace(0.1, 1.0, 256, dtype=np.float32)[:, None], (1, 3))
    out = floor_weights(w, [14, 0, 16])
    assert np.all(out[:15, 0] == 0) and np.all(out[15:, 0] == w[15:, 0])
    assert np.array_equal(out[:, 1], w[:, 1])
    assert np.all(out[:17, 2] == 0) and np.all(out[17:, 2] == w[17:, 2])
    assert floor_weights(w, [0, 0, 0]) is w
    per_frame = floor_weights(np.stack([w, w]), [14, 0, 16])
    assert np.array_equal(per_frame[1], out)


@pytest.mark.parametrize("method", ["debevec", "robertson"])
def test_a_floored_bracket_merges_its_dark_decade_like_its_black_free_twin(method):
    """The same scene with and without a film floor: without the floor's weight the darkest
    pixels the longest frame measures (every channel at least 20 codes above the floor there;
    their darkest decile) merge within 10 % of the black-free twin (after one scale per channel).
    With the floor weighted (FLOOR_MIN_CODE set above it) they came out at 0.42-0.85 (debevec) and
    0.04-0.20 (robertson) of the twin per channel."""
    pixels = 128 * 96
    codes, times, scene = _bracket([13, 17, 15], pixels=pixels, noise=0.01)
    free, _, _ = _bracket([0, 0, 0], pixels=pixels, noise=0.01)
    res = []
    for c in (codes, free):
        st = Stack(images=(c.reshape(-1, 96, 128, 3) / 255.0).astype(np.float32), times=times)
        res.append(dr.merge(st, method))
    assert res[0].info["black_codes"] == [14, 18, 16] and res[1].info["black_codes"] == [0, 0, 0]
    a, b = (np.asarray(r.radiance, dtype=np.float64).reshape(-1, 3) for r in res)
    lum = scene @ [0.2126, 0.7152, 0.0722]
    seen = np.all(codes[-1] >= np.array([33, 37, 35]), axis=-1) & np.all(codes[-1] < 250, axis=-1)
    dark = seen & (lum < np.quantile(lum[seen], 0.1))
    k = np.exp(np.median(np.log(a) - np.log(b), axis=0))
    ratio = np.exp(np.median(np.log(a[dark] / k) - np.log(b[dark]), axis=0))
    assert np.all(np.abs(ratio - 1) < 0.10), ratio
