"""Minimal DNG writer (tifffile): a Bayer CFA mosaic with the tags LibRaw needs.

Writes DNG 1.4 with: NewSubfileType 0, PhotometricInterpretation CFA (32803),
CFARepeatPatternDim / CFAPattern, BlackLevelRepeatDim / BlackLevel, WhiteLevel,
ColorMatrix1 (XYZ -> camera, SRATIONAL), CalibrationIlluminant1 (21 = D65),
AsShotNeutral, ExposureTime (tag 33434 in IFD0, as TIFF/EP allows), Make, Model,
UniqueCameraModel and, when given, FNumber, ISOSpeedRatings, SensitivityType (with ISOSpeed when
it is 3, a saturation-based speed, as EXIF 2.3 writes it) and NoiseProfile (51041: ``Var[x] = S x + O`` for the signal
``x = (raw - black) / (white - black)``, as Adobe's converter writes it). Adobe DNG
Specification 1.4, chapter 4.
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from derender.io.files import atomic_output

__all__ = [
    "to_rational",
    "write_dng",
]


_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def to_rational(value: float, max_den: int = 1_000_000) -> tuple[int, int]:
    """Closest fraction with denominator <= ``max_den`` as ``(num, den)``."""
    f = Fraction(float(value)).limit_denominator(max_den)
    return f.numerator, f.denominator


def _srational_list(values) -> tuple[int, ...]:
    out: list[int] = []
    for v in np.asarray(values, dtype=np.float64).reshape(-1):
        n, d = to_rational(v, 10000)
        out += [n, d]
    return tuple(out)


def write_dng(path: str | os.PathLike, mosaic: np.ndarray, *, cfa_pattern: str, black_level: int,
              white_level: int, xyz_to_camera: np.ndarray, as_shot_neutral: np.ndarray,
              exposure_time: float, make: str, model: str, bits: int = 14,
              noise_profile: tuple[float, float] | None = None, fnumber: float | None = None,
              iso: int | None = None, sensitivity_type: int | None = None) -> Path:
    """Write ``mosaic`` (H, W) uint16 as an uncompressed single-IFD DNG, atomically
    (``noise_profile``: the (S, O) of the NoiseProfile tag; ``fnumber``, ``iso``: FNumber and
    ISOSpeedRatings in IFD0, as TIFF/EP allows; ``sensitivity_type``: EXIF 2.3's SensitivityType,
    3 for an ISO speed from saturation, which then also goes to ISOSpeed)."""
    import tifffile

    mosaic = np.ascontiguousarray(mosaic, dtype=np.uint16)
    if mosaic.ndim != 2:
        raise ValueError("mosaic must be 2-D")
    cfa = bytes(_CFA_CODES[c] for c in cfa_pattern.upper())
    num, den = to_rational(exposure_time)
    neutral = []
    for v in np.asarray(as_shot_neutral, dtype=np.float64).reshape(3):
        n, d = to_rational(v, 100000)
        neutral += [n, d]
    unique = f"{make} {model}".strip()
    extratags = [
        (254, "I", 1, 0, True),                                   # NewSubfileType: main image
        (271, "s", 0, make, True),                                # Make
        (272, "s", 0, model, True),                               # Model
        (33421, "H", 2, (2, 2), True),                            # CFARepeatPatternDim
        (33422, "B", 4, cfa, True),                               # CFAPattern
        (33434, "2I", 1, (num, den), True),                       # ExposureTime
        (50706, "B", 4, (1, 4, 0, 0), True),                      # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),                      # DNGBackwardVersion
        (50708, "s", 0, unique, True),                            # UniqueCameraModel
        (50713, "H", 2, (1, 1), True),                            # BlackLevelRepeatDim
        (50714, "I", 1, int(black_level), True),                  # BlackLevel
        (50717, "I", 1, int(white_level), True),                  # WhiteLevel
        (50721, "2i", 9, _srational_list(xyz_to_camera), True),   # ColorMatrix1
        (50728, "2I", 3, tuple(neutral), True),                   # AsShotNeutral
        (50778, "H", 1, 21, True),                                # CalibrationIlluminant1 = D65
    ]
    if fnumber is not None:
        extratags.append((33437, "2I", 1, to_rational(fnumber, 1000), True))            # FNumber
    if iso is not None:
        extratags.append((34855, "H", 1, int(iso), True))                                # ISOSpeedRatings
    if sensitivity_type is not None:
        extratags.append((34864, "H", 1, int(sensitivity_type), True))                   # SensitivityType
        if int(sensitivity_type) == 3 and iso is not None:
            extratags.append((34867, "I", 1, int(iso), True))                            # ISOSpeed
    if noise_profile is not None:
        extratags.append((51041, "d", 2, tuple(float(v) for v in noise_profile), True))   # NoiseProfile
    path = Path(path)
    with atomic_output(path) as tmp:
        tifffile.imwrite(
            tmp, mosaic, photometric=32803, planarconfig=None, compression=None,
            bitspersample=16, extratags=extratags, metadata=None, software="derender simulator",
        )
    return path
