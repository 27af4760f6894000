"""Colour-space constants and conversions used across the pipeline.

Matrices follow IEC 61966-2-1 (sRGB, Rec. 709 primaries, D65 white); they are
checked against colour-science in the tests.
"""

from __future__ import annotations

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "LINEAR_SRGB_TO_XYZ",
    "XYZ_TO_LINEAR_SRGB",
    "LUMINANCE_WEIGHTS_REC709",
    "D65_XYZ",
    "luminance",
    "srgb_encode",
    "srgb_decode",
    "camera_to_xyz_matrix",
    "camera_to_linear_srgb_matrix",
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


#: Rec. 709 luminance weights (the HDR PSNR protocol, ``docs/paper1.md``).
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


# --------------------------------------------------------------------------- colour matrices
def camera_to_xyz_matrix(xyz_to_camera: np.ndarray, white_xyz: np.ndarray | None = None) -> np.ndarray:
    """Camera RGB (white balanced) -> CIE XYZ matrix from a DNG ``ColorMatrix``.

    ``xyz_to_camera`` (M) maps XYZ to raw camera RGB, un-normalised (DNG ColorMatrix
    semantics). As dcraw/LibRaw do with ``cam_xyz`` and ``pre_mul``, each row of M is
    scaled so that the reference white ``white_xyz`` (default D65 with Y = 1) maps to
    camera ``(1, 1, 1)``: ``M_n = diag(1 / (M @ white_xyz)) @ M``. The result is
    ``inv(M_n)``, so the white-balanced camera white ``(1, 1, 1)`` maps exactly to
    ``white_xyz`` (Y = 1). Applied after white balancing with the scene's multipliers,
    this is dcraw's von Kries adaptation in camera space: the scene's neutral becomes
    D65 white. Raises :class:`InputError` for a singular or non-finite matrix.
    """
    m = np.asarray(xyz_to_camera, dtype=np.float64)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise InputError(f"xyz_to_camera must be a finite 3x3 matrix, got shape {m.shape}")
    white = D65_XYZ if white_xyz is None else np.asarray(white_xyz, dtype=np.float64).reshape(3)
    cam_white = m @ white
    if not np.all(cam_white > 0):
        raise InputError(f"xyz_to_camera maps the white point to non-positive camera RGB {cam_white.tolist()}")
    m_n = m / cam_white[:, None]
    if abs(np.linalg.det(m_n)) < 1e-12 or np.linalg.cond(m_n) > 1e8:
        raise InputError("xyz_to_camera matrix is singular")
    return np.linalg.inv(m_n)


def camera_to_linear_srgb_matrix(xyz_to_camera: np.ndarray) -> np.ndarray:
    """White-balanced camera RGB -> linear sRGB (D65): ``XYZ_TO_LINEAR_SRGB @ camera_to_xyz``.

    Equals LibRaw's ``rgb_cam`` (``rawpy.RawPy.color_matrix``) for the same ColorMatrix;
    every row sums to 1 (camera white -> sRGB white).
    """
    return XYZ_TO_LINEAR_SRGB @ camera_to_xyz_matrix(xyz_to_camera)
