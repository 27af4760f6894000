"""Lens vignetting: a radial falloff fitted on a flat field, divided out of radiance maps.

A lens passes less light towards the edges of the frame (natural ``cos^4`` falloff, optical
vignetting; at wide apertures and fisheye corners 0.5 or less), so a merged map's value at
radius ``r`` is the scene's radiance times ``V(r)``. The model is the even polynomial of the
normalised radius that camera-calibration tools use (e.g. Adobe's lens profiles, Hugin's
``Vb, Vc, Vd``):

    V(r) = 1 + a_1 r^2 + a_2 r^4 + a_3 r^6,    r = dist(p, c) / (half the image diagonal),

with ``c`` the optical centre (default the image centre). It is fitted by linear least
squares on the luminance of a merged *flat field* (a bracket of a uniform, evenly lit
surface filling the frame: an integrating sphere, an overcast sky through a diffuser),
normalised by the fitted ``V(0)``; :func:`fit_vignetting` refuses a field whose residual
around the radial model is larger than ``max_residual`` (5 % rms by default: the surface
is not uniform, or the falloff is not radial). Because every merge method is linear in the
scene's radiance, dividing the merged map by ``V`` (:func:`correct_vignetting`) is the same
as dividing every frame's radiance before merging; the variance is divided by ``V^2``.

The profile is a small versioned JSON file (:data:`VIGNETTING_FORMAT`) holding the
coefficients, the centre, the image size it was fitted on (other sizes are refused: the
radius is normalised by the diagonal, but a crop changes the centre), the fit's rms residual
and the fitted samples' radius range.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from derender.core.errors import InputError

__all__ = ["VIGNETTING_FORMAT", "Vignetting", "fit_vignetting", "correct_vignetting", "save_vignetting",
           "load_vignetting"]

#: The ``format`` field of a vignetting file, and its version.
VIGNETTING_FORMAT = ("derender-vignetting", 1)


@dataclass(frozen=True)
class Vignetting:
    """A fitted radial falloff: ``coefficients`` (a_1, a_2, a_3), ``centre`` (x, y) in pixels,
    ``size`` (W, H) of the images it applies to, the fit's ``rms_residual`` (relative) and the
    largest normalised radius ``r_max`` (1 for a full frame)."""

    coefficients: tuple[float, float, float]
    centre: tuple[float, float]
    size: tuple[int, int]
    rms_residual: float
    r_max: float = 1.0

    def gain(self) -> np.ndarray:
        """``V`` at every pixel centre, (H, W) float64."""
        w, h = self.size
        r2 = _radius2(w, h, self.centre)
        a1, a2, a3 = self.coefficients
        return 1.0 + r2 * (a1 + r2 * (a2 + r2 * a3))


def _radius2(w: int, h: int, centre: tuple[float, float]) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    half_diag2 = (w * w + h * h) / 4.0
    return ((x + 0.5 - centre[0]) ** 2 + (y + 0.5 - centre[1]) ** 2) / half_diag2


def fit_vignetting(flat_radiance: np.ndarray, centre: tuple[float, float] | None = None,
                   max_residual: float = 0.05, usable: np.ndarray | None = None) -> Vignetting:
    """Fit ``V`` to a merged flat field (H, W, 3) (module docstring); ``usable`` (H, W) bool
    leaves pixels out (e.g. those over-exposed in every frame)."""
    from derender.core.colorimetry import luminance

    rad = np.asarray(flat_radiance, dtype=np.float64)
    if rad.ndim != 3 or rad.shape[2] != 3:
        raise InputError(f"a flat field is an (H, W, 3) radiance map, got {rad.shape}")
    h, w = rad.shape[:2]
    c = (w / 2.0, h / 2.0) if centre is None else (float(centre[0]), float(centre[1]))
    lum = luminance(rad)
    ok = np.isfinite(lum) & (lum > 0)
    if usable is not None:
        ok &= np.asarray(usable, dtype=bool)
    if ok.mean() < 0.5:
        raise InputError("the flat field has too few usable pixels (under half are finite, positive and "
                         "well exposed)")
    r2 = _radius2(w, h, c)
    a = np.stack([np.ones(ok.sum()), r2[ok], r2[ok] ** 2, r2[ok] ** 3], axis=1)
    coef, *_ = np.linalg.lstsq(a, lum[ok], rcond=None)
    if coef[0] <= 0:
        raise InputError("the flat field's fitted centre value is not positive")
    norm = coef[1:] / coef[0]
    model = coef[0] * (1.0 + r2 * (norm[0] + r2 * (norm[1] + r2 * norm[2])))
    resid = float(np.sqrt(np.mean((lum[ok] / model[ok] - 1.0) ** 2)))
    vig = Vignetting(coefficients=(float(norm[0]), float(norm[1]), float(norm[2])), centre=c, size=(w, h),
                     rms_residual=resid, r_max=float(np.sqrt(r2[ok].max())))
    if resid > max_residual:
        raise InputError(f"the flat field is not flat: {100 * resid:.1f} % rms around the radial model "
                         f"(limit {100 * max_residual:.0f} %); use a uniform, evenly lit surface filling the frame")
    g = vig.gain()
    if g.min() <= 0.05:
        raise InputError(f"the fitted falloff reaches {g.min():.3f} in the frame; the flat field does not "
                         "describe this lens")
    return vig


def correct_vignetting(radiance: np.ndarray, vignetting: Vignetting,
                       variance: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Divide a map (and its variance by ``V^2``) by the falloff; the sizes must match."""
    rad = np.asarray(radiance)
    h, w = rad.shape[:2]
    if (w, h) != tuple(vignetting.size):
        raise InputError(f"the vignetting profile is for {vignetting.size[0]}x{vignetting.size[1]} images, "
                         f"the map is {w}x{h}")
    g = vignetting.gain().astype(np.float32)[..., None]
    out = (rad / g).astype(np.float32)
    var = None if variance is None else (np.asarray(variance) / (g * g)).astype(np.float32)
    return out, var


def save_vignetting(vignetting: Vignetting, path: str | os.PathLike, inputs=()) -> Path:
    """Write the profile as JSON (atomically)."""
    from derender.io.files import atomic_output

    doc = {"format": VIGNETTING_FORMAT[0], "version": VIGNETTING_FORMAT[1],
           "model": "V(r) = 1 + a1 r^2 + a2 r^4 + a3 r^6, r = distance to the centre / half the image diagonal",
           **asdict(vignetting)}
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=2), encoding="utf-8")
    return path


def load_vignetting(path: str | os.PathLike) -> Vignetting:
    """Read a profile written by :func:`save_vignetting` (format and version checked)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such vignetting file: {path}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if (doc.get("format"), doc.get("version")) != VIGNETTING_FORMAT:
            raise InputError(f"{path} is not a derender vignetting file (format {doc.get('format')!r} "
                             f"version {doc.get('version')!r})")
        return Vignetting(coefficients=tuple(float(v) for v in doc["coefficients"]),
                          centre=tuple(float(v) for v in doc["centre"]), size=tuple(int(v) for v in doc["size"]),
                          rms_residual=float(doc["rms_residual"]), r_max=float(doc.get("r_max", 1.0)))
    except (ValueError, KeyError, TypeError, AttributeError):
        raise InputError(f"{path} is not a readable vignetting file") from None
