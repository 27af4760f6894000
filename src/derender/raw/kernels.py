"""Compiled per-photosite loops (numba) of the RAW merge: one pass for the merge, one for the demosaic.

:func:`derender.raw.optimal.raw_merge` spends its time in three whole-array chains when
written in NumPy (float64): the noise fit's samples, the merge's reweighted rounds and Newton
steps, and the demosaic with its twelve variance filters. Each is one compiled pass here,
rows in parallel (``prange``), every photosite independently (so results do not depend on
the thread count):

* :func:`pair_row_counts` / :func:`pair_samples` -- the samples of the noise fit of
  :mod:`derender.raw.noise` (eq. 2): the same regular subsample ``idx[::stride]`` of the
  photosites usable in both frames of a pair as :func:`derender.raw.noise.estimate_noise_pairs`
  takes, read straight from the uint16 mosaics;
* :func:`merge_rows` -- the censored maximum-likelihood merge of
  :func:`derender.raw.optimal.merge_mosaic_optimal` (pooled start, two reweighted rounds,
  Newton steps where a saturated sample is within ``near`` sigma of its level), with a
  gain and read variance *per frame* and exposures ``e_j`` (``t_j S_j / N_j^2``, relative),
  the sums in float64 registers, the outputs stored as float32;
* :func:`demosaic_rows` -- white balance, the demosaic (a linear filter per CFA phase: the
  taps of :func:`derender.raw.optimal.demosaic_variance`), the colour matrix and the
  variance ``sum_p (sum_c M_oc K_c(p))^2 w_p^2 Var[X_p]`` in one pass, borders reflected
  as ``scipy.ndimage`` does (``mode="reflect"``).

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

__all__ = ["KERNEL_LOCK", "inverse_mills", "pair_row_counts", "pair_samples", "merge_rows", "demosaic_rows",
           "wls_normal"]

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
def pair_row_counts(mosaics, pairs, black, white, ceiling_fraction):  # pragma: no cover - compiled
    """(P, H) int64: per pair ``(j, k)`` and row, the photosites unsaturated in both frames and
    below ``ceiling_fraction`` of the level ``white - black`` (the noise fit's samples)."""
    h, w = mosaics[0].shape
    npairs = pairs.shape[0]
    counts = np.zeros((npairs, h), np.int64)
    for y in prange(h):
        py = y & 1
        for p in range(npairs):
            j = pairs[p, 0]
            k = pairs[p, 1]
            mj = mosaics[j][y]
            mk = mosaics[k][y]
            c = 0
            for x in range(w):
                px = x & 1
                yj = mj[x]
                yk = mk[x]
                if yj >= white[j] or yk >= white[k]:
                    continue
                bj = black[j, py, px]
                bk = black[k, py, px]
                if yj - bj < ceiling_fraction * (white[j] - bj) and yk - bk < ceiling_fraction * (white[k] - bk):
                    c += 1
            counts[p, y] = c
    return counts


@njit(parallel=True, nogil=True, cache=True)
def pair_samples(mosaics, pairs, black, white, expo, ceiling_fraction, row_start, strides, offsets,
                 r2_out, x_out):  # pragma: no cover - compiled
    """The noise fit's samples: for pair ``p`` every ``strides[p]``-th usable photosite in row-major
    order (the usable index of row ``y`` starts at ``row_start[p, y]``) goes to position
    ``offsets[p] + index // stride`` of ``r2_out`` (``(d_k / e_k - d_j / e_j)^2``) and ``x_out``
    (the pooled estimate ``sum d / sum e`` over the frames unsaturated there)."""
    n = len(mosaics)
    h, w = mosaics[0].shape
    npairs = pairs.shape[0]
    for y in prange(h):
        py = y & 1
        rows = np.empty((n, w), mosaics[0].dtype)
        for i in range(n):
            rows[i, :] = mosaics[i][y, :]
        for p in range(npairs):
            j = pairs[p, 0]
            k = pairs[p, 1]
            mj = rows[j]
            mk = rows[k]
            idx = row_start[p, y]
            s = strides[p]
            for x in range(w):
                px = x & 1
                yj = mj[x]
                yk = mk[x]
                if yj >= white[j] or yk >= white[k]:
                    continue
                bj = black[j, py, px]
                bk = black[k, py, px]
                dj = yj - bj
                dk = yk - bk
                if not (dj < ceiling_fraction * (white[j] - bj) and dk < ceiling_fraction * (white[k] - bk)):
                    continue
                if idx % s == 0:
                    num = 0.0
                    den = 0.0
                    for i in range(n):
                        code = rows[i, x]
                        if code < white[i]:
                            num += code - black[i, py, px]
                            den += expo[i]
                    pos = offsets[p] + idx // s
                    r = dk / expo[k] - dj / expo[j]
                    r2_out[pos] = r * r
                    x_out[pos] = num / den
                idx += 1


@njit(cache=True, nogil=True)
def wls_normal(r2, xs, pair_of, design_g, design_s, params, first, clip):  # pragma: no cover - compiled
    """Normal equations of the noise fit ``E[r2] = sum_q params_q row_q`` with the row
    ``[x * design_g[p], design_s[p]]`` of a sample of pair ``p``: weights ``1 / pred^2`` (the
    variance of ``r2`` for Gaussian ``r``), or ``1 / (sum design_s[p])^2`` in the ``first``
    round; samples with ``r2 > clip * pred`` left out. Returns ``(M, v, used)``."""
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


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def merge_rows(mosaics, black, white, expo, gain, s2, censored, iterations, near, inv_span,
               x_out, var_out, mask_out, bright):  # pragma: no cover - compiled
    """The censored ML merge of :func:`derender.raw.optimal.merge_mosaic_optimal`, per photosite.

    ``mosaics``: a typed list of (H, W) uint16; ``black`` (N, 2, 2), ``white`` (N,), ``expo``
    (N,), ``gain`` (N,), ``s2`` (N,) per frame: ``d_j = y_j - black_j ~ N(X e_j, gain_j
    max(X e_j, 0) + s2_j)``, censored at ``white_j - black_j`` where ``y_j >= white_j``.
    Writes ``X`` and ``1 / I`` times ``inv_span[py, px]`` (and its square) as float32, and
    ``bright`` in ``mask_out`` where every frame is saturated (``X`` the bound ``max_j c_j / e_j``,
    variance ``X^2``)."""
    n = len(mosaics)
    h, w = x_out.shape
    for y in prange(h):
        py = y & 1
        d = np.empty(n)
        c = np.empty(n)
        sat = np.empty(n, np.bool_)
        rows = np.empty((n, w), mosaics[0].dtype)     # the row of every frame (one list access per frame)
        for j in range(n):
            rows[j, :] = mosaics[j][y, :]
        for xx in range(w):
            px = xx & 1
            num = 0.0
            den = 0.0
            bound = 0.0
            for j in range(n):
                code = rows[j, xx]
                bj = black[j, py, px]
                cj = white[j] - bj
                d[j] = code - bj
                c[j] = cj
                sj = code >= white[j]
                sat[j] = sj
                if not sj:
                    num += code - bj
                    den += expo[j]
                b = cj / expo[j]
                if b > bound:
                    bound = b
            sp = inv_span[py, px]
            if den == 0.0:
                x_out[y, xx] = bound * sp
                var_out[y, xx] = (bound * sp) ** 2
                mask_out[y, xx] = bright
                continue
            x = num / den
            info = 0.0
            for _ in range(2):
                score = 0.0
                info = 0.0
                for j in range(n):
                    if not sat[j]:
                        e = expo[j]
                        wj = e / (gain[j] * max(x * e, 0.0) + s2[j])
                        score += wj * (d[j] - x * e)
                        info += wj * e
                if info > 0.0:
                    x += score / info
            close = False
            if censored:
                for j in range(n):
                    if sat[j]:
                        e = expo[j]
                        if c[j] - x * e > -near * math.sqrt(gain[j] * max(x * e, 0.0) + s2[j]):
                            close = True
            if close:
                for _ in range(max(iterations, 1)):
                    score = 0.0
                    info = 0.0
                    for j in range(n):
                        e = expo[j]
                        v = gain[j] * max(x * e, 0.0) + s2[j]
                        if not sat[j]:
                            score += e * (d[j] - x * e) / v
                            info += e * e / v
                        else:
                            sd = math.sqrt(v)
                            z = (c[j] - x * e) / sd
                            lam = inverse_mills(z)
                            score += e * lam / sd
                            info += e * e * lam * max(lam - z, 0.0) / v
                    if info > 0.0:
                        x += score / info
            x_out[y, xx] = x * sp
            var_out[y, xx] = (1.0 / info) * sp * sp if info > 0.0 else 0.0
            mask_out[y, xx] = 0


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def demosaic_rows(x, var, mult, ntaps, tap_dy, tap_dx, taps, taps2, clip_negative, do_var,
                  out, var_out):  # pragma: no cover - compiled
    """White balance, demosaic, colour matrix (and variance) in one pass.

    ``x``, ``var`` (H, W) float32 mosaics; ``mult`` (2, 2) the multiplier of the photosite's
    CFA phase; per output phase ``(py, px)`` the ``ntaps[py, px]`` taps at ``(tap_dy, tap_dx)``
    with weights ``taps[py, px, t, o]`` (the matrix times the demosaic's kernels) and their
    squares ``taps2``. ``out`` (H, W, 3) float32 finite (negatives set to 0 if ``clip_negative``),
    ``var_out`` (H, W, 3) float32 if ``do_var``. Inside the 2-photosite border each tap's
    multiplier is folded into its weights once per row and phase; on the border the taps
    read reflected photosites (whose phase, so multiplier, may differ)."""
    h, w = x.shape
    for y in prange(h):
        py = y & 1
        inner_row = y >= 2 and y < h - 2
        for px in range(2):
            nt = ntaps[py, px]
            wr = np.empty((nt, 3))
            wv = np.empty((nt, 3))
            for t in range(nt):
                m = mult[(py + tap_dy[py, px, t]) & 1, (px + tap_dx[py, px, t]) & 1]
                for o in range(3):
                    wr[t, o] = taps[py, px, t, o] * m
                    wv[t, o] = taps2[py, px, t, o] * (m * m)
            for xx in range(px, w, 2):
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                v0 = 0.0
                v1 = 0.0
                v2 = 0.0
                if inner_row and xx >= 2 and xx < w - 2:
                    for t in range(nt):
                        val = x[y + tap_dy[py, px, t], xx + tap_dx[py, px, t]]
                        a0 += wr[t, 0] * val
                        a1 += wr[t, 1] * val
                        a2 += wr[t, 2] * val
                    if do_var:
                        for t in range(nt):
                            vv = var[y + tap_dy[py, px, t], xx + tap_dx[py, px, t]]
                            v0 += wv[t, 0] * vv
                            v1 += wv[t, 1] * vv
                            v2 += wv[t, 2] * vv
                else:
                    for t in range(nt):
                        yy = _reflect(y + tap_dy[py, px, t], h)
                        xq = _reflect(xx + tap_dx[py, px, t], w)
                        m = mult[yy & 1, xq & 1]
                        val = x[yy, xq] * m
                        a0 += taps[py, px, t, 0] * val
                        a1 += taps[py, px, t, 1] * val
                        a2 += taps[py, px, t, 2] * val
                        if do_var:
                            vv = var[yy, xq] * (m * m)
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
