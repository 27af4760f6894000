"""Adaptive homogeneity-directed demosaicing (AHD; Hirakawa & Parks 2005), compiled, with its variance.

Hirakawa & Parks, "Adaptive homogeneity-directed demosaicing algorithm", IEEE Trans. Image
Processing 14(3), 2005, as dcraw's and LibRaw's ``ahd_interpolate`` compute it (the steps
below; borders mirrored, which keeps the CFA phase, where dcraw fills a 5-pixel frame by a
bilinear average). On a white-balanced Bayer mosaic ``x``:

1. **Green in two directions** (Sec. III; dcraw's filter): at a red or blue photosite ``(i, j)``

       G_H = (2 (x[i, j-1] + x[i, j] + x[i, j+1]) - x[i, j-2] - x[i, j+2]) / 4,

   ``G_V`` the same down the column, each clamped to the interval of its two green neighbours
   (``G_H`` between ``x[i, j-1]`` and ``x[i, j+1]``); at a green photosite ``G = x``.
2. **Red and blue from colour differences**, within each direction ``d`` (its greens ``G_d``):
   at a green photosite the colour of its row is ``G + (K_l + K_r - G_d,l - G_d,r) / 2`` from its
   two row neighbours, the colour of its column the same from its column neighbours; at a red
   (blue) photosite the blue (red) is ``G_d + sum_diag (K - G_d) / 4`` over its four diagonal
   neighbours. This gives two full images ``rgb_H`` and ``rgb_V``.
3. **CIELab** of each image (Sec. IV-A): ``XYZ = A s rgb`` with ``A`` linear sRGB to XYZ divided
   by the D65 white (so ``rgb = (1, 1, 1)`` is ``XYZ = (1, 1, 1)``; dcraw's ``xyz_rgb /
   d65_white`` with its camera-to-sRGB matrix, which is the identity on the white-balanced
   mosaic here) and ``L = 116 f(Y) - 16``, ``a = 500 (f(X) - f(Y))``, ``b = 200 (f(Y) - f(Z))``,
   ``f(t) = t^(1/3)`` above 0.008856, else ``7.787 t + 16 / 116``. ``s`` puts the mosaic's
   brightest photosites (99.9th percentile of a grid of them) at 1, where dcraw's white level is.
4. **Homogeneity** (Sec. IV-B, eq. (19)-(21) with dcraw's adaptive thresholds): at each pixel
   the luminance distances ``dL_d,n = |L_d(p) - L_d(n)|`` and colour distances ``dC_d,n = (a_d(p)
   - a_d(n))^2 + (b_d(p) - b_d(n))^2`` to its four neighbours ``n``; ``eps_L = min(max(dL_H,left,
   dL_H,right), max(dL_V,up, dL_V,down))``, ``eps_C`` the same of ``dC``; ``H_d(p)`` counts the
   neighbours with ``dL_d,n <= eps_L`` and ``dC_d,n <= eps_C``.
5. **Direction per pixel**: ``h_d`` = the sum of ``H_d`` over the 3x3 around it; the output is
   ``rgb_H`` where ``h_H > h_V``, ``rgb_V`` where ``h_V > h_H``, their mean where equal.

**Variance.** Once the direction of every pixel (and which green estimates were clamped) is
fixed, each output is a linear combination of photosites within 3 of it: ``out_o = sum_p
(sum_c M_oc K_c(p)) x_p`` with ``K_c`` the weights of ``rgb_H``, ``rgb_V`` or their mean and
``M`` the output matrix, so for independent photosites of variance ``v_p``

    Var[out_o] = sum_p (sum_c M_oc K_c(p))^2 v_p                       (given the directions),

exact (:func:`ahd_rows` builds ``K`` per pixel). The direction is chosen from the noisy
photosites; where the noise may have chosen the other one the output moves by ``Delta_o =
out_H,o - out_V,o`` (half of it from or to a tie). As for Menon's demosaic
(:func:`derender.raw.menon.menon_rows`) that adds ``P(flip) Delta_o^2``, with ``P(flip) =
Phi(-z)`` and ``z^2 = sum_o Delta_o^2 / sum_o Var[Delta_o]`` (``Var[Delta_o] = sum_p (sum_c
M_oc (K_H,c(p) - K_V,c(p)))^2 v_p``): the chance that noise alone makes the two directions'
difference look as it does. Where the two directions agree within their noise the choice is a
coin toss and costs little; where they differ by many sigmas the choice is the signal's.
The clamps of step 1 are taken as they fell.

Kernels (numba, rows in parallel; every pixel independently, so results do not depend on the
thread count): :func:`ahd_greens`, :func:`ahd_homogeneity`, :func:`ahd_rows`. The entry point is
:func:`ahd_demosaic` (an (H, W) mosaic) or :func:`ahd_planes` (the phase planes of the RAW
merge, :func:`derender.raw.optimal.demosaic_compiled` with ``method="ahd"``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from derender.core.colorimetry import LINEAR_SRGB_TO_XYZ
from derender.raw.kernels import mirror_index as _mirror

__all__ = ["LAB_MATRIX", "LAB_KNEE", "AHD_RADIUS", "ahd_greens", "ahd_homogeneity", "ahd_rows", "lab_scale",
           "ahd_demosaic", "ahd_planes"]

#: Linear sRGB to XYZ, each row divided by the D65 white's component (rgb (1, 1, 1) -> XYZ (1, 1, 1)):
#: dcraw's ``xyz_rgb / d65_white`` (step 3 of the module docstring).
LAB_MATRIX = LINEAR_SRGB_TO_XYZ / (LINEAR_SRGB_TO_XYZ @ np.ones(3))[:, None]

#: CIELab's knee: ``f(t) = t^(1/3)`` above it, ``7.787 t + 16/116`` below.
LAB_KNEE = 0.008856

#: The photosites an output combines lie within this many of it (rows and columns).
AHD_RADIUS = 3

#: Rows per band of :func:`ahd_homogeneity` (its CIELab rows are kept for one band at a time).
_BAND = 32


@njit(cache=True, nogil=True)
def _green_estimate(x, y, xx, h, w, vertical):  # pragma: no cover - compiled
    """Step 1 at the red or blue photosite (y, xx): ``(value, state)``, ``state`` 0 for the
    filter, 1 when clamped to the first neighbour (left, up), 2 to the second (right, down)."""
    if vertical:
        a = np.float64(x[_mirror(y - 1, h), xx])
        b = np.float64(x[_mirror(y + 1, h), xx])
        far = np.float64(x[_mirror(y - 2, h), xx]) + x[_mirror(y + 2, h), xx]
    else:
        a = np.float64(x[y, _mirror(xx - 1, w)])
        b = np.float64(x[y, _mirror(xx + 1, w)])
        far = np.float64(x[y, _mirror(xx - 2, w)]) + x[y, _mirror(xx + 2, w)]
    val = 0.5 * (a + x[y, xx] + b) - 0.25 * far
    if a <= b:
        if val < a:
            return a, 1
        if val > b:
            return b, 2
    else:
        if val < b:
            return b, 2
        if val > a:
            return a, 1
    return val, 0


@njit(parallel=True, nogil=True, cache=True)
def ahd_greens(x, chan, gh, gv, state):  # pragma: no cover - compiled
    """Step 1: ``gh``, ``gv`` (H, W) the horizontal and vertical greens of the white-balanced
    mosaic ``x`` (``chan`` (2, 2): the CFA colour of each phase, 0 R, 1 G, 2 B); ``state`` (H, W)
    uint8 their clamps, ``s_H + 4 s_V`` (0 the filter, 1 the first neighbour, 2 the second)."""
    h, w = x.shape
    for row in prange(h):
        y = np.int64(row)                        # prange's index is unsigned (uint64 - int64 is float)
        for xx in range(w):
            if chan[y & 1, xx & 1] == 1:
                gh[y, xx] = x[y, xx]
                gv[y, xx] = x[y, xx]
                state[y, xx] = 0
            else:
                vh, sh = _green_estimate(x, y, xx, h, w, False)
                vv, sv = _green_estimate(x, y, xx, h, w, True)
                gh[y, xx] = vh
                gv[y, xx] = vv
                state[y, xx] = sh + 4 * sv


@njit(cache=True, nogil=True)
def _rgb(x, g, y, xx, h, w, chan, red_row):  # pragma: no cover - compiled
    """Step 2 at (y, xx) in the direction whose greens are ``g``: ``(r, g, b)``."""
    c = chan[y & 1, xx & 1]
    if c == 1:
        gg = np.float64(x[y, xx])
        a = _mirror(xx - 1, w)
        b = _mirror(xx + 1, w)
        along_row = gg + 0.5 * ((np.float64(x[y, a]) + x[y, b]) - (np.float64(g[y, a]) + g[y, b]))
        a = _mirror(y - 1, h)
        b = _mirror(y + 1, h)
        along_col = gg + 0.5 * ((np.float64(x[a, xx]) + x[b, xx]) - (np.float64(g[a, xx]) + g[b, xx]))
        if red_row[y & 1]:
            return along_row, gg, along_col
        return along_col, gg, along_row
    gg = np.float64(g[y, xx])
    s = 0.0
    for dy in (-1, 1):
        yy = _mirror(y + dy, h)
        for dx in (-1, 1):
            x1 = _mirror(xx + dx, w)
            s += np.float64(x[yy, x1]) - g[yy, x1]
    other = gg + 0.25 * s
    own = np.float64(x[y, xx])
    if c == 0:
        return own, gg, other
    return other, gg, own


@njit(cache=True, nogil=True)
def _f(t):  # pragma: no cover - compiled
    """CIELab's ``f``."""
    if t > 0.008856:
        return math.pow(t, 1.0 / 3.0)
    return 7.787 * t + 16.0 / 116.0


