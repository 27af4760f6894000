"""Compiled passes of the probabilistic merge's variance with shared model error (paper 2, Sec. 3.1).

Paper 2's eq. 3 multiplies the exposures' Gaussians as if their errors were independent,
so the product's variance ``1 / sum_i p_i`` shrinks like ``1 / N`` with the number of frames
that see a pixel. The model's error for a colour is not independent across those frames:
the same scene colour is de-rendered by the same fitted curve in every frame, so the part of
each frame's log variance that comes from the model (the GP's own predictive variance,
``s2m_i``) is shared, while the pixel's code noise (``s2n_i``) is independent. With the
merge's weights ``w_i = p_i / P`` (``P = sum_i p_i``, unchanged: the mean is eq. 3's) the
merged log-space mean ``m = sum_i w_i y_i`` has variance

    V = sum_i w_i^2 s2n_i                       (independent noise: averages out)
      + k_m (sum_i w_i sqrt(s2m_i))^2           (model error, fully correlated: does not)
      + k_p sum_i w_i (y_i - m)^2               (pipeline change: the frames' disagreement)

where ``y_i`` is frame i's log estimate scaled to the target exposure. The third term is the
weighted spread of the frames' estimates around the merged mean: white balance or gain that
changes between frames (outside the model) moves each frame's estimate by its own amount, and
the spread measures that per pixel; ``k_p`` and ``k_m`` are chosen on the tuning families
(:mod:`derender.hdr.probabilistic_variance`).

:func:`gaussian_variance_band` is :func:`derender.engine.kernels.gaussian_moments_band` with
these three extra sums (``sum p y^2``, ``sum p sqrt(s2m)``, ``sum p^2 s2n``) accumulated in
the same pass: the radiance is computed by the same float64 operations in the same order
(the same bytes), the variance from ``V``. The table (M, 8) is the probabilistic merge's
``[lg (3), p, low (3), sm]`` with ``sm = sqrt(s2m)`` in the column that was padding
(:func:`model_sd_rows` fills it). Per row it also counts, in ``hist`` (H, 3, NBINS), the share
of each source in ``V`` (model, noise, pipeline change) of every measured pixel-channel, so
the medians of the shares are read off without a full-size array.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from derender.engine.kernels import normal_cdf, table_mu  # the same compiled helpers as the merge kernels

__all__ = ["NBINS", "gaussian_variance_band", "model_sd_rows"]

#: Bins of the per-row histograms of the variance sources' shares (share in [0, 1]).
NBINS = 50


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True, error_model="numpy")
def model_sd_rows(colours, s0, s1, tab_lv, tab_mu, lut_lo, lut_w, eps, floor, clip_code, censor, per_channel,
                  max_log, table):  # pragma: no cover - compiled
    """Column 7 of the colour-major table for colours ``s0:s1``: ``sqrt(mean_c s2m_c)`` over the
    colour's measured (uncensored) channels, ``s2m_c = min(s2_c (e / r)^2, 1e6) + floor`` the
    GP's own log variance by the delta method of
    :func:`derender.engine.kernels.log_tables_rows` (0 where every channel is censored)."""
    tiny = 1e-30
    for i in range(s0, s1):
        c0 = np.int64(colours[i, 0])
        c1 = np.int64(colours[i, 1])
        c2 = np.int64(colours[i, 2])
        any_clipped = censor and (c0 >= clip_code or c1 >= clip_code or c2 >= clip_code)
        tot = 0.0
        n_ok = 0
        for ch in range(3):
            cc = c0 if ch == 0 else (c1 if ch == 1 else c2)
            clipped = censor and cc >= clip_code
            if not per_channel:
                clipped = any_clipped
            if clipped:
                continue
            mu = table_mu(tab_mu, lut_lo, lut_w, c0, c1, c2, ch)
            s2 = math.exp(table_mu(tab_lv, lut_lo, lut_w, c0, c1, c2, ch))
            if np.isnan(mu):
                mu = 0.0
            mu = min(max(mu, -max_log), max_log)
            if np.isnan(s2):
                s2 = 1e6
            s2 = min(max(s2, 1e-12), 1e6)
            e = math.exp(mu)
            r = max(e - eps, tiny)
            q = e / r
            tot += min(s2 * (q * q), 1e6) + floor
            n_ok += 1
        table[i, 7] = math.sqrt(tot / np.float64(n_ok)) if n_ok > 0 else 0.0


@njit(inline="always")
def _truncated(m, v, bd, max_log):  # pragma: no cover - compiled
    """:func:`derender.hdr.lognormal.truncate_below_log` of one channel: (m, v) truncated below at ``bd`` (see the kernel)."""
    active = np.isfinite(bd)
    finite = np.isfinite(v)
    om = m
    ov = v
    if active and finite:
        sd = math.sqrt(v)
        alpha = (bd - m) / max(sd, 1e-300)
        if alpha < 3.0 and alpha > -8.0:
            tail = max(1.0 - normal_cdf(alpha), 1e-300)
            lam = math.exp(-0.5 * alpha * alpha) * (1.0 / math.sqrt(2.0 * math.pi)) / tail
            om = m + sd * lam
            ov = v * max(1.0 + alpha * lam - lam * lam, 1e-6)
    elif active:
        om = bd - 0.5
        ov = 1.0
    if not (np.isfinite(ov) and np.isfinite(om)):
        om = -max_log
        ov = 1.0
    return om, ov


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True, error_model="numpy")
def _spatial_row(r, y, nr, w, row0, lf, b3, radiance, variance, k_spatial, big, hist):  # pragma: no cover
    """Add the spatial-mixing term to output row ``y`` (band row ``r``) from the floored log
    output ``lf`` of rows ``r - 1 .. r + 1`` (rings of 3 rows; only rows of the band), and count
    the sources' shares of row ``y`` (``b3``: ring of 2 rows of the log-space terms)."""
    nb = hist.shape[2]
    i0 = r % 3
    im = (r + 2) % 3
    ip = (r + 1) % 3
    count = y % 4 == 0           # the sources' shares on a 1-in-4 grid of rows and columns
    for x in range(w):
        for c in range(3):
            f = np.float64(lf[i0, x, c])
            d2 = 0.0
            nd = 0
            if x > 0:
                dd = f - np.float64(lf[i0, x - 1, c])
                d2 += dd * dd
                nd += 1
            if x + 1 < w:
                dd = f - np.float64(lf[i0, x + 1, c])
                d2 += dd * dd
                nd += 1
            if r > 0:
                dd = f - np.float64(lf[im, x, c])
                d2 += dd * dd
                nd += 1
            if r + 1 < nr:
                dd = f - np.float64(lf[ip, x, c])
                d2 += dd * dd
                nd += 1
            rs = k_spatial * math.sqrt(d2 / nd) if nd > 0 else 0.0        # relative variance
            lo_ = np.float64(radiance[y - row0, x, c])
            vo = np.float64(variance[y - row0, x, c])
            if rs > 0.0 and lo_ > 0.0:
                vo = min(vo + rs * (lo_ * lo_), big)
                variance[y - row0, x, c] = np.float32(vo)
            i1 = r % 2
            if not count:
                continue
            t3 = b3[i1, x, c, 0] + b3[i1, x, c, 1] + b3[i1, x, c, 2]
            if t3 > 0.0 and lo_ > 0.0 and x % 4 == 0:
                rel = vo / (lo_ * lo_)              # total relative variance, spatial included
                sh_s = min(rs / rel, 1.0) if rel > 0.0 else 0.0
                rest = (1.0 - sh_s) / t3
                for q in range(3):
                    hist[y, q, min(int(b3[i1, x, c, q] * rest * nb), nb - 1)] += 1
                hist[y, 3, min(int(sh_s * nb), nb - 1)] += 1


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True, error_model="numpy")
def gaussian_variance_band(frames, valid, lut, table, log_scales, y0, y1, censor, max_log, max_v, a, use_a,
                           row0, radiance, variance, k_model, k_pipe, k_spatial, floor_share,
                           hist):  # pragma: no cover - compiled
    """Rows ``y0:y1`` of the probabilistic merge with the shared-error variance (module docstring):
    ``radiance`` as :func:`derender.engine.kernels.gaussian_moments_band` (same operations), the
    variance the log-normal's about that radiance for the log variance ``V`` (censored channels:
    ``V`` truncated below at the bound as the mean's ``v`` is), the mean's squared distance to the
    log-normal ``(m, V)``'s mean added; through ``a`` by its squares. Then, on the band's output,
    the spatial-mixing term ``k_spatial L_c^2 sqrt(D_c)``: ``D_c`` the mean squared difference of
    ``log(L_c + floor_share mean_c L)`` (float32) to the four neighbours within the band (rows outside
    ``y0:y1`` are not read: a band's result does not depend on the others), added one row behind.
    The noise sums need no division per frame: with ``1 / p = sm^2 + vn`` (joint means over the
    same channels), ``sum p^2 vn = P - sum (p sm)^2`` and ``sum p vn = N - sum p sm^2``.
    float32 outputs. ``hist[y]`` (4, NBINS) int64 counts, per measured pixel-channel of row
    ``y`` on a 1-in-4 grid (rows and columns divisible by 4), the shares of model / noise / pipeline change / spatial mixing in the relative
    variance. Releases the GIL."""
    n = frames.shape[0]
    w = frames.shape[2]
    nr = y1 - y0
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    prec = np.empty((3, w))
    acc = np.empty((3, w))
    bound = np.empty((3, w))
    # per pixel, one cache line: sum p y^2 (3 channels), then over frames with every channel measured
    # sum p sm, sum (p sm)^2, sum p sm^2, their count
    ex = np.empty((w, 8))
    ct = np.empty((3, w, 4))        # the last four per channel, frames with a channel censored (zeroed on use)
    b3 = np.empty((2, w, 3, 3))     # ring of 2 rows: model / noise / pipeline terms of V (0: unmeasured)
    lf = np.empty((3, w, 3), dtype=np.float32)   # ring of 3 rows: floored log of the output (spatial term)
    big = np.float64(np.finfo(np.float32).max) / 4.0
    inf = np.inf
    mean0 = np.empty(3)
    var0 = np.empty(3)
    for y in range(y0, y1):
        r = y - y0
        i1 = r % 2
        prec[:, :] = 0.0
        acc[:, :] = 0.0
        bound[:, :] = -inf
        ex[:, :] = 0.0
        cens = False
        for j in range(n):
            ls = log_scales[j]
            for x in range(w):
                if not whole and valid[j, y, x] == 0:
                    continue
                k = lut[(np.int64(frames[j, y, x, 0]) << 16) | (np.int64(frames[j, y, x, 1]) << 8)
                        | np.int64(frames[j, y, x, 2])]
                pj = table[k, 3]
                for c in range(3):
                    lo = table[k, 4 + c]
                    p = pj if lo == -inf else 0.0
                    prec[c, x] += p
                    yy = table[k, c] + ls
                    acc[c, x] += yy * p
                    ex[x, c] += p * (yy * yy)
                    b = lo + ls
                    if b > bound[c, x]:
                        bound[c, x] = b
                sm = table[k, 7]
                psm = pj * sm
                if table[k, 4] == -inf and table[k, 5] == -inf and table[k, 6] == -inf:
                    ex[x, 3] += psm
                    ex[x, 4] += psm * psm
                    ex[x, 5] += psm * sm
                    ex[x, 6] += 1.0
                else:
                    if not cens:
                        ct[:, :, :] = 0.0
                        cens = True
                    for c in range(3):
                        if table[k, 4 + c] == -inf:
                            ct[c, x, 0] += psm
                            ct[c, x, 1] += psm * psm
                            ct[c, x, 2] += psm * sm
                            ct[c, x, 3] += 1.0
        for x in range(w):
            for c in range(3):
                pr = prec[c, x]
                if pr > 0.0:
                    v = 1.0 / pr
                    m = acc[c, x] * v
                    s0 = ex[x, 3]
                    s1 = ex[x, 4]
                    s2 = ex[x, 5]
                    s3 = ex[x, 6]
                    if cens:
                        s0 += ct[c, x, 0]
                        s1 += ct[c, x, 1]
                        s2 += ct[c, x, 2]
                        s3 += ct[c, x, 3]
                    vm = s0 * v
                    vm = k_model * (vm * vm)
                    noi = max(pr - s1, 0.0)                 # sum p^2 vn
                    nw = max(s3 - s2, 0.0)                  # sum p vn
                    vnz = noi * (v * v)
                    # the spread beyond what the independent noise explains: sum w vn - sum w^2 vn
                    vp = k_pipe * max(ex[x, c] * v - m * m - (nw * v - vnz), 0.0)
                    b3[i1, x, c, 0] = vm
                    b3[i1, x, c, 1] = vnz
                    b3[i1, x, c, 2] = vp
                    vv = max(vm + vnz + vp, v)
                else:
                    v = inf
                    m = 0.0
                    vv = inf
                    b3[i1, x, c, 0] = 0.0
                    b3[i1, x, c, 1] = 0.0
                    b3[i1, x, c, 2] = 0.0
                mv = m
                if censor:
                    m, v = _truncated(m, v, bound[c, x], max_log)
                    mv, vv = _truncated(mv, vv, bound[c, x], max_log)
                m = min(max(m, -max_log), max_log)
                v = min(max(v, 0.0), max_v)
                mv = min(max(mv, -max_log), max_log)
                vv = min(max(vv, 0.0), max_v)
                e = math.exp(m + 0.5 * v)
                mean0[c] = e
                ev = math.exp(mv + 0.5 * vv)
                d = ev - e
                var0[c] = math.expm1(vv) * (ev * ev) + d * d
            tot = 0.0
            for c in range(3):
                if use_a:
                    mo = mean0[0] * a[c, 0] + mean0[1] * a[c, 1] + mean0[2] * a[c, 2]
                    vo = var0[0] * (a[c, 0] * a[c, 0]) + var0[1] * (a[c, 1] * a[c, 1]) + var0[2] * (a[c, 2] * a[c, 2])
                else:
                    mo = mean0[c]
                    vo = var0[c]
                if np.isnan(mo):
                    mo = 0.0
                if mo < 0.0:          # projected onto the non-negative orthant (finite_outputs)
                    vo = vo + mo * mo
                    mo = 0.0
                mo = min(mo, big)
                radiance[y - row0, x, c] = np.float32(mo)
                if np.isnan(vo):
                    vo = big
                variance[y - row0, x, c] = np.float32(min(max(vo, 0.0), big))
                tot += np.float64(np.float32(mo))
            for c in range(3):
                lf[r % 3, x, c] = math.log(np.float32(np.float64(radiance[y - row0, x, c]) + floor_share * tot / 3.0)
                                           + np.float32(1e-30))
        if r > 0:
            _spatial_row(r - 1, y - 1, nr, w, row0, lf, b3, radiance, variance, k_spatial, big, hist)
    if nr > 0:
        _spatial_row(nr - 1, y1 - 1, nr, w, row0, lf, b3, radiance, variance, k_spatial, big, hist)
