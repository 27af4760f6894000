"""Compiled merges that also give the variance (:mod:`derender.engine.variance`).

:func:`table_merge_var_rows` and :func:`stabilized_merge_var_rows` are
:func:`derender.engine.kernels.table_merge_rows` and
:func:`derender.engine.kernels.stabilized_merge_rows` with the same radiance arithmetic
(the same bytes) plus, per pixel and channel, the sums ``sum w``, ``sum w u``,
``sum w u^2`` (float64: the difference ``D`` below cancels), ``sum w^2`` and ``sum w^2 s^2``
(noise and quantisation apart; float32, sums of positive terms), fused into the radiance's
pass: each frame's codes are read once and one look-up in a packed table (weight or
inverse variance, value, noise + quantisation, quantisation: 16 bytes per frame, code and
channel) serves both. At the end of each tile they become the variance of
:mod:`derender.engine.variance`:

    Var u = a (Qn + Qq) / S0^2 + b D r / max(1 - r, r_floor) + c D + e R,   r = W2 / S0^2,
    D = S2 / S0 - (S1 / S0)^2,   R = (P2 - 2 mu P1 + mu^2 W2) / S0^2,   mu = S1 / S0,
    Var r = [r^2 if log] Var u + shared^2 r^2

(``k = [a, b, shared^2, censored, r_floor, c, e]``; ``P1 = sum w^2 u``, ``P2 = sum w^2 u^2``,
float64, summed only when ``e`` is not 0: ``R = sum w^2 (u - mu)^2 / S0^2`` is the robust
variance of the weighted mean, :mod:`derender.engine.variance`). In the log domain the kernel writes the
relative variance (``Var u`` + ``shared^2``, without the factor ``r^2``) and the caller
multiplies it by the radiance squared after its exponential (vectorised, instead of one
``exp`` per pixel-channel here); in the ``"mean"`` mode (one weight per pixel) ``sum w`` and
``sum w^2`` are kept once per pixel, frames without weight add exact zeros (no branch), and the log domain
reads ``sum w``, ``sum w u`` from the radiance's own float64 sums. Rows ``y`` with ``y % stride == 0`` also
write the four sources (noise, quantisation, disagreement, shared) into ``parts``
(4, ceil(H / stride), W, 3) for ``info["variance_sources"]``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from derender.engine.kernels import MERGE_TILE
from derender.engine.merge_parts import add_frame_to_tile_var, add_table_observation, fallback_frame

__all__ = ["table_merge_var_rows", "stabilized_merge_var_rows", "variance_finish_rows"]


@njit(inline="always")
def _acc(vs, c, t, wc, uc, nq, q, split, own, log_domain):  # pragma: no cover - compiled
    """Add one observation (weight ``wc``, value ``uc``, noise + quantisation variance ``nq``) to the
    sums; ``own`` False: the pixel's weight is shared by its channels (``"mean"`` mode) and
    ``sum w``, ``sum w^2`` are kept once, in channel 0's planes. In the log domain the radiance's
    own float64 sums ``den64``, ``num64`` are ``sum w`` and ``sum w u`` (the same products, in the
    same order), so only ``sum w u^2`` and the variance sums are added here."""
    ww = wc * wc
    wu = wc * uc
    if own:
        if not log_domain:
            vs[0, c, t] += wc
        vs[3, c, t] += ww
    if not log_domain:
        vs[1, c, t] += wu
    vs[2, c, t] += wu * uc
    vs[4, c, t] += ww * nq
    if split:
        vs[5, c, t] += ww * q


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(inline="always")
def _finish_var(s0, s1, s2, w2, qn, qq, k, log_domain, m, p1, p2):  # pragma: no cover - compiled
    """(noise, quant, disagreement, shared) variance of a merged value ``m`` (radiance) from its
    sums (``p1``, ``p2``: ``sum w^2 u``, ``sum w^2 u^2``, read when ``k[6]`` is not 0)."""
    inv = 1.0 / s0
    r = w2 * inv * inv
    mu = s1 * inv
    d = max(s2 * inv - mu * mu, 0.0)
    vd = k[5] * d
    if k[6] != 0.0:
        vd += k[6] * max((p2 - 2.0 * mu * p1 + mu * mu * w2) * inv * inv, 0.0)
    if k[1] != 0.0:        # the methods' constants have none: no division
        vd += k[1] * d * r / max(1.0 - r, k[4])
    vn = k[0] * qn * inv * inv
    vq = k[0] * qq * inv * inv
    if log_domain:      # relative: the caller multiplies by the radiance squared after its exponential
        return vn, vq, vd, k[2]
    return vn, vq, vd, k[2] * m * m


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(inline="always")
def _store(var, parts, y, row0, x, c, pn, pq, pd, ps, stride, big):  # pragma: no cover - compiled
    """A pixel-channel's variance (the sum of its sources, ``big`` where not finite or beyond) and,
    on every ``stride``-th row, its sources (noise, quantisation, disagreement, shared)."""
    tot = pn + pq + pd + ps
    if not (tot >= 0.0):
        tot = big
    var[c, y - row0, x] = np.float32(min(tot, big))
    if y % stride == 0:
        yy = y // stride
        parts[0, yy, x, c] = np.float32(min(pn, big))
        parts[1, yy, x, c] = np.float32(min(pq, big))
        parts[2, yy, x, c] = np.float32(min(pd, big))
        parts[3, yy, x, c] = np.float32(min(ps, big))


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def table_merge_var_rows(frames, valid, ref, order, values, weights, independent, log_domain, v_short, v_long,
                         j_short, j_long, bright, y0, y1, row0, out, mask, tn, tq, k, var, parts,
                         stride):  # pragma: no cover - compiled
    """:func:`derender.engine.kernels.table_merge_rows` (same arguments up to ``mask``, same
    radiance) and the variance into ``var`` (3, rows, W) float32 (row ``y`` at ``y - row0``),
    the radiance's own units (linear, after the caller's exponential in the log domain):
    ``tn``, ``tq`` (N, 256, 3) the noise and quantisation variance of each frame's values,
    ``k`` the constants (module docstring).

    One pass per tile: each frame's codes are read once (:func:`add_table_observation`, the
    radiance's own arithmetic) and their weights and values serve the variance's sums too,
    without a branch (a frame without weight adds exact zeros). ``sum w u^2`` (and, in the
    linear domain, ``sum w``, ``sum w u``) are float64, as the difference ``D`` needs; the sums
    of positive terms ``sum w^2``, ``sum w^2 s^2`` are float32 (relative error ~1e-7)."""
    n = order.shape[0]
    nf = frames.shape[0]
    w = frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    tile = MERGE_TILE
    f32max = np.float32(3.4028234663852886e38)
    big = np.float64(f32max) / 4.0
    # one 16-byte entry per (frame, code, channel): weight, value, noise + quantisation,
    # quantisation, so that a look-up reads one cache line instead of four
    nfr = values.shape[0]
    pk = np.empty((nfr, values.shape[1], 3, 4), dtype=np.float32)
    for jf in range(nfr):
        for zf in range(values.shape[1]):
            for cf in range(3):
                pk[jf, zf, cf, 0] = weights[jf, zf, cf]
                pk[jf, zf, cf, 1] = values[jf, zf, cf]
                pk[jf, zf, cf, 2] = tn[jf, zf, cf] + tq[jf, zf, cf]
                pk[jf, zf, cf, 3] = tq[jf, zf, cf]
    wts = pk[:, :, :, 0]
    vals = pk[:, :, :, 1]
    tnq = pk[:, :, :, 2]
    tqq = pk[:, :, :, 3]
    robust = k[6] != 0.0
    for y in prange(y0, y1):
        split = y % stride == 0
        num64 = np.zeros((3, tile), dtype=np.float64)
        den64 = np.zeros((3, tile), dtype=np.float64)
        num32 = np.zeros((3, tile), dtype=np.float32)
        den32 = np.zeros((3, tile), dtype=np.float32)
        s2 = np.zeros((3, tile), dtype=np.float64)       # sum w u^2
        s0 = np.zeros((3, tile), dtype=np.float64)       # sum w (linear domain)
        s1 = np.zeros((3, tile), dtype=np.float64)       # sum w u (linear domain)
        w2s = np.zeros((3, tile), dtype=np.float32)      # sum w^2
        qnq = np.zeros((3, tile), dtype=np.float32)      # sum w^2 (noise + quantisation)
        qq = np.zeros((3, tile), dtype=np.float32)       # sum w^2 quantisation (sampled rows)
        p1 = np.zeros((3, tile), dtype=np.float64)       # sum w^2 u (robust term)
        p2 = np.zeros((3, tile), dtype=np.float64)       # sum w^2 u^2 (robust term)
        for x0 in range(0, w, tile):
            xe = min(x0 + tile, w)
            num64[:, :] = 0.0
            den64[:, :] = 0.0
            num32[:, :] = 0.0
            den32[:, :] = 0.0
            s2[:, :] = 0.0
            w2s[:, :] = 0.0
            qnq[:, :] = 0.0
            if not log_domain:
                s0[:, :] = 0.0
                s1[:, :] = 0.0
            if split:
                qq[:, :] = 0.0
            if robust:
                p1[:, :] = 0.0
                p2[:, :] = 0.0
            for kk in range(n):
                j = order[kk]
                for x in range(x0, xe):
                    if not whole and valid[j, y, x] == 0:
                        continue
                    t = x - x0
                    z0, z1, z2, w0, w1, w2, v0, v1, v2 = add_table_observation(
                        frames, j, y, x, t, wts, vals, independent, log_domain, num64, den64, num32, den32)
                    a0 = np.float64(v0) * np.float64(w0)
                    a1 = np.float64(v1) * np.float64(w1)
                    a2 = np.float64(v2) * np.float64(w2)
                    s2[0, t] += a0 * np.float64(v0)
                    s2[1, t] += a1 * np.float64(v1)
                    s2[2, t] += a2 * np.float64(v2)
                    e0 = w0 * w0
                    if independent:
                        e1 = w1 * w1
                        e2 = w2 * w2
                        w2s[1, t] += e1
                        w2s[2, t] += e2
                    else:
                        e1 = e0
                        e2 = e0
                    w2s[0, t] += e0
                    if robust:
                        b0 = np.float64(e0) * np.float64(v0)
                        b1 = np.float64(e1) * np.float64(v1)
                        b2 = np.float64(e2) * np.float64(v2)
                        p1[0, t] += b0
                        p1[1, t] += b1
                        p1[2, t] += b2
                        p2[0, t] += b0 * np.float64(v0)
                        p2[1, t] += b1 * np.float64(v1)
                        p2[2, t] += b2 * np.float64(v2)
                    qnq[0, t] += e0 * tnq[j, z0, 0]
                    qnq[1, t] += e1 * tnq[j, z1, 1]
                    qnq[2, t] += e2 * tnq[j, z2, 2]
                    if not log_domain:
                        s0[0, t] += np.float64(w0)
                        if independent:
                            s0[1, t] += np.float64(w1)
                            s0[2, t] += np.float64(w2)
                        s1[0, t] += a0
                        s1[1, t] += a1
                        s1[2, t] += a2
                    if split:
                        qq[0, t] += e0 * tqq[j, z0, 0]
                        qq[1, t] += e1 * tqq[j, z1, 1]
                        qq[2, t] += e2 * tqq[j, z2, 2]
            for x in range(x0, xe):
                t = x - x0
                nb = False
                ndk = False
                for c in range(3):
                    dc = c if independent else 0
                    jj = -1
                    if log_domain:
                        ok = den64[dc, t] > 0.0
                        r = num64[c, t] / den64[dc, t] if ok else 0.0
                    else:
                        ok = den32[dc, t] > np.float32(0.0)
                        r = np.float64(num32[c, t] / den32[dc, t]) if ok else 0.0
                    if not ok and (whole or ref < 0):
                        zs = frames[j_short, y, x, c]
                        if bright[zs]:
                            r = np.float64(v_short[zs, c])
                            nb = True
                            jj = j_short
                        else:
                            r = np.float64(v_long[frames[j_long, y, x, c], c])
                            ndk = True
                            jj = j_long
                    elif not ok:
                        up = bright[frames[ref, y, x, c]]
                        jj = ref
                        for kk in range(nf):
                            jv = kk if up else nf - 1 - kk
                            if valid[jv, y, x] != 0 and bright[frames[jv, y, x, c]] == up:
                                jj = jv
                                break
                        r = np.float64(values[jj, frames[jj, y, x, c], c])
                        if up:
                            nb = True
                        else:
                            ndk = True
                    if log_domain:
                        out[c, y - row0, x] = np.float32(min(r, 88.0))
                        m = 1.0       # the variance stays relative (module docstring)
                    else:
                        o = np.float32(r)
                        if np.isnan(o):
                            o = np.float32(0.0)
                        elif o > f32max:
                            o = f32max
                        elif o < -f32max:
                            o = -f32max
                        out[c, y - row0, x] = o
                        m = np.float64(o)
                    sw = den64[dc, t] if log_domain else s0[dc, t]
                    if jj < 0 and sw > 0.0:
                        swu = num64[c, t] if log_domain else s1[c, t]
                        qc = np.float64(qq[c, t]) if split else 0.0
                        pn, pq, pd, ps = _finish_var(sw, swu, s2[c, t], np.float64(w2s[dc, t]),
                                                     np.float64(qnq[c, t]) - qc, qc, k, log_domain, m, p1[c, t],
                                                     p2[c, t])
                    else:
                        if jj < 0:
                            jj = j_short if bright[frames[j_short, y, x, c]] else j_long
                        zc = frames[jj, y, x, c]
                        pn = np.float64(tn[jj, zc, c])
                        pq = np.float64(tq[jj, zc, c])
                        pd = k[3] * m * m
                        ps = k[2] * m * m
                    _store(var, parts, y, row0, x, c, pn, pq, pd, ps, stride, big)
                mask[y, x] = 1 if nb else (2 if ndk else 0)


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(inline="always")
def _bright_set_sums(frames, valid, whole, shifts, y, x, h, w, weights, inv_var, inv_k, use_inv_var, colour_w,
                     use_colour_w, lin, mats32, sqm, tnq, tq, mu0, mu1, mu2, split, vs):  # pragma: no cover
    """A pixel no frame measures in every channel (the brightest-channel weights): its sums
    ``vs`` (14,) (S0, W2, sum w (v - mu)^2 (3), Qnq (3), Qq (3), sum w^2 (v - mu)^2 (3)) around its merged mean, the
    frames read a second time (rare pixels)."""
    zero = np.float32(0.0)
    tiny = np.float32(1e-30)
    n = frames.shape[0]
    vs[:] = 0.0
    for j in range(n):
        yy = y + shifts[j, 0]
        xx = x + shifts[j, 1]
        if yy < 0 or yy >= h or xx < 0 or xx >= w:
            continue
        if not whole and valid[j, y, x] == 0:
            continue
        z0 = frames[j, yy, xx, 0]
        z1 = frames[j, yy, xx, 1]
        z2 = frames[j, yy, xx, 2]
        ws = weights[max(max(z0, z1), z2), 0]
        if ws == zero:
            continue
        if use_inv_var:
            d = inv_var[j, z0, 0] + inv_var[j, z1, 1]
            d = d + inv_var[j, z2, 2]
            ws = ws * (inv_k[j] / max(d, tiny))
        if use_colour_w:
            ws = ws * colour_w[(np.int64(z0) << 16) | (np.int64(z1) << 8) | np.int64(z2)]
        l0 = lin[j, z0, 0]
        l1 = lin[j, z1, 1]
        l2 = lin[j, z2, 2]
        wd = np.float64(ws)
        ww = wd * wd
        n0 = np.float64(tnq[j, z0, 0])
        n1 = np.float64(tnq[j, z1, 1])
        n2 = np.float64(tnq[j, z2, 2])
        vs[0] += wd
        vs[1] += ww
        m32 = mats32[j]
        sq = sqm[j]
        for c in range(3):
            mu = mu0 if c == 0 else (mu1 if c == 1 else mu2)
            vc = np.float64(max(l0 * m32[c, 0] + l1 * m32[c, 1] + l2 * m32[c, 2], zero)) - mu
            vs[2 + c] += wd * vc * vc
            vs[11 + c] += ww * vc * vc
            vs[5 + c] += ww * (sq[c, 0] * n0 + sq[c, 1] * n1 + sq[c, 2] * n2)
            if split:
                vs[8 + c] += ww * (sq[c, 0] * tq[j, z0, 0] + sq[c, 1] * tq[j, z1, 1] + sq[c, 2] * tq[j, z2, 2])


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def stabilized_merge_var_rows(frames, shifts, valid, ref, lin, mats32, mats64, weights, inv_var, inv_k, use_inv_var,
                              colour_w, use_colour_w, j_short, j_long, bright, y0, y1, row0, out, mask, tn, tq, k, var,
                              parts, stride):  # pragma: no cover - compiled
    """:func:`derender.engine.kernels.stabilized_merge_rows` (same arguments up to ``mask``, same
    radiance) and the variance into ``var`` (3, rows, W) float32: frame ``j``'s channel ``c``
    has noise variance ``sum_k mats64[j, c, k]^2 tn[j, z_k, k]`` (and so quantisation with
    ``tq``).

    One pass over each tile's frames (:func:`~derender.engine.merge_parts.add_frame_to_tile_var`:
    the radiance's arithmetic and, for the weights of frames measured in every channel, the
    variance's float64 sums ``sum w``, ``sum w v``, ``sum w v^2``, float32 ``sum w^2`` and
    ``sum w^2 s^2``; ``D = sum w v^2 / sum w - (sum w v / sum w)^2``). The rare pixels no
    frame measures in every channel (the brightest-channel weights) are summed again around
    their mean (:func:`_bright_set_sums`)."""
    n = frames.shape[0]
    h, w = frames.shape[1], frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    zero = np.float32(0.0)
    tile = MERGE_TILE
    big = np.float64(np.finfo(np.float32).max) / 4.0
    sqm = mats64 * mats64
    sqm32 = sqm.astype(np.float32)
    # one 16-byte entry per (frame, code, channel): linear value, inverse variance, noise +
    # quantisation, quantisation (one cache line per look-up instead of four)
    pk = np.empty((n, lin.shape[1], 3, 4), dtype=np.float32)
    for jf in range(n):
        for zf in range(lin.shape[1]):
            for cf in range(3):
                pk[jf, zf, cf, 0] = lin[jf, zf, cf]
                pk[jf, zf, cf, 1] = inv_var[jf, zf, cf] if use_inv_var else zero
                pk[jf, zf, cf, 2] = tn[jf, zf, cf] + tq[jf, zf, cf]
                pk[jf, zf, cf, 3] = tq[jf, zf, cf]
    linp = pk[:, :, :, 0]
    ivp = pk[:, :, :, 1]
    tnq = pk[:, :, :, 2]
    tqp = pk[:, :, :, 3]
    robust = k[6] != 0.0
    for y in prange(y0, y1):
        split = y % stride == 0
        acc = np.empty((8, tile), dtype=np.float32)
        usable = np.empty(tile, dtype=np.bool_)
        s64 = np.empty((13, tile), dtype=np.float64)   # S0, sum w v (3), sum w v^2 (3), sum w^2 v (3), sum w^2 v^2 (3)
        s32 = np.empty((7, tile), dtype=np.float32)    # W2, Qnq (3), Qq (3)
        vb = np.empty(14, dtype=np.float64)
        for x0 in range(0, w, tile):
            xe = min(x0 + tile, w)
            acc[:, :] = zero
            usable[:] = False
            s64[:, :] = 0.0
            s32[:, :] = zero
            for j in range(n):
                yy = y + shifts[j, 0]
                if yy < 0 or yy >= h:
                    continue
                add_frame_to_tile_var(frames, valid, whole, j, y, yy, shifts[j, 1], x0, xe, w, weights, ivp,
                                      inv_k[j], use_inv_var, colour_w, use_colour_w, linp, mats32, acc, usable,
                                      tnq, tqp, sqm32, split, s64, s32, robust)
            for x in range(x0, xe):
                t = x - x0
                if usable[t] and acc[0, t] > zero:
                    dm = acc[0, t]
                    out[0, y - row0, x] = acc[1, t] / dm
                    out[1, y - row0, x] = acc[2, t] / dm
                    out[2, y - row0, x] = acc[3, t] / dm
                    mask[y, x] = 0
                    sw = s64[0, t]
                    for c in range(3):
                        m = np.float64(out[c, y - row0, x])
                        qc = np.float64(s32[4 + c, t]) if split else 0.0
                        pn, pq, pd, ps = _finish_var(sw, s64[1 + c, t], s64[4 + c, t], np.float64(s32[0, t]),
                                                     np.float64(s32[1 + c, t]) - qc, qc, k, False, m,
                                                     s64[7 + c, t], s64[10 + c, t])
                        _store(var, parts, y, row0, x, c, pn, pq, pd, ps, stride, big)
                    continue
                if not usable[t] and acc[4, t] > zero:
                    dm = acc[4, t]
                    out[0, y - row0, x] = acc[5, t] / dm
                    out[1, y - row0, x] = acc[6, t] / dm
                    out[2, y - row0, x] = acc[7, t] / dm
                    mask[y, x] = 0
                    _bright_set_sums(frames, valid, whole, shifts, y, x, h, w, weights, inv_var, inv_k, use_inv_var,
                                     colour_w, use_colour_w, lin, mats32, sqm, tnq, tq,
                                     np.float64(acc[5, t] / dm), np.float64(acc[6, t] / dm),
                                     np.float64(acc[7, t] / dm), split, vb)
                    for c in range(3):
                        m = np.float64(out[c, y - row0, x])
                        pn, pq, pd, ps = _finish_var(vb[0], 0.0, vb[2 + c], vb[1], vb[5 + c] - vb[8 + c], vb[8 + c],
                                                     k, False, m, 0.0, vb[11 + c])
                        _store(var, parts, y, row0, x, c, pn, pq, pd, ps, stride, big)
                    continue
                jj, code = fallback_frame(frames, valid, whole, ref, shifts, j_short, j_long, bright, y, x, h, w)
                mask[y, x] = code
                ys = min(max(y + shifts[jj, 0], 0), h - 1)
                xs = min(max(x + shifts[jj, 1], 0), w - 1)
                c0 = frames[jj, ys, xs, 0]
                c1 = frames[jj, ys, xs, 1]
                c2 = frames[jj, ys, xs, 2]
                e0 = np.float64(lin[jj, c0, 0])
                e1 = np.float64(lin[jj, c1, 1])
                e2 = np.float64(lin[jj, c2, 2])
                for c in range(3):
                    o = np.float32(max(e0 * mats64[jj, c, 0] + e1 * mats64[jj, c, 1] + e2 * mats64[jj, c, 2], 0.0))
                    out[c, y - row0, x] = o
                    m = np.float64(o)
                    m0 = mats64[jj, c, 0] * mats64[jj, c, 0]
                    m1 = mats64[jj, c, 1] * mats64[jj, c, 1]
                    m2 = mats64[jj, c, 2] * mats64[jj, c, 2]
                    pn = m0 * tn[jj, c0, 0] + m1 * tn[jj, c1, 1] + m2 * tn[jj, c2, 2]
                    pq = m0 * tq[jj, c0, 0] + m1 * tq[jj, c1, 1] + m2 * tq[jj, c2, 2]
                    _store(var, parts, y, row0, x, c, pn, pq, k[3] * m * m, k[2] * m * m, stride, big)


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def variance_finish_rows(radiance, var, parts, e2, relative, y0, y1, row0, stride, cap):  # pragma: no cover
    """The variance's last steps on rows ``y0:y1`` of a band (``radiance``, ``var`` (3, rows, W)
    float32, image row ``y`` at ``y - row0``), in one pass per pixel-channel:

    * ``relative`` (the log-domain kernel's relative variance): ``var *= r^2`` with ``r^2`` the
      float32 square of the radiance (:func:`derender.engine.variance.scale_relative_variance`'s
      products), and the sampled rows' sources ``parts[:4]`` too; non-finite or beyond ``cap``: ``cap``;
    * the edge term ``e2 Var_3x3(r)`` (:func:`derender.engine.variance.add_edge_term`; the
      3x3 neighbourhood within the band, its first and last rows and columns repeated; float64
      sums), added to ``var`` (capped at ``cap``) and written as the sampled rows' ``parts[4]``."""
    w = radiance.shape[2]
    ninth = 1.0 / 9.0
    for y in prange(y0, y1):
        split = y % stride == 0
        yy = y // stride
        ra = max(y - 1, y0) - row0
        rb = y - row0
        rc = min(y + 1, y1 - 1) - row0
        for c in range(3):
            for x in range(w):
                v = var[c, rb, x]
                if relative:
                    r = radiance[c, rb, x]
                    r2 = r * r
                    v = v * r2
                    if not (v <= cap):        # NaN, inf or beyond
                        v = cap
                    if split:
                        for p in range(4):
                            q = parts[p, yy, x, c] * r2
                            parts[p, yy, x, c] = q if q <= cap else cap
                if e2 > 0.0:
                    xa = max(x - 1, 0)
                    xc = min(x + 1, w - 1)
                    u0 = np.float64(radiance[c, ra, xa])
                    u1 = np.float64(radiance[c, ra, x])
                    u2 = np.float64(radiance[c, ra, xc])
                    u3 = np.float64(radiance[c, rb, xa])
                    u4 = np.float64(radiance[c, rb, x])
                    u5 = np.float64(radiance[c, rb, xc])
                    u6 = np.float64(radiance[c, rc, xa])
                    u7 = np.float64(radiance[c, rc, x])
                    u8 = np.float64(radiance[c, rc, xc])
                    s = ((u0 + u1) + (u2 + u3)) + ((u4 + u5) + (u6 + u7)) + u8
                    q2 = ((u0 * u0 + u1 * u1) + (u2 * u2 + u3 * u3)) + ((u4 * u4 + u5 * u5) + (u6 * u6 + u7 * u7)) + u8 * u8
                    mu = s * ninth
                    lv = max(q2 * ninth - mu * mu, 0.0) * e2
                    lv32 = np.float32(min(lv, cap))
                    v = np.float32(min(np.float64(v) + np.float64(lv32), cap))
                    if split:
                        parts[4, yy, x, c] = lv32
                var[c, rb, x] = v