@njit(cache=True, nogil=True)
def _lab(r, g, b, a, out, k, i, j):  # pragma: no cover - compiled
    """CIELab of ``(r, g, b)`` through ``a`` (3, 3; the scale folded in) into ``out[k, :, i, j]``."""
    fx = _f(a[0, 0] * r + a[0, 1] * g + a[0, 2] * b)
    fy = _f(a[1, 0] * r + a[1, 1] * g + a[1, 2] * b)
    fz = _f(a[2, 0] * r + a[2, 1] * g + a[2, 2] * b)
    out[k, 0, i, j] = 116.0 * fy - 16.0
    out[k, 1, i, j] = 500.0 * (fx - fy)
    out[k, 2, i, j] = 200.0 * (fy - fz)


@njit(parallel=True, nogil=True, cache=True)
def ahd_homogeneity(x, gh, gv, chan, red_row, lab_matrix, homo):  # pragma: no cover - compiled
    """Steps 2-4: ``homo`` (2, H, W) uint8, the homogeneity ``H_d`` of each direction (0
    horizontal, 1 vertical) at every pixel, from the CIELab (``lab_matrix``: ``A s``) of the two
    images built from ``gh`` and ``gv``; bands of rows in parallel, each keeping its CIELab rows
    (and the one above and below it)."""
    h, w = x.shape
    nb = (h + _BAND - 1) // _BAND
    for band in prange(nb):
        r0 = np.int64(band) * _BAND
        r1 = min(r0 + _BAND, h)
        lab = np.empty((2, 3, r1 - r0 + 2, w), np.float32)
        for i in range(r1 - r0 + 2):
            y = _mirror(r0 - 1 + i, h)
            for xx in range(w):
                r, g, b = _rgb(x, gh, y, xx, h, w, chan, red_row)
                _lab(r, g, b, lab_matrix, lab, 0, i, xx)
                r, g, b = _rgb(x, gv, y, xx, h, w, chan, red_row)
                _lab(r, g, b, lab_matrix, lab, 1, i, xx)
        ld = np.empty((2, 4))
        cd = np.empty((2, 4))
        for i in range(1, r1 - r0 + 1):
            y = r0 - 1 + i
            for xx in range(w):
                xl = _mirror(xx - 1, w)
                xr = _mirror(xx + 1, w)
                for d in range(2):
                    l0 = np.float64(lab[d, 0, i, xx])
                    a0 = np.float64(lab[d, 1, i, xx])
                    b0 = np.float64(lab[d, 2, i, xx])
                    for n in range(4):
                        if n == 0:
                            ii, jj = i, xl
                        elif n == 1:
                            ii, jj = i, xr
                        elif n == 2:
                            ii, jj = i - 1, xx
                        else:
                            ii, jj = i + 1, xx
                        ld[d, n] = abs(l0 - lab[d, 0, ii, jj])
                        cd[d, n] = (a0 - lab[d, 1, ii, jj]) ** 2 + (b0 - lab[d, 2, ii, jj]) ** 2
                eps_l = min(max(ld[0, 0], ld[0, 1]), max(ld[1, 2], ld[1, 3]))
                eps_c = min(max(cd[0, 0], cd[0, 1]), max(cd[1, 2], cd[1, 3]))
                for d in range(2):
                    k = 0
                    for n in range(4):
                        if ld[d, n] <= eps_l and cd[d, n] <= eps_c:
                            k += 1
                    homo[d, y, xx] = k


