"""Neutral axis: do pixels a frame renders grey stay grey in the merged radiance?

A camera's white balance renders neutral surfaces with equal codes ``R = G = B``. A merge
that recovers linear radiance without a colour model should keep such pixels neutral at
every level of brightness, from shadows to highlights, unless the camera's own channel
curves differ. :func:`neutral_axis` measures it: it selects the pixels that frame ``j``
renders neutral

``max_c z_c - min_c z_c <= tolerance``, every code in ``[low, high]``, and the pixel's
3x3 neighbourhood flat (each channel's codes within ``flat`` of the centre's: away from
edges, where demosaicing and chroma filters mix neighbouring colours),

and reports, per decade of the result's luminance ``L = 0.2126 R + 0.7152 G + 0.0722 B``
(relative to the median luminance of the selected pixels, so that the result's unknown scale
does not matter: decade ``k`` holds ``10^k <= L / median <= 10^(k+1)``), the medians of the
result's ``R/G`` and ``B/G`` and the number of pixels. The figure of merit is the largest
deviation of these medians from 1 (``max_deviation``): 0.03 means every decade's greys are
within 3 % of neutral.

With the simulator's exact radiance, :func:`neutral_axis_truth` selects the pixels whose
*truth* is neutral (chromaticity within ``tolerance`` of grey) and reports the same per
decade, normalised by the ratio over all of them (``R/G`` and ``B/G`` relative to their
overall median: a constant cast is the white balance the per-channel PSNR forgives; what
varies with brightness is not). :func:`scale_gap` is the other half of the issue's line:
PSNR L with the one least-squares scale of the protocol (:mod:`derender.evaluation.metrics`)
against PSNR L after one scale per channel (each channel fitted to the truth's, then the
luminance): a colour cast or a brightness-dependent tint costs the former and not the latter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from derender.core.colorimetry import luminance
from derender.core.errors import InputError

__all__ = [
    "NeutralAxis",
    "neutral_pixels",
    "neutral_axis",
    "neutral_axis_truth",
    "scale_gap",
]


@dataclass
class NeutralAxis:
    """Per-decade medians of a result's ``R/G`` and ``B/G`` on neutral pixels.

    ``decades`` (K,) int: decade ``k`` holds ``10^k <= L / L_median < 10^(k+1)``; ``rg``,
    ``bg`` (K,) medians, ``count`` (K,) pixels; decades with fewer than ``min_count``
    pixels are left out. ``reference``: (R/G, B/G) the decades are compared with (1, 1 for
    a frame's greys; the overall medians for the truth's).
    """

    decades: np.ndarray
    rg: np.ndarray
    bg: np.ndarray
    count: np.ndarray
    reference: tuple[float, float] = (1.0, 1.0)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def max_deviation(self) -> float:
        """Largest ``|ratio / reference - 1|`` over the decades and both ratios (NaN without decades)."""
        if self.decades.size == 0:
            return float("nan")
        d = np.concatenate([self.rg / self.reference[0], self.bg / self.reference[1]])
        return float(np.max(np.abs(d - 1.0)))

    def rows(self) -> list[dict[str, float]]:
        """One dict per decade: ``decade``, ``rg``, ``bg``, ``count``."""
        return [{"decade": int(k), "rg": float(r), "bg": float(b), "count": int(n)}
                for k, r, b, n in zip(self.decades, self.rg, self.bg, self.count)]


def _flat(codes: np.ndarray, flat: int) -> np.ndarray:
    """(H, W) bool: every channel of the 3x3 neighbourhood within ``flat`` codes of the centre (border False)."""
    z = codes.astype(np.int16)
    h, w, _ = z.shape
    ok = np.zeros((h, w), dtype=bool)
    if h < 3 or w < 3:
        return ok
    c = z[1:-1, 1:-1]
    inner = np.ones((h - 2, w - 2), dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            nb = z[1 + dy:h - 1 + dy, 1 + dx:w - 1 + dx]
            inner &= (np.abs(nb - c) <= flat).all(axis=-1)
    ok[1:-1, 1:-1] = inner
    return ok


def neutral_pixels(codes: np.ndarray, *, tolerance: int = 2, low: int = 10, high: int = 245,
                   flat: int = 4) -> np.ndarray:
    """(H, W) bool: the pixels an 8-bit frame (H, W, 3) renders neutral (see the module docstring)."""
    z = np.asarray(codes)
    if z.ndim != 3 or z.shape[-1] != 3:
        raise InputError(f"expected an (H, W, 3) frame of codes, got {z.shape}")
    if z.dtype.kind == "f":
        z = np.rint(np.clip(z, 0.0, 1.0) * 255.0)
    z = z.astype(np.int16)
    grey = (z.max(axis=-1) - z.min(axis=-1)) <= tolerance
    grey &= (z.min(axis=-1) >= low) & (z.max(axis=-1) <= high)
    return grey & _flat(z, flat)


def _per_decade(rad: np.ndarray, sel: np.ndarray, min_count: int, reference: tuple[float, float] | None
                ) -> NeutralAxis:
    r = np.asarray(rad, dtype=np.float64)[sel]
    lum = luminance(r)
    ok = (r > 0).all(axis=-1) & (lum > 0)
    r, lum = r[ok], lum[ok]
    empty = NeutralAxis(np.zeros(0, int), np.zeros(0), np.zeros(0), np.zeros(0, int),
                        reference or (1.0, 1.0), {"pixels": int(r.shape[0])})
    if r.shape[0] < min_count:
        return empty
    rg, bg = r[:, 0] / r[:, 1], r[:, 2] / r[:, 1]
    if reference is None:
        reference = (float(np.median(rg)), float(np.median(bg)))
    dec = np.floor(np.log10(lum / np.median(lum))).astype(int)
    ks, rgs, bgs, ns = [], [], [], []
    for k in np.unique(dec):
        m = dec == k
        if int(m.sum()) >= min_count:
            ks.append(int(k))
            rgs.append(float(np.median(rg[m])))
            bgs.append(float(np.median(bg[m])))
            ns.append(int(m.sum()))
    return NeutralAxis(np.asarray(ks, dtype=int), np.asarray(rgs), np.asarray(bgs), np.asarray(ns, dtype=int),
                       reference, {"pixels": int(r.shape[0]), "median_luminance": float(np.median(lum))})


def neutral_axis(codes: np.ndarray, radiance: Any, frame: int, *, tolerance: int = 2, low: int = 10,
                 high: int = 245, flat: int = 4, min_count: int = 20) -> NeutralAxis:
    """The result's ``R/G``, ``B/G`` per luminance decade on the pixels frame ``frame`` renders neutral.

    ``codes``: the bracket's 8-bit frames (N, H, W, 3) (uint8, or floats in [0, 1]), aligned
    with ``radiance`` (H, W, 3) linear; ``frame``: 0-based index in the bracket's (time) order.
    Compared with (1, 1): ``max_deviation`` 0.05 means every decade within 5 % of the frame's grey.
    """
    z = np.asarray(codes)
    if z.ndim != 4 or z.shape[-1] != 3:
        raise InputError(f"expected frames of shape (N, H, W, 3), got {z.shape}")
    if not 0 <= int(frame) < z.shape[0]:
        raise InputError(f"frame {frame} is not in the bracket of {z.shape[0]} frames")
    rad = np.asarray(getattr(radiance, "radiance", radiance))
    if rad.shape != z.shape[1:]:
        raise InputError(f"radiance shape {rad.shape} differs from the frames' {z.shape[1:]}")
    sel = neutral_pixels(z[int(frame)], tolerance=tolerance, low=low, high=high, flat=flat)
    out = _per_decade(rad, sel, min_count, (1.0, 1.0))
    out.info["frame"] = int(frame)
    return out


def neutral_axis_truth(truth_linear: np.ndarray, radiance: Any, *, tolerance: float = 0.02, flat: float = 0.02,
                       min_count: int = 20) -> NeutralAxis:
    """The result's ``R/G``, ``B/G`` per decade on pixels whose *truth* is neutral (exact oracle).

    Neutral: truth ``R/G`` and ``B/G`` within ``tolerance`` of 1, and the truth's 3x3
    neighbourhood within ``flat`` (relative) of the centre. Compared with the overall medians
    (a constant cast is a white balance; ``max_deviation`` measures how it varies with brightness).
    """
    g = np.asarray(truth_linear, dtype=np.float64)
    rad = np.asarray(getattr(radiance, "radiance", radiance))
    if g.shape != rad.shape or g.ndim != 3 or g.shape[-1] != 3:
        raise InputError(f"truth {g.shape} and radiance {rad.shape} must be the same (H, W, 3)")
    gp = np.maximum(g, 1e-30)
    sel = (np.abs(gp[..., 0] / gp[..., 1] - 1) <= tolerance) & (np.abs(gp[..., 2] / gp[..., 1] - 1) <= tolerance)
    sel &= (g > 0).all(axis=-1)
    h, w, _ = g.shape
    flat_ok = np.zeros((h, w), dtype=bool)
    if h >= 3 and w >= 3:
        c = gp[1:-1, 1:-1]
        inner = np.ones((h - 2, w - 2), dtype=bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                nb = g[1 + dy:h - 1 + dy, 1 + dx:w - 1 + dx]
                inner &= (np.abs(nb / c - 1) <= flat).all(axis=-1)
        flat_ok[1:-1, 1:-1] = inner
    return _per_decade(rad, sel & flat_ok, min_count, None)


def scale_gap(radiance: Any, truth_linear: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """PSNR L (dB) with one scale (the protocol) and after one least-squares scale per channel.

    Returns ``{"L_one": .., "L_per_channel": .., "gap": L_per_channel - L_one, "rg": k_R / k_G,
    "bg": k_B / k_G}`` with ``k_c`` the per-channel scales (1 for a result whose colour balance
    matches the truth's).
    """
    from derender.evaluation.metrics import fit_scale, psnr_rgbl

    rad = np.asarray(getattr(radiance, "radiance", radiance), dtype=np.float64)
    g = np.asarray(truth_linear, dtype=np.float64)
    if mask is not None:
        rad, g = rad[mask][:, None, :], g[mask][:, None, :]
    k = np.asarray([fit_scale(rad[..., c], g[..., c]) for c in range(3)])
    one = psnr_rgbl(rad, g)["L"]
    per = psnr_rgbl(rad * (k / k[1]), g)["L"]
    return {"L_one": float(one), "L_per_channel": float(per), "gap": float(per - one),
            "rg": float(k[0] / k[1]), "bg": float(k[2] / k[1])}
