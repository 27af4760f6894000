"""HDR evaluation protocol ("HDR PSNR", ``docs/paper1.md``), as in paper 1 (Sec. 4, Table 1).

A radiance map is known only up to scale. For each plane (R, G, B, and the Rec. 709
luminance ``L = 0.2126 R + 0.7152 G + 0.0722 B``, computed from the *unscaled* result
and scaled on its own) the result ``r`` is first mapped onto the truth ``g``:

* ``remap="lstsq"`` (default, the project's protocol): ``k r`` with the one factor
  ``k = sum(r g) / sum(r^2)`` minimising ``||k r - g||^2`` over the plane's pixels;
* ``remap="minmax"``: the paper's "remap ... to the range of the ground truth by linear
  scaling": ``(r - min r) / (max r - min r) * (max g - min g) + min g``.

Then ``PSNR = 10 log10(max(g)^2 / MSE)`` with ``max(g)`` the largest truth value of
the plane (over the evaluated pixels). Identical planes (MSE = 0) score
:data:`PSNR_CAP` dB so that every output stays finite (JSON-safe).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.core.colorimetry import luminance
from derender.core.errors import InputError
from derender.core.types import HDRResult

__all__ = [
    "PSNR_CAP",
    "fit_scale",
    "remap_minmax",
    "psnr",
    "psnr_rgbl",
]


#: PSNR reported for a perfect match (MSE = 0), in dB.
PSNR_CAP = 200.0


def _as_array(x: Any, what: str) -> np.ndarray:
    if isinstance(x, HDRResult):
        x = x.radiance
    arr = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what} contains NaN or inf")
    return arr


def fit_scale(result: Any, truth: Any, mask: np.ndarray | None = None) -> float:
    """Least-squares scale ``k = sum(r g) / sum(r^2)`` minimising ``||k r - g||^2`` (1.0 if ``r`` is all zero)."""
    r = _as_array(result, "result")
    g = _as_array(truth, "truth")
    if r.shape != g.shape:
        raise InputError(f"result shape {r.shape} differs from truth shape {g.shape}")
    if mask is not None:
        r, g = r[mask], g[mask]
    rr = float(np.dot(r.ravel(), r.ravel()))
    if rr <= 0.0:
        return 1.0
    return float(np.dot(r.ravel(), g.ravel()) / rr)


def remap_minmax(result: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Paper 1's remap: map ``[min r, max r]`` linearly onto ``[min g, max g]`` (constant r -> min g)."""
    r = np.asarray(result, dtype=np.float64)
    g = np.asarray(truth, dtype=np.float64)
    rmin, rmax = float(r.min()), float(r.max())
    gmin, gmax = float(g.min()), float(g.max())
    if rmax <= rmin:
        return np.full_like(r, gmin)
    return (r - rmin) * ((gmax - gmin) / (rmax - rmin)) + gmin


def psnr(result_plane: np.ndarray, truth_plane: np.ndarray, remap: str = "lstsq") -> float:
    """PSNR (dB) of one plane after the remap (1-D or any shape; pixels already selected)."""
    r = np.asarray(result_plane, dtype=np.float64).ravel()
    g = np.asarray(truth_plane, dtype=np.float64).ravel()
    if r.size == 0:
        raise InputError("no pixels to evaluate (empty image or mask)")
    if remap == "lstsq":
        rr = float(np.dot(r, r))
        r = r * (float(np.dot(r, g)) / rr if rr > 0 else 1.0)
    elif remap == "minmax":
        r = remap_minmax(r, g)
    else:
        raise InputError(f"remap must be 'lstsq' or 'minmax', got {remap!r}")
    peak = float(np.max(g))
    if peak <= 0:
        raise InputError("the ground truth plane has no positive value; PSNR is undefined")
    mse = float(np.mean((r - g) ** 2))
    if mse <= 0.0:
        return PSNR_CAP
    return float(min(PSNR_CAP, 10.0 * np.log10(peak * peak / mse)))


def psnr_rgbl(result_linear_srgb: Any, truth_linear_srgb: Any, remap: str = "lstsq",
              mask: np.ndarray | None = None) -> dict[str, float]:
    """PSNR on R, G, B and luminance L (dB), per the "HDR PSNR" protocol (see module docstring).

    ``result_linear_srgb`` / ``truth_linear_srgb``: (H, W, 3) linear images (or an
    :class:`HDRResult`). ``mask``: optional boolean (H, W), True where a pixel is
    evaluated (pass ``result.mask == 0`` to skip fallback pixels of a merge).
    """
    r = _as_array(result_linear_srgb, "result")
    g = _as_array(truth_linear_srgb, "truth")
    if r.ndim != 3 or r.shape[-1] != 3:
        raise InputError(f"result must be an (H, W, 3) image, got shape {r.shape}")
    if r.shape != g.shape:
        raise InputError(f"result shape {r.shape} differs from truth shape {g.shape}")
    if mask is not None:
        m = np.asarray(mask)
        if m.dtype != bool:
            raise InputError("mask must be a boolean (H, W) array, True where pixels are evaluated")
        if m.shape != r.shape[:2]:
            raise InputError(f"mask shape {m.shape} differs from image shape {r.shape[:2]}")
        r, g = r[m], g[m]
    else:
        r, g = r.reshape(-1, 3), g.reshape(-1, 3)
    out = {name: psnr(r[:, c], g[:, c], remap) for c, name in enumerate("RGB")}
    out["L"] = psnr(luminance(r), luminance(g), remap)
    return out
