"""The window ghost test's pieces: 2x2-window sums of a frame at a shift, against the reference's.

For a bracket resampled at sub-photosite shifts (:mod:`derender.raw.register`) the ghost test
(:func:`derender.hdr.raw.merge_raw`, ``--deghost``) compares each frame's and the reference's
sliding 2x2-window sums of ``d / (e k)`` (``d`` DN above black, ``e`` the exposure, ``k`` per CFA
phase the reference's median level: :func:`derender.raw.register.phase_scale`). A window holds
one photosite of every colour whatever its phase, so a frame's window at ``p + s``
(:func:`shifted_box`, Keys' (1981) cubic convolution between whole shifts) needs no demosaic:

    z^2(p) = (M[B_j(. + s) - B_r](p))^2 / (Var_j + Var_r + (M[T](p))^2)            (1)

with ``M`` the 3x3 mean, the variances the Poisson-Gaussian model's through the window, the
mean and Keys' weights, and ``T`` (:func:`phase_offset_difference`) the reference's own change
across the part of ``s`` that is not whole and even: there the two windows see the scene
through other colour filters. ``z^2``'s 5x5 mean against the engine's threshold rejects
(Granados et al. 2013's consistency test on the noise model).
"""

from __future__ import annotations

import math

import numpy as np

from derender.raw.register import SNAP, keys_weights
from derender.raw.register_kernels import separable_taps, window_sums

__all__ = ["shifted_box", "phase_offset_difference"]


def shifted_box(values: np.ndarray, saturated: np.ndarray, shift, scale: np.ndarray) -> tuple:
    """The sliding 2x2 sum of ``values / scale`` (per CFA phase; (H, W) per photosite) at the
    reference's photosites ``p + shift`` (window ``[p + s, p + s + 1]``, Keys between whole
    shifts): ``(box, saturated, inside, (wy, wx))`` -- (H, W) float64, (H, W) bool (a saturated
    photosite in the support), (H, W) bool (the support inside the frame) and Keys' weights
    per axis (rows, columns)."""
    v = np.ascontiguousarray(values, np.float64)
    h, w = v.shape
    box, sbox = np.empty((h, w)), np.empty((h, w))
    window_sums(v, np.ascontiguousarray(saturated, np.bool_), np.ascontiguousarray(scale, np.float64).reshape(2, 2),
                box, sbox)
    iy, ix = math.floor(float(shift[0])), math.floor(float(shift[1]))
    wy, wx = keys_weights(float(shift[0]) - iy), keys_weights(float(shift[1]) - ix)
    out = np.zeros((h, w))
    sat = np.ones((h, w), bool)
    inside = np.zeros((h, w), bool)
    vals, (rs, cs) = _convolve(box, (iy, ix), wy, wx, (h, w))
    out[rs, cs] = vals
    ns, (rs2, cs2) = _convolve(sbox, (iy, ix), (wy != 0).astype(float), (wx != 0).astype(float), (h, w))
    sat[rs2, cs2] = ns > 0.5
    inside[rs, cs] = True
    return out, sat, inside, (wy, wx)


def phase_offset_difference(box: np.ndarray, shift) -> np.ndarray:
    """The reference's 2x2-window sums' change across the part of ``shift`` that is not whole
    and even (``delta = s - 2 round(s / 2)`` per axis, in [-1, 1]), to first order:
    ``|delta_y| (box[p + sign(delta_y) e_y] - box[p]) + |delta_x| (box[p + sign(delta_x) e_x] - box[p])``
    (edges repeated). A frame's window at ``p + s`` covers the reference window's scene points
    through other colour filters when ``s`` is not whole and even (each point's colour moves
    with the CFA phase), so where the scene has texture the two windows' sums differ by about
    the scene's change over that offset even where nothing moves; the ghost test on window sums
    (:func:`derender.hdr.raw.raw_motion`) allows for it, squared after the test's 3x3 mean, in
    its variance (without it, 19-24 % of the static zone of the frames next to the reference
    was rejected on a handheld bracket, measured, docs/results-raw.md)."""
    b = np.asarray(box, np.float64)
    out = np.zeros(b.shape)
    for axis, v in enumerate((float(shift[0]), float(shift[1]))):
        delta = v - 2.0 * round(v / 2.0)
        step = int(np.sign(delta))
        if step == 0 or abs(delta) <= SNAP:
            continue
        idx = np.clip(np.arange(b.shape[axis]) + step, 0, b.shape[axis] - 1)
        out += abs(delta) * (np.take(b, idx, axis=axis) - b)
    return out


def _taps(w: np.ndarray) -> np.ndarray:
    """The indices of the non-zero weights."""
    return np.flatnonzero(w != 0.0)


def _convolve(plane: np.ndarray, off: tuple[int, int], wy: np.ndarray, wx: np.ndarray,
              shape: tuple[int, int]) -> tuple[np.ndarray, tuple[slice, slice]]:
    """``out[i, k] = sum_mn wy[m] wx[n] plane[i + oy + m - 1, k + ox + n - 1]`` over the output
    samples whose taps (the non-zero weights) lie inside ``plane``: ``(values, (rows, cols))``,
    the values on that sub-rectangle of an output of ``shape``."""
    ty, tx = _taps(wy), _taps(wx)
    oy, ox = off
    hs, ws = plane.shape
    i0 = max(0, -(oy + ty[0] - 1))
    i1 = min(shape[0], hs - (oy + ty[-1] - 1))
    k0 = max(0, -(ox + tx[0] - 1))
    k1 = min(shape[1], ws - (ox + tx[-1] - 1))
    if i1 <= i0 or k1 <= k0:
        return np.zeros((0, 0)), (slice(0, 0), slice(0, 0))
    out = np.empty((i1 - i0, k1 - k0))
    separable_taps(np.ascontiguousarray(plane, np.float64), int(oy), int(ox), np.asarray(wy, np.float64),
                   np.asarray(wx, np.float64), int(i0), int(k0), out)
    return out, (slice(i0, i1), slice(k0, k1))
