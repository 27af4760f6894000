"""Falsecolor luminance maps with a legend in cd/m2, as lighting practice reads them.

Radiance's ``falsecolor`` maps luminance onto a colour scale with a legend; lighting
studies read glare sources and contrast from it. Here the scale is logarithmic by default
(``decades`` decades below its top; the top defaults to the map's 99.9th percentile of
luminance rounded up to 1, 2 or 5 times a power of ten, :func:`scale_top`) or linear from 0
to the top, in matplotlib's perceptually uniform ``viridis`` unless ``cmap`` says otherwise
(a map whose colours grow monotonically in lightness reads in grey print too). Luminance is that of :func:`derender.photometry.illuminance.luminance_cd_m2`
(``179 w·RGB``: cd/m2 for a map in Radiance units, e.g. after ``derender merge --spot``;
relative units otherwise, and the legend says so). Pixels above the scale are drawn in the
top colour, pixels at or below zero in the bottom one.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from derender.core.errors import InputError
from derender.photometry.illuminance import luminance_cd_m2

__all__ = ["falsecolor_figure", "scale_top"]


def scale_top(lum: np.ndarray) -> float:
    """The default top of the scale: the 99.9th percentile of the positive luminance, rounded up
    to 1, 2 or 5 times a power of ten."""
    pos = lum[lum > 0]
    if pos.size == 0:
        raise InputError("the map has no positive luminance to show")
    p = float(np.percentile(pos, 99.9))
    e = np.floor(np.log10(p))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10 ** e >= p:
            return float(m * 10 ** e)
    return float(10 ** (e + 1))  # pragma: no cover - the loop always returns


def falsecolor_figure(radiance: np.ndarray, path: str | os.PathLike, *, primaries=None, top: float | None = None,
                      decades: float | None = 4.0, absolute: bool = False, cmap: str = "viridis",
                      title: str | None = None, inputs=()) -> dict:
    """Write a falsecolor image of the map's luminance with a colour bar (PNG/PDF/SVG by
    suffix), atomically. ``decades=None``: linear scale from 0 to ``top``. Returns the scale
    (``{"top", "bottom", "log", "units"}``)."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import LogNorm, Normalize
    from matplotlib.figure import Figure

    from derender.io.files import atomic_output

    rad = np.asarray(radiance, dtype=np.float64)
    if rad.ndim != 3 or rad.shape[2] != 3:
        raise InputError(f"a radiance map is (H, W, 3), got {rad.shape}")
    lum = luminance_cd_m2(rad, primaries)
    top = scale_top(lum) if top is None else float(top)
    if not (np.isfinite(top) and top > 0):
        raise InputError(f"--max must be a positive luminance, got {top!r}")
    if decades is not None and not (0 < decades <= 12):
        raise InputError(f"--log takes 0 < DECADES <= 12, got {decades!r}")
    if cmap not in colormaps:
        raise InputError(f"unknown colour map {cmap!r}")
    units = "cd/m²" if absolute else "relative luminance (179 Y)"
    h, w = lum.shape
    fig = Figure(figsize=(max(4.0, 6.0 * w / max(h, w)) + 1.4, max(3.0, 6.0 * h / max(h, w))), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if decades is not None:
        bottom = top / 10 ** decades
        norm = LogNorm(vmin=bottom, vmax=top, clip=True)
        shown = np.clip(lum, bottom, top)
    else:
        bottom = 0.0
        norm = Normalize(vmin=0.0, vmax=top, clip=True)
        shown = np.clip(lum, 0.0, top)
    im = ax.imshow(shown, cmap=cmap, norm=norm, interpolation="nearest")
    ax.set_xlabel(f"x (pixels, {w} wide)")
    ax.set_ylabel(f"y (pixels, {h} high)")
    if title:
        ax.set_title(title)
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    bar.set_label(f"luminance, {units} ({'log' if decades is not None else 'linear'} scale)")
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".").lower() or "png")
    return {"top": top, "bottom": bottom, "log": decades is not None, "units": units}
