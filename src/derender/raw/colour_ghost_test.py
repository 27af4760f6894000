"""Ghost removal colour by colour, for frames resampled at sub-photosite shifts (:mod:`derender.raw.register`).

Beside a frame's own saturation the ghost test on 2x2-window sums (:func:`derender.hdr.raw.merge_raw`)
cannot decide: a window holds a saturated photosite, and the frame's resampled colour of the
reference's photosite is partly saturated. There the frame's resampled colour ``v`` (DN above
black, exposure ``e``) is tested against the reference's ``v_r`` (``e_r``) colour by colour:

    z^2 = (v / e - v_r / e_r)^2 / (V f / e^2 + V_r f_r / e_r^2 + (k x_r)^2)

with ``V = g x_r e + sigma^2`` the Poisson-Gaussian variance at the reference's level ``x_r``
per unit exposure, ``f`` the resampling's variance factor per CFA phase and ``k``
(:data:`COLOUR_GHOST_ERROR`) the demosaic's error at the shifted photosite; a censored sample
is inconsistent where the other frame puts the value :data:`COLOUR_GHOST_SIGMA` sigma below its
level (as the ghost test on the mosaic, Granados et al. 2013's consistency test with
Aguerrebere et al. 2014's censoring).
"""

from __future__ import annotations

import numpy as np

__all__ = ["colour_ghosts", "COLOUR_GHOST_ERROR", "COLOUR_GHOST_SIGMA"]


#: Relative error of a resampled colour (its demosaic's, at the shifted photosite) allowed for in
#: :func:`colour_ghosts` (as the ghost test beside saturation, :func:`derender.hdr.raw.merge_raw`).
COLOUR_GHOST_ERROR = 0.1

#: A censored colour is inconsistent in :func:`colour_ghosts` where the other frame puts the
#: value more than this many sigma below its level (as the ghost test on the mosaic).
COLOUR_GHOST_SIGMA = 3.0


def colour_ghosts(values: np.ndarray, state: np.ndarray, ref_values: np.ndarray, ref_state: np.ndarray, *,
                  exposures: tuple, gain: tuple, read_variance: tuple, factors: tuple, ceiling: tuple,
                  where: np.ndarray, threshold: float) -> np.ndarray:
    """Ghost removal colour by colour where the test on window sums could not decide (``where``,
    (H, W): beside a frame's own saturation, the 2x2 windows hold a saturated photosite and the
    frame's resampled colour of the reference's photosite is partly saturated). ``values`` and
    ``state`` a frame's resampled colour (DN above black, censored at ``ceiling``; :func:`~derender.raw.register.resample_rgb`'s
    state), ``ref_*`` the reference's same colour; the pairs ``(frame, reference)``: exposures,
    gain, read variance, variance factors (2, 2) per CFA phase and ceilings. Where both are
    measured, ``z^2 = (v / e - v_r / e_r)^2 / (V f / e^2 + V_r f_r / e_r^2 + (0.1 x_r)^2)``
    (``V = g x_r e + sigma^2``, ``x_r`` the reference's value per unit exposure, the resampling's
    error allowed for as :data:`COLOUR_GHOST_ERROR`); a censored sample is inconsistent where the
    other puts the value :data:`COLOUR_GHOST_SIGMA` sigma below its level. Returns (H, W) bool:
    where the frame's colour is to be left out -- within ``where``, the 5x5 mean of ``z^2`` over
    the photosites tested there above ``threshold``, or not testable (either colour takes no part)."""
    from scipy.ndimage import uniform_filter

    where = np.asarray(where, bool)
    out = np.zeros(where.shape, bool)
    rows, cols = np.flatnonzero(where.any(axis=1)), np.flatnonzero(where.any(axis=0))
    if rows.size == 0:
        return out
    # the 5x5 means of the photosites in ``where`` read only photosites within 2 of them: the
    # bounding box grown by 2 (a crop of even offset, so the CFA phases stay) gives the same result
    y0, x0 = max(0, int(rows[0]) - 2) & ~1, max(0, int(cols[0]) - 2) & ~1
    y1, x1 = min(where.shape[0], int(rows[-1]) + 3), min(where.shape[1], int(cols[-1]) + 3)
    box = (slice(y0, y1), slice(x0, x1))
    values, state, ref_values, ref_state, where = values[box], state[box], ref_values[box], ref_state[box], where[box]
    e, e_r = float(exposures[0]), float(exposures[1])
    h, w = values.shape
    f = np.tile(np.asarray(factors[0], np.float64), ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    f_r = np.tile(np.asarray(factors[1], np.float64), ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    x_r = np.maximum(ref_values / e_r, 0.0)
    x = np.maximum(values / e, 0.0)
    v = gain[0] * x_r * e + read_variance[0]
    v_r = gain[1] * x_r * e_r + read_variance[1]
    z2 = (values / e - ref_values / e_r) ** 2 / (v * f / e ** 2 + v_r * f_r / e_r ** 2 + (COLOUR_GHOST_ERROR * x_r) ** 2)
    big = 4.0 * float(threshold)
    below = x_r * e < ceiling[0] - COLOUR_GHOST_SIGMA * np.sqrt(v)
    below_r = x * e_r < ceiling[1] - COLOUR_GHOST_SIGMA * np.sqrt(gain[1] * x * e_r + read_variance[1])
    z2 = np.where((state == 2) & (ref_state == 2), 0.0, z2)
    z2 = np.where((state == 2) & (ref_state == 1), np.where(below, big, 0.0), z2)
    z2 = np.where((state == 1) & (ref_state == 2), np.where(below_r, big, 0.0), z2)
    tested = where & (state != 0) & (ref_state != 0)
    t = tested.astype(np.float64)
    num = uniform_filter(np.where(tested, z2, 0.0), size=5, mode="nearest")
    den = uniform_filter(t, size=5, mode="nearest")
    mean = np.where(den > 0, num / np.maximum(den, 1e-30), np.inf)
    out[box] = where & (~tested | (mean > float(threshold)))
    return out
