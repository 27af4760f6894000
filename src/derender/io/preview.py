"""Previews of radiance maps: Reinhard's photographic tone mapping and 8-bit PNG writing.

E. Reinhard, M. Stark, P. Shirley, J. Ferwerda, "Photographic Tone Reproduction for
Digital Images", SIGGRAPH 2002, global operator (eqs. 1-4): log-average luminance
``L_w_bar = exp(mean(log(delta + L_w)))``, scaled luminance ``L = a L_w / L_w_bar``,
display luminance ``L_d = L (1 + L / L_white^2) / (1 + L)`` with ``L_white`` the
largest scaled luminance (burn-out) unless given. Paper 1 uses it for its figures.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

import numpy as np

from derender.core.colorimetry import luminance, srgb_encode
from derender.core.errors import InputError
from derender.io.files import atomic_output

__all__ = [
    "IMAGE8_SUFFIXES",
    "write_png",
    "write_preview",
    "reinhard_photographic",
    "encode_srgb",
]


# --------------------------------------------------------------------------- previews
#: 8-bit image formats the previews and masks can be written in (by file suffix).
IMAGE8_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def write_png(path: str | os.PathLike, image: np.ndarray, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Write an (H, W, 3) float image in [0, 1] (or uint8/uint16) atomically, as PNG, or as
    JPEG (quality 95) / TIFF when the suffix says so (any other suffix is refused)."""
    import cv2

    arr = np.asarray(image)
    if arr.dtype.kind == "f":
        arr = np.rint(np.clip(np.nan_to_num(arr), 0.0, 1.0) * 255.0).astype(np.uint8)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE8_SUFFIXES:
        raise InputError(f"cannot write {path.name}: use one of {', '.join(IMAGE8_SUFFIXES)}")
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix in (".jpg", ".jpeg") else []
    with atomic_output(path, inputs) as tmp:
        ok, enc = cv2.imencode(suffix, np.ascontiguousarray(arr), params)
        if not ok:
            raise InputError(f"could not encode {suffix} for {path}")
        enc.tofile(tmp)
    return path


def write_preview(path: str | os.PathLike, radiance: np.ndarray, inputs: Iterable[str | os.PathLike] = (),
                  key: float = 0.18) -> Path:
    """Tone-map a linear-sRGB radiance map (Reinhard et al. 2002) and write it as 8-bit sRGB (PNG/JPEG/TIFF by suffix)."""
    return write_png(path, encode_srgb(reinhard_photographic(radiance, key=key)), inputs)


def reinhard_photographic(radiance_linear_srgb: np.ndarray, key: float = 0.18,
                          l_white: float | None = None, delta: float = 1e-6) -> np.ndarray:
    """Global Reinhard 2002 operator; returns display-linear RGB in [0, 1], finite."""
    rgb = np.nan_to_num(np.asarray(radiance_linear_srgb, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    rgb = np.maximum(rgb, 0.0)
    lum = luminance(rgb).astype(np.float64)
    positive = lum[lum > 0]
    if positive.size == 0:
        return np.zeros_like(rgb)
    log_avg = float(np.exp(np.mean(np.log(delta + positive))))
    scaled = key * lum / log_avg
    lw = float(np.max(scaled)) if l_white is None else float(l_white) * key / log_avg
    lw = max(lw, 1e-12)
    display = scaled * (1.0 + scaled / (lw * lw)) / (1.0 + scaled)
    ratio = np.divide(display, lum, out=np.zeros_like(lum), where=lum > 0)
    out = rgb * ratio[..., None].astype(np.float32)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def encode_srgb(display_linear: np.ndarray) -> np.ndarray:
    """Display-linear [0, 1] to sRGB-encoded [0, 1] (for 8-bit PNG)."""
    return srgb_encode(display_linear)
