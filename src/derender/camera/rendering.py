"""The in-camera rendering pipeline of the simulator (the JPEG engine).

:func:`isp_render` turns a raw mosaic into 8-bit codes: bilinear demosaicing, chroma noise
reduction, white balance, camera-to-sRGB matrix, gain, saturation, tone rendering (the
``simple`` power law of paper 1's eq. 4, or the ``camera`` style: gamut compression and a
filmic S-curve with highlight shoulder, then the display gamma with a linear toe), 8-bit.
:func:`pipeline_settings` draws the per-exposure settings of the ``fixed`` and ``auto``
pipelines (see :mod:`derender.camera`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.camera.sensor import CFA_PATTERN
from derender.camera.spectral import CameraSpectral, cmfs_xyz, illuminant_spd, reflectance_library
from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709
from derender.core.errors import InputError

__all__ = [
    "fit_xyz_to_camera",
    "white_balance_for",
    "RenderSettings",
    "encode_gamma_with_toe",
    "saturation_matrix",
    "filmic_curve",
    "s_curve",
    "gamut_compress",
    "demosaic_bilinear",
    "chroma_denoise",
    "camera_rgb_from_mosaic",
    "render_style",
    "isp_render",
    "pipeline_settings",
]


def fit_xyz_to_camera(camera: CameraSpectral, illuminant: str = "D65") -> np.ndarray:
    """XYZ -> camera 3x3 matrix (DNG ColorMatrix semantics) by least squares on reflectances.

    Fits camera-to-XYZ on the 24 ColorChecker + 190 rawtoaces reflectances under
    ``illuminant`` (XYZ ~= M @ camera_rgb), and returns its inverse.
    """
    names, library, groups = reflectance_library()
    rows = np.r_[np.arange(groups["colorchecker24"].start, groups["colorchecker24"].stop),
                 np.arange(groups["rawtoaces190"].start, groups["rawtoaces190"].stop)]
    e = illuminant_spd(illuminant)
    refl = library[rows] * e[None, :]
    cam = refl @ camera.sensitivities
    xyz = refl @ cmfs_xyz()
    m, *_ = np.linalg.lstsq(cam, xyz, rcond=None)  # xyz = cam @ m
    cam_to_xyz = m.T
    return np.linalg.inv(cam_to_xyz)


def white_balance_for(camera: CameraSpectral, illuminant: str) -> np.ndarray:
    """White-balance multipliers (R, G, B; G = 1) that make a neutral under ``illuminant`` grey."""
    neutral = illuminant_spd(illuminant) @ camera.sensitivities
    return neutral[1] / neutral


# --------------------------------------------------------------------------- ISP
@dataclass
class RenderSettings:
    """In-camera rendering parameters of one exposure."""

    wb: list[float]                 # multipliers R, G, B
    gain: float = 1.0               # alpha_j
    gamma: float = 2.2              # display gamma; encoding exponent is 1 / gamma
    saturation: float = 1.0         # s_j of the saturation matrix S_j
    style: str = "camera"           # "simple" | "camera"
    tone_curve: bool = False        # simple style: extra fixed S-curve

    @property
    def exponent(self) -> float:
        return 1.0 / self.gamma


def encode_gamma_with_toe(y: np.ndarray, gamma: float, a: float = 0.055) -> np.ndarray:
    """Display encoding ``(1 + a) y^(1/gamma) - a`` with a linear toe (as sRGB / Rec. 709).

    The toe ``k y`` below ``y0 = (a / ((1 + a)(1 - 1/gamma)))^gamma`` joins the power law
    with matching value and slope (for gamma = 2.4 this is sRGB: y0 = 0.0030, k = 12.9).
    Real cameras' curves have a finite slope at black; a pure power law would amplify
    sensor noise in the shadows without bound.
    """
    inv = 1.0 / gamma
    y0 = (a / ((1.0 + a) * (1.0 - inv))) ** gamma
    k = (1.0 + a) * inv * y0 ** (inv - 1.0)
    y = np.clip(y, 0.0, 1.0)
    return np.where(y < y0, k * y, (1.0 + a) * np.power(np.maximum(y, y0), inv) - a)


def saturation_matrix(s: float) -> np.ndarray:
    """S = s I + (1 - s) 1 w^T with Rec. 709 luminance weights w (keeps luminance)."""
    w = LUMINANCE_WEIGHTS_REC709
    return s * np.eye(3) + (1.0 - s) * np.outer(np.ones(3), w)


def _hable(x: np.ndarray) -> np.ndarray:
    a, b, c, d, e, f = 0.15, 0.50, 0.10, 0.20, 0.02, 0.30
    return ((x * (a * x + c * b) + d * e) / (x * (a * x + b) + d * f)) - e / f


def filmic_curve(x: np.ndarray, exposure_bias: float = 6.0, white: float = 1.0) -> np.ndarray:
    """Hable's filmic curve (toe + highlight shoulder): ``hable(b x) / hable(b W)``, 0 -> 0, W -> 1.

    With W = 1 the sensor's saturation (linear 1 after white balance) renders as white, as
    in a real camera; mid grey 0.18 renders at about 0.385 display-linear.
    """
    x = np.minimum(np.maximum(x, 0.0), white)
    return np.clip(_hable(x * exposure_bias) / _hable(np.float64(white * exposure_bias)), 0.0, 1.0)


def s_curve(y: np.ndarray, strength: float = 2.0) -> np.ndarray:
    """Spatially uniform S-shaped tone curve on [0, 1] (0 -> 0, 1 -> 1)."""
    return 0.5 + 0.5 * np.tanh(strength * (y - 0.5)) / np.tanh(strength / 2)


def gamut_compress(linear_rgb: np.ndarray, knee: float = 0.8) -> np.ndarray:
    """Soft, hue-preserving gamut compression towards luminance.

    d = max_c (L - x_c) / L is the chroma distance (1 where a channel reaches 0);
    d above ``knee`` is compressed smoothly into [knee, 1) and the chroma vector
    x - L is scaled by d' / d, so hue (chroma direction) is kept and no channel is negative.
    """
    lum = linear_rgb @ LUMINANCE_WEIGHTS_REC709
    lum_safe = np.maximum(lum, 1e-12)[..., None]
    chroma = linear_rgb - lum[..., None]
    d = np.max(-chroma, axis=-1) / lum_safe[..., 0]
    d = np.maximum(d, 0.0)
    over = d > knee
    d_new = np.where(over, knee + (1 - knee) * np.tanh((d - knee) / (1 - knee)), d)
    factor = np.where(over, d_new / np.maximum(d, 1e-12), 1.0)
    out = lum[..., None] + chroma * factor[..., None]
    return np.where(lum[..., None] > 0, out, 0.0)


def demosaic_bilinear(normalised_mosaic: np.ndarray, pattern: str = CFA_PATTERN) -> np.ndarray:
    """In-camera demosaicing (bilinear, colour-demosaicing)."""
    from colour_demosaicing import demosaicing_CFA_Bayer_bilinear

    return np.asarray(demosaicing_CFA_Bayer_bilinear(normalised_mosaic, pattern), dtype=np.float64)


def chroma_denoise(rgb: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """In-camera chroma noise reduction: Gaussian blur (``sigma`` px) of ``rgb - mean(rgb)``."""
    import cv2

    lum = rgb.mean(axis=-1, keepdims=True)
    chroma = np.ascontiguousarray(rgb - lum, dtype=np.float64)
    k = int(6 * sigma) | 1
    chroma = cv2.GaussianBlur(chroma, (k, k), sigma, borderType=cv2.BORDER_REFLECT)
    return np.clip(lum + chroma, 0.0, 1.0)


def camera_rgb_from_mosaic(mosaic: np.ndarray, camera: CameraSpectral, pattern: str = CFA_PATTERN) -> np.ndarray:
    """The JPEG engine's first stages: normalise a RAW mosaic, demosaic, chroma-denoise -> camera RGB in [0, 1]."""
    x = (mosaic.astype(np.float64) - camera.black_level) / (camera.white_level - camera.black_level)
    return chroma_denoise(np.clip(demosaic_bilinear(x, pattern), 0.0, 1.0))


