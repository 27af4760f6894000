"""Compiled per-photosite loops (numba) of the RAW merge: one pass for the merge, one for the demosaic.

:func:`derender.raw.optimal.raw_merge` spends its time in three whole-array chains when
written in NumPy (float64): the noise fit's samples, the merge's reweighted rounds and Newton
steps, and the demosaic with its twelve variance filters. Each is one compiled pass here,
rows in parallel (``prange``), every photosite independently (so results do not depend on
the thread count):

* :func:`grid_samples` -- the samples of the noise fit of :mod:`derender.raw.noise` (eq. 2)
  on a regular grid of photosites (every ``stride``-th in row-major order, ``stride`` odd so
  that every CFA phase is met), read straight from the uint16 mosaics: its cost goes with
  the samples, not with the frame;
* :func:`merge_rows` -- the censored maximum-likelihood merge of
  :func:`derender.raw.optimal.merge_mosaic_optimal` (pooled start, two reweighted rounds,
  Newton steps where a saturated sample is within ``near`` sigma of its level), with a
  gain and read variance *per frame* and CFA phase (a resampled frame's variance factor,
  :mod:`derender.raw.register`, folded in) and exposures ``e_j`` (``t_j S_j / N_j^2``, relative),
  the sums in float64 registers, the outputs stored as float32;
* :func:`demosaic_rows` -- white balance, the demosaic (a linear filter per CFA phase: the
  taps of :func:`derender.raw.optimal.demosaic_variance`), the colour matrix and the
  variance ``sum_p (sum_c M_oc K_c(p))^2 w_p^2 Var[X_p]`` in one pass, borders reflected
  as ``scipy.ndimage`` does (``mode="reflect"``);
* :func:`menon_directions`, :func:`menon_values`, :func:`menon_rows` -- Menon, Andriani &
  Calvagno (2007, "Demosaicing with directional filtering and a posteriori decision", IEEE
  TIP 16(1)), without its refining step, as ``colour_demosaicing`` computes it (borders
  mirrored): the direction per red and blue photosite, the values by the formulas, and the
  variance through each pixel's weights given the directions (slow: ~86 s at 24 MP).

The inverse Mills ratio ``lambda(z) = phi(z) / Q(z)`` is ``sqrt(2/pi) exp(-z^2/2) /
erfc(z / sqrt 2)`` (erfc keeps its relative accuracy in the tail) for ``z < 30`` and Laplace's
continued fraction ``z + 1/(z + 2/(z + 3/(z + ...)))`` beyond. Launches are serialised by
:data:`KERNEL_LOCK` (numba's fallback thread pool cannot run two parallel kernels at once).
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numba import njit, prange

__all__ = ["KERNEL_LOCK", "inverse_mills", "grid_samples", "merge_rows", "demosaic_rows", "wls_normal",
           "menon_directions", "menon_values", "menon_rows"]

#: Serialises launches of this module's parallel kernels.
KERNEL_LOCK = threading.Lock()


@njit(cache=True, nogil=True)
def inverse_mills(z):  # pragma: no cover - compiled
    """``phi(z) / (1 - Phi(z))`` for a float ``z`` (module docstring)."""
    if z < 30.0:
        q = 0.5 * math.erfc(z * 0.7071067811865476)
        if q <= 0.0:
            return z
        return 0.3989422804014327 * math.exp(-0.5 * z * z) / q
    f = z
    for k in range(24, 0, -1):
        f = z + k / f
    return f


@njit(inline="always")
def _reflect(i, n):  # pragma: no cover - compiled
    """scipy.ndimage's ``reflect`` border: ``d c b a | a b c d | d c b a`` (period 2n)."""
    m = 2 * n
    i = i % m
    if i < 0:
        i += m
    if i >= n:
        i = m - 1 - i
    return i


