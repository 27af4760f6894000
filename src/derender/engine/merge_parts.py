"""Inlined parts shared by the compiled merge kernels (:mod:`derender.engine.kernels` and
:mod:`derender.engine.variance_kernels`): one frame's observations added to a tile's sums, for
the matrix merge (paper 1's stabilised merge) and the table merge (Debevec, Robertson). Numba
inlines them (``inline="always"``), so the kernels compile as if the loop bodies were written
in place: the radiance and its variance kernels share one copy of the arithmetic.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["add_frame_to_tile", "add_frame_to_tile_var", "add_table_observation", "fallback_frame",
           "stabilized_observation"]


# Positional on purpose (as the kernels): an inlined part of them.
@njit(inline="always")
def stabilized_observation(frames, valid, whole, j, y, yy, x, sx, weights, inv_var, ik, use_inv_var, colour_w,
                           use_colour_w, lin, a00, a01, a02, a10, a11, a12, a20, a21, a22):  # pragma: no cover
    """Frame ``j``'s observation of pixel ``(y, x)`` (read at ``(yy, x + sx)``) in the stabilised
    merge: ``(state, wmin, wbright, v0, v1, v2, z0, z1, z2)``, ``state`` 0 when it adds nothing,
    1 when every channel is usable (``wmin > 0``), 2 when only the brightest code's weight counts;
    ``v`` the frame's estimate ``M_j L_j(z)`` projected onto the non-negative orthant."""
    zero = np.float32(0.0)
    tiny = np.float32(1e-30)
    if not whole and valid[j, y, x] == 0:
        return 0, zero, zero, zero, zero, zero, 0, 0, 0
    xx = x + sx
    z0 = frames[j, yy, xx, 0]
    z1 = frames[j, yy, xx, 1]
    z2 = frames[j, yy, xx, 2]
    wmin = min(min(weights[z0, 0], weights[z1, 1]), weights[z2, 2])
    wbright = weights[max(max(z0, z1), z2), 0]
    state = 1
    if wmin <= zero:
        if wbright == zero:
            return 0, zero, zero, zero, zero, zero, 0, 0, 0
        state = 2
    if use_inv_var:
        d = inv_var[j, z0, 0] + inv_var[j, z1, 1]
        d = d + inv_var[j, z2, 2]
        f = ik / max(d, tiny)
        wmin = wmin * f
        wbright = wbright * f
    if use_colour_w:
        cw = colour_w[(np.int64(z0) << 16) | (np.int64(z1) << 8) | np.int64(z2)]
        wmin = wmin * cw
        wbright = wbright * cw
    l0 = lin[j, z0, 0]
    l1 = lin[j, z1, 1]
    l2 = lin[j, z2, 2]
    v0 = max(l0 * a00 + l1 * a01 + l2 * a02, zero)
    v1 = max(l0 * a10 + l1 * a11 + l2 * a12, zero)
    v2 = max(l0 * a20 + l1 * a21 + l2 * a22, zero)
    return state, wmin, wbright, v0, v1, v2, z0, z1, z2


@njit(inline="always")
def _add_observation(acc, t, wmin, wbright, v0, v1, v2):  # pragma: no cover - compiled
    acc[0, t] += wmin
    acc[1, t] += v0 * wmin
    acc[2, t] += v1 * wmin
    acc[3, t] += v2 * wmin
    acc[4, t] += wbright
    acc[5, t] += v0 * wbright
    acc[6, t] += v1 * wbright
    acc[7, t] += v2 * wbright


# Positional on purpose (as the kernels): an inlined part of them.
@njit(inline="always")
def add_frame_to_tile(frames, valid, whole, j, y, yy, sx, x0, xe, w, weights, inv_var, ik, use_inv_var, colour_w,
                       use_colour_w, lin, mats32, acc, usable):  # pragma: no cover - compiled
    """Frame ``j``'s observations of row ``y`` (read at row ``yy``, shifted by ``sx``) added to a
    tile's sums ``acc`` (8, tile) and ``usable`` (:func:`stabilized_merge_rows`; the variance
    kernel's pass adds them the same way, :func:`add_frame_to_tile_var`)."""
    a00 = mats32[j, 0, 0]
    a01 = mats32[j, 0, 1]
    a02 = mats32[j, 0, 2]
    a10 = mats32[j, 1, 0]
    a11 = mats32[j, 1, 1]
    a12 = mats32[j, 1, 2]
    a20 = mats32[j, 2, 0]
    a21 = mats32[j, 2, 1]
    a22 = mats32[j, 2, 2]
    for x in range(max(x0, -sx), min(xe, w - sx)):
        state, wmin, wbright, v0, v1, v2, z0, z1, z2 = stabilized_observation(
            frames, valid, whole, j, y, yy, x, sx, weights, inv_var, ik, use_inv_var, colour_w, use_colour_w, lin,
            a00, a01, a02, a10, a11, a12, a20, a21, a22)
        if state == 0:
            continue
        t = x - x0
        if state == 1:
            usable[t] = True
        _add_observation(acc, t, wmin, wbright, v0, v1, v2)


