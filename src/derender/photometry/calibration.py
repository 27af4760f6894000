"""The photometric factor: from relative radiance to cd/m2 with a luminance-meter reading.

A merged map is linear in the scene's radiance but in relative units. A spot reading of a
luminance meter over a region of the scene (a grey card, a wall; ``L_meter`` in cd/m2) fixes
the one factor ``k`` that makes the map's luminance (:mod:`derender.photometry.illuminance`,
``179 w·RGB``) there equal the reading:

    k = L_meter / mean_{region}(179 w·RGB),

and the calibrated map is ``k`` times the merged one (its variance ``k^2`` times), the
procedure of the luminance-map literature (Inanici 2006; Pierson et al., LEUKOS 2021),
in which the factor is taken on a uniform, well-exposed target. The region must lie inside
the image, hold no pixel that is over-exposed in every frame (there the map is only a
bound) and have a positive luminance; its relative spread is reported, since a factor taken
on a textured region is only as good as the meter's alignment with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult
from derender.photometry.illuminance import luminance_cd_m2

__all__ = ["Spot", "parse_spot", "SpotCalibration", "spot_factor"]


@dataclass(frozen=True)
class Spot:
    """A luminance-meter reading: rectangle ``x, y, width, height`` (pixels of the output map,
    origin at the top left) and its luminance ``nits`` (cd/m2)."""

    x: int
    y: int
    width: int
    height: int
    nits: float


def parse_spot(text: str) -> Spot:
    """``"X,Y,W,H=NITS"`` as a :class:`Spot`."""
    rect, sep, value = str(text).partition("=")
    try:
        x, y, w, h = (int(v) for v in rect.split(","))
        nits = float(value)
    except ValueError:
        raise InputError(f"--spot takes X,Y,W,H=NITS (pixels, cd/m2), got {text!r}") from None
    if not sep or w < 1 or h < 1 or x < 0 or y < 0:
        raise InputError(f"--spot takes X,Y,W,H=NITS with a non-empty rectangle, got {text!r}")
    if not (np.isfinite(nits) and nits > 0):
        raise InputError(f"--spot luminance must be a positive number of cd/m2, got {value!r}")
    return Spot(x, y, w, h, nits)


@dataclass(frozen=True)
class SpotCalibration:
    """The factor ``k``, the map's mean relative luminance over the spot before scaling, and
    the relative standard deviation of the luminance inside the spot."""

    factor: float
    relative_luminance: float
    spread: float


def spot_factor(radiance: np.ndarray, spot: Spot, primaries=None, mask: np.ndarray | None = None) -> SpotCalibration:
    """The photometric factor of ``radiance`` (H, W, 3) for ``spot`` (module docstring);
    ``mask`` is the merge's (``HDRResult.mask``: 1 over-exposed in every frame)."""
    rad = np.asarray(radiance)
    h, w = rad.shape[:2]
    if spot.x + spot.width > w or spot.y + spot.height > h:
        raise InputError(f"--spot rectangle {spot.x},{spot.y},{spot.width},{spot.height} lies outside the "
                         f"{w}x{h} image")
    ys, xs = slice(spot.y, spot.y + spot.height), slice(spot.x, spot.x + spot.width)
    if mask is not None and np.any(np.asarray(mask)[ys, xs] == HDRResult.MASK_BRIGHT):
        n = int(np.count_nonzero(np.asarray(mask)[ys, xs] == HDRResult.MASK_BRIGHT))
        raise InputError(f"--spot rectangle holds {n} pixel(s) over-exposed in every frame; a photometric "
                         "factor needs a well-exposed region")
    lum = luminance_cd_m2(rad[ys, xs], primaries)
    mean = float(lum.mean())
    if not (np.isfinite(mean) and mean > 0):
        raise InputError("--spot rectangle has no positive luminance in the map")
    return SpotCalibration(factor=spot.nits / mean, relative_luminance=mean, spread=float(lum.std() / mean))
