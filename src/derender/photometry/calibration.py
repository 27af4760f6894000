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
from what the camera's stated ISO speed ``S`` means (ISO 12232:2019; the exposure at the sensor
is ``H = q L t / N^2`` lx s, with ``q = 0.65``, :data:`ISO12232_Q`, for a lens of typical
transmittance and vignetting). The rating the camera uses is read from EXIF
``SensitivityType`` (and the ``StandardOutputSensitivity`` / ``RecommendedExposureIndex`` /
``ISOSpeed`` tags when present; :func:`sensitivity_rating`):

* ``sos``, the standard output sensitivity most cameras report (CIPA DC-004): ``S = 10 / H``
  where ``H`` renders at the sRGB code 118 (0.461). So a surface that frame j renders at code
  118 has ``L = (10 / q) N_j^2 / (t_j S_j)`` = ``15.4 N^2 / (t S)`` cd/m2, whatever the tone curve;
* ``rei``, the maker's recommended exposure index: taken as ``sos`` (that is what makers aim
  at), with a wider spread;
* ``saturation``, ISO speed from the sensor's saturation, ``S = 78 / H_sat``: where mid-grey
  lands then depends on the rendering's tone curve; for an sRGB rendering whose white is the
  sensor's saturation, code 118 is linear 0.181 of it, ``L = 0.181 (78 / q) N^2 / (t S)`` =
  ``21.7 N^2 / (t S)`` cd/m2;
* ``unknown`` (no ``SensitivityType``, as in older files): taken as ``sos``, with a spread that
  covers the ``saturation`` reading (0.5 EV apart).

Each frame's pixels whose luma code ``0.2126 R + 0.7152 G + 0.0722 B`` is 118 +- 6 (and not
over-exposed in every frame; frames with at least 64 such pixels) give a factor ``k_j = L_j /
median(179 w·m)``; the median over frames is taken. It is a nominal figure; its relative
standard uncertainty (:data:`SENSITIVITY_RATINGS`, each spread taken as uniform) is 15 %
(``sos``: ``q`` within +-10 %, the stated speed within +-1/3 EV), 21 % (``rei``: +-1/2 EV) and
44 % (``saturation`` and ``unknown``: mid-grey placed within +-1 EV of sRGB's by the tone
curve), against the about 7 % of a spot reading on a grey card (Inanici 2006). Measured on the
simulator's luminance family (saturation rated; ``derender simulate --luminance time``, 192x128,
seed 0; median ratio of the map's luminance to the truth on smooth pixels, debevec /
stabilized): tuning renderings ``gamma`` 0.98 / 1.01, ``paper`` 1.08 / 1.09, ``camera`` 2.14 /
1.87 (its filmic curve lifts mid-grey by about 1 EV, the case a saturation rating cannot know,
and the one that sets the +-1 EV); held out ``dslr-lut`` 1.18 / 1.12, ``phone-local`` 0.77 /
0.73, ``drift`` 2.34 / 2.27.

**RAW frames** (:func:`raw_exif_factor`) need no mid-grey pixel: the RAW merge's map is in units
of the white level per second (:mod:`derender.raw.optimal`), and ISO 12232's saturation-based
speed puts the white level at ``H_sat = 78 / S`` lx s, so a neutral surface whose map luminance
is ``m`` (white levels per second) has

    L = (78 / q) N^2 m / S = 120 N^2 m / S  cd/m2            (:data:`RAW_SATURATION_EXPOSURE`),

the factor ``k = 120 N^2 / (179 S)`` on ``179 w·m``, the same for every frame of a bracket that
keeps N and S. Its relative standard uncertainty is 15 % when the file states a saturation speed
(``q`` within +-10 %, the speed within +-1/3 EV) and 44 % otherwise (an SOS or REI rating puts
mid-grey, not the RAW white level, at a stated exposure: the headroom above it is the maker's
choice, taken within +-1 EV). Measured on the simulator's luminance family (saturation rated
sensor; RAW merge, ``--luminance time``, 192x128, 9 exposures): see docs/raw.md.

