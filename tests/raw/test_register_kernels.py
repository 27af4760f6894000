"""The compiled loops of RAW registration and ghost removal (derender.raw.register_kernels) against the
NumPy formulas they replaced (written out here as they were in derender.raw.register and
derender.hdr.raw before the loops were compiled; the resampling filter's border since then mirrors
each CFA phase on its own), on small random mosaics with saturated photosites: equal within 1e-12
relative (the same sums in the same order)."""

import math

import numpy as np
import pytest

from derender.raw.register import keys_weights, resample_mosaic, resample_rgb
from derender.raw.register_kernels import (
    PAD,
    box_image,
    filter_phase,
    ghost_z2,
    mirror_cfa,
    separable_taps,
    window_sums,
)
from derender.raw.window_ghost_test import shifted_box

TOL = 1e-12


def _close(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert a.shape == b.shape
    assert np.all(np.abs(a - b) <= TOL * np.maximum(np.abs(b), 1.0))


def _mosaic(shape=(21, 18), seed=0, white=4000):
    rng = np.random.default_rng(seed)
    m = rng.integers(500, white + 300, size=shape)
    m = np.minimum(m, white).astype(np.uint16)               # about 7 % saturated
    black = np.array([[512.0, 510.0], [511.0, 509.0]])
    return m, black, float(white)


def _pad_cfa(a):
    """``a`` padded by PAD, each CFA phase's samples mirrored on their own (numpy.pad symmetric)."""
    h, w = a.shape
    out = np.empty((h + 2 * PAD, w + 2 * PAD), a.dtype)
    for p in range(2):
        for q in range(2):
            plane = np.pad(a[p::2, q::2], 1, mode="symmetric")       # one sample each side = 2 photosites
            # the padded plane's sample i sits at photosite 2 (i - 1) + p, i.e. padded row 2 i + p
            rows, cols = np.arange(plane.shape[0]) * 2 + p, np.arange(plane.shape[1]) * 2 + q
            keep_r, keep_c = rows < h + 2 * PAD, cols < w + 2 * PAD
            out[np.ix_(rows[keep_r], cols[keep_c])] = plane[np.ix_(keep_r, keep_c)]
    return out


@pytest.mark.parametrize("shape", [(21, 18), (20, 17)])
def test_mirror_cfa_keeps_the_colour(shape):
    h, w = shape
    idx = np.arange(h).reshape(-1, 1) * 1000 + np.arange(w).reshape(1, -1)
    padded = _pad_cfa(idx)
    for y in range(-PAD, h + PAD):
        for x in range(-PAD, w + PAD):
            ry, rx = mirror_cfa(y, h), mirror_cfa(x, w)
            assert padded[y + PAD, x + PAD] == ry * 1000 + rx
            assert (ry - y) % 2 == 0 and (rx - x) % 2 == 0 and 0 <= ry < h and 0 <= rx < w


def test_filter_phase_is_the_padded_numpy_filter():
    m, black, white = _mosaic()
    h, w = m.shape
    bl = np.tile(black, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    d = _pad_cfa(m.astype(np.float64) - bl)
    sat = _pad_cfa((m >= white).astype(np.float64))
    ker = np.random.default_rng(1).normal(size=(6, 5))
    ker[2, 3] = 0.0
    r0, c0, ni, nk = 1, 0, 10, 9
    vals, nsat = np.zeros((ni, nk)), np.zeros((ni, nk))
    for u in range(ker.shape[0]):
        for v in range(ker.shape[1]):
            if ker[u, v] == 0.0:
                continue
            sl = (slice(r0 + u, r0 + u + 2 * ni - 1, 2), slice(c0 + v, c0 + v + 2 * nk - 1, 2))
            vals += ker[u, v] * d[sl]
            nsat += sat[sl]
    got_v, got_s = np.empty((ni, nk)), np.empty((ni, nk))
    filter_phase(m, black, white, ker, r0, c0, got_v, got_s)
    _close(got_v, vals)
    assert np.array_equal(got_s, nsat)
    filter_phase(m.astype(np.float64), black, white, ker, r0, c0, got_v, got_s)     # resampled codes
    _close(got_v, vals)


def test_window_sums_and_separable_taps_are_shifted_box_in_numpy():
    rng = np.random.default_rng(2)
    v = rng.uniform(0, 3, size=(15, 12))
    sat = rng.random((15, 12)) < 0.1
    scale = np.array([[0.7, 1.1], [1.2, 1.0]])
    h, w = v.shape
    sc = np.tile(scale, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    q = np.pad(v / sc, ((0, 1), (0, 1)), mode="edge")
    st = np.pad(sat.astype(np.float64), ((0, 1), (0, 1)), mode="edge")
    box = q[:-1, :-1] + q[1:, :-1] + q[:-1, 1:] + q[1:, 1:]
    sbox = st[:-1, :-1] + st[1:, :-1] + st[:-1, 1:] + st[1:, 1:]
    got_b, got_s = np.empty((h, w)), np.empty((h, w))
    window_sums(v, sat, scale, got_b, got_s)
    _close(got_b, box)
    assert np.array_equal(got_s, sbox)
    for shift in [(0.0, 0.0), (1.5, -0.25), (-2.0, 1.0), (0.3, 0.7)]:
        iy, ix = math.floor(shift[0]), math.floor(shift[1])
        wy, wx = keys_weights(shift[0] - iy), keys_weights(shift[1] - ix)
        ty, tx = np.flatnonzero(wy), np.flatnonzero(wx)
        i0, i1 = max(0, -(iy + ty[0] - 1)), min(h, h - (iy + ty[-1] - 1))
        k0, k1 = max(0, -(ix + tx[0] - 1)), min(w, w - (ix + tx[-1] - 1))
        rows = np.zeros((i1 - i0, w))
        for m in ty:
            rows += wy[m] * box[i0 + iy + m - 1:i0 + iy + m - 1 + (i1 - i0)]
        out = np.zeros((i1 - i0, k1 - k0))
        for n in tx:
            out += wx[n] * rows[:, k0 + ix + n - 1:k0 + ix + n - 1 + (k1 - k0)]
        got = np.empty_like(out)
        separable_taps(box, iy, ix, wy, wx, i0, k0, got)
        _close(got, out)
        sb = shifted_box(v, sat, shift, scale)[0]
        _close(sb[i0:i1, k0:k1], out)


def test_box_image_is_the_numpy_window_sum():
    m, black, white = _mosaic((17, 14), seed=3)
    scale = np.array([[0.8, 1.1], [1.05, 1.05]])
    e, read_sd = 0.25, 2.0
    mm = m.astype(np.float64)
    h, w = m.shape
    bl = np.tile(black, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    sc = np.tile(scale, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    d = mm - bl
    bad = (mm >= white) | (d >= 0.85 * (white - bl))
    q = d / (e * sc)
    y = q[:-1, :-1] + q[1:, :-1] + q[:-1, 1:] + q[1:, 1:]
    dsum = d[:-1, :-1] + d[1:, :-1] + d[:-1, 1:] + d[1:, 1:]
    nbad = bad[:-1, :-1] | bad[1:, :-1] | bad[:-1, 1:] | bad[1:, 1:]
    ok = ~nbad & (dsum > 10.0 * read_sd)
    got_y, got_ok = np.empty((h - 1, w - 1)), np.empty((h - 1, w - 1), bool)
    box_image(m, e, black, white, scale, read_sd, got_y, got_ok)
    _close(got_y, y)
    assert np.array_equal(got_ok, ok) and 0 < ok.sum() < ok.size


@pytest.mark.parametrize("resampled", [False, True])
def test_ghost_z2_is_the_numpy_test(resampled):
    mj, black_j, white = _mosaic((16, 13), seed=4)
    mr, black_r, _ = _mosaic((16, 13), seed=5)
    t_j, t_r, g_j, s2_j, g_r, s2_r = 4.0, 1.0, 0.3, 9.0, 0.3, 9.5
    f_j, f_r = np.array([[1.3, 1.1], [1.2, 0.9]]), np.ones((2, 2))
    cs, thr = 3.0, 2.5
    err = 0.1 if resampled else 0.0
    h, w = mj.shape
    tested = np.random.default_rng(6).random((h, w)) < 0.5 if resampled else np.empty((0, 0), bool)

    def plane(a22):
        return np.tile(a22, ((h + 1) // 2, (w + 1) // 2))[:h, :w]

    d_j, d_r = mj.astype(np.float64) - plane(black_j), mr.astype(np.float64) - plane(black_r)
    sat_j, sat_r = mj >= white, mr >= white
    x_r = np.maximum(d_r / t_r, 0.0)
    v_r = (g_r * x_r * t_r + s2_r) * plane(f_r)
    v_j = g_j * x_r * t_j + s2_j
    z2 = (d_j / t_j - d_r / t_r) ** 2 / (v_j * plane(f_j) / t_j ** 2 + v_r / t_r ** 2 + (err * x_r) ** 2)
    below_j = x_r * t_j < white - plane(black_j) - cs * np.sqrt(v_j)
    x_j = np.maximum(d_j / t_j, 0.0)
    below_r = x_j * t_r < (white - plane(black_r)) - cs * np.sqrt(g_r * x_j * t_r + s2_r)
    if resampled:
        z2 = np.where(tested, z2, 0.0)
    z2 = np.where(sat_j & sat_r, 0.0, z2)
    z2 = np.where(sat_j & ~sat_r, np.where(below_j, 4.0 * thr, 0.0), z2)
    z2 = np.where(~sat_j & sat_r, np.where(below_r, 4.0 * thr, 0.0), z2)
    got = np.empty((h, w))
    ghost_z2(mj, mr, black_j, black_r, white, white, t_j, t_r, g_j, s2_j, g_r, s2_r, f_j, f_r, cs, 4.0 * thr,
             err, tested, got)
    _close(got, z2)
    assert np.any(got == 4.0 * thr) and np.any((got > 0) & (got != 4.0 * thr))


def test_resampling_at_a_whole_even_shift_is_the_mosaic():
    """The compiled filters through resample_mosaic / resample_rgb: at shift (0, 0) a frame's own
    colour is its photosite exactly and its support is the photosite (Malvar's centre tap)."""
    m, black, white = _mosaic((20, 16), seed=7)
    codes, valid, _ = resample_mosaic(m, (0, 0), black, white, "RGGB")
    unsat = m < white
    assert np.array_equal(codes[unsat], m.astype(np.float64)[unsat])
    vals, state, _ = resample_rgb(m, (0.0, 0.0), black, white, "RGGB")
    h, w = m.shape
    bl = np.tile(black, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    own = vals[0, 0::2, 0::2]                                       # red at the red photosites
    _close(own[state[0, 0::2, 0::2] == 1], (m.astype(np.float64) - bl)[0::2, 0::2][state[0, 0::2, 0::2] == 1])


@pytest.mark.parametrize("ny, nx", [(3, 3), (4, 4), (5, 7), (6, 1)])
def test_correlate_nearest_is_scipy_correlate1d(ny, nx):
    from scipy.ndimage import correlate1d

    from derender.raw.register_kernels import correlate_nearest

    rng = np.random.default_rng(ny * 10 + nx)
    img = rng.uniform(0, 5, size=(13, 11))
    ty, tx = rng.uniform(0.1, 1, size=ny), rng.uniform(0.1, 1, size=nx)
    want = correlate1d(correlate1d(img, ty, axis=0, mode="nearest"), tx, axis=1, mode="nearest")
    got = np.empty_like(img)
    correlate_nearest(img, ty, tx, got)
    _close(got, want)


def test_colour_variance_is_the_einsum_per_phase():
    from derender.raw.register_kernels import colour_variance

    rng = np.random.default_rng(8)
    sd = rng.uniform(0, 2, size=(9, 8, 3))
    q = rng.normal(size=(2, 2, 3, 3, 3))
    want = np.empty((9, 8, 3))
    for a in range(2):
        for b in range(2):
            want[a::2, b::2] = np.einsum("ocd,yxc,yxd->yxo", q[a, b], sd[a::2, b::2], sd[a::2, b::2])
    got = np.empty((9, 8, 3), np.float32)
    colour_variance(sd, q, got)
    assert np.all(np.abs(got - want) <= 1e-6 * np.maximum(np.abs(want), 1.0))
