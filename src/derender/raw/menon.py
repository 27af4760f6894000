"""Menon, Andriani & Calvagno (2007): the demosaic and its variance, compiled (numba).

"Demosaicing with directional filtering and a posteriori decision", IEEE TIP 16(1), 132-141
(DDFAPD), without its refining step, as ``colour_demosaicing.demosaicing_CFA_Bayer_Menon2007``
computes it (borders mirrored), on the white-balanced mosaic ``x``:

* green at a red or blue photosite, along its row (H) or column (V), eq. (3):
  ``G_H = (x(-1) + x(+1)) / 2 + x(0) / 2 - (x(-2) + x(+2)) / 4``;
* the direction (Sec. II-A, :func:`menon_directions`): the colour differences ``C_H = x - G_H``,
  ``C_V = x - G_V``, their gradients ``D_H = |C_H(y, x) - C_H(y, x + 2)|`` (``D_V`` down the
  column) summed over the classifier window (:data:`CLASSIFIER`) to ``d_H``, ``d_V``;
  horizontal where ``d_V >= d_H``;
* red and blue at green photosites, eq. (7): ``G + mean(K) - mean(G)`` over the two ``K``
  neighbours (along the row holding ``K``, else the column);
* red at a blue photosite, eq. (8): ``B + mean(R - B)`` over the estimates of eq. (7) at its
  two green neighbours in the direction chosen there (blue at a red photosite alike).

Given the directions every output is a linear combination ``out_o = sum_p W_o(p) x_p`` of
the photosites within 4 of it, ``W_o = sum_c M_oc K_c`` with the colour matrix ``M``; for
independent photosites ``Var[out_o] = sum_p W_o(p)^2 Var[x_p]``. The weights depend only on the
pixel's CFA phase, its own direction and the directions of at most a few red and blue
photosites near it (those whose green, eq. (3), enters eqs. (7)-(8)): a fixed filter bank,
one filter per phase and per pattern of those directions (:func:`weight_table`, built once per
CFA pattern from the per-pixel construction :func:`menon_rows` uses). :func:`menon_table_rows`
looks the filter up at each pixel and applies it to the values and the variances in one pass;
pixels within 4 of the border (mirrored photosites) take the per-pixel construction. The
direction is itself chosen from noisy photosites: at a red or blue photosite the output with
its direction flipped, ``out'``, adds ``P(flip) (out' - out)^2``, ``P(flip) = Phi(-|d_V - d_H| /
sd)``, ``sd = MARGIN_SD * sqrt(mean var over the 3x3 around it)`` (the classifier's noise).

Speed (24 MP, benchmarks/bench_raw.py ``--demosaic-speed 6016x4000``; docs/results-raw.md):
the per-pixel construction took 86 s with the variance; the filter bank 5.3 s of CPU, 4.4x
Malvar's compiled pass (:func:`derender.raw.kernels.demosaic_rows`), 2.9 s without the variance.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit, prange

from derender.raw.kernels import KERNEL_LOCK, finite_value
from derender.raw.kernels import mirror_index as _mirror

__all__ = ["CLASSIFIER", "MARGIN_SD", "RADIUS", "menon_directions", "menon_rows", "weight_table",
           "menon_table_rows", "menon_demosaic"]


#: Menon 2007's direction classifier (``colour_demosaicing``'s kernel ``k``): offsets (dy, dx) and
#: weights of ``scipy.ndimage.convolve(D_H, k)`` (the kernel flipped); ``d_V`` uses them transposed.
CLASSIFIER = np.array([[0, 0, 1, 0, 1], [0, 0, 0, 1, 0], [0, 0, 3, 0, 3], [0, 0, 0, 1, 0], [0, 0, 1, 0, 1]],
                      np.float64)


#: The classifier's noise in units of the photosites' sigma: ``d_V - d_H`` sums 2 x 8 gradients
#: ``|C(x) - C(x + 2)|`` with weights of squares summing to 24 per direction, each gradient a
#: combination of photosites whose squared weights sum to 0.75 (eq. (3)); taken as independent:
#: ``sqrt(2 * 24 * 0.75) = 6``.
MARGIN_SD = 6.0


#: An output combines photosites at most this far away (rows and columns): the filters' half-width.
RADIUS = 4


@njit(inline="always")
def _directional_green(x, y, xx, h, w, horizontal):  # pragma: no cover - compiled
    """Menon 2007 eq. (3): green at a red or blue photosite from its row (``horizontal``) or column."""
    if horizontal:
        return (0.5 * (x[y, _mirror(xx - 1, w)] + x[y, _mirror(xx + 1, w)] + x[y, xx])
                - 0.25 * (x[y, _mirror(xx - 2, w)] + x[y, _mirror(xx + 2, w)]))
    return (0.5 * (x[_mirror(y - 1, h), xx] + x[_mirror(y + 1, h), xx] + x[y, xx])
            - 0.25 * (x[_mirror(y - 2, h), xx] + x[_mirror(y + 2, h), xx]))


@njit(parallel=True, nogil=True, cache=True)
def menon_directions(x, chan, kdy, kdx, kw, direction, margin):  # pragma: no cover - compiled
    """Menon, Andriani & Calvagno (2007) Sec. II-A: the direction of the green interpolation.

    ``x`` (H, W) the white-balanced mosaic, ``chan`` (2, 2) the CFA colour of each phase (0 R,
    1 G, 2 B). At every red and blue photosite the colour differences ``C_H = x - G_H`` and
    ``C_V = x - G_V`` (eq. 3), their gradients ``D_H = |C_H(y, x) - C_H(y, x + 2)|`` (and ``D_V``
    down the column, borders mirrored), summed over the classifier's window (offsets ``kdy``,
    ``kdx``, weights ``kw``; zero outside the image) give ``d_H``, ``d_V``; ``direction`` (H, W)
    uint8 is 1 (horizontal) where ``d_V >= d_H``, else 0 -- as
    ``colour_demosaicing.demosaicing_CFA_Bayer_Menon2007`` decides it; ``margin`` (H, W)
    float32 is ``d_V - d_H`` (0 at green photosites)."""
    h, w = x.shape
    ch = np.zeros((h, w), np.float32)
    cv = np.zeros((h, w), np.float32)
    for y in prange(h):
        inner = 2 <= y < h - 2
        for xx in range(w):
            if chan[y & 1, xx & 1] != 1:
                if inner and 2 <= xx < w - 2:    # no mirrored photosite: the same sums, no index arithmetic
                    ch[y, xx] = x[y, xx] - (0.5 * (x[y, xx - 1] + x[y, xx + 1] + x[y, xx])
                                            - 0.25 * (x[y, xx - 2] + x[y, xx + 2]))
                    cv[y, xx] = x[y, xx] - (0.5 * (x[y - 1, xx] + x[y + 1, xx] + x[y, xx])
                                            - 0.25 * (x[y - 2, xx] + x[y + 2, xx]))
                else:
                    ch[y, xx] = x[y, xx] - _directional_green(x, y, xx, h, w, True)
                    cv[y, xx] = x[y, xx] - _directional_green(x, y, xx, h, w, False)
    for y in prange(h):
        inner = 2 <= y < h - 4
        for xx in range(w):
            if chan[y & 1, xx & 1] == 1:
                direction[y, xx] = 1
                margin[y, xx] = 0.0
                continue
            dh = 0.0
            dv = 0.0
            if inner and 2 <= xx < w - 4:        # every tap inside, none mirrored
                for t in range(kw.shape[0]):
                    yy = y + kdy[t]
                    x1 = xx + kdx[t]
                    dh += kw[t] * abs(np.float64(ch[yy, x1]) - ch[yy, x1 + 2])
                    yy = y + kdx[t]
                    x1 = xx + kdy[t]
                    dv += kw[t] * abs(np.float64(cv[yy, x1]) - cv[yy + 2, x1])
            else:
                for t in range(kw.shape[0]):
                    yy = y + kdy[t]
                    x1 = xx + kdx[t]
                    if 0 <= yy < h and 0 <= x1 < w:
                        dh += kw[t] * abs(np.float64(ch[yy, x1]) - ch[yy, _mirror(x1 + 2, w)])
                    yy = y + kdx[t]
                    x1 = xx + kdy[t]
                    if 0 <= yy < h and 0 <= x1 < w:
                        dv += kw[t] * abs(np.float64(cv[yy, x1]) - cv[_mirror(yy + 2, h), x1])
            direction[y, xx] = 1 if dv >= dh else 0
            margin[y, xx] = dv - dh


@njit(inline="always")
def _tap(g, c, y, x, cy, cx, h, w, wt, touched, tl, nt):  # pragma: no cover - compiled
    """Add ``wt`` to channel ``c``'s weight of photosite (y, x) (mirrored) in the 9x9 window at (cy, cx)."""
    yy = _mirror(y, h)
    xx = _mirror(x, w)
    k = (yy - cy + 4) * 9 + (xx - cx + 4)
    if not touched[k]:
        touched[k] = True
        tl[nt[0]] = k
        nt[0] += 1
    g[c, k] += wt


