"""Compiled merges that also give the variance (:mod:`derender.engine.variance`).

:func:`table_merge_var_rows` and :func:`stabilized_merge_var_rows` are
:func:`derender.engine.kernels.table_merge_rows` and
:func:`derender.engine.kernels.stabilized_merge_rows` with the same radiance arithmetic
(the same bytes) plus, per pixel and channel, float64 sums ``sum w``, ``sum w u``,
``sum w u^2``, ``sum w^2`` and ``sum w^2 s^2`` (noise and quantisation apart), turned at the
end of each tile into the variance of :mod:`derender.engine.variance`:

    Var u = a (Qn + Qq) / S0^2 + b D r / max(1 - r, r_floor) + c D,   r = W2 / S0^2,
    D = S2 / S0 - (S1 / S0)^2,   Var r = [r^2 if log] Var u + shared^2 r^2

(``k = [a, b, shared^2, censored, r_floor, c]``). In the log domain the kernel writes the
relative variance (``Var u`` + ``shared^2``, without the factor ``r^2``) and the caller
multiplies it by the radiance squared after its exponential (vectorised, instead of one
``exp`` per pixel-channel here); in the ``"mean"`` mode (one weight per pixel) ``sum w`` and
``sum w^2`` are kept once per pixel, frames without weight add nothing, and the log domain
reads ``sum w``, ``sum w u`` from the radiance's own float64 sums. Rows ``y`` with ``y % stride == 0`` also
write the four sources (noise, quantisation, disagreement, shared) into ``parts``
(4, ceil(H / stride), W, 3) for ``info["variance_sources"]``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from derender.engine.kernels import MERGE_TILE
from derender.engine.merge_parts import add_frame_to_tile, add_table_observation, fallback_frame

__all__ = ["table_merge_var_rows", "stabilized_merge_var_rows"]


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
def _finish_var(s0, s1, s2, w2, qn, qq, k, log_domain, m):  # pragma: no cover - compiled
    """(noise, quant, disagreement, shared) variance of a merged value ``m`` (radiance) from its sums."""
    inv = 1.0 / s0
    r = w2 * inv * inv
    mu = s1 * inv
    d = max(s2 * inv - mu * mu, 0.0)
    vd = k[1] * d * r / max(1.0 - r, k[4]) + k[5] * d
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
    ``k`` the constants (module docstring)."""
    n = order.shape[0]
    nf = frames.shape[0]
    w = frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    tile = MERGE_TILE
    f32max = np.float32(3.4028234663852886e38)
    big = np.float64(f32max) / 4.0
    tnq = tn + tq      # noise and quantisation in one look-up; apart only on the sampled rows
    for y in prange(y0, y1):
        split = y % stride == 0
        num64 = np.zeros((3, tile), dtype=np.float64)
        den64 = np.zeros((3, tile), dtype=np.float64)
        num32 = np.zeros((3, tile), dtype=np.float32)
        den32 = np.zeros((3, tile), dtype=np.float32)
        vs = np.zeros((6, 3, tile), dtype=np.float64)     # S0, S1, S2, W2, Qn, Qq
        for x0 in range(0, w, tile):
            xe = min(x0 + tile, w)
            num64[:, :] = 0.0
            den64[:, :] = 0.0
            num32[:, :] = 0.0
            den32[:, :] = 0.0
            vs[:, :, :] = 0.0
            for kk in range(n):
                j = order[kk]
                for x in range(x0, xe):
                    if not whole and valid[j, y, x] == 0:
                        continue
                    t = x - x0
                    z0, z1, z2, w0, w1, w2, v0, v1, v2 = add_table_observation(
                        frames, j, y, x, t, weights, values, independent, log_domain, num64, den64, num32, den32)
                    # a frame without weight adds nothing (most of a long bracket's frames, per pixel)
                    if w0 != 0.0:
                        _acc(vs, 0, t, np.float64(w0), np.float64(v0), tnq[j, z0, 0], tq[j, z0, 0], split, True, log_domain)
                    if w1 != 0.0:
                        _acc(vs, 1, t, np.float64(w1), np.float64(v1), tnq[j, z1, 1], tq[j, z1, 1], split,
                             independent, log_domain)
                    if w2 != 0.0:
                        _acc(vs, 2, t, np.float64(w2), np.float64(v2), tnq[j, z2, 2], tq[j, z2, 2], split,
                             independent, log_domain)
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
                    s0 = den64[dc, t] if log_domain else vs[0, dc, t]
                    if jj < 0 and s0 > 0.0:
                        s1 = num64[c, t] if log_domain else vs[1, c, t]
                        pn, pq, pd, ps = _finish_var(s0, s1, vs[2, c, t], vs[3, dc, t],
                                                     vs[4, c, t] - vs[5, c, t], vs[5, c, t], k, log_domain, m)
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
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def stabilized_merge_var_rows(frames, shifts, valid, ref, lin, mats32, mats64, weights, inv_var, inv_k, use_inv_var,
                              colour_w, use_colour_w, j_short, j_long, bright, y0, y1, row0, out, mask, tn, tq, k, var,
                              parts, stride):  # pragma: no cover - compiled
    """:func:`derender.engine.kernels.stabilized_merge_rows` (same arguments up to ``mask``, same
    radiance) and the variance into ``var`` (3, rows, W) float32: frame ``j``'s channel ``c``
    has noise variance ``sum_k mats64[j, c, k]^2 tn[j, z_k, k]`` (and so quantisation with
    ``tq``); the sums of both weight sets are kept, the one the radiance uses gives the variance."""
    n = frames.shape[0]
    h, w = frames.shape[1], frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    zero = np.float32(0.0)
    tiny = np.float32(1e-30)
    tile = MERGE_TILE
    big = np.float64(np.finfo(np.float32).max) / 4.0
    tnq = tn + tq      # noise and quantisation in one look-up; apart only on the sampled rows
    sqm = mats64 * mats64
    for y in prange(y0, y1):
        split = y % stride == 0
        acc = np.empty((8, tile), dtype=np.float32)
        usable = np.empty(tile, dtype=np.bool_)
        vs = np.empty((11, tile), dtype=np.float64)   # S0, W2, sum w (v - mean)^2 (3), Qnq (3), Qq (3)
        mu3 = np.zeros((3, tile), dtype=np.float64)
        for x0 in range(0, w, tile):
            xe = min(x0 + tile, w)
            acc[:, :] = zero
            usable[:] = False
            for j in range(n):
                yy = y + shifts[j, 0]
                if yy < 0 or yy >= h:
                    continue
                add_frame_to_tile(frames, valid, whole, j, y, yy, shifts[j, 1], x0, xe, w, weights, inv_var,
                                   inv_k[j], use_inv_var, colour_w, use_colour_w, lin, mats32, acc, usable)
            # second look at the tile's frames: the spread around the merged mean, with the set it used
            for x in range(x0, xe):
                t = x - x0
                kset = 0 if usable[t] else 4
                dm = acc[kset, t]
                if dm > zero:
                    for c in range(3):
                        mu3[c, t] = np.float64(acc[kset + 1 + c, t] / dm)
            vs[:, :] = 0.0
            for j in range(n):
                yy = y + shifts[j, 0]
                if yy < 0 or yy >= h:
                    continue
                sx = shifts[j, 1]
                ik = inv_k[j]
                sq = sqm[j]
                m32 = mats32[j]
                for x in range(max(x0, -sx), min(xe, w - sx)):
                    if not whole and valid[j, y, x] == 0:
                        continue
                    t = x - x0
                    xx = x + sx
                    z0 = frames[j, yy, xx, 0]
                    z1 = frames[j, yy, xx, 1]
                    z2 = frames[j, yy, xx, 2]
                    if usable[t]:
                        ws = min(min(weights[z0, 0], weights[z1, 1]), weights[z2, 2])
                    else:
                        ws = weights[max(max(z0, z1), z2), 0]
                    if ws == zero:
                        continue
                    if use_inv_var:
                        d = inv_var[j, z0, 0] + inv_var[j, z1, 1]
                        d = d + inv_var[j, z2, 2]
                        ws = ws * (ik / max(d, tiny))
                    if use_colour_w:
                        ws = ws * colour_w[(np.int64(z0) << 16) | (np.int64(z1) << 8) | np.int64(z2)]
                    l0 = lin[j, z0, 0]
                    l1 = lin[j, z1, 1]
                    l2 = lin[j, z2, 2]
                    wd = np.float64(ws)
                    ww = wd * wd
                    n0 = tnq[j, z0, 0]
                    n1 = tnq[j, z1, 1]
                    n2 = tnq[j, z2, 2]
                    vs[0, t] += wd
                    vs[1, t] += ww
                    for c in range(3):
                        vc = np.float64(max(l0 * m32[c, 0] + l1 * m32[c, 1] + l2 * m32[c, 2], zero)) - mu3[c, t]
                        vs[2 + c, t] += wd * vc * vc
                        vs[5 + c, t] += ww * (sq[c, 0] * n0 + sq[c, 1] * n1 + sq[c, 2] * n2)
                        if split:
                            vs[8 + c, t] += ww * (sq[c, 0] * tq[j, z0, 0] + sq[c, 1] * tq[j, z1, 1]
                                                  + sq[c, 2] * tq[j, z2, 2])
            for x in range(x0, xe):
                t = x - x0
                kset = 0 if usable[t] else 4
                dm = acc[kset, t]
                if dm > zero:
                    out[0, y - row0, x] = acc[kset + 1, t] / dm
                    out[1, y - row0, x] = acc[kset + 2, t] / dm
                    out[2, y - row0, x] = acc[kset + 3, t] / dm
                    mask[y, x] = 0
                    for c in range(3):
                        m = np.float64(out[c, y - row0, x])
                        pn, pq, pd, ps = _finish_var(vs[0, t], 0.0, vs[2 + c, t], vs[1, t],
                                                     vs[5 + c, t] - vs[8 + c, t], vs[8 + c, t], k, False, m)
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