# Positional on purpose (as the kernels): an inlined part of them.
@njit(inline="always")
def add_frame_to_tile_var(frames, valid, whole, j, y, yy, sx, x0, xe, w, weights, inv_var, ik, use_inv_var, colour_w,
                          use_colour_w, lin, mats32, acc, usable, tnq, tq, sqm32, split, s64,
                          s32, robust):  # pragma: no cover - compiled
    """:func:`add_frame_to_tile` (the same arithmetic, the same ``acc``) and, with the weight of
    frames measured in every channel (``wmin``; zero adds zeros), the variance's sums of the
    frame's estimate ``v`` (:func:`derender.engine.variance_kernels.stabilized_merge_var_rows`):
    ``s64`` (13, tile) float64 ``sum w``, ``sum w v_c``, ``sum w v_c^2`` and, when ``robust``,
    ``sum w^2 v_c``, ``sum w^2 v_c^2`` (the robust term of :mod:`derender.engine.variance`); ``s32`` (7, tile)
    float32 ``sum w^2``, ``sum w^2 s_c^2`` (noise + quantisation, ``s_c^2 = sum_k M_ck^2
    tnq[z_k, k]``) and, on ``split`` rows, the quantisation alone (``tq``)."""
    a00 = mats32[j, 0, 0]
    a01 = mats32[j, 0, 1]
    a02 = mats32[j, 0, 2]
    a10 = mats32[j, 1, 0]
    a11 = mats32[j, 1, 1]
    a12 = mats32[j, 1, 2]
    a20 = mats32[j, 2, 0]
    a21 = mats32[j, 2, 1]
    a22 = mats32[j, 2, 2]
    q00 = sqm32[j, 0, 0]
    q01 = sqm32[j, 0, 1]
    q02 = sqm32[j, 0, 2]
    q10 = sqm32[j, 1, 0]
    q11 = sqm32[j, 1, 1]
    q12 = sqm32[j, 1, 2]
    q20 = sqm32[j, 2, 0]
    q21 = sqm32[j, 2, 1]
    q22 = sqm32[j, 2, 2]
    for x in range(max(x0, -sx), min(xe, w - sx)):
        state, wmin, wbright, v0, v1, v2, z0, z1, z2 = stabilized_observation(
            frames, valid, whole, j, y, yy, x, sx, weights, inv_var, ik, use_inv_var, colour_w, use_colour_w, lin,
            a00, a01, a02, a10, a11, a12, a20, a21, a22)
        if state == 0:
            continue
        t = x - x0
        if state == 1:
            usable[t] = True
        _add_observation(acc, t, wmin, wbright, v0, v1, v2)
        wd = np.float64(wmin)
        b0 = wd * np.float64(v0)
        b1 = wd * np.float64(v1)
        b2 = wd * np.float64(v2)
        s64[0, t] += wd
        s64[1, t] += b0
        s64[2, t] += b1
        s64[3, t] += b2
        s64[4, t] += b0 * np.float64(v0)
        s64[5, t] += b1 * np.float64(v1)
        s64[6, t] += b2 * np.float64(v2)
        ww = wmin * wmin
        if robust:
            wwd = np.float64(ww)
            c0 = wwd * np.float64(v0)
            c1 = wwd * np.float64(v1)
            c2 = wwd * np.float64(v2)
            s64[7, t] += c0
            s64[8, t] += c1
            s64[9, t] += c2
            s64[10, t] += c0 * np.float64(v0)
            s64[11, t] += c1 * np.float64(v1)
            s64[12, t] += c2 * np.float64(v2)
        n0 = tnq[j, z0, 0]
        n1 = tnq[j, z1, 1]
        n2 = tnq[j, z2, 2]
        s32[0, t] += ww
        s32[1, t] += ww * (q00 * n0 + q01 * n1 + q02 * n2)
        s32[2, t] += ww * (q10 * n0 + q11 * n1 + q12 * n2)
        s32[3, t] += ww * (q20 * n0 + q21 * n1 + q22 * n2)
        if split:
            r0 = tq[j, z0, 0]
            r1 = tq[j, z1, 1]
            r2 = tq[j, z2, 2]
            s32[4, t] += ww * (q00 * r0 + q01 * r1 + q02 * r2)
            s32[5, t] += ww * (q10 * r0 + q11 * r1 + q12 * r2)
            s32[6, t] += ww * (q20 * r0 + q21 * r1 + q22 * r2)


