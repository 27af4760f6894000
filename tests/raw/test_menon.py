"""Menon 2007's filter bank (derender.raw.menon) against its per-pixel construction."""

import numpy as np
import pytest

from derender.raw import menon


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "BGGR", "GBRG"])
def test_filter_bank_is_the_per_pixel_weights(pattern):
    """menon_demosaic (the filter bank away from the border) gives menon_rows' values and
    variance (every pixel's weights built from eqs. (3), (7), (8)) on the same directions, odd
    sizes and the direction-flip term included. Measured: values equal to 6e-11 absolute (the
    sums' order), variances equal."""
    rng = np.random.default_rng(4)
    m = np.array([[1.8, -0.6, -0.2], [-0.2, 1.5, -0.3], [0.0, -0.5, 1.5]])
    for shape in ((40, 46), (41, 37), (9, 11)):
        x = (rng.uniform(0, 1, shape) ** 3).astype(np.float32)
        v = (rng.uniform(0.5, 1.5, shape) * 1e-3).astype(np.float32)     # large enough for flips
        chan = np.array([["RGB".index(c) for c in pattern[:2]], ["RGB".index(c) for c in pattern[2:]]], np.int64)
        red_row = np.array([np.any(chan[0] == 0), np.any(chan[1] == 0)])
        ia, ib = np.nonzero(menon.CLASSIFIER)
        direction = np.empty(shape, np.uint8)
        margin = np.empty(shape, np.float32)
        menon.menon_directions(x, chan, (2 - ia).astype(np.int64), (2 - ib).astype(np.int64),
                               menon.CLASSIFIER[ia, ib].copy(), direction, margin)
        ref, ref_var = np.empty(shape + (3,), np.float32), np.empty(shape + (3,), np.float32)
        menon.menon_rows(x, v, chan, red_row, direction, margin, menon.MARGIN_SD, m, False, True, ref, ref_var)
        out, var = np.empty_like(ref), np.empty_like(ref)
        menon.menon_demosaic(x, v, pattern, m, False, out, var)
        np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6)
        np.testing.assert_allclose(var, ref_var, rtol=1e-6, atol=0)
        assert np.mean(var > 1.01 * menon_no_flip(x, v, chan, red_row, direction, margin, m)) > 0.05


def menon_no_flip(x, v, chan, red_row, direction, margin, m):
    """menon_rows' variance without the direction-flip term (margin_sd 0: P(flip) = 0)."""
    out, var = np.empty(x.shape + (3,), np.float32), np.empty(x.shape + (3,), np.float32)
    menon.menon_rows(x, v, chan, red_row, direction, margin, 0.0, m, False, True, out, var)
    return var


def test_filter_bank_size():
    """Each phase's filter depends on its own direction and at most 6 others (64 filters of 9-25 taps)."""
    key_n, _, _, set_start, tap_start, *_ = menon.weight_table("RGGB")
    assert key_n.max() == 6 and len(tap_start) - 1 == 2 * 2 * 64 + 2 * 16
    assert 9 <= np.diff(tap_start).min() and np.diff(tap_start).max() <= 25