(The reflected-light meter constant of ISO 2720, ``K = 12.5`` cd s/m2, :data:`ISO2720_K`, is
what a meter aims at: ``H = q K / S``, 0.81 of an SOS camera's code-118 exposure. An earlier
version took ``K N^2 / (t S)`` at code 118; that reads an SOS camera 19 % low and a saturation
rated one 44 % low.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult
from derender.photometry.illuminance import luminance_cd_m2

__all__ = ["Spot", "parse_spot", "SpotCalibration", "spot_factor", "ISO2720_K", "ISO12232_Q", "MID_GREY_CODE",
           "MID_GREY_LINEAR", "SensitivityRating", "SENSITIVITY_RATINGS", "sensitivity_rating", "ExifCalibration",
           "exif_factor", "RAW_SATURATION_EXPOSURE", "raw_exif_factor"]

#: The reflected-light meter calibration constant of ISO 2720 (cd s / m2), as most makers use it.
ISO2720_K = 12.5
#: ISO 12232's factor of the sensor exposure ``H = q L t / N^2`` (lens transmittance, vignetting, angle).
ISO12232_Q = 0.65
#: The 8-bit sRGB code of an 18 % grey (0.461 x 255): where an SOS-rated camera renders ``H = 10 / S``.
MID_GREY_CODE = 118
#: Code :data:`MID_GREY_CODE` in linear light (the sRGB decoding of 118 / 255).
MID_GREY_LINEAR = float(((MID_GREY_CODE / 255 + 0.055) / 1.055) ** 2.4)
#: ``L t S / N^2`` (cd s / m2) that brings a neutral to the RAW white level: ISO 12232's ``78 / q``.
RAW_SATURATION_EXPOSURE = 78.0 / ISO12232_Q


def _uniform_sd(ev: float) -> float:
    """Relative standard deviation of a factor spread uniformly over +-``ev`` stops."""
    return float((2.0 ** ev - 2.0 ** -ev) / (2.0 * np.sqrt(3.0)))


@dataclass(frozen=True)
class SensitivityRating:
    """What a stated ISO speed means: ``constant`` is the luminance (cd/m2) that renders at
    :data:`MID_GREY_CODE` per ``N^2 / (t S)``; ``uncertainty`` the relative standard uncertainty
    of the nominal factor; ``name`` as printed."""

    name: str
    constant: float
    uncertainty: float


_Q_SD = 0.10 / np.sqrt(3.0)          # q within +-10 %
#: The ratings of :func:`sensitivity_rating` (module docstring).
SENSITIVITY_RATINGS = {
    "sos": SensitivityRating("ISO 12232 standard output sensitivity", 10.0 / ISO12232_Q,
                             float(np.hypot(_Q_SD, _uniform_sd(1 / 3)))),
    "rei": SensitivityRating("recommended exposure index (taken as SOS)", 10.0 / ISO12232_Q,
                             float(np.hypot(_Q_SD, _uniform_sd(1 / 2)))),
    "saturation": SensitivityRating("ISO 12232 saturation speed, sRGB mid-grey", MID_GREY_LINEAR * 78.0 / ISO12232_Q,
                                    float(np.hypot(_Q_SD, _uniform_sd(1.0)))),
    "unknown": SensitivityRating("unstated rating, taken as SOS", 10.0 / ISO12232_Q,
                                 float(np.hypot(_Q_SD, _uniform_sd(1.0)))),
}


def sensitivity_rating(exif: dict) -> tuple[str, float | None]:
    """The rating (a key of :data:`SENSITIVITY_RATINGS`) and the speed ``S`` a frame's EXIF states
    (:func:`derender.io.exif.read_exif`): the ``SOS`` / ``REI`` / ``ISOSpeed`` tag its
    ``SensitivityType`` names when present, else ``ISO`` (``PhotographicSensitivity``).
    ``SensitivityType`` (EXIF 2.3): 1 SOS, 2 REI, 3 ISO speed, 4 SOS+REI, 5 SOS+ISO speed,
    6 REI+ISO speed, 7 all three; 0 or absent: unknown."""
    kind = int(exif.get("SensitivityType", 0) or 0)
    iso = exif.get("ISO")
    if kind in (1, 4, 5, 7):
        return "sos", exif.get("SOS", iso)
    if kind in (2, 6):
        return "rei", exif.get("REI", iso)
    if kind == 3:
        return "saturation", exif.get("ISOSpeed", iso)
    return "unknown", iso


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
    rating it assumed (a key of :data:`SENSITIVITY_RATINGS`), the per-frame factors it is the
    median of, and the pixels each used."""

    factor: float
    uncertainty: float
    rating: str
    per_frame: tuple
    counts: tuple


def exif_factor(radiance: np.ndarray, frames, primaries=None, mask: np.ndarray | None = None, *,
                rating: str = "unknown", tolerance: int = 6, min_pixels: int = 64) -> ExifCalibration:
    """The nominal EXIF factor of ``radiance`` (H, W, 3), the merge of ``frames``: an iterable
    of ``(codes, t, N, S)``, each frame's 8-bit codes (H, W, 3) on the map's grid, time (s),
    f-number and ISO speed, stated under ``rating`` (:func:`sensitivity_rating`; module docstring)."""
    if rating not in SENSITIVITY_RATINGS:
        raise InputError(f"unknown ISO rating {rating!r}: use {', '.join(SENSITIVITY_RATINGS)}")
    spec = SENSITIVITY_RATINGS[rating]
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
        ks.append(spec.constant * float(n) ** 2 / (float(t) * float(s)) / float(np.median(lum[sel])))
        counts.append(int(sel.sum()))
    if not ks:
        raise InputError(f"no frame has {min_pixels} pixels near mid-grey (luma code {MID_GREY_CODE} +- "
                         f"{tolerance}) for the nominal EXIF factor; use --spot")
    return ExifCalibration(factor=float(np.median(ks)), uncertainty=spec.uncertainty, rating=rating,
                           per_frame=tuple(ks), counts=tuple(counts))


def raw_exif_factor(settings, rating: str = "unknown") -> ExifCalibration:
    """The nominal EXIF factor of a RAW merge (module docstring, "RAW frames"): ``settings`` is an
    iterable of ``(N, S)`` per frame (f-number, ISO speed), the map in white levels per second;
    ``rating`` as :func:`sensitivity_rating` names it (``"saturation"``: 15 %, else 44 %).
    ``per_frame`` holds each frame's factor and ``counts`` is empty (no pixel is selected)."""
    if rating not in SENSITIVITY_RATINGS:
        raise InputError(f"unknown ISO rating {rating!r}: use {', '.join(SENSITIVITY_RATINGS)}")
    ks = []
    for n, s in settings:
        if not (n and s and np.isfinite(n) and np.isfinite(s) and n > 0 and s > 0):
            raise InputError(f"--absolute exif needs a positive f-number and ISO speed, got f/{n} ISO {s}")
        ks.append(RAW_SATURATION_EXPOSURE * float(n) ** 2 / (179.0 * float(s)))
    if not ks:
        raise InputError("--absolute exif: no RAW frame given")
    if max(ks) > min(ks) * (1.0 + 1e-9):
        raise InputError("--absolute exif: the RAW frames vary the f-number or ISO; the nominal factor needs "
                         "them fixed (use --spot)")
    unc = np.hypot(_Q_SD, _uniform_sd(1 / 3 if rating == "saturation" else 1.0))
    return ExifCalibration(factor=float(ks[0]), uncertainty=float(unc), rating=rating, per_frame=tuple(ks),
                           counts=())