@njit(cache=True, nogil=True)
def _tap_green(g, c, y, x, cy, cx, h, w, wt, chan, direction, flip, touched, tl, nt):  # pragma: no cover - compiled
    """Green at photosite (y, x): its own value, or eq. (3) in the direction chosen there (the
    other one at the centre (cy, cx) with ``flip``)."""
    yy = _mirror(y, h)
    xx = _mirror(x, w)
    if chan[yy & 1, xx & 1] == 1:
        _tap(g, c, yy, xx, cy, cx, h, w, wt, touched, tl, nt)
        return
    _tap(g, c, yy, xx, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
    horizontal = direction[yy, xx] == 1
    if flip and yy == cy and xx == cx:
        horizontal = not horizontal
    if horizontal:
        _tap(g, c, yy, xx - 1, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap(g, c, yy, xx + 1, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap(g, c, yy, xx - 2, cy, cx, h, w, -0.25 * wt, touched, tl, nt)
        _tap(g, c, yy, xx + 2, cy, cx, h, w, -0.25 * wt, touched, tl, nt)
    else:
        _tap(g, c, yy - 1, xx, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap(g, c, yy + 1, xx, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap(g, c, yy - 2, xx, cy, cx, h, w, -0.25 * wt, touched, tl, nt)
        _tap(g, c, yy + 2, xx, cy, cx, h, w, -0.25 * wt, touched, tl, nt)


@njit(cache=True, nogil=True)
def _tap_at_green(g, c, k, y, x, cy, cx, h, w, wt, chan, red_row, direction, flip, touched, tl,
                  nt):  # pragma: no cover - compiled
    """Colour ``k`` (0 red, 2 blue) at the green photosite (y, x): ``G + mean(K) - mean(G)`` over
    its two ``k`` neighbours (along the row that holds ``k``, else the column; eq. (7))."""
    yy = _mirror(y, h)
    xx = _mirror(x, w)
    _tap(g, c, yy, xx, cy, cx, h, w, wt, touched, tl, nt)
    along_row = red_row[yy & 1] == (k == 0)
    if along_row:
        _tap(g, c, yy, xx - 1, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap(g, c, yy, xx + 1, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap_green(g, c, yy, xx - 1, cy, cx, h, w, -0.5 * wt, chan, direction, flip, touched, tl, nt)
        _tap_green(g, c, yy, xx + 1, cy, cx, h, w, -0.5 * wt, chan, direction, flip, touched, tl, nt)
    else:
        _tap(g, c, yy - 1, xx, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap(g, c, yy + 1, xx, cy, cx, h, w, 0.5 * wt, touched, tl, nt)
        _tap_green(g, c, yy - 1, xx, cy, cx, h, w, -0.5 * wt, chan, direction, flip, touched, tl, nt)
        _tap_green(g, c, yy + 1, xx, cy, cx, h, w, -0.5 * wt, chan, direction, flip, touched, tl, nt)


@njit(cache=True, nogil=True)
def _menon_weights(g, cy, cx, h, w, chan, red_row, direction, flip, touched, tl, nt):  # pragma: no cover - compiled
    """The weights ``K_c(p)`` of the three outputs at (cy, cx) given the directions (the centre's
    flipped with ``flip``), into the 9x9 window ``g`` (3, 81); ``tl[:nt[0]]`` lists the cells set."""
    nt[0] = 0
    own = chan[cy & 1, cx & 1]
    for c in range(3):
        if c == own:
            _tap(g, c, cy, cx, cy, cx, h, w, 1.0, touched, tl, nt)
        elif c == 1:
            _tap_green(g, c, cy, cx, cy, cx, h, w, 1.0, chan, direction, flip, touched, tl, nt)
        elif own == 1:
            _tap_at_green(g, c, c, cy, cx, cy, cx, h, w, 1.0, chan, red_row, direction, flip, touched, tl, nt)
        else:                      # red at blue, blue at red: eq. (8) in the chosen direction
            _tap(g, c, cy, cx, cy, cx, h, w, 1.0, touched, tl, nt)
            horizontal = direction[cy, cx] == 1
            if flip:
                horizontal = not horizontal
            for s in (-1, 1):
                sy = 0 if horizontal else s
                sx = s if horizontal else 0
                _tap_at_green(g, c, c, cy + sy, cx + sx, cy, cx, h, w, 0.5, chan, red_row, direction, flip,
                              touched, tl, nt)
                _tap_at_green(g, c, own, cy + sy, cx + sx, cy, cx, h, w, -0.5, chan, red_row, direction, flip,
                              touched, tl, nt)


@njit(cache=True, nogil=True)
def _apply_weights(g, x, var, cy, cx, matrix, do_var, touched, tl, nt, acc):  # pragma: no cover - compiled
    """``acc[0:3] = sum_p (M K(p)) x_p``, ``acc[3:6] = sum_p (M K(p))^2 var_p``; clears ``g``."""
    for o in range(6):
        acc[o] = 0.0
    for n in range(nt[0]):
        k = tl[n]
        yy = cy - 4 + k // 9
        xx = cx - 4 + k % 9
        val = np.float64(x[yy, xx])
        vv = np.float64(var[yy, xx]) if do_var else 0.0
        for o in range(3):
            wo = matrix[o, 0] * g[0, k] + matrix[o, 1] * g[1, k] + matrix[o, 2] * g[2, k]
            acc[o] += wo * val
            acc[3 + o] += wo * wo * vv
        g[0, k] = 0.0
        g[1, k] = 0.0
        g[2, k] = 0.0
        touched[k] = False




@njit(cache=True, nogil=True, error_model="numpy")
def _pixel_by_weights(x, var, chan, red_row, direction, margin, margin_sd, matrix, clip_negative, do_var, cy,
                      cx, g, touched, tl, nt, acc, alt, out, var_out):  # pragma: no cover - compiled
    """One output pixel of :func:`menon_rows` (its weights built, borders mirrored)."""
    h, w = x.shape
    _menon_weights(g, cy, cx, h, w, chan, red_row, direction, False, touched, tl, nt)
    _apply_weights(g, x, var, cy, cx, matrix, do_var, touched, tl, nt, acc)
    for o in range(3):
        out[cy, cx, o] = finite_value(acc[o], clip_negative)
    if not do_var:
        return
    if chan[cy & 1, cx & 1] != 1:
        p = _flip_probability(var, margin, margin_sd, cy, cx)
        if p > 1e-6:
            _menon_weights(g, cy, cx, h, w, chan, red_row, direction, True, touched, tl, nt)
            _apply_weights(g, x, var, cy, cx, matrix, False, touched, tl, nt, alt)
            for o in range(3):
                acc[3 + o] += p * (alt[o] - acc[o]) ** 2
    for o in range(3):
        var_out[cy, cx, o] = finite_value(acc[3 + o], False)


@njit(inline="always")
def _flip_probability(var, margin, margin_sd, cy, cx):  # pragma: no cover - compiled
    """``Phi(-|margin| / sd)``, ``sd = margin_sd * sqrt(mean var over the 3x3 around (cy, cx))`` (mirrored)."""
    h, w = var.shape
    s = 0.0
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            s += var[_mirror(cy + dy, h), _mirror(cx + dx, w)]
    sd = margin_sd * math.sqrt(max(s / 9.0, 0.0))
    z = abs(np.float64(margin[cy, cx])) / sd if sd > 0 else np.inf
    return 0.5 * math.erfc(z * 0.7071067811865476)


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def menon_rows(x, var, chan, red_row, direction, margin, margin_sd, matrix, clip_negative, do_var, out,
               var_out):  # pragma: no cover - compiled
    """Menon 2007's demosaic (without its refining step), the colour matrix and the variance,
    each pixel's weights built from the formulas (the reference :func:`menon_table_rows` is
    checked against, and its path within :data:`RADIUS` of the border).

    ``x`` (H, W) the white-balanced mosaic (``var`` its variance), ``direction`` and ``margin``
    from :func:`menon_directions`. Given the directions every output is a linear combination of
    photosites within 4 of it (green: eq. (3); red and blue at green: eq. (7); red at blue and
    blue at red: eq. (8) in the chosen direction, through the estimates at green): the pass
    builds those weights per pixel (``K_c(p)``, borders mirrored), then ``out_o = sum_p (sum_c
    M_oc K_c(p)) x_p`` and ``var_o = sum_p (sum_c M_oc K_c(p))^2 var_p`` -- exact for
    independent photosites *given the directions* -- plus the direction-flip term of the module
    docstring at red and blue photosites. ``out`` (H, W, 3) float32 (negatives 0 with
    ``clip_negative``), ``var_out`` (H, W, 3) float32 if ``do_var``."""
    h, w = x.shape
    for cy in prange(h):
        g = np.zeros((3, 81))
        touched = np.zeros(81, np.bool_)
        tl = np.zeros(81, np.int64)
        nt = np.zeros(1, np.int64)
        acc = np.zeros(6)
        alt = np.zeros(6)
        for cx in range(w):
            _pixel_by_weights(x, var, chan, red_row, direction, margin, margin_sd, matrix, clip_negative, do_var,
                              cy, cx, g, touched, tl, nt, acc, alt, out, var_out)


@njit(inline="always")
def _entry(direction, cy, cx, ks, key_n, key_dy, key_dx, set_start):  # pragma: no cover - compiled
    """The filter of key set ``ks`` at (cy, cx): its index from the directions at the set's offsets."""
    idx = 0
    for b in range(key_n[ks]):
        idx |= np.int64(direction[cy + key_dy[ks, b], cx + key_dx[ks, b]] & 1) << b
    return set_start[ks] + idx


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def menon_table_rows(x, var, chan, red_row, direction, margin, margin_sd, key_n, key_dy, key_dx, set_start,
                     tap_start, tap_dy, tap_dx, tap_w, matrix, clip_negative, do_var, out,
                     var_out):  # pragma: no cover - compiled
    """:func:`menon_rows` by the filter bank of :func:`weight_table` (``tap_w`` its weights with
    the colour matrix applied, (T, 3)): at a pixel of phase ``ph = 2 (y % 2) + x % 2`` and
    direction ``d`` (0 at green photosites) the key set ``ks = 2 ph + d`` names the offsets
    ``key_dy[ks, :key_n[ks]]``, ``key_dx`` whose directions (bit ``b``) pick the filter
    ``set_start[ks] + bits``: taps ``tap_start[f]:tap_start[f + 1]``. Values and variances
    in one sweep of the taps (float64 sums); the flipped direction's filter for the flip term.
    Pixels within :data:`RADIUS` of the border take :func:`menon_rows`' per-pixel weights."""
    h, w = x.shape
    r = RADIUS
    xf = x.reshape(h * w)
    vf = var.reshape(h * w) if do_var else xf
    offs = (tap_dy * w + tap_dx).astype(np.int32)     # flat offsets of the taps
    for cy in prange(h):
        g = np.zeros((3, 81))
        touched = np.zeros(81, np.bool_)
        tl = np.zeros(81, np.int64)
        nt = np.zeros(1, np.int64)
        acc = np.zeros(6)
        alt = np.zeros(6)
        inner = r <= cy < h - r
        for cx in range(w):
            if not inner or cx < r or cx >= w - r:
                _pixel_by_weights(x, var, chan, red_row, direction, margin, margin_sd, matrix, clip_negative,
                                  do_var, cy, cx, g, touched, tl, nt, acc, alt, out, var_out)
                continue
            c = chan[cy & 1, cx & 1]
            ph = 2 * (cy & 1) + (cx & 1)
            d = 0 if c == 1 else np.int64(direction[cy, cx] & 1)
            f = _entry(direction, cy, cx, 2 * ph + d, key_n, key_dy, key_dx, set_start)
            base = cy * w + cx
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            v0 = 0.0
            v1 = 0.0
            v2 = 0.0
            for t in range(tap_start[f], tap_start[f + 1]):
                k = base + offs[t]
                val = np.float64(xf[k])
                w0 = tap_w[t, 0]
                w1 = tap_w[t, 1]
                w2 = tap_w[t, 2]
                a0 += w0 * val
                a1 += w1 * val
                a2 += w2 * val
                if do_var:
                    vv = np.float64(vf[k])
                    v0 += w0 * w0 * vv
                    v1 += w1 * w1 * vv
                    v2 += w2 * w2 * vv
            out[cy, cx, 0] = finite_value(a0, clip_negative)
            out[cy, cx, 1] = finite_value(a1, clip_negative)
            out[cy, cx, 2] = finite_value(a2, clip_negative)
            if not do_var:
                continue
            if c != 1:
                s = 0.0                                 # the 3x3 around it: inside the image here
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        s += var[cy + dy, cx + dx]
                sd = margin_sd * math.sqrt(max(s / 9.0, 0.0))
                z = abs(np.float64(margin[cy, cx])) / sd if sd > 0 else np.inf
                p = 0.5 * math.erfc(z * 0.7071067811865476) if z < 5.0 else 0.0    # Phi(-5) < 1e-6
                if p > 1e-6:
                    f = _entry(direction, cy, cx, 2 * ph + 1 - d, key_n, key_dy, key_dx, set_start)
                    b0 = 0.0
                    b1 = 0.0
                    b2 = 0.0
                    for t in range(tap_start[f], tap_start[f + 1]):
                        val = np.float64(xf[base + offs[t]])
                        b0 += tap_w[t, 0] * val
                        b1 += tap_w[t, 1] * val
                        b2 += tap_w[t, 2] * val
                    v0 += p * (b0 - a0) ** 2
                    v1 += p * (b1 - a1) ** 2
                    v2 += p * (b2 - a2) ** 2
            var_out[cy, cx, 0] = finite_value(v0, False)
            var_out[cy, cx, 1] = finite_value(v1, False)
            var_out[cy, cx, 2] = finite_value(v2, False)


def _pattern_arrays(pattern: str) -> tuple[np.ndarray, np.ndarray]:
    """``chan`` (2, 2): the CFA colour of each phase (0 R, 1 G, 2 B); ``red_row`` (2,): which rows hold red."""
    lut = {"R": 0, "G": 1, "B": 2}
    p = pattern.upper()
    chan = np.array([[lut[p[0]], lut[p[1]]], [lut[p[2]], lut[p[3]]]], np.int64)
    return chan, np.array([np.any(chan[0] == 0), np.any(chan[1] == 0)])


@njit(cache=True, nogil=True)
def _window_weights(chan, red_row, field, cy, cx, g, touched, tl, nt):  # pragma: no cover - compiled
    """The (3, 81) weights ``g`` of :func:`menon_rows` at (cy, cx) of a direction field (no flip)."""
    n = field.shape[0]
    g[:] = 0.0
    touched[:] = False
    _menon_weights(g, cy, cx, n, n, chan, red_row, field, False, touched, tl, nt)


@njit(cache=True, nogil=True)
def _build_table(chan, red_row, key_n, key_dy, key_dx, set_start, tap_start, tap_dy, tap_dx,
                 tap_k):  # pragma: no cover - compiled
    """:func:`weight_table`'s loops into preallocated arrays; returns the number of filters."""
    n = 24
    g = np.zeros((3, 81))
    g2 = np.zeros((3, 81))
    touched = np.zeros(81, np.bool_)
    tl = np.zeros(81, np.int64)
    nt = np.zeros(1, np.int64)
    nf = 0
    ntap = 0
    tap_start[0] = 0
    for py in range(2):
        for px in range(2):
            cy = 10 + py
            cx = 10 + px
            green = chan[py, px] == 1
            for d in range(2):
                ks = 2 * (2 * py + px) + d
                if green and d == 1:              # a green photosite has no direction of its own
                    set_start[ks] = set_start[ks - 1]
                    key_n[ks] = key_n[ks - 1]
                    key_dy[ks, :] = key_dy[ks - 1, :]
                    key_dx[ks, :] = key_dx[ks - 1, :]
                    continue
                set_start[ks] = nf
                nk = 0
                for dy in range(-RADIUS, RADIUS + 1):
                    for dx in range(-RADIUS, RADIUS + 1):
                        if (dy == 0 and dx == 0) or chan[(py + dy) & 1, (px + dx) & 1] == 1:
                            continue
                        found = False
                        for trial in range(3):            # the weights read a direction or they do not
                            field = np.zeros((n, n), np.uint8)
                            for yy in range(n):
                                for xx in range(n):
                                    field[yy, xx] = ((yy * 7 + xx * 13 + trial * 5) >> trial) & 1
                            field[cy, cx] = d
                            field[cy + dy, cx + dx] = 0
                            _window_weights(chan, red_row, field, cy, cx, g, touched, tl, nt)
                            field[cy + dy, cx + dx] = 1
                            _window_weights(chan, red_row, field, cy, cx, g2, touched, tl, nt)
                            for k in range(81):
                                for c in range(3):
                                    if g[c, k] != g2[c, k]:
                                        found = True
                        if found:
                            key_dy[ks, nk] = dy
                            key_dx[ks, nk] = dx
                            nk += 1
                key_n[ks] = nk
                if nf + (1 << nk) > tap_start.shape[0] - 1:
                    return -1                     # more filters than the arrays hold
                for idx in range(1 << nk):
                    field = np.zeros((n, n), np.uint8)
                    field[cy, cx] = d
                    for b in range(nk):
                        field[cy + key_dy[ks, b], cx + key_dx[ks, b]] = (idx >> b) & 1
                    _window_weights(chan, red_row, field, cy, cx, g, touched, tl, nt)
                    for k in range(81):
                        if g[0, k] != 0.0 or g[1, k] != 0.0 or g[2, k] != 0.0:
                            tap_dy[ntap] = k // 9 - RADIUS
                            tap_dx[ntap] = k % 9 - RADIUS
                            for c in range(3):
                                tap_k[ntap, c] = g[c, k]
                            ntap += 1
                    nf += 1
                    tap_start[nf] = ntap
    return nf


@lru_cache(maxsize=8)
def weight_table(pattern: str) -> tuple[np.ndarray, ...]:
    """Menon's filter bank for a CFA ``pattern`` (module docstring), from the per-pixel weights
    of :func:`menon_rows` away from the border: for each phase and own direction (key set ``ks
    = 2 ph + d``) the red and blue photosites whose direction changes the weights (found by
    flipping each one on direction fields), and one filter per pattern of their directions
    (at most 6 of them: 64 filters of 9 to 25 taps). Returns ``(key_n, key_dy, key_dx,
    set_start, tap_start, tap_dy, tap_dx, tap_k)``: ``tap_k`` (T, 3) the weights per CFA colour
    (R, G, B) before the colour matrix."""
    chan, red_row = _pattern_arrays(pattern)
    key_n = np.zeros(8, np.int64)
    key_dy = np.zeros((8, 16), np.int64)
    key_dx = np.zeros((8, 16), np.int64)
    set_start = np.zeros(8, np.int64)
    tap_start = np.zeros(8 * 64 + 1, np.int64)
    tap_dy = np.zeros(8 * 64 * 81, np.int64)
    tap_dx = np.zeros(8 * 64 * 81, np.int64)
    tap_k = np.zeros((8 * 64 * 81, 3))
    nf = _build_table(chan, red_row, key_n, key_dy, key_dx, set_start, tap_start, tap_dy, tap_dx, tap_k)
    if nf < 0:
        raise RuntimeError("Menon's filter bank needs more than 64 filters per phase and direction")
    nt = tap_start[nf]
    return (key_n, key_dy, key_dx, set_start, tap_start[:nf + 1].copy(), tap_dy[:nt].copy(), tap_dx[:nt].copy(),
            tap_k[:nt].copy())


def menon_demosaic(xm: np.ndarray, vm: np.ndarray | None, pattern: str, matrix: np.ndarray, clip_negative: bool,
                   out: np.ndarray, var_out: np.ndarray | None) -> None:
    """Menon 2007 on the white-balanced (H, W) mosaic ``xm`` (float32; ``vm`` its variance, or
    None): the directions (:func:`menon_directions`), then the values, colour ``matrix`` and
    variance by the filter bank (:func:`menon_table_rows`) into ``out`` and ``var_out`` ((H, W,
    3) float32; negatives 0 with ``clip_negative``)."""
    chan, red_row = _pattern_arrays(pattern)
    h, w = xm.shape
    ia, ib = np.nonzero(CLASSIFIER)
    kdy, kdx, kw = (2 - ia).astype(np.int64), (2 - ib).astype(np.int64), CLASSIFIER[ia, ib].copy()
    direction = np.empty((h, w), np.uint8)
    margin = np.empty((h, w), np.float32)
    key_n, key_dy, key_dx, set_start, tap_start, tap_dy, tap_dx, tap_k = weight_table(pattern.upper())
    m = np.ascontiguousarray(matrix, np.float64)
    tap_w = np.ascontiguousarray(tap_k @ m.T)
    do_var = vm is not None
    with KERNEL_LOCK:
        menon_directions(xm, chan, kdy, kdx, kw, direction, margin)
        menon_table_rows(xm, xm if vm is None else vm, chan, red_row, direction, margin, MARGIN_SD, key_n, key_dy,
                         key_dx, set_start, tap_start, tap_dy, tap_dx, tap_w, m, bool(clip_negative), do_var, out,
                         np.empty((1, 1, 3), np.float32) if var_out is None else var_out)
