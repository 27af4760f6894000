"""The oracle inverse of the simulator's JPEG engines: one frame's codes -> linear radiance.

:func:`invert_frame_codes` undoes every stage of :func:`derender.camera.stages.render_frame`
for the frame's true :class:`~derender.camera.stages.FrameSettings`: tone curves (analytic for
the display gamma with its toe and for the S-curve, dense monotone tables otherwise), the
filmic style's gamut compression and saturation boost, the ``dslr`` gamut map (fixed-point
iteration on the same trilinear LUT; the map's slope is below 1, so it converges) and its
hue-dependent saturation, the ``local`` gain map, the 3x3 colour transform and the white
balance, and maps the result into the truth's space (linear sRGB of the white-balanced
camera RGB, as ``truth.exr``). It cannot undo the demosaicing and chroma denoising (spatial
filters; the identity on smooth regions) nor the clipping: it says where the inversion is
exact up to 8-bit quantisation (the mask).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from derender.camera.rendering import filmic_curve
from derender.camera.stages import (
    FrameSettings,
    apply_lut,
    channel_curve,
    frame_matrix,
    gamut_lut,
    hue_angle,
    hue_saturation_factor,
)
from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709
from derender.core.errors import InputError

__all__ = [
    "invert_curve",
    "invert_frame_codes",
    "invert_frame_values",
]


def invert_curve(f: Callable[[np.ndarray], np.ndarray], y: np.ndarray, n: int = 16385, power: float = 3.0) -> np.ndarray:
    """Invert a monotone increasing curve ``f`` on [0, 1] at ``y`` by a dense table.

    The table samples ``x = s ** power`` (``s`` uniform), dense in the shadows where the
    display curves are steep; between samples it interpolates linearly.
    """
    x = np.linspace(0.0, 1.0, n) ** power
    fx = np.maximum.accumulate(np.asarray(f(x), dtype=np.float64))
    return np.interp(np.asarray(y, dtype=np.float64), fx, x)


def _inverse_gamma_with_toe(y: np.ndarray, gamma: float, a: float = 0.055) -> np.ndarray:
    inv = 1.0 / gamma
    y0 = (a / ((1.0 + a) * (1.0 - inv))) ** gamma
    k = (1.0 + a) * inv * y0 ** (inv - 1.0)
    y = np.clip(y, 0.0, 1.0)
    return np.where(y < k * y0, y / k, ((y + a) / (1.0 + a)) ** gamma)


def _inverse_s_curve(y: np.ndarray, strength: float = 2.0) -> np.ndarray:
    arg = np.clip((y - 0.5) * 2.0 * np.tanh(strength / 2.0), -1.0 + 1e-12, 1.0 - 1e-12)
    return np.clip(0.5 + np.arctanh(arg) / strength, 0.0, 1.0)


def _inverse_gamut_compress(lin: np.ndarray, knee: float = 0.8) -> np.ndarray:
    lum = lin @ LUMINANCE_WEIGHTS_REC709
    chroma = lin - lum[..., None]
    d_new = np.maximum(np.max(-chroma, axis=-1) / np.maximum(lum, 1e-12), 0.0)
    over = d_new > knee
    arg = np.clip((d_new - knee) / (1.0 - knee), 0.0, 1.0 - 1e-9)
    d = knee + (1.0 - knee) * np.arctanh(arg)
    factor = np.where(over, d / np.maximum(d_new, 1e-12), 1.0)
    out = lum[..., None] + chroma * factor[..., None]
    return np.where(lum[..., None] > 0, out, 0.0)


def _inverse_lut_map(lut: np.ndarray, u_out: np.ndarray, iterations: int = 200, tol: float = 1e-12) -> np.ndarray:
    u = u_out.copy()
    for _ in range(iterations):
        nxt = np.clip(u_out - apply_lut(lut, u), 0.0, 1.0)
        done = float(np.abs(nxt - u).max()) if u.size else 0.0
        u = nxt
        if done < tol:
            break
    return u


def invert_frame_codes(codes: np.ndarray, settings: FrameSettings, clip_margin: float = 0.03,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Invert one frame's true pipeline: 8-bit codes (H, W, 3) -> (linear, valid).

    ``linear`` (H, W, 3) float64: radiance in the truth's space (linear sRGB of camera RGB
    white-balanced with ``settings.wb_as_shot``) times the exposure time, i.e. per unit
    exposure *before* dividing by the time; finite everywhere (a best effort where not valid).
    ``valid`` (H, W) bool: the inversion is exact up to quantisation: no channel code is
    255, and no white-balanced or sensor channel is within ``clip_margin`` of its clip
    (information lost before the matrix mixes the channels, which spreads the loss to
    every channel). A code of 0 leaves the pixel valid: its own channel is known only to
    be below half a code (the weights of the merge ignore it) and the error it spreads
    through the matrix is below that bound.
    """
    codes = np.asarray(codes)
    if codes.ndim != 3 or codes.shape[-1] != 3:
        raise InputError(f"codes must have shape (H, W, 3), got {codes.shape}")
    valid = np.all(codes < 255, axis=-1)
    linear, ok = invert_frame_values(codes.astype(np.float64) / 255.0, settings, clip_margin)
    return linear, valid & ok