# Positional on purpose (as the kernels): an inlined part of them.
@njit(inline="always")
def add_table_observation(frames, j, y, x, t, weights, values, independent, log_domain, num64, den64, num32,
                           den32):  # pragma: no cover - compiled
    """Frame ``j``'s observation of pixel ``(y, x)`` added to the tile's sums at ``t``
    (:func:`table_merge_rows`; the variance kernel adds them the same way and reads the codes,
    weights and values back): returns ``(z0, z1, z2, w0, w1, w2, v0, v1, v2)``."""
    z0 = frames[j, y, x, 0]
    z1 = frames[j, y, x, 1]
    z2 = frames[j, y, x, 2]
    w0 = weights[j, z0, 0]
    w1 = weights[j, z1, 1]
    w2 = weights[j, z2, 2]
    if not independent:
        s = w0 + w1
        s = s + w2
        w0 = s
        w1 = s
        w2 = s
    v0 = values[j, z0, 0]
    v1 = values[j, z1, 1]
    v2 = values[j, z2, 2]
    if log_domain:
        den64[0, t] += np.float64(w0)
        if independent:
            den64[1, t] += np.float64(w1)
            den64[2, t] += np.float64(w2)
        num64[0, t] += np.float64(v0) * np.float64(w0)
        num64[1, t] += np.float64(v1) * np.float64(w1)
        num64[2, t] += np.float64(v2) * np.float64(w2)
    else:
        den32[0, t] += w0
        if independent:
            den32[1, t] += w1
            den32[2, t] += w2
        num32[0, t] = np.float32(np.float64(num32[0, t]) + np.float64(v0) * np.float64(w0))
        num32[1, t] = np.float32(np.float64(num32[1, t]) + np.float64(v1) * np.float64(w1))
        num32[2, t] = np.float32(np.float64(num32[2, t]) + np.float64(v2) * np.float64(w2))
    return z0, z1, z2, w0, w1, w2, v0, v1, v2


@njit(inline="always")
def fallback_frame(frames, valid, whole, ref, shifts, j_short, j_long, bright, y, x, h, w):  # pragma: no cover
    """Where no frame has weight at ``(y, x)``: the frame the value comes from and the mask code
    (1 over-exposed, 2 under-exposed). Without frames left out, the shortest exposure if its
    largest code is ``bright``, else the longest; with frames left out (``valid``, ``ref >= 0``),
    the reference decides the side and the tightest bound among the frames taking part gives
    the value (the stabilised merge kernels)."""
    n = frames.shape[0]
    if whole or ref < 0:
        ys = min(max(y + shifts[j_short, 0], 0), h - 1)
        xs = min(max(x + shifts[j_short, 1], 0), w - 1)
        zmax = max(max(frames[j_short, ys, xs, 0], frames[j_short, ys, xs, 1]), frames[j_short, ys, xs, 2])
        if bright[zmax]:
            return j_short, 1
        return j_long, 2
    zr = max(max(frames[ref, y, x, 0], frames[ref, y, x, 1]), frames[ref, y, x, 2])
    up = bright[zr]
    jj = ref
    for k in range(n):
        jv = k if up else n - 1 - k
        if valid[jv, y, x] == 0:
            continue
        yv = min(max(y + shifts[jv, 0], 0), h - 1)
        xv = min(max(x + shifts[jv, 1], 0), w - 1)
        zv = max(max(frames[jv, yv, xv, 0], frames[jv, yv, xv, 1]), frames[jv, yv, xv, 2])
        if bright[zv] == up:
            jj = jv
            break
    return jj, (1 if up else 2)
