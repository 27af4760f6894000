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

PSNR on radiance only sees the highlights: on HDR scenes the brightest few per cent of
the pixels carry nearly all of the squared error (issue 18). Two measures in which every
pixel counts alike are reported beside it:

* :func:`relative_errors` -- per-pixel relative error ``e_i = ||M r_i - g_i|| / ||g_i||``
  after the 3x3 matrix ``M`` (``fit="matrix"``, default: absorbs white balance and colour
  rendering differences that the per-channel PSNR also forgives) or the one scale ``k I``
  (``fit="scale"``) minimising ``sum_i ||M r_i - g_i||^2 / ||g_i||^2`` (weighted least
  squares with weights ``1 / ||g_i||^2``, so each pixel's *relative* error counts alike);
  the median and the 90th percentile of ``e_i`` over pixels with ``||g_i|| > 0``.
* :func:`log_psnr` -- PSNR of log10 luminance: ``l = log10(max(L, eps))`` with
  ``eps = 1e-6 max(L_g)``, the result shifted by the mean log offset (its best scale in the
  log domain), ``10 log10(range^2 / MSE)`` with ``range = max(l_g) - min(l_g)`` (the
  truth's dynamic range in decades). Logarithmic encodings of luminance are the simplest
  of the perceptually uniform encodings HDR image-quality work uses (Aydin, Mantiuk &
  Seidel, "Extending quality metrics to full luminance range images", SPIE 2008, whose
  PU encoding is logarithmic above ~1 cd/m^2); we use plain log10, which needs no
  absolute calibration of the radiance.
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
    "fit_colour_matrix",
    "relative_errors",
    "log_psnr",
    "hdr_scores",
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


def _pixels(result: Any, truth: Any, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    r = _as_array(result, "result")
    g = _as_array(truth, "truth")
    if r.shape != g.shape or r.ndim != 3 or r.shape[-1] != 3:
        raise InputError(f"result {r.shape} and truth {g.shape} must be (H, W, 3) images of one size")
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != r.shape[:2]:
            raise InputError(f"mask shape {m.shape} differs from image shape {r.shape[:2]}")
        return r[m], g[m]
    return r.reshape(-1, 3), g.reshape(-1, 3)


def fit_colour_matrix(result: np.ndarray, truth: np.ndarray, weights: np.ndarray | None = None,
                      fit: str = "matrix") -> np.ndarray:
    """The 3x3 ``M`` (``fit="matrix"``) or ``k I`` (``fit="scale"``) minimising
    ``sum_i w_i ||M r_i - g_i||^2`` over pixel rows ``r``, ``g`` (P, 3)."""
    r = np.asarray(result, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    w = np.ones(r.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if fit == "scale":
        rr = float(np.sum(w * np.sum(r * r, axis=1)))
        k = float(np.sum(w * np.sum(r * g, axis=1)) / rr) if rr > 0 else 1.0
        return k * np.eye(3)
    if fit != "matrix":
        raise InputError(f"fit must be 'matrix' or 'scale', got {fit!r}")
    a = (r * w[:, None]).T @ r
    b = (r * w[:, None]).T @ g
    try:
        m = np.linalg.solve(a, b).T
    except np.linalg.LinAlgError:
        m = np.linalg.lstsq(a, b, rcond=None)[0].T
    return m if np.all(np.isfinite(m)) else np.eye(3)


def relative_errors(result: Any, truth: Any, fit: str = "matrix", mask: np.ndarray | None = None
                    ) -> dict[str, Any]:
    """Median and 90th percentile of ``||M r_i - g_i|| / ||g_i||`` (see the module docstring).

    Returns ``{"median", "p90", "fit", "matrix"}`` (the fitted ``M`` as nested lists)."""
    r, g = _pixels(result, truth, mask)
    n2 = np.sum(g * g, axis=1)
    ok = n2 > 0
    if not ok.any():
        raise InputError("the ground truth has no non-zero pixel; relative error is undefined")
    r, g, n2 = r[ok], g[ok], n2[ok]
    m = fit_colour_matrix(r, g, 1.0 / n2, fit)
    e = np.sqrt(np.sum((r @ m.T - g) ** 2, axis=1) / n2)
    return {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)), "fit": fit,
            "matrix": m.tolist()}


def log_psnr(result: Any, truth: Any, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of log10 luminance after the best log offset (see the module docstring)."""
    r, g = _pixels(result, truth, mask)
    lr, lg = luminance(r), luminance(g)
    peak = float(np.max(lg))
    if peak <= 0:
        raise InputError("the ground truth has no positive luminance; log PSNR is undefined")
    eps = 1e-6 * peak
    a = np.log10(np.maximum(lr, eps))
    b = np.log10(np.maximum(lg, eps))
    a = a + float(np.mean(b - a))
    rng = float(np.max(b) - np.min(b))
    mse = float(np.mean((a - b) ** 2))
    if mse <= 0.0:
        return PSNR_CAP
    if rng <= 0:
        rng = 1.0
    return float(min(PSNR_CAP, 10.0 * np.log10(rng * rng / mse)))


def hdr_scores(result: Any, truth: Any, remap: str = "lstsq", mask: np.ndarray | None = None,
               fit: str = "matrix") -> dict[str, Any]:
    """Everything :command:`derender evaluate` reports: PSNR R/G/B/L, relative-error median and
    p90 (``rel_median``, ``rel_p90``, ``rel_fit``) and ``log_psnr_L``."""
    out: dict[str, Any] = dict(psnr_rgbl(result, truth, remap=remap, mask=mask))
    rel = relative_errors(result, truth, fit=fit, mask=mask)
    out.update({"rel_median": rel["median"], "rel_p90": rel["p90"], "rel_fit": fit,
                "log_psnr_L": log_psnr(result, truth, mask=mask)})
    return out
