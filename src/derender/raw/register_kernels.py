"""Compiled loops (numba) of sub-photosite RAW registration and its ghost test (:mod:`derender.raw.register`).

At 1536 x 1024 and 7 frames, ``--align translation --deghost`` on a handheld RAW bracket spent
most of its time in whole-array NumPy chains (``benchmarks/bench_raw.py --motion-speed``,
docs/results-raw.md): the resampling filters of a shifted mosaic, the 2x2-window sums and their
Keys interpolation, and the ghost test's per-photosite ``z^2``. Each is one compiled pass here,
in the order of the NumPy formula it replaces (the same sums in the same order, so its result
is the same to rounding; ``tests/raw/test_register_kernels.py`` checks them against NumPy), no
threads, deterministic:

* :func:`filter_phase` -- one CFA phase of a resampling filter ``C`` (:func:`derender.raw.register.resample_rgb`):
  ``out(i, k) = sum_uv C[u, v] d(r0 + 2i + u, c0 + 2k + v)`` and the count of saturated taps,
  read straight from the mosaic (``d`` the value above its phase's black, borders mirrored
  within each CFA phase by :func:`mirror_cfa`, :data:`PAD` photosites);
* :func:`window_sums` -- the sliding 2x2 sums of ``v / scale`` (per CFA phase) and of the
  saturation flags, the last row and column repeated (:func:`derender.raw.window_ghost_test.shifted_box`);
* :func:`separable_taps` -- ``out(i, k) = sum_n wx[n] sum_m wy[m] plane(i + oy + m - 1, k + ox + n - 1)``,
  rows first, over the taps whose weight is not zero (Keys' interpolation at a shift);
* :func:`box_image` -- the registration's exposure-normalised 2x2-window sums and where they are
  well exposed (:func:`derender.raw.register.refine_shift`);
* :func:`ghost_z2` -- the ghost test's ``z^2`` of a frame against the reference per photosite,
  censored samples by the level's rule (:func:`derender.hdr.raw.merge_raw`'s ghost removal);
* :func:`correlate_nearest` -- a separable correlation with the border repeated (the ghost
  test's window means; ``scipy.ndimage.correlate1d`` pairs symmetric taps, so the last bit may differ);
* :func:`colour_variance` -- the output colours' variance through the matrix, per CFA phase's
  correlation of the merged colours.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["PAD", "mirror_cfa", "filter_phase", "window_sums", "separable_taps", "box_image", "ghost_z2", "correlate_nearest",
           "colour_variance"]

#: Photosites mirrored beyond each edge by :func:`filter_phase` (within each CFA phase: :func:`mirror_cfa`).
PAD = 2


@njit(inline="always")
def mirror_cfa(i, n):  # pragma: no cover - compiled
    """The photosite read for index ``i`` of an axis of ``n`` photosites, mirrored within its CFA
    phase (each phase's samples ``numpy.pad(mode="symmetric")``-ed: index -1 reads 1, -2 reads 0,
    -3 reads 3; for even ``n``, ``n`` reads ``n - 2`` and ``n + 1`` reads ``n - 1``), so a mirrored
    photosite has the colour of the one it stands for. Mirroring the mosaic itself (-1 reads 0)
    gives a border row the other row's colours: on handheld brackets the frames' border rows,
    shifted into the reference's frame, were 11-13x the still twin's error there (seed 0, measured)."""
    if 0 <= i < n:
        return i
    p = i & 1
    q = i >> 1
    m = (n - p + 1) // 2
    if q < 0:
        q = -q - 1
    elif q >= m:
        q = 2 * m - 1 - q
    return 2 * q + p


@njit(cache=True, nogil=True)
def filter_phase(mosaic, black, white, ker, r0, c0, vals, nsat):  # pragma: no cover - compiled
    """``vals[i, k] = sum_uv ker[u, v] d(r0 + 2i + u, c0 + 2k + v)`` over the non-zero taps, in
    row-major tap order, and ``nsat[i, k]`` the number of those taps whose photosite is
    saturated (``mosaic >= white``); coordinates are of the mosaic padded by :data:`PAD`
    (mirrored within each CFA phase, :func:`mirror_cfa`), ``d = mosaic - black[y % 2, x % 2]``. Fills ``vals`` and ``nsat`` (float64)."""
    h, w = mosaic.shape
    kh, kw = ker.shape
    ni, nk = vals.shape
    nt = 0
    for u in range(kh):
        for t in range(kw):
            if ker[u, t] != 0.0:
                nt += 1
    tu = np.empty(nt, np.int64)
    tv = np.empty(nt, np.int64)
    tc = np.empty(nt)
    n = 0
    for u in range(kh):
        for t in range(kw):
            if ker[u, t] != 0.0:
                tu[n] = u
                tv[n] = t
                tc[n] = ker[u, t]
                n += 1
    xs = np.empty((nk, nt), np.int64)
    for k in range(nk):
        for n in range(nt):
            xs[k, n] = mirror_cfa(c0 + 2 * k + tv[n] - PAD, w)
    ys = np.empty(nt, np.int64)
    for i in range(ni):
        for n in range(nt):
            ys[n] = mirror_cfa(r0 + 2 * i + tu[n] - PAD, h)
        for k in range(nk):
            v = 0.0
            s = 0.0
            for n in range(nt):
                y = ys[n]
                x = xs[k, n]
                m = mosaic[y, x]
                v += tc[n] * (np.float64(m) - black[y & 1, x & 1])
                if m >= white:
                    s += 1.0
            vals[i, k] = v
            nsat[i, k] = s


@njit(cache=True, nogil=True, error_model="numpy")
def window_sums(values, saturated, scale, box, sbox):  # pragma: no cover - compiled
    """``box[y, x]`` the sum of ``values / scale[phase]`` over the photosites ``(y, x)``,
    ``(y + 1, x)``, ``(y, x + 1)``, ``(y + 1, x + 1)`` (in that order; beyond the last row or
    column the last is repeated) and ``sbox`` the number of them ``saturated``."""
    h, w = values.shape
    for y in range(h):
        y1 = min(y + 1, h - 1)
        for x in range(w):
            x1 = min(x + 1, w - 1)
            a = values[y, x] / scale[y & 1, x & 1]
            b = values[y1, x] / scale[y1 & 1, x & 1]
            c = values[y, x1] / scale[y & 1, x1 & 1]
            d = values[y1, x1] / scale[y1 & 1, x1 & 1]
            box[y, x] = a + b + c + d
            sbox[y, x] = (np.float64(saturated[y, x]) + np.float64(saturated[y1, x])
                          + np.float64(saturated[y, x1]) + np.float64(saturated[y1, x1]))


@njit(cache=True, nogil=True)
def separable_taps(plane, oy, ox, wy, wx, i0, k0, out):  # pragma: no cover - compiled
    """``out[i - i0, k - k0] = sum_n wx[n] r(i, k + ox + n - 1)``, ``r(i, x) = sum_m wy[m]
    plane[i + oy + m - 1, x]``, the sums over the taps ``m``, ``n`` (0-3) whose weight is not
    zero, in order (rows first, as :func:`derender.raw.window_ghost_test.shifted_box` did in NumPy)."""
    ni, nk = out.shape
    w = plane.shape[1]
    buf = np.empty(w)
    for i in range(ni):
        for x in range(w):
            r = 0.0
            for m in range(4):
                if wy[m] != 0.0:
                    r += wy[m] * plane[i0 + i + oy + m - 1, x]
            buf[x] = r
        for k in range(nk):
            v = 0.0
            for n in range(4):
                if wx[n] != 0.0:
                    v += wx[n] * buf[k0 + k + ox + n - 1]
            out[i, k] = v


@njit(cache=True, nogil=True, error_model="numpy")
def box_image(mosaic, e, black, white, scale, read_sd, y, ok):  # pragma: no cover - compiled
    """The sliding 2x2 sum ``y`` ((H - 1, W - 1)) of ``d / (e scale[phase])``, ``d`` the value above
    black, and ``ok`` where its four photosites are below ``white`` and below 85 % of their
    phase's ``white - black`` and the sum of their ``d`` exceeds ``10 read_sd``."""
    h, w = mosaic.shape
    for r in range(h - 1):
        for c in range(w - 1):
            q = 0.0
            ds = 0.0
            bad = False
            for t in range(4):
                yy = r + (t & 1)
                xx = c + (t >> 1)
                m = np.float64(mosaic[yy, xx])
                bl = black[yy & 1, xx & 1]
                d = m - bl
                if m >= white or d >= 0.85 * (white - bl):
                    bad = True
                q += d / (e * scale[yy & 1, xx & 1])
                ds += d
            y[r, c] = q
            ok[r, c] = (not bad) and ds > 10.0 * read_sd


