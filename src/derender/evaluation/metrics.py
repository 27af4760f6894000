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
the pixels carry nearly all of the squared error. Two measures in which every
pixel counts alike are reported beside it:

* :func:`relative_errors` -- per-pixel relative error ``e_i = ||M r_i - g_i|| / ||g_i||``
  after the 3x3 matrix ``M`` (``fit="matrix"``, default: absorbs white balance and colour
  rendering differences that the per-channel PSNR also forgives) or the one scale ``k I``
  (``fit="scale"``) fitted to the relative residuals by *least trimmed squares*: start
  from the weighted least squares ``min sum_i ||M r_i - g_i||^2 / ||g_i||^2`` (weights
  ``1 / ||g_i||^2``, so each pixel's *relative* error counts alike), reweight it towards the
  least mean relative error ``min sum_i e_i`` (:data:`L1_STEPS` steps of iteratively
  reweighted least squares, weights ``1 / (||g_i||^2 e_i)``) and from fits to random pixel
  subsets (seeded), then refit on the half of the pixels with the smallest ``e_i`` until
  that half no longer changes (concentration steps of FAST-LTS, at most
  :data:`TRIM_STEPS`); report the median and the 90th percentile of ``e_i``
  over all pixels with ``||g_i|| > 0``. Why trimmed: the plain weighted fit is a squared
  loss, ruled by the pixels with the largest relative errors (dark, noisy pixels and colour
  fringes at edges, which no merge recovers); on simulated brackets it moved the oracle
  that inverts the true pipeline from a median of 0.10 (no fit at all) to 0.44. The trimmed
  fit gives the oracle 0.08-0.12, its no-fit figure, and so measures what a method gets
  wrong on the typical pixel. ``fit="none"`` compares ``r`` with ``g`` as they are.
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
    "TRIM_STEPS",
    "L1_STEPS",
    "TRIM_STARTS",
    "TRIM_SUBSET",
    "TRIM_SELECT_PIXELS",
    "TRIM_FIT_PIXELS",
    "relative_errors",
    "log_psnr",
    "hdr_scores",
]


#: Concentration steps of the trimmed fit in :func:`relative_errors` (it stops earlier when
#: the kept half no longer changes).
TRIM_STEPS = 20

#: Reweighting steps towards the least mean relative error that start the trimmed fit.
L1_STEPS = 10

#: Random starts of the trimmed fit, each a fit to :data:`TRIM_SUBSET` random pixels.
TRIM_STARTS = 30

#: Pixels per random start of the trimmed fit (a 3x3 needs three).
TRIM_SUBSET = 4

#: Pixels (a seeded random subset) on which the trimmed fit's starts are compared.
TRIM_SELECT_PIXELS = 20000