@njit(inline="always")
def _finite(a, clip_negative):  # pragma: no cover - compiled
    """``a``, or 0 where it is NaN or infinite (or negative, with ``clip_negative``)."""
    if not math.isfinite(a) or (clip_negative and a < 0.0):
        return 0.0
    return a


@njit(parallel=True, nogil=True, cache=True)
def grid_samples(mosaics, pairs, black, white, expo, ceiling_fraction, stride, r2_out, x_out,
                 ok_out):  # pragma: no cover - compiled
    """The noise fit's candidate samples: the photosites ``i = m * stride`` (row-major), for
    every pair ``p = (j, k)`` of ``pairs``: ``ok_out[p, m]`` where both frames are unsaturated
    and below ``ceiling_fraction`` of their level ``white - black``, ``r2_out[p, m] =
    (d_k / e_k - d_j / e_j)^2``; ``x_out[m]`` the pooled estimate ``sum d / sum e`` over the
    frames unsaturated there (0 where none is)."""
    n = len(mosaics)
    h, w = mosaics[0].shape
    npairs = pairs.shape[0]
    total = x_out.shape[0]
    for y in prange(h):
        m0 = (y * w + stride - 1) // stride                  # the grid's photosites in row y
        m1 = min(((y + 1) * w + stride - 1) // stride, total)
        if m1 <= m0:
            continue
        py = y & 1
        codes = np.empty((n, m1 - m0), np.float64)
        for j in range(n):
            r = mosaics[j][y]                                 # one list access per frame and row
            for m in range(m0, m1):
                codes[j, m - m0] = r[m * stride - y * w]
        d = np.empty(n)
        usable = np.empty(n, np.bool_)
        for m in range(m0, m1):
            px = (m * stride - y * w) & 1
            num = 0.0
            den = 0.0
            for j in range(n):
                code = codes[j, m - m0]
                bj = black[j, py, px]
                d[j] = code - bj
                un = code < white[j]
                usable[j] = un and d[j] < ceiling_fraction * (white[j] - bj)
                if un:
                    num += code - bj
                    den += expo[j]
            x_out[m] = num / den if den > 0.0 else 0.0
            for p in range(npairs):
                j = pairs[p, 0]
                k = pairs[p, 1]
                if usable[j] and usable[k]:
                    r = d[k] / expo[k] - d[j] / expo[j]
                    r2_out[p, m] = r * r
                    ok_out[p, m] = True
                else:
                    r2_out[p, m] = 0.0
                    ok_out[p, m] = False


@njit(cache=True, nogil=True)
def wls_normal(r2, xs, pair_of, design_g, design_s, params, first, clip):  # pragma: no cover - compiled
    """Normal equations of the noise fit ``E[r2] = sum_q params_q row_q`` with the row
    ``[x * design_g[p], design_s[p]]`` of a sample of pair ``p``: weights ``1 / pred^2`` (the
    variance of ``r2`` for Gaussian ``r``), or ``1 / (sum design_s[p])^2`` in the ``first``
    round; samples with ``r2 > clip * pred`` left out. Returns ``(M, v, used)`` (one thread:
    the samples are capped, ~0.02 s a round)."""
    kg = design_g.shape[1]
    ks = design_s.shape[1]
    m = kg + ks
    mat = np.zeros((m, m))
    vec = np.zeros(m)
    row = np.zeros(m)
    used = 0
    for i in range(r2.shape[0]):
        p = pair_of[i]
        x = max(xs[i], 0.0)
        for q in range(kg):
            row[q] = x * design_g[p, q]
        for q in range(ks):
            row[kg + q] = design_s[p, q]
        if first:
            b = 0.0
            for q in range(ks):
                b += design_s[p, q]
            wt = 1.0 / max(b, 1e-30) ** 2
        else:
            pred = 0.0
            for q in range(m):
                pred += params[q] * row[q]
            pred = max(pred, 1e-12)
            if r2[i] > clip * pred:
                continue
            wt = 1.0 / (pred * pred)
        used += 1
        for a in range(m):
            wa = wt * row[a]
            vec[a] += wa * r2[i]
            for b2 in range(m):
                mat[a, b2] += wa * row[b2]
    return mat, vec, used


@njit(inline="always")
def _newton_photosite(rows, vrows, y, xx, black, white, expo, gain, s2, iterations, x):  # pragma: no cover - compiled
    """Newton steps of the censored likelihood at photosite ``xx`` of row ``y`` (``rows``: that
    row of every frame; ``vrows``: whether each frame takes part there) from ``x``:
    ``(x, information)``."""
    py = y & 1
    px = xx & 1
    info = 0.0
    for _ in range(max(iterations, 1)):
        score = 0.0
        info = 0.0
        for j in range(rows.shape[0]):
            if vrows[j, xx] == 0:
                continue
            code = rows[j, xx]
            e = expo[j]
            v = gain[j, py, px] * max(x * e, 0.0) + s2[j, py, px]
            if code < white[j]:
                score += e * (code - black[j, py, px] - x * e) / v
                info += e * e / v
            else:
                sd = math.sqrt(v)
                z = (white[j] - black[j, py, px] - x * e) / sd
                lam = inverse_mills(z)
                score += e * lam / sd
                info += e * e * lam * max(lam - z, 0.0) / v
        if info > 0.0:
            x += score / info
    return x, info


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def merge_rows(mosaics, valid, black, white, expo, gain, s2, censored, iterations, near, inv_span,
               x_out, var_out, mask_out, bright):  # pragma: no cover - compiled
    """The censored ML merge of :func:`derender.raw.optimal.merge_mosaic_optimal`, per photosite.

    ``mosaics``: a typed list of (H, W) uint16; ``black`` (N, 2, 2), ``white`` (N,), ``expo``
    (N,), ``gain`` (N, 2, 2), ``s2`` (N, 2, 2) per frame and CFA phase (a resampled frame's
    variance factor folded in, :mod:`derender.raw.register`): ``d_j = y_j - black_j ~ N(X e_j,
    gain_j max(X e_j, 0) + s2_j)``, censored at ``white_j - black_j`` where ``y_j >= white_j``;
    ``valid`` (N, H, W) uint8 says where each frame takes part (alignment's border, ghost
    removal), or (N, 1, 1) for everywhere. Where no frame takes part unsaturated the photosite
    is the bound of the frames that take part (of every frame, if none does).
    Writes ``X`` and ``1 / I`` times ``inv_span[py, px]`` (and its square) as float32 split
    by CFA phase (``x_out[py, px, y // 2, x // 2]``, (2, 2, ceil(H/2), ceil(W/2)): the layout
    :func:`demosaic_rows` reads), and
    ``bright`` in ``mask_out`` where every frame is saturated (``X`` the bound ``max_j c_j / e_j``,
    variance ``X^2``). Each row is done frame by frame over the whole row (the pooled start,
    two reweighted rounds: loops without branches that the compiler vectorises), then the
    Newton steps at the photosites that need them."""
    n = len(mosaics)
    h, w = mask_out.shape
    for y in prange(h):
        py = y & 1
        i = y >> 1
        num = np.zeros(w)
        den = np.zeros(w)
        bound = np.zeros(w)
        bound_all = np.zeros(w)
        nsat = np.zeros(w, np.int64)
        rows = np.empty((n, w), mosaics[0].dtype)     # the row of every frame (one list access per frame)
        vrows = np.ones((n, w), np.uint8)
        for j in range(n):
            rows[j, :] = mosaics[j][y, :]
            if valid.shape[1] > 1:
                vrows[j, :] = valid[j, y, :]
        for j in range(n):
            r = rows[j]
            vr = vrows[j]
            e = expo[j]
            wl = white[j]
            b0 = black[j, py, 0]
            b1 = black[j, py, 1]
            q0 = (wl - b0) / e
            q1 = (wl - b1) / e
            for xx in range(w):
                code = np.float64(r[xx])
                odd = (xx & 1) == 1
                bb = b1 if odd else b0
                ok = vr[xx] != 0
                un = code < wl and ok
                num[xx] += (code - bb) if un else 0.0
                den[xx] += e if un else 0.0
                nsat[xx] += 1 if (ok and not un) else 0
                q = q1 if odd else q0
                bound[xx] = max(bound[xx], q if ok else 0.0)
                bound_all[xx] = max(bound_all[xx], q)
        # the reweighted rounds in float32 (twice the vector lanes; the float64 reference
        # merge_mosaic_optimal agrees to 5e-8 relative per photosite)
        zero = np.float32(0.0)
        x = np.empty(w, np.float32)
        score = np.empty(w, np.float32)
        info = np.empty(w, np.float32)
        for xx in range(w):
            if bound[xx] == 0.0:
                bound[xx] = bound_all[xx]                     # no frame takes part: every frame's bound
            x[xx] = num[xx] / den[xx] if den[xx] > 0.0 else bound[xx]
        for _ in range(2):
            score[:] = zero
            info[:] = zero
            for j in range(n):
                r = rows[j]
                e = np.float32(expo[j])
                wl = np.float32(white[j])
                g0 = np.float32(gain[j, py, 0])
                g1 = np.float32(gain[j, py, 1])
                sv0 = np.float32(s2[j, py, 0])
                sv1 = np.float32(s2[j, py, 1])
                b0 = np.float32(black[j, py, 0])
                b1 = np.float32(black[j, py, 1])
                for xx in range(w):
                    code = np.float32(r[xx])
                    odd = (xx & 1) == 1
                    bb = b1 if odd else b0
                    g = g1 if odd else g0
                    sv = sv1 if odd else sv0
                    xe = x[xx] * e
                    wj = e / (g * max(xe, zero) + sv) if (code < wl and vrows[j, xx] != 0) else zero
                    score[xx] += wj * (code - bb - xe)
                    info[xx] += wj * e
            for xx in range(w):
                if info[xx] > zero and den[xx] > 0.0:
                    x[xx] += score[xx] / info[xx]
        for xx in range(w):
            px = xx & 1
            jx = xx >> 1
            sp = inv_span[py, px]
            if den[xx] == 0.0:
                x_out[py, px, i, jx] = bound[xx] * sp
                var_out[py, px, i, jx] = (bound[xx] * sp) ** 2
                mask_out[y, xx] = bright
                continue
            xv = np.float64(x[xx])
            iv = np.float64(info[xx])
            if censored and nsat[xx] > 0:
                close = False
                for j in range(n):
                    code = rows[j, xx]
                    if code >= white[j] and vrows[j, xx] != 0:
                        e = expo[j]
                        if white[j] - black[j, py, px] - xv * e > -near * math.sqrt(gain[j, py, px] * max(xv * e, 0.0)
                                                                                      + s2[j, py, px]):
                            close = True
                if close:
                    xv, iv = _newton_photosite(rows, vrows, y, xx, black, white, expo, gain, s2, iterations, xv)
            x_out[py, px, i, jx] = xv * sp
            var_out[py, px, i, jx] = (1.0 / iv) * sp * sp if iv > 0.0 else 0.0
            mask_out[y, xx] = 0


@njit(inline="always")
def _border_pixel(x, var, mult, ntaps, tap_dy, tap_dx, taps, taps2, do_var, y, xx, clip_negative, out,
                  var_out):  # pragma: no cover - compiled
    """One output pixel with reflected taps (the multiplier of the photosite actually read;
    ``x``, ``var`` split by phase)."""
    h = out.shape[0]
    w = out.shape[1]
    py = y & 1
    px = xx & 1
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    v0 = 0.0
    v1 = 0.0
    v2 = 0.0
    for t in range(ntaps[py, px]):
        yy = _reflect(y + tap_dy[py, px, t], h)
        xq = _reflect(xx + tap_dx[py, px, t], w)
        m = mult[yy & 1, xq & 1]
        val = x[yy & 1, xq & 1, yy >> 1, xq >> 1] * m
        a0 += taps[py, px, t, 0] * val
        a1 += taps[py, px, t, 1] * val
        a2 += taps[py, px, t, 2] * val
        if do_var:
            vv = var[yy & 1, xq & 1, yy >> 1, xq >> 1] * (m * m)
            v0 += taps2[py, px, t, 0] * vv
            v1 += taps2[py, px, t, 1] * vv
            v2 += taps2[py, px, t, 2] * vv
    out[y, xx, 0] = _finite(a0, clip_negative)
    out[y, xx, 1] = _finite(a1, clip_negative)
    out[y, xx, 2] = _finite(a2, clip_negative)
    if do_var:
        var_out[y, xx, 0] = _finite(v0, False)
        var_out[y, xx, 1] = _finite(v1, False)
        var_out[y, xx, 2] = _finite(v2, False)


@njit(inline="always")
def _tap_sums(planes, weights, ntaps, tap_dy, tap_dx, py, px, i, j0, j1, a0, a1, a2):  # pragma: no cover
    """Inside the border: ``a_o[jj] += sum_t weights[py, px, t, o] * planes[tap's phase, row][jj + off]``
    over the taps of output phase ``(py, px)`` on plane row ``i`` (values or their variances)."""
    for t in range(ntaps[py, px]):
        sy = py + tap_dy[py, px, t]
        sx = px + tap_dx[py, px, t]
        src = planes[sy & 1, sx & 1, i + (sy >> 1)]
        off = sx >> 1
        w0 = weights[py, px, t, 0]
        w1 = weights[py, px, t, 1]
        w2 = weights[py, px, t, 2]
        for jj in range(j0, j1):
            val = np.float64(src[jj + off])
            a0[jj] += w0 * val
            a1[jj] += w1 * val
            a2[jj] += w2 * val


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def demosaic_rows(planes, var_planes, mult, ntaps, tap_dy, tap_dx, taps, taps2, folded, folded2, clip_negative,
                  do_var, out, var_out):  # pragma: no cover - compiled
    """White balance, demosaic, colour matrix (and variance) in one pass.

    ``planes`` (2, 2, ceil(H/2), ceil(W/2)) float32: the mosaic split by CFA phase
    (``planes[a, b] = x[a::2, b::2]``, as :func:`merge_rows` writes it; ``var_planes`` its
    variance); ``mult`` (2, 2) the white-balance multiplier of each CFA phase; per output
    phase ``(py, px)`` the ``ntaps[py, px]`` taps at ``(tap_dy, tap_dx)`` with weights
    ``taps[py, px, t, o]`` (the matrix times the demosaic's kernels), their squares ``taps2``,
    and both with the multiplier of the tap's photosite folded in (``folded``, ``folded2``:
    inside the border a tap's phase is fixed). ``out`` (H, W, 3) float32 finite (negatives set to
    0 if ``clip_negative``), ``var_out`` (H, W, 3) float32 if ``do_var``. Inside the
    2-photosite border a tap reads one phase plane contiguously along the row (loops the
    compiler vectorises); on the border the taps read reflected photosites
    (:func:`_border_pixel`)."""
    h = out.shape[0]
    w = out.shape[1]
    x = planes
    var = var_planes
    for y in prange(h):
        py = y & 1
        i = y >> 1
        for px in range(2):
            nj = (w - px + 1) // 2
            if y < 2 or y >= h - 2:
                for jj in range(nj):
                    _border_pixel(x, var, mult, ntaps, tap_dy, tap_dx, taps, taps2, do_var, y, 2 * jj + px,
                                  clip_negative, out, var_out)
                continue
            j0 = (3 - px) // 2
            j1 = max(j0, (w - 1 - px) // 2)
            a0 = np.zeros(nj)
            a1 = np.zeros(nj)
            a2 = np.zeros(nj)
            _tap_sums(planes, folded, ntaps, tap_dy, tap_dx, py, px, i, j0, j1, a0, a1, a2)
            for jj in range(j0, j1):
                xx = 2 * jj + px
                out[y, xx, 0] = _finite(a0[jj], clip_negative)
                out[y, xx, 1] = _finite(a1[jj], clip_negative)
                out[y, xx, 2] = _finite(a2[jj], clip_negative)
            if do_var:
                a0[:] = 0.0
                a1[:] = 0.0
                a2[:] = 0.0
                _tap_sums(var_planes, folded2, ntaps, tap_dy, tap_dx, py, px, i, j0, j1, a0, a1, a2)
                for jj in range(j0, j1):
                    xx = 2 * jj + px
                    var_out[y, xx, 0] = _finite(a0[jj], False)
                    var_out[y, xx, 1] = _finite(a1[jj], False)
                    var_out[y, xx, 2] = _finite(a2[jj], False)
            for jj in range(0, j0):
                _border_pixel(x, var, mult, ntaps, tap_dy, tap_dx, taps, taps2, do_var, y, 2 * jj + px,
                              clip_negative, out, var_out)
            for jj in range(j1, nj):
                _border_pixel(x, var, mult, ntaps, tap_dy, tap_dx, taps, taps2, do_var, y, 2 * jj + px,
                              clip_negative, out, var_out)


# --------------------------------------------------------------------------- Menon 2007 (DDFAPD)
@njit(inline="always")
def _mirror(i, n):  # pragma: no cover - compiled
    """scipy.ndimage's ``mirror`` border (``c b | a b c | b a``, period 2n - 2): keeps the CFA phase."""
    if n == 1:
        return 0
    m = 2 * n - 2
    i = i % m
    if i >= n:
        i = m - i
    return i


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
        for xx in range(w):
            if chan[y & 1, xx & 1] != 1:
                ch[y, xx] = x[y, xx] - _directional_green(x, y, xx, h, w, True)
                cv[y, xx] = x[y, xx] - _directional_green(x, y, xx, h, w, False)
    for y in prange(h):
        for xx in range(w):
            if chan[y & 1, xx & 1] == 1:
                direction[y, xx] = 1
                margin[y, xx] = 0.0
                continue
            dh = 0.0
            dv = 0.0
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


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def menon_rows(x, var, chan, red_row, direction, margin, margin_sd, matrix, clip_negative, do_var, out,
               var_out):  # pragma: no cover - compiled
    """Menon 2007's demosaic (without its refining step), the colour matrix and the variance in one pass.

    ``x`` (H, W) the white-balanced mosaic (``var`` its variance), ``direction`` and ``margin``
    from :func:`menon_directions`. Given the directions every output is a linear combination of
    photosites within 4 of it (green: eq. (3); red and blue at green: eq. (7); red at blue and
    blue at red: eq. (8) in the chosen direction, through the estimates at green): the pass
    builds those weights per pixel (``K_c(p)``, borders mirrored), then ``out_o = sum_p (sum_c
    M_oc K_c(p)) x_p`` and ``var_o = sum_p (sum_c M_oc K_c(p))^2 var_p`` -- exact for
    independent photosites *given the directions*. The direction is itself chosen from noisy
    photosites: at a red or blue photosite the other direction's output ``out'`` (the centre's
    direction flipped) adds ``P(flip) (out' - out)^2``, with ``P(flip) = Phi(-|margin| / sd)``
    and ``sd = margin_sd * sqrt(mean var over the 3x3 around it)`` (the classifier's noise, its
    eight gradient terms taken as independent). ``out`` (H, W, 3) float32 (negatives 0 with
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
            _menon_weights(g, cy, cx, h, w, chan, red_row, direction, False, touched, tl, nt)
            _apply_weights(g, x, var, cy, cx, matrix, do_var, touched, tl, nt, acc)
            for o in range(3):
                out[cy, cx, o] = _finite(acc[o], clip_negative)
            if not do_var:
                continue
            if chan[cy & 1, cx & 1] != 1:
                s = 0.0
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        s += var[_mirror(cy + dy, h), _mirror(cx + dx, w)]
                sd = margin_sd * math.sqrt(max(s / 9.0, 0.0))
                z = abs(np.float64(margin[cy, cx])) / sd if sd > 0 else np.inf
                p = 0.5 * math.erfc(z * 0.7071067811865476)
                if p > 1e-6:
                    _menon_weights(g, cy, cx, h, w, chan, red_row, direction, True, touched, tl, nt)
                    _apply_weights(g, x, var, cy, cx, matrix, False, touched, tl, nt, alt)
                    for o in range(3):
                        acc[3 + o] += p * (alt[o] - acc[o]) ** 2
            for o in range(3):
                var_out[cy, cx, o] = _finite(acc[3 + o], False)


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def menon_values(x, chan, red_row, direction, matrix, clip_negative, rgb, out):  # pragma: no cover - compiled
    """Menon 2007's demosaic (no refining step) and the colour matrix by its formulas, plane by
    plane (the values of :func:`menon_rows` without building weights): green (eq. (3) in the
    chosen direction), red and blue at green (eq. (7)), red at blue and blue at red (eq. (8)),
    borders mirrored. ``rgb`` (3, H, W) float32 scratch; ``out`` (H, W, 3) float32."""
    h, w = x.shape
    for y in prange(h):
        for xx in range(w):
            c = chan[y & 1, xx & 1]
            rgb[0, y, xx] = 0.0
            rgb[2, y, xx] = 0.0
            if c == 1:
                rgb[1, y, xx] = x[y, xx]
            else:
                rgb[1, y, xx] = _directional_green(x, y, xx, h, w, direction[y, xx] == 1)
                rgb[c, y, xx] = x[y, xx]
    for y in prange(h):                      # red and blue at green photosites
        for xx in range(w):
            if chan[y & 1, xx & 1] != 1:
                continue
            for k in (0, 2):
                if red_row[y & 1] == (k == 0):
                    a = _mirror(xx - 1, w)
                    b = _mirror(xx + 1, w)
                    rgb[k, y, xx] = rgb[1, y, xx] + 0.5 * (x[y, a] + x[y, b]) - 0.5 * (rgb[1, y, a] + rgb[1, y, b])
                else:
                    a = _mirror(y - 1, h)
                    b = _mirror(y + 1, h)
                    rgb[k, y, xx] = rgb[1, y, xx] + 0.5 * (x[a, xx] + x[b, xx]) - 0.5 * (rgb[1, a, xx] + rgb[1, b, xx])
    for y in prange(h):                      # red at blue, blue at red
        for xx in range(w):
            c = chan[y & 1, xx & 1]
            if c == 1:
                continue
            k = 2 - c
            if direction[y, xx] == 1:
                a = _mirror(xx - 1, w)
                b = _mirror(xx + 1, w)
                rgb[k, y, xx] = x[y, xx] + 0.5 * (rgb[k, y, a] + rgb[k, y, b]) - 0.5 * (rgb[c, y, a] + rgb[c, y, b])
            else:
                a = _mirror(y - 1, h)
                b = _mirror(y + 1, h)
                rgb[k, y, xx] = x[y, xx] + 0.5 * (rgb[k, a, xx] + rgb[k, b, xx]) - 0.5 * (rgb[c, a, xx] + rgb[c, b, xx])
    for y in prange(h):
        for xx in range(w):
            r = np.float64(rgb[0, y, xx])
            g = np.float64(rgb[1, y, xx])
            b = np.float64(rgb[2, y, xx])
            for o in range(3):
                out[y, xx, o] = _finite(matrix[o, 0] * r + matrix[o, 1] * g + matrix[o, 2] * b, clip_negative)