@njit(cache=True, nogil=True)
def _tap(k, c, y, xx, cy, cx, wt):  # pragma: no cover - compiled
    """Add ``wt`` to channel ``c``'s weight of photosite (y, xx) (mirrored) in the 7x7 window at (cy, cx)."""
    k[c, y - cy + 3, xx - cx + 3] += wt


@njit(cache=True, nogil=True)
def _green_taps(k, c, clamps, y, xx, cy, cx, h, w, chan, vertical, wt):  # pragma: no cover - compiled
    """The weights of the green at (y, xx) (mirrored) in direction ``vertical``, times ``wt``
    (``clamps``: the ``state`` of :func:`ahd_greens`)."""
    if chan[y & 1, xx & 1] == 1:
        _tap(k, c, y, xx, cy, cx, wt)
        return
    state = (clamps[y, xx] >> 2) if vertical else (clamps[y, xx] & 3)
    if vertical:
        a, b = _mirror(y - 1, h), _mirror(y + 1, h)
        if state == 1:
            _tap(k, c, a, xx, cy, cx, wt)
        elif state == 2:
            _tap(k, c, b, xx, cy, cx, wt)
        else:
            _tap(k, c, y, xx, cy, cx, 0.5 * wt)
            _tap(k, c, a, xx, cy, cx, 0.5 * wt)
            _tap(k, c, b, xx, cy, cx, 0.5 * wt)
            _tap(k, c, _mirror(y - 2, h), xx, cy, cx, -0.25 * wt)
            _tap(k, c, _mirror(y + 2, h), xx, cy, cx, -0.25 * wt)
    else:
        a, b = _mirror(xx - 1, w), _mirror(xx + 1, w)
        if state == 1:
            _tap(k, c, y, a, cy, cx, wt)
        elif state == 2:
            _tap(k, c, y, b, cy, cx, wt)
        else:
            _tap(k, c, y, xx, cy, cx, 0.5 * wt)
            _tap(k, c, y, a, cy, cx, 0.5 * wt)
            _tap(k, c, y, b, cy, cx, 0.5 * wt)
            _tap(k, c, y, _mirror(xx - 2, w), cy, cx, -0.25 * wt)
            _tap(k, c, y, _mirror(xx + 2, w), cy, cx, -0.25 * wt)