#: Pixels (a seeded random subset) the trimmed fit uses on larger images.
TRIM_FIT_PIXELS = 200000

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

    Parameters
    ----------
    result_linear_srgb : numpy.ndarray or HDRResult
        (H, W, 3) linear-sRGB result, any scale.
    truth_linear_srgb : numpy.ndarray or HDRResult
        (H, W, 3) linear-sRGB truth.
    remap : str
        How the result is scaled onto the truth per plane: ``"lstsq"`` (one least-squares
        factor) or ``"minmax"`` (the paper's linear range mapping).
    mask : numpy.ndarray, optional
        (H, W) bool, True where pixels are evaluated.

    Returns
    -------
    dict of str to float
        PSNR in dB of the planes ``"R"``, ``"G"``, ``"B"`` and ``"L"``, at most
        :data:`PSNR_CAP`.

    Raises
    ------
    InputError
        Images of different shapes or not (H, W, 3), a mask not boolean (H, W), an unknown
        ``remap``.

    Examples
    --------
    A radiance map is known up to scale: twice the truth scores the cap; a 1 % ripple
    does not:

    >>> import numpy as np
    >>> import derender
    >>> truth = np.linspace(0.01, 4.0, 4 * 4 * 3).reshape(4, 4, 3)
    >>> derender.psnr_rgbl(2 * truth, truth)
    {'R': 200.0, 'G': 200.0, 'B': 200.0, 'L': 200.0}
    >>> ripple = 1 + 0.01 * np.cos(np.arange(48)).reshape(4, 4, 3)
    >>> {plane: round(db, 1) for plane, db in derender.psnr_rgbl(2 * truth * ripple, truth).items()}
    {'R': 52.7, 'G': 47.0, 'B': 45.6, 'L': 48.9}
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


def _trimmed_fit(r: np.ndarray, g: np.ndarray, n2: np.ndarray, fit: str) -> np.ndarray:
    """Least trimmed squares of the relative residuals (FAST-LTS, Rousseeuw & Van Driessen 2006).

    Candidate starts: the weighted fit, its reweighting towards ``sum_i e_i``, and
    :data:`TRIM_STARTS` exact fits to :data:`TRIM_SUBSET` random pixels (a 3x3 needs three; a
    start is clean with probability ``(1 - outliers)^4``). Each takes two concentration steps
    on at most :data:`TRIM_SELECT_PIXELS` random pixels; the best (lowest median) is then
    iterated until its kept half is stable. Images of more than :data:`TRIM_FIT_PIXELS` pixels
    are fitted on a random subset of that many (the errors are then taken over every pixel).
    The generator has seed 0, so the metric is deterministic."""

    rng = np.random.default_rng(0)
    if r.shape[0] > TRIM_FIT_PIXELS:
        idx = np.sort(rng.choice(r.shape[0], TRIM_FIT_PIXELS, replace=False))
        r, g, n2 = r[idx], g[idx], n2[idx]

    def errors(mm: np.ndarray) -> np.ndarray:
        return np.sqrt(np.sum((r @ mm.T - g) ** 2, axis=1) / n2)

    w = 1.0 / n2
    sel = (rng.choice(r.shape[0], TRIM_SELECT_PIXELS, replace=False) if r.shape[0] > TRIM_SELECT_PIXELS
           else np.arange(r.shape[0]))

    def csteps(m: np.ndarray, rows: np.ndarray | None, steps: int) -> tuple[np.ndarray, np.ndarray]:
        rr, gg, ww = (r, g, w) if rows is None else (r[rows], g[rows], w[rows])

        def err(mm: np.ndarray) -> np.ndarray:
            return np.sqrt(np.sum((rr @ mm.T - gg) ** 2, axis=1) * ww)

        e = err(m)
        keep = None
        for _ in range(steps):
            new_keep = e <= np.median(e)
            if keep is not None and np.array_equal(new_keep, keep):
                break
            keep = new_keep
            m = fit_colour_matrix(rr[keep], gg[keep], ww[keep], fit)
            e = err(m)
        return m, e

    starts = [fit_colour_matrix(r, g, w, fit)]
    m = starts[0]
    for _ in range(L1_STEPS):
        m = fit_colour_matrix(r, g, w / np.maximum(errors(m), 1e-6), fit)
    starts.append(m)
    if r.shape[0] >= 4 * TRIM_SUBSET:
        for _ in range(TRIM_STARTS):
            idx = rng.choice(r.shape[0], TRIM_SUBSET, replace=False)
            starts.append(fit_colour_matrix(r[idx], g[idx], w[idx], fit))
    best = min((csteps(m0, sel, 2) for m0 in starts), key=lambda me: float(np.median(me[1])))
    m, _ = csteps(best[0], None, TRIM_STEPS)
    return m


def relative_errors(result: Any, truth: Any, fit: str = "matrix", mask: np.ndarray | None = None
                    ) -> dict[str, Any]:
    """Median and 90th percentile of ``||M r_i - g_i|| / ||g_i||`` (see the module docstring).

    ``fit``: ``"matrix"`` (3x3), ``"scale"`` (``k I``), both by the trimmed fit, or ``"none"``
    (``M = I``). Returns ``{"median", "p90", "fit", "matrix"}`` (``M`` as nested lists)."""
    if fit not in ("matrix", "scale", "none"):
        raise InputError(f"fit must be 'matrix', 'scale' or 'none', got {fit!r}")
    r, g = _pixels(result, truth, mask)
    r, g = r.astype(np.float64), g.astype(np.float64)
    n2 = np.sum(g * g, axis=1)
    ok = n2 > 0
    if not ok.any():
        raise InputError("the ground truth has no non-zero pixel; relative error is undefined")
    r, g, n2 = r[ok], g[ok], n2[ok]

    def errors(m: np.ndarray) -> np.ndarray:
        return np.sqrt(np.sum((r @ m.T - g) ** 2, axis=1) / n2)

    if fit == "none":
        m = np.eye(3)
        e = errors(m)
    else:
        m = _trimmed_fit(r, g, n2, fit)
        e = errors(m)
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
