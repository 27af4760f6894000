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
* :func:`interpolation_rows` -- the interpolation term of the variance
  (:mod:`derender.raw.interpolation`, eq. 1) added in place, with its share of the total on
  every 4th row, in one pass instead of NumPy's six whole-array passes and copies.

Menon 2007's demosaic and its variance are :mod:`derender.raw.menon`. The inverse Mills ratio ``lambda(z) = phi(z) / Q(z)`` is ``sqrt(2/pi) exp(-z^2/2) /
erfc(z / sqrt 2)`` (erfc keeps its relative accuracy in the tail) for ``z < 30`` and Laplace's
continued fraction ``z + 1/(z + 2/(z + 3/(z + ...)))`` beyond. Launches are serialised by
:data:`KERNEL_LOCK` (numba's fallback thread pool cannot run two parallel kernels at once).
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numba import njit, prange

__all__ = ["KERNEL_LOCK", "inverse_mills", "mirror_index", "finite_value", "grid_samples", "merge_rows",
           "demosaic_rows", "wls_normal", "interpolation_rows"]

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
def mirror_index(i, n):  # pragma: no cover - compiled
    """scipy.ndimage's ``mirror`` border (``c b | a b c | b a``, period 2n - 2): keeps the CFA phase.

    An int64 whatever the integer ``i``: a ``prange`` index is typed uint64 in numba's parfor
    lowering, and returning it unconverted beside the int64 of the border branch unified to a
    float64 index (``Unsupported array index type float64`` in
    :func:`derender.raw.menon.menon_table_rows`). No division inside the image."""
    j = np.int64(i)
    if j < 0 or j >= n:
        m = max(2 * n - 2, 1)                    # n = 1: every index is 0
        j = j % m                                # Python's sign: 0 <= j < m
        j = min(j, m - j)                        # the second half of a period runs back
    return j


@njit(inline="always")
def finite_value(a, clip_negative):  # pragma: no cover - compiled
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
def _newton_photosite(rows, vrows, y, xx, black, white, expo, gain, s2, iterations, near, tol, x):  # pragma: no cover - compiled
    """Newton steps of the censored likelihood at photosite ``xx`` of row ``y`` (``rows``: that
    row of every frame; ``vrows``: whether each frame takes part there) from ``x``:
    ``(x, information)``. A censored sample more than ``near`` sigma above its level
    (``z < -near``: ``lambda(z) < 1e-14``, the score's term ``< 1e-14 e / sd``) is skipped; the
    steps stop once one is below ``tol`` sigma (``step^2 I < tol^2``), else after ``iterations``."""
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
                if z < -near:
                    continue
                lam = inverse_mills(z)
                score += e * lam / sd
                info += e * e * lam * max(lam - z, 0.0) / v
        if info > 0.0:
            step = score / info
            x += step
            if step * step * info < tol * tol:
                break
    return x, info


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def merge_rows(mosaics, valid, black, white, expo, gain, s2, censored, iterations, near, newton_tol, inv_span,
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
    two reweighted rounds, which photosites have a censored sample within ``near`` sigma of its
    level: loops without branches that the compiler vectorises), then the Newton steps at the
    photosites that need them, until a step is below ``newton_tol`` sigma or after ``iterations``."""
    n = len(mosaics)
    h, w = mask_out.shape
    for y in prange(h):
        py = y & 1
        i = y >> 1
        num = np.zeros(w)
        den = np.zeros(w)
        bound = np.zeros(w)
        bound_all = np.zeros(w)
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
        # which photosites need the Newton steps: a censored sample within ``near`` sigma of its
        # level (a branch-free loop per frame, float32; elsewhere lambda(z) < 1e-14)
        close = np.zeros(w, np.uint8)
        if censored:
            nr = np.float32(near)
            for j in range(n):
                r = rows[j]
                vr = vrows[j]
                e = np.float32(expo[j])
                wl = white[j]
                g0 = np.float32(gain[j, py, 0])
                g1 = np.float32(gain[j, py, 1])
                sv0 = np.float32(s2[j, py, 0])
                sv1 = np.float32(s2[j, py, 1])
                c0 = np.float32(wl - black[j, py, 0])
                c1 = np.float32(wl - black[j, py, 1])
                for xx in range(w):
                    xe = x[xx] * e
                    odd = (xx & 1) == 1
                    cc = c1 if odd else c0
                    g = g1 if odd else g0
                    sv = sv1 if odd else sv0
                    hit = r[xx] >= wl and vr[xx] != 0 and cc - xe > -nr * math.sqrt(g * max(xe, zero) + sv)
                    close[xx] |= np.uint8(1) if hit else np.uint8(0)
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
            if close[xx] != 0:
                xv, iv = _newton_photosite(rows, vrows, y, xx, black, white, expo, gain, s2, iterations, near,
                                           newton_tol, xv)
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
    out[y, xx, 0] = finite_value(a0, clip_negative)
    out[y, xx, 1] = finite_value(a1, clip_negative)
    out[y, xx, 2] = finite_value(a2, clip_negative)
    if do_var:
        var_out[y, xx, 0] = finite_value(v0, False)
        var_out[y, xx, 1] = finite_value(v1, False)
        var_out[y, xx, 2] = finite_value(v2, False)


@njit(inline="always")
def _tap_sums(planes, weights, ntaps, tap_dy, tap_dx, py, px, i, j0, j1, a0, a1, a2):  # pragma: no cover
    """Inside the border: ``a_o[jj] += sum_t weights[py, px, t, o] * planes[tap's phase, row][jj + off]``
    over the taps of output phase ``(py, px)`` on plane row ``i`` (values or their variances);
    four taps per sweep of the row (a quarter of the accumulators' loads and stores), then the rest."""
    nt = ntaps[py, px]
    t = 0
    while t + 4 <= nt:
        sy0 = py + tap_dy[py, px, t]
        sx0 = px + tap_dx[py, px, t]
        sy1 = py + tap_dy[py, px, t + 1]
        sx1 = px + tap_dx[py, px, t + 1]
        sy2 = py + tap_dy[py, px, t + 2]
        sx2 = px + tap_dx[py, px, t + 2]
        sy3 = py + tap_dy[py, px, t + 3]
        sx3 = px + tap_dx[py, px, t + 3]
        s0 = planes[sy0 & 1, sx0 & 1, i + (sy0 >> 1)]
        s1 = planes[sy1 & 1, sx1 & 1, i + (sy1 >> 1)]
        s2 = planes[sy2 & 1, sx2 & 1, i + (sy2 >> 1)]
        s3 = planes[sy3 & 1, sx3 & 1, i + (sy3 >> 1)]
        o0 = sx0 >> 1
        o1 = sx1 >> 1
        o2 = sx2 >> 1
        o3 = sx3 >> 1
        w00 = weights[py, px, t, 0]
        w01 = weights[py, px, t, 1]
        w02 = weights[py, px, t, 2]
        w10 = weights[py, px, t + 1, 0]
        w11 = weights[py, px, t + 1, 1]
        w12 = weights[py, px, t + 1, 2]
        w20 = weights[py, px, t + 2, 0]
        w21 = weights[py, px, t + 2, 1]
        w22 = weights[py, px, t + 2, 2]
        w30 = weights[py, px, t + 3, 0]
        w31 = weights[py, px, t + 3, 1]
        w32 = weights[py, px, t + 3, 2]
        for jj in range(j0, j1):
            v0 = np.float64(s0[jj + o0])
            v1 = np.float64(s1[jj + o1])
            v2 = np.float64(s2[jj + o2])
            v3 = np.float64(s3[jj + o3])
            a0[jj] += w00 * v0 + w10 * v1 + w20 * v2 + w30 * v3
            a1[jj] += w01 * v0 + w11 * v1 + w21 * v2 + w31 * v3
            a2[jj] += w02 * v0 + w12 * v1 + w22 * v2 + w32 * v3
        t += 4
    while t < nt:
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
        t += 1


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
                out[y, xx, 0] = finite_value(a0[jj], clip_negative)
                out[y, xx, 1] = finite_value(a1[jj], clip_negative)
                out[y, xx, 2] = finite_value(a2[jj], clip_negative)
            if do_var:
                a0[:] = 0.0
                a1[:] = 0.0
                a2[:] = 0.0
                _tap_sums(var_planes, folded2, ntaps, tap_dy, tap_dx, py, px, i, j0, j1, a0, a1, a2)
                for jj in range(j0, j1):
                    xx = 2 * jj + px
                    var_out[y, xx, 0] = finite_value(a0[jj], False)
                    var_out[y, xx, 1] = finite_value(a1[jj], False)
                    var_out[y, xx, 2] = finite_value(a2[jj], False)
            for jj in range(0, j0):
                _border_pixel(x, var, mult, ntaps, tap_dy, tap_dx, taps, taps2, do_var, y, 2 * jj + px,
                              clip_negative, out, var_out)
            for jj in range(j1, nj):
                _border_pixel(x, var, mult, ntaps, tap_dy, tap_dx, taps, taps2, do_var, y, 2 * jj + px,
                              clip_negative, out, var_out)


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def interpolation_rows(out, other0, other1, source, phase, k0, k1, kc, var, stride, ratio):  # pragma: no cover - compiled
    """The interpolation term of :func:`derender.raw.interpolation.interpolation_variance` (its
    eqs. 1-2: ``k0 (o - o_0)^2 + k1 (o - o_1)^2 + kc c^2`` in float32, in that order) added to
    ``var`` in place, in one pass over the (H, W, 3) float32 arrays; and, on every
    ``stride``-th row, the term's share of the total ``extra / total`` (float64) in ``ratio``
    ((ceil(H / stride), W, 3), -1 where the total is not positive).

    ``c`` is eq. 2's colour texture (:func:`derender.raw.interpolation.chroma_texture`) of the
    (H, W, 3) ``source``, computed here without its (H, W, 3) array: the distance-2 Laplacian
    of every channel (borders mirrored, :func:`mirror_index`) through ``phase`` (2, 2, 3, 3),
    the matrix ``M Pi_p P M^-1`` of each CFA phase. ``source`` and ``phase`` are read only
    when ``kc > 0`` (else they may be (1, 1, 3) and (2, 2, 3, 3) placeholders)."""
    h = out.shape[0]
    w = out.shape[1]
    c0 = np.float32(k0)
    c1 = np.float32(k1)
    c2 = np.float32(kc)
    use_chroma = kc > 0.0
    zero = np.float32(0.0)
    quarter = np.float32(0.25)
    for y in prange(h):
        sample = y % stride == 0
        r = y // stride
        lap = np.zeros(3, np.float32)
        if use_chroma:
            ya = mirror_index(y - 2, h)
            yb = mirror_index(y + 2, h)
        for xx in range(w):
            if use_chroma:
                xa = mirror_index(xx - 2, w)
                xb = mirror_index(xx + 2, w)
                for k in range(3):
                    ring = source[ya, xx, k] + source[yb, xx, k]
                    ring = ring + source[y, xa, k]
                    ring = ring + source[y, xb, k]
                    lap[k] = source[y, xx, k] - quarter * ring
            for c in range(3):
                o = out[y, xx, c]
                e0 = o - other0[y, xx, c]
                e1 = o - other1[y, xx, c]
                extra = zero + c0 * e0 * e0
                extra = extra + c1 * e1 * e1
                if use_chroma:
                    f = phase[y % 2, xx % 2, c]
                    e2 = f[0] * lap[0] + f[1] * lap[1] + f[2] * lap[2]
                    extra = extra + c2 * e2 * e2
                t = var[y, xx, c] + extra
                var[y, xx, c] = t
                if sample:
                    ratio[r, xx, c] = np.float64(extra) / np.float64(t) if t > zero else -1.0