def render_style(lin: np.ndarray, settings: RenderSettings) -> np.ndarray:
    """Tone rendering of the ``simple`` or ``camera`` style: linear sRGB (after gain and
    saturation) -> display values in [0, 1] (before 8-bit rounding)."""
    if settings.style == "simple":
        y = np.clip(lin, 0.0, 1.0) ** settings.exponent
        if settings.tone_curve:
            y = s_curve(y)
    elif settings.style == "camera":
        lum = lin @ LUMINANCE_WEIGHTS_REC709
        lin = lum[..., None] + 1.2 * (lin - lum[..., None])           # picture-style saturation boost
        lin = gamut_compress(lin)
        y = encode_gamma_with_toe(filmic_curve(lin), settings.gamma)
    else:
        raise InputError(f"unknown render style {settings.style!r}: use 'simple' or 'camera'")
    return y


def isp_render(mosaic: np.ndarray, camera: CameraSpectral, camera_to_srgb: np.ndarray,
               settings: RenderSettings, pattern: str = CFA_PATTERN) -> np.ndarray:
    """Render a RAW mosaic to 8-bit sRGB codes (H, W, 3) uint8 as the camera's JPEG engine does."""
    rgb = camera_rgb_from_mosaic(mosaic, camera, pattern)
    rgb = np.minimum(rgb * np.asarray(settings.wb), 1.0)          # white balance + highlight clip
    m = settings.gain * saturation_matrix(settings.saturation) @ camera_to_srgb
    lin = rgb @ m.T                                                # linear sRGB (may leave the gamut)
    y = render_style(lin, settings)
    return np.clip(np.rint(y * 255.0), 0, 255).astype(np.uint8)


def pipeline_settings(pipeline: str, n: int, wb_true: np.ndarray, style: str, rng: np.random.Generator,
                      tone_curve: bool = False) -> list[RenderSettings]:
    """Per-exposure rendering parameters for the ``fixed`` or ``auto`` pipeline (see module doc)."""
    if pipeline == "fixed":
        return [RenderSettings(wb=[float(v) for v in wb_true], style=style, tone_curve=tone_curve) for _ in range(n)]
    if pipeline != "auto":
        raise InputError(f"unknown pipeline {pipeline!r}: use 'fixed' or 'auto'")
    out = []
    drift = np.linspace(-1.0, 1.0, n)
    for j in range(n):
        d_r = 0.10 * drift[j] + rng.normal(0.0, 0.04)
        d_b = -0.08 * drift[j] + rng.normal(0.0, 0.04)
        wb = np.asarray(wb_true, dtype=np.float64) * np.exp([d_r, 0.0, d_b])
        gain = float(np.exp(rng.uniform(0.0, 0.3)))
        gamma = float(rng.uniform(1.8, 2.6))
        sat = float(rng.uniform(0.85, 1.15))
        out.append(RenderSettings(wb=[float(v) for v in wb], gain=gain, gamma=gamma, saturation=sat,
                                  style=style, tone_curve=tone_curve))
    return out