@njit(cache=True, nogil=True)
def _weights(k, clamps, cy, cx, h, w, chan, red_row, vertical):  # pragma: no cover - compiled
    """``K_c(p)`` of step 2 at (cy, cx) in one direction, into the zeroed (3, 7, 7) ``k``
    (``clamps``: the ``state`` of :func:`ahd_greens`)."""
    c = chan[cy & 1, cx & 1]
    if c == 1:
        _tap(k, 1, cy, cx, cy, cx, 1.0)
        for side in range(2):                    # side 0: along the row; 1: along the column
            o = (0 if red_row[cy & 1] else 2) if side == 0 else (2 if red_row[cy & 1] else 0)
            _tap(k, o, cy, cx, cy, cx, 1.0)
            for s in (-1, 1):
                yy = cy if side == 0 else _mirror(cy + s, h)
                x1 = _mirror(cx + s, w) if side == 0 else cx
                _tap(k, o, yy, x1, cy, cx, 0.5)
                _green_taps(k, o, clamps, yy, x1, cy, cx, h, w, chan, vertical, -0.5)
        return
    _tap(k, c, cy, cx, cy, cx, 1.0)
    _green_taps(k, 1, clamps, cy, cx, cy, cx, h, w, chan, vertical, 1.0)
    o = 2 - c
    _green_taps(k, o, clamps, cy, cx, cy, cx, h, w, chan, vertical, 1.0)
    for dy in (-1, 1):
        yy = _mirror(cy + dy, h)
        for dx in (-1, 1):
            x1 = _mirror(cx + dx, w)
            _tap(k, o, yy, x1, cy, cx, 0.25)
            _green_taps(k, o, clamps, yy, x1, cy, cx, h, w, chan, vertical, -0.25)


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def ahd_rows(x, var, gh, gv, clamps, homo, chan, red_row, matrix, clip_negative, do_var, out, var_out, choice,
             direction_term=True):  # pragma: no cover - compiled
    """Step 5, the output matrix and the variance (module docstring) in one pass.

    ``x`` (H, W) the white-balanced mosaic (``var`` its variance, photosites independent),
    ``gh``, ``gv`` and their ``clamps`` from :func:`ahd_greens`, ``homo`` from :func:`ahd_homogeneity`; ``matrix``
    (3, 3). Writes ``out`` (H, W, 3) float32 (negatives 0 with ``clip_negative``), with
    ``do_var`` ``var_out`` (H, W, 3) float32, and ``choice`` (H, W) uint8: 0 horizontal, 1
    vertical, 2 the mean of both. ``direction_term=False`` leaves out ``P(flip) Delta^2`` (for
    comparison)."""
    h, w = x.shape
    for row in prange(h):
        cy = np.int64(row)
        kh = np.zeros((3, 7, 7))
        kv = np.zeros((3, 7, 7))
        for cx in range(w):
            sh = 0
            sv = 0
            for dy in range(-1, 2):
                yy = _mirror(cy + dy, h)
                for dx in range(-1, 2):
                    x1 = _mirror(cx + dx, w)
                    sh += homo[0, yy, x1]
                    sv += homo[1, yy, x1]
            pick = 0 if sh > sv else (1 if sv > sh else 2)
            choice[cy, cx] = pick
            rh, gh_, bh = _rgb(x, gh, cy, cx, h, w, chan, red_row)
            rv, gv_, bv = _rgb(x, gv, cy, cx, h, w, chan, red_row)
            wh = 1.0 if pick == 0 else (0.0 if pick == 1 else 0.5)
            wv = 1.0 - wh
            r = wh * rh + wv * rv
            g = wh * gh_ + wv * gv_
            b = wh * bh + wv * bv
            for o in range(3):
                v = matrix[o, 0] * r + matrix[o, 1] * g + matrix[o, 2] * b
                if not math.isfinite(v) or (clip_negative and v < 0.0):
                    v = 0.0
                out[cy, cx, o] = v
            if not do_var:
                continue
            _weights(kh, clamps, cy, cx, h, w, chan, red_row, False)
            _weights(kv, clamps, cy, cx, h, w, chan, red_row, True)
            v0 = 0.0
            v1 = 0.0
            v2 = 0.0
            d0 = 0.0
            d1 = 0.0
            d2 = 0.0
            for i in range(7):
                yy = cy + i - 3
                if yy < 0 or yy >= h:
                    continue
                for j in range(0 if 2 <= i <= 4 else 2, 7 if 2 <= i <= 4 else 5):   # the support: a cross
                    xj = cx + j - 3
                    if xj < 0 or xj >= w:
                        continue
                    ar = kh[0, i, j]
                    ag = kh[1, i, j]
                    ab = kh[2, i, j]
                    br = kv[0, i, j]
                    bg = kv[1, i, j]
                    bb = kv[2, i, j]
                    if ar == 0.0 and ag == 0.0 and ab == 0.0 and br == 0.0 and bg == 0.0 and bb == 0.0:
                        continue
                    kh[0, i, j] = 0.0
                    kh[1, i, j] = 0.0
                    kh[2, i, j] = 0.0
                    kv[0, i, j] = 0.0
                    kv[1, i, j] = 0.0
                    kv[2, i, j] = 0.0
                    vp = np.float64(var[yy, xj])
                    cr = wh * ar + wv * br
                    cg = wh * ag + wv * bg
                    cb = wh * ab + wv * bb
                    dr = ar - br
                    dg = ag - bg
                    db = ab - bb
                    t = matrix[0, 0] * cr + matrix[0, 1] * cg + matrix[0, 2] * cb
                    v0 += t * t * vp
                    t = matrix[1, 0] * cr + matrix[1, 1] * cg + matrix[1, 2] * cb
                    v1 += t * t * vp
                    t = matrix[2, 0] * cr + matrix[2, 1] * cg + matrix[2, 2] * cb
                    v2 += t * t * vp
                    t = matrix[0, 0] * dr + matrix[0, 1] * dg + matrix[0, 2] * db
                    d0 += t * t * vp
                    t = matrix[1, 0] * dr + matrix[1, 1] * dg + matrix[1, 2] * db
                    d1 += t * t * vp
                    t = matrix[2, 0] * dr + matrix[2, 1] * dg + matrix[2, 2] * db
                    d2 += t * t * vp
            # the direction term: Delta = out_H - out_V, P(flip) = Phi(-z)
            dr = rh - rv
            dg = gh_ - gv_
            db = bh - bv
            e0 = matrix[0, 0] * dr + matrix[0, 1] * dg + matrix[0, 2] * db
            e1 = matrix[1, 0] * dr + matrix[1, 1] * dg + matrix[1, 2] * db
            e2 = matrix[2, 0] * dr + matrix[2, 1] * dg + matrix[2, 2] * db
            dd = d0 + d1 + d2
            ee = e0 * e0 + e1 * e1 + e2 * e2
            if direction_term and dd > 0.0 and ee > 0.0:
                p = 0.5 * math.erfc(math.sqrt(ee / dd) * 0.7071067811865476)
                f = 0.25 if pick == 2 else 1.0           # from or to the mean: half of Delta
                v0 += p * f * e0 * e0
                v1 += p * f * e1 * e1
                v2 += p * f * e2 * e2
            var_out[cy, cx, 0] = v0 if math.isfinite(v0) else 0.0
            var_out[cy, cx, 1] = v1 if math.isfinite(v1) else 0.0
            var_out[cy, cx, 2] = v2 if math.isfinite(v2) else 0.0


