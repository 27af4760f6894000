"""Colour-space constants and conversions used across the pipeline.

Matrices follow IEC 61966-2-1 (sRGB, Rec. 709 primaries, D65 white); they are
checked against colour-science in the tests.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "LINEAR_SRGB_TO_XYZ",
    "XYZ_TO_LINEAR_SRGB",
    "LUMINANCE_WEIGHTS_REC709",
    "D65_XYZ",
    "luminance",
    "srgb_encode",
    "srgb_decode",
]

#: Linear sRGB (Rec. 709 primaries, D65) to CIE XYZ (Y of white = 1), IEC 61966-2-1.
LINEAR_SRGB_TO_XYZ = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
#: CIE XYZ to linear sRGB.
XYZ_TO_LINEAR_SRGB = np.linalg.inv(LINEAR_SRGB_TO_XYZ)
#: Rec. 709 luminance weights (DESIGN.md evaluation protocol).
LUMINANCE_WEIGHTS_REC709 = np.array([0.2126, 0.7152, 0.0722])
#: D65 white point, Y = 1.
D65_XYZ = LINEAR_SRGB_TO_XYZ @ np.ones(3)


def luminance(linear_rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance ``0.2126 R + 0.7152 G + 0.0722 B`` of (..., 3) linear RGB."""
    rgb = np.asarray(linear_rgb)
    w = LUMINANCE_WEIGHTS_REC709.astype(rgb.dtype if rgb.dtype.kind == "f" else np.float64)
    # explicit sum, not a BLAS product: identical results whatever the BLAS thread count
    return rgb[..., 0] * w[0] + rgb[..., 1] * w[1] + rgb[..., 2] * w[2]


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB OETF (IEC 61966-2-1): linear [0, 1] -> encoded [0, 1]; input is clipped to [0, 1]."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Inverse sRGB OETF: encoded [0, 1] -> linear [0, 1]."""
    v = np.clip(np.asarray(encoded, dtype=np.float32), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4)).astype(np.float32)

