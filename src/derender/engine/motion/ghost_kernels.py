"""The compiled per-pixel test of ghost removal (:mod:`derender.engine.motion.deghost`).

:func:`ghost_statistic` turns two frames' log radiance, its standard deviation and clipping
flags into the capped ``z^2`` of the consistency test in one pass per pixel. It is compiled
once and cached on disk (``cache=True``), runs on one thread with the GIL released, and the
engine runs it for several frames at once. It is not a parallel kernel, because numba
cannot launch parallel kernels from two threads. :func:`upsample_into` writes a
detection-grid mask into a full-resolution plane in place. The merge kernels live in
:mod:`derender.engine.kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["ghost_statistic", "upsample_into"]


@njit(inline="always")
def _interval(m, c, bright):  # pragma: no cover - compiled
    """One frame's interval of log radiance for a channel with estimate ``m`` and censoring ``c``
    (:func:`ghost_statistic`): a point, ``(-inf, m]`` clipped dark; in a pixel clipped bright
    ``(-inf, inf)`` for a clipped channel and ``(-inf, m]`` for the others."""
    if bright:
        return -np.inf, (np.inf if c > 0 else m)
    return (m if c >= 0 else -np.inf), m


@njit(inline="always")
def _interval_gap(lo_j, hi_j, lo_r, hi_r):  # pragma: no cover - compiled
    """Signed distance between two intervals (0 where they overlap)."""
    if lo_j - hi_r > 0.0:
        return lo_j - hi_r
    if hi_j - lo_r < 0.0:
        return hi_j - lo_r
    return 0.0


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True, error_model="numpy")
def ghost_statistic(mu_j, sd_j, cens_j, mu_r, sd_r, cens_r, offset, extra_var, edge_shift, cap, ok, out):  # pragma: no cover - compiled
    """Per pixel of the detection grid, :mod:`derender.engine.motion.deghost`'s ``min(Q, cap)`` of frame j
    against the reference (0 where ``ok`` is 0, e.g. a pixel one frame does not cover).

    ``mu_*``, ``sd_*`` (h, w, 3) float32 log radiance and its standard deviation, ``cens_*``
    (h, w, 3) int8 (0 observed, +1 clipped bright, -1 clipped dark); frame j is shifted by
    ``-offset[y, x, c]`` (its log offset, (h, w, 3)) and the variance of a channel is
    ``sd_j^2 + sd_r^2 + extra_var[y, x, c] + edge_shift^2 (|grad mu_j|^2 + |grad mu_r|^2)`` (central
    differences, clamped at the borders). Each frame says, per channel, an interval of log
    radiance: a point where observed, ``(-inf, mu]`` where clipped dark; a pixel with a channel
    clipped bright says nothing of that channel and ``(-inf, mu]`` of its others (a camera
    desaturates such a pixel towards white), and that its brightest channel is at least its
    bound. ``z`` is the gap between the two frames' intervals over the standard deviation;
    ``Q = max(mean_c z_c^2, z_top^2)``, ``z_top`` comparing the brightest channels where
    either frame is clipped bright (its variance the mean of both argmax channels'). One thread,
    the GIL released: the engine runs it for several frames at once (not a parallel kernel,
    which numba cannot launch from two threads)."""
    h, w = mu_j.shape[0], mu_j.shape[1]
    inf = np.inf
    e2 = edge_shift * edge_shift
    for y in range(h):
        ya = max(y - 1, 0)
        yb = min(y + 1, h - 1)
        dy = 1.0 / max(yb - ya, 1)
        var_c = np.empty(3)
        for x in range(w):
            if ok[y, x] == 0:
                out[y, x] = 0.0
                continue
            xa = max(x - 1, 0)
            xb = min(x + 1, w - 1)
            dx = 1.0 / max(xb - xa, 1)
            bright_j = cens_j[y, x, 0] > 0 or cens_j[y, x, 1] > 0 or cens_j[y, x, 2] > 0
            bright_r = cens_r[y, x, 0] > 0 or cens_r[y, x, 1] > 0 or cens_r[y, x, 2] > 0
            qsum = 0.0
            kj = 0
            kr = 0
            best_j = -inf
            best_r = -inf
            for c in range(3):
                mj = np.float64(mu_j[y, x, c]) - np.float64(offset[y, x, c])
                mr = np.float64(mu_r[y, x, c])
                gjy = (np.float64(mu_j[yb, x, c]) - np.float64(mu_j[ya, x, c])) * dy
                gjx = (np.float64(mu_j[y, xb, c]) - np.float64(mu_j[y, xa, c])) * dx
                gry = (np.float64(mu_r[yb, x, c]) - np.float64(mu_r[ya, x, c])) * dy
                grx = (np.float64(mu_r[y, xb, c]) - np.float64(mu_r[y, xa, c])) * dx
                sj = np.float64(sd_j[y, x, c])
                sr = np.float64(sd_r[y, x, c])
                var = sj * sj + sr * sr + np.float64(extra_var[y, x, c]) + e2 * (gjy * gjy + gjx * gjx + gry * gry
                                                                                 + grx * grx)
                var_c[c] = var
                cj = cens_j[y, x, c]
                cr = cens_r[y, x, c]
                if mj > best_j:
                    best_j = mj
                    kj = c
                if mr > best_r:
                    best_r = mr
                    kr = c
                lo_j, hi_j = _interval(mj, cj, bright_j)
                lo_r, hi_r = _interval(mr, cr, bright_r)
                gap = _interval_gap(lo_j, hi_j, lo_r, hi_r)
                if gap != 0.0 and var > 0.0 and np.isfinite(var):
                    z2 = gap * gap / var
                    if np.isfinite(z2):
                        qsum += z2
            q = qsum / 3.0
            if bright_j or bright_r:
                gap = _interval_gap(best_j, inf if bright_j else best_j, best_r, inf if bright_r else best_r)
                var = 0.5 * (var_c[kj] + var_c[kr])
                if gap != 0.0 and var > 0.0 and np.isfinite(var):
                    qt = gap * gap / var
                    if np.isfinite(qt) and qt > q:
                        q = qt
            out[y, x] = min(q, cap)


@njit(nogil=True, cache=True)
def upsample_into(mask, step, out):  # pragma: no cover - compiled
    """``out[y, x] = mask[y // step, x // step] != 0`` for every pixel of ``out`` ((H, W) bool or
    uint8; ``mask`` the (hs, ws) detection grid, every ``step``-th row and column): a grid
    mask at full resolution written in place, no temporary plane (fresh memory costs a page
    fault per 4 kB on first touch). The index is OpenCV's nearest-neighbour rule
    ``floor(y * (1 / step))``, clamped to the grid, so that the planes equal
    ``cv2.resize(..., INTER_NEAREST)``'s."""
    h, w = out.shape[0], out.shape[1]
    hs, ws = mask.shape[0], mask.shape[1]
    inv = 1.0 / step
    cols = np.empty(w, np.int64)
    for x in range(w):
        cols[x] = min(int(np.floor(x * inv)), ws - 1)
    prev = -1
    for y in range(h):
        sy = min(int(np.floor(y * inv)), hs - 1)
        if sy == prev:          # the row above read the same grid row: copy it
            for x in range(w):
                out[y, x] = out[y - 1, x]
            continue
        prev = sy
        for x in range(w):
            out[y, x] = mask[sy, cols[x]] != 0