def _channels(pattern: str) -> tuple[np.ndarray, np.ndarray]:
    """``chan`` (2, 2), the colour of each CFA phase (0 R, 1 G, 2 B), and ``red_row`` (2,)."""
    p = pattern.upper()
    lut = {"R": 0, "G": 1, "B": 2}
    chan = np.array([[lut[p[0]], lut[p[1]]], [lut[p[2]], lut[p[3]]]], np.int64)
    return chan, np.array([np.any(chan[0] == 0), np.any(chan[1] == 0)])


def lab_scale(mosaic: np.ndarray) -> float:
    """The ``s`` of step 3: 1 over the 99.9th percentile of every 3rd photosite in both
    directions (every CFA phase), or 1 where that is not positive and finite."""
    a = np.asarray(mosaic)
    top = float(np.percentile(a[::3, ::3], 99.9)) if a.size else 0.0
    return 1.0 / top if np.isfinite(top) and top > 0 else 1.0


def ahd_demosaic(mosaic: np.ndarray, pattern: str, variance: np.ndarray | None = None,
                 matrix: np.ndarray | None = None, *, scale: float | None = None, clip_negative: bool = False,
                 lab_matrix: np.ndarray | None = None,
                 direction_term: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """AHD (module docstring) of a white-balanced (H, W) Bayer mosaic.

    Parameters
    ----------
    mosaic : (H, W) array
        The white-balanced mosaic (float32 inside).
    pattern : str
        The Bayer pattern, e.g. ``"RGGB"``.
    variance : (H, W) array, optional
        The photosites' variances (independent); then the output's variance is given too.
    matrix : (3, 3) array, optional
        Applied to the demosaiced RGB (identity by default).
    scale : float, optional
        CIELab's ``s`` (step 3); :func:`lab_scale` of the mosaic by default.
    clip_negative : bool
        Set negative outputs to 0.
    lab_matrix : (3, 3) array, optional
        The RGB-to-XYZ matrix of step 3 (default :data:`LAB_MATRIX`).
    direction_term : bool
        Add ``P(flip) Delta^2`` to the variance (module docstring); False for comparison.

    Returns
    -------
    (out, var, choice)
        ``out`` (H, W, 3) float32; ``var`` (H, W, 3) float32 or None; ``choice`` (H, W) uint8
        (0 horizontal, 1 vertical, 2 their mean).

    Examples
    --------
    A flat grey mosaic stays flat:

    >>> import numpy as np
    >>> out, var, _ = ahd_demosaic(np.full((8, 8), 0.5), "RGGB", np.full((8, 8), 1e-4))
    >>> bool(np.allclose(out, 0.5)), bool(np.all(var > 0))
    (True, True)
    """
    x = np.ascontiguousarray(mosaic, np.float32)
    if x.ndim != 2:
        raise ValueError("the mosaic must be 2-D")
    h, w = x.shape
    chan, red_row = _channels(pattern)
    s = lab_scale(x) if scale is None else float(scale)
    lab = np.ascontiguousarray((LAB_MATRIX if lab_matrix is None else np.asarray(lab_matrix, np.float64)) * s)
    m = np.eye(3) if matrix is None else np.ascontiguousarray(matrix, np.float64)
    gh = np.empty((h, w), np.float32)
    gv = np.empty((h, w), np.float32)
    clamps = np.empty((h, w), np.uint8)
    homo = np.empty((2, h, w), np.uint8)
    out = np.empty((h, w, 3), np.float32)
    choice = np.empty((h, w), np.uint8)
    if variance is None:
        v, var_out = x, np.empty((1, 1, 3), np.float32)
    else:
        v = np.ascontiguousarray(variance, np.float32)
        var_out = np.empty((h, w, 3), np.float32)
    from derender.raw.kernels import KERNEL_LOCK

    with KERNEL_LOCK:
        ahd_greens(x, chan, gh, gv, clamps)
        ahd_homogeneity(x, gh, gv, chan, red_row, lab, homo)
        ahd_rows(x, v, gh, gv, clamps, homo, chan, red_row, m, bool(clip_negative), variance is not None, out, var_out,
                 choice, bool(direction_term))
    return out, (var_out if variance is not None else None), choice


def ahd_planes(x: np.ndarray, var: np.ndarray | None, shape: tuple[int, int], pattern: str,
               multipliers: np.ndarray, matrix: np.ndarray,
               clip_negative: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`ahd_demosaic` of the RAW merge's phase planes ``x`` (``var``), (2, 2, ceil(H/2),
    ceil(W/2)) of an (H, W) = ``shape`` mosaic, white-balanced by ``multipliers`` (R, G, B) first
    and put through ``matrix``: ``(radiance, variance)`` (H, W, 3) float32."""
    chan, _ = _channels(pattern)
    mult = np.asarray(multipliers, np.float64)[chan]
    h, w = shape
    xm = np.empty((h, w), np.float32)
    vm = np.empty((h, w), np.float32) if var is not None else None
    for a in range(2):
        for b in range(2):
            sub = xm[a::2, b::2]
            sub[...] = np.asarray(x[a, b, :sub.shape[0], :sub.shape[1]], np.float64) * mult[a, b]
            if vm is not None:
                vs = vm[a::2, b::2]
                vs[...] = np.asarray(var[a, b, :vs.shape[0], :vs.shape[1]], np.float64) * mult[a, b] ** 2
    out, v, _ = ahd_demosaic(xm, pattern, vm, matrix, clip_negative=clip_negative)
    return out, v
