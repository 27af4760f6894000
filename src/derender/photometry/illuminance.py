"""Luminance (cd/m2) of a radiance map and the vertical illuminance Ev at the camera.

Radiance's convention, which ``pvalue``, ``falsecolor`` and ``evalglare`` follow: a map
stores radiance in W sr^-1 m^-2 per channel (after dividing by its ``EXPOSURE``), and its
luminance is

    L = 179 (w_R R + w_G G + w_B B)    [cd/m2],

179 lm/W being Radiance's white efficacy and ``w`` the luminance row of the map's RGB
primaries: ``(0.265, 0.670, 0.065)`` for Radiance's standard primaries (a file without
``PRIMARIES``), the Y row of the RGB-to-XYZ matrix of the stated primaries and white
otherwise (Rec. 709 / sRGB: ``(0.2126, 0.7152, 0.0722)``, :func:`luminance_weights`).
``evalglare`` uses the standard weights whatever the header says, so on strongly coloured
scenes its luminance differs from the sRGB one by the weights' difference (grey pixels
agree: both rows sum to 1).

The vertical illuminance at the lens is the cosine-weighted integral of the luminance over
the view's solid angle,

    Ev = sum_i L_i cos(theta_i) Omega_i,

``theta_i`` the angle of pixel i from the view direction and ``Omega_i`` its solid angle
(:mod:`derender.photometry.projection`), over pixels in front of the lens (cos > 0), as
``evalglare -V`` computes it. With a per-pixel variance map the pixels are taken as
independent: ``Var[Ev] = sum_i (179 cos(theta_i) Omega_i)^2 w^T diag(var_i) w``; model
errors that pixels share make the true uncertainty larger (docs, uncertainty).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.core.errors import InputError
from derender.photometry.projection import View, pixel_directions, pixel_solid_angles

__all__ = ["RADIANCE_EFFICACY", "RADIANCE_LUMINANCE_WEIGHTS", "luminance_weights", "luminance_cd_m2",
           "vertical_illuminance", "IlluminanceResult"]

#: Radiance's white luminous efficacy (lm/W): a map's luminance is 179 Y.
RADIANCE_EFFICACY = 179.0

#: Luminance row of Radiance's standard RGB primaries (``RED/GRN/BLU`` of ``color.h``).
RADIANCE_LUMINANCE_WEIGHTS = (0.265, 0.670, 0.065)


def luminance_weights(primaries: str | tuple[float, ...] | None) -> np.ndarray:
    """Weights ``w`` with ``Y = w·RGB`` for a ``PRIMARIES`` header (8 numbers: x y of R, G,
    B, white, as text or a tuple); Radiance's standard weights when ``None``."""
    if primaries is None:
        return np.asarray(RADIANCE_LUMINANCE_WEIGHTS, dtype=np.float64)
    vals = [float(v) for v in (primaries.split() if isinstance(primaries, str) else primaries)]
    if len(vals) != 8 or any(not np.isfinite(v) for v in vals) or min(vals[1::2]) <= 0:
        raise InputError(f"PRIMARIES needs 8 numbers (x y of R, G, B, white), got {primaries!r}")
    xy = np.asarray(vals, dtype=np.float64).reshape(4, 2)
    xyz = np.stack([xy[:, 0] / xy[:, 1], np.ones(4), (1.0 - xy[:, 0] - xy[:, 1]) / xy[:, 1]], axis=1)
    prim, white = xyz[:3].T, xyz[3]
    scale = np.linalg.solve(prim, white)       # channel scales that make R = G = B = 1 the white (Y = 1)
    return prim[1] * scale


def luminance_cd_m2(radiance: np.ndarray, primaries=None) -> np.ndarray:
    """Per-pixel luminance ``179 w·RGB`` (cd/m2 for a map in Radiance units)."""
    w = luminance_weights(primaries)
    rad = np.asarray(radiance, dtype=np.float64)
    return RADIANCE_EFFICACY * (rad @ w)


@dataclass(frozen=True)
class IlluminanceResult:
    """Vertical illuminance ``ev`` (lx), its standard deviation ``ev_sd`` (None without a
    variance map), the covered solid angle (sr) and the share of ``ev`` from ``flagged``
    pixels (e.g. clipped in every exposure: a lower bound there)."""

    ev: float
    ev_sd: float | None
    solid_angle: float
    flagged_share: float | None


def vertical_illuminance(radiance: np.ndarray, view: View, primaries=None, variance: np.ndarray | None = None,
                         flagged: np.ndarray | None = None) -> IlluminanceResult:
    """Ev of an (H, W, 3) map seen through ``view`` (module docstring)."""
    rad = np.asarray(radiance, dtype=np.float64)
    if rad.ndim != 3 or rad.shape[2] != 3:
        raise InputError(f"a radiance map is (H, W, 3), got {rad.shape}")
    h, w = rad.shape[:2]
    dirs, inside = pixel_directions(view, h, w)
    omega = pixel_solid_angles(view, h, w)
    cos = np.where(inside, dirs[..., 2], 0.0)
    k = RADIANCE_EFFICACY * np.clip(cos, 0.0, None) * omega
    wts = luminance_weights(primaries)
    lum_y = rad @ wts
    ev = float(np.sum(k * lum_y))
    sd = None
    if variance is not None:
        var = np.asarray(variance, dtype=np.float64)
        if var.shape != rad.shape:
            raise InputError(f"variance {var.shape} and map {rad.shape} differ in size")
        sd = float(np.sqrt(np.sum(k * k * (np.clip(var, 0.0, None) @ (wts * wts)))))
    share = None
    if flagged is not None:
        f = np.asarray(flagged, dtype=bool)
        if f.shape != (h, w):
            raise InputError(f"flag mask {f.shape} and map {(h, w)} differ in size")
        share = float(np.sum((k * lum_y)[f]) / ev) if ev > 0 else 0.0
    return IlluminanceResult(ev=ev, ev_sd=sd, solid_angle=float(np.sum(omega[inside & (cos > 0)])),
                             flagged_share=share)