@njit(cache=True, nogil=True, error_model="numpy")
def ghost_z2(mosaic_j, mosaic_r, black_j, black_r, white_j, white_r, t_j, t_r, g_j, s2_j, g_r, s2_r,
             factor_j, factor_r, censor_sigma, censored_z2, resample_error, tested, out):  # pragma: no cover - compiled
    """Per photosite, the ghost test's ``z^2`` of frame ``j`` against the reference ``r``:
    ``(d_j / t_j - d_r / t_r)^2 / (V_j f_j / t_j^2 + V_r / t_r^2 + (resample_error x_r)^2)``,
    ``x_r = max(d_r / t_r, 0)``, ``V_j = g_j x_r t_j + s2_j``, ``V_r = (g_r x_r t_r + s2_r) f_r``
    (``f`` the variance factor per CFA phase); where a sample is saturated (``>= white``): 0 if
    both are, else ``censored_z2`` where the other frame's value lies more than ``censor_sigma``
    sigma below the saturated frame's level, else 0. ``tested`` (H, W) bool or an empty array
    (everywhere): where neither is saturated and ``tested`` is False, 0."""
    h, w = out.shape
    every = tested.size == 0
    tj2 = t_j ** 2
    tr2 = t_r ** 2
    re2 = resample_error
    for y in range(h):
        for x in range(w):
            a = y & 1
            b = x & 1
            mj = np.float64(mosaic_j[y, x])
            mr = np.float64(mosaic_r[y, x])
            d_j = mj - black_j[a, b]
            d_r = mr - black_r[a, b]
            sat_j = mj >= white_j
            sat_r = mr >= white_r
            x_r = max(d_r / t_r, 0.0)
            v_j = g_j * x_r * t_j + s2_j
            if sat_j and sat_r:
                z = 0.0
            elif sat_j:
                below_j = x_r * t_j < white_j - black_j[a, b] - censor_sigma * math.sqrt(v_j)
                z = censored_z2 if below_j else 0.0
            elif sat_r:
                x_j = max(d_j / t_j, 0.0)
                below_r = x_j * t_r < (white_r - black_r[a, b]) - censor_sigma * math.sqrt(g_r * x_j * t_r + s2_r)
                z = censored_z2 if below_r else 0.0
            elif every or tested[y, x]:
                v_r = (g_r * x_r * t_r + s2_r) * factor_r[a, b]
                diff = d_j / t_j - d_r / t_r
                den = v_j * factor_j[a, b] / tj2 + v_r / tr2
                if re2 != 0.0:
                    den = den + (re2 * x_r) ** 2
                z = diff ** 2 / den
            else:
                z = 0.0
            out[y, x] = z


