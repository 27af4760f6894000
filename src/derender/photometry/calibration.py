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

Without a meter reading, EXIF gives a nominal factor (:func:`exif_factor`, ``--absolute exif``)
from the reflected-light meter equation of ISO 2720, ``N^2 / t = L S / K`` with the
calibration constant ``K = 12.5 cd s/m2``: the convention is that a surface the meter exposes
correctly, rendered at the sRGB mid-grey code 118 (``0.461``, linear 0.18: an 18 % grey
card), has luminance ``L = K N^2 / (t S)`` in a frame of time ``t``, f-number ``N`` and ISO
speed ``S``. Each frame's pixels whose luma code ``0.2126 R + 0.7152 G + 0.0722 B`` is
118 +- 6 (and not over-exposed in every frame; frames with at least 64 such pixels) give a factor
``k_j = K N_j^2 / (t_j S_j) / median(179 w·m)``; the median over frames is taken. It is a
nominal figure: ISO 2720 allows ``K`` from 10.6 to 13.4, ISO 12232 lets a camera's stated
speed differ by 1/3 EV, and cameras place mid-grey anywhere within about 1/3 EV of code
118. Taking each as a uniform spread, the relative standard uncertainty is
``sqrt(0.07^2 + 0.15^2 + 0.15^2) = 0.22`` (:data:`EXIF_FACTOR_UNCERTAINTY`), against the
about 7 % of a spot reading on a grey card (Inanici 2006).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult
from derender.photometry.illuminance import luminance_cd_m2

__all__ = ["Spot", "parse_spot", "SpotCalibration", "spot_factor", "ISO2720_K", "MID_GREY_CODE",
           "EXIF_FACTOR_UNCERTAINTY", "ExifCalibration", "exif_factor"]

#: The reflected-light meter calibration constant of ISO 2720 (cd s / m2), as most makers use it.
ISO2720_K = 12.5
#: The 8-bit sRGB code of an 18 % grey (0.461 x 255): where a correctly metered surface renders.
MID_GREY_CODE = 118
#: Relative standard uncertainty of the nominal factor: K (uniform over 10.6..13.4: 0.07),
#: the camera's ISO speed (uniform over +-1/3 EV: 0.15), the mid-grey placement (+-1/3 EV: 0.15).
EXIF_FACTOR_UNCERTAINTY = float(np.sqrt(0.07 ** 2 + 0.15 ** 2 + 0.15 ** 2))


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


@dataclass(frozen=True)
class ExifCalibration:
    """The nominal factor ``k`` (module docstring), its relative standard uncertainty, the
    per-frame factors it is the median of, and the pixels each used."""

    factor: float
    uncertainty: float
    per_frame: tuple
    counts: tuple


def exif_factor(radiance: np.ndarray, frames, primaries=None, mask: np.ndarray | None = None,
                tolerance: int = 6, min_pixels: int = 64) -> ExifCalibration:
    """The nominal EXIF factor of ``radiance`` (H, W, 3), the merge of ``frames``: an iterable
    of ``(codes, t, N, S)``, each frame's 8-bit codes (H, W, 3) on the map's grid, time (s),
    f-number and ISO speed (module docstring)."""
    rad = np.asarray(radiance)
    lum = luminance_cd_m2(rad, primaries)
    ok_map = np.isfinite(lum) & (lum > 0)
    if mask is not None:
        ok_map &= np.asarray(mask) == 0
    ks, counts = [], []
    for codes, t, n, s in frames:
        c = np.asarray(codes, dtype=np.float32)
        if c.shape[:2] != rad.shape[:2]:
            raise InputError(f"a frame is {c.shape[1]}x{c.shape[0]}, the map {rad.shape[1]}x{rad.shape[0]}")
        luma = 0.2126 * c[..., 0] + 0.7152 * c[..., 1] + 0.0722 * c[..., 2]
        sel = ok_map & (np.abs(luma - MID_GREY_CODE) <= tolerance) & (c.max(axis=-1) < 250)
        if int(sel.sum()) < min_pixels:
            continue
        ks.append(ISO2720_K * float(n) ** 2 / (float(t) * float(s)) / float(np.median(lum[sel])))
        counts.append(int(sel.sum()))
    if not ks:
        raise InputError(f"no frame has {min_pixels} pixels near mid-grey (luma code {MID_GREY_CODE} +- "
                         f"{tolerance}) for the nominal EXIF factor; use --spot")
    return ExifCalibration(factor=float(np.median(ks)), uncertainty=EXIF_FACTOR_UNCERTAINTY,
                           per_frame=tuple(ks), counts=tuple(counts))