def invert_frame_values(y: np.ndarray, settings: FrameSettings, clip_margin: float = 0.03,
                        ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`invert_frame_codes` of display values ``y`` = code / 255 (H, W, 3), which may lie
    between codes (e.g. half a code above 0, for the bound a code of 0 implies).

    Returns ``(linear, ok)``, ``ok`` False where a white-balanced or sensor channel is within
    ``clip_margin`` of its clip (clipped codes are not looked at here).
    """
    y = np.asarray(y, dtype=np.float64)
    style = settings.style
    if style == "simple":
        if settings.tone_curve:
            y = _inverse_s_curve(y)
        lin = np.clip(y, 0.0, 1.0) ** settings.gamma
    elif style == "camera":
        x = invert_curve(filmic_curve, _inverse_gamma_with_toe(y, settings.gamma))
        lin = _inverse_gamut_compress(x)
        lum = (lin @ LUMINANCE_WEIGHTS_REC709)[..., None]
        lin = lum + (lin - lum) / 1.2
    elif style == "dslr":
        x = np.stack([invert_curve(lambda v, p=settings.curves[c]: channel_curve(v, p), y[..., c])
                      for c in range(3)], axis=-1)
        u = _inverse_lut_map(gamut_lut(settings.gamut), np.sqrt(np.clip(x, 0.0, 1.0)))
        lin = u * u
        lum = (lin @ LUMINANCE_WEIGHTS_REC709)[..., None]
        s = hue_saturation_factor(hue_angle(lin), settings.hue_sat)[..., None]
        lin = lum + (lin - lum) / s
    elif style == "local":
        if settings.gain_map is None:
            raise InputError("a 'local' frame's settings carry no gain map")
        from derender.camera.stages import inverse_local_curve, upsample_gain

        gain = upsample_gain(settings.gain_map, y.shape[:2])
        lin = inverse_local_curve(_inverse_gamma_with_toe(y, settings.gamma), gain[..., None])
    else:
        raise InputError(f"unknown render style {style!r}")
    rgb_wb = lin @ np.linalg.inv(frame_matrix(settings)).T
    wb = np.asarray(settings.wb, dtype=np.float64)
    cam = rgb_wb / wb
    valid = np.all((rgb_wb < 1.0 - clip_margin) & (cam < 1.0 - clip_margin), axis=-1)
    c2s = np.asarray(settings.camera_to_srgb, dtype=np.float64)
    linear = (cam * np.asarray(settings.wb_as_shot, dtype=np.float64)) @ c2s.T
    linear = np.nan_to_num(linear, nan=0.0, posinf=0.0, neginf=0.0)
    return linear, valid