@njit(cache=True, nogil=True)
def correlate_nearest(img, ty, tx, out):  # pragma: no cover - compiled
    """``scipy.ndimage.correlate1d`` along rows (``ty``) then columns (``tx``), ``mode="nearest"``,
    origin 0 (tap ``k`` at offset ``k - len // 2``): ``out`` (the shape of ``img``). The sums are
    in tap order, so they may differ from scipy's in the last bit (scipy pairs symmetric taps)."""
    h, w = img.shape
    ny, nx = ty.shape[0], tx.shape[0]
    cy, cx = ny // 2, nx // 2
    tmp = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            v = 0.0
            for m in range(ny):
                yy = min(max(y + m - cy, 0), h - 1)
                v += ty[m] * img[yy, x]
            tmp[y, x] = v
    for y in range(h):
        for x in range(w):
            v = 0.0
            for n in range(nx):
                xx = min(max(x + n - cx, 0), w - 1)
                v += tx[n] * tmp[y, xx]
            out[y, x] = v


@njit(cache=True, nogil=True)
def colour_variance(sd, q, out):  # pragma: no cover - compiled
    """``out[y, x, o] = sum_cd q[y % 2, x % 2, o, c, d] sd[y, x, c] sd[y, x, d]`` (float32 out):
    the variance of an output colour through the matrix from the merged colours' sigmas and their
    correlation per CFA phase (:func:`derender.raw.register.raw_merge_shifted`)."""
    h, w, nc = sd.shape
    no = out.shape[2]
    for y in range(h):
        for x in range(w):
            a = y & 1
            b = x & 1
            for o in range(no):
                v = 0.0
                for c in range(nc):
                    for d in range(nc):
                        v += q[a, b, o, c, d] * sd[y, x, c] * sd[y, x, d]
                out[y, x, o] = v
