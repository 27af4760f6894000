"""Radiance views: where each pixel of a map looks, and the solid angle it covers.

A luminance map is only a measurement with its geometry: glare indices and the vertical
illuminance weigh each pixel by its direction and solid angle, which the lens projection
fixes. Radiance writes it as a ``VIEW=`` header line (``-vt?`` type, ``-vh``/``-vv`` full
angles in degrees); derender reads the same syntax (:func:`parse_view`) and maps image
coordinates to view-frame directions as Radiance's ``viewray`` does (``src/common/image.c``),
with ``x, y`` in ``[-1/2, 1/2]`` (x right, y up; ``-vs``/``-vl`` shift the centre):

* ``-vta`` angular fisheye (equidistant): ``theta = sqrt((x h)^2 + (y v)^2)`` with ``h, v``
  the full angles in radians, direction ``(sin theta / theta) (x h, y v), cos theta``;
* ``-vth`` hemispherical (equisolid-in-sine, orthographic): ``(x 2 sin(h/2), y 2 sin(v/2))``
  is the direction's transverse part, ``z = sqrt(1 - r^2)``;
* ``-vtv`` perspective: ``(x 2 tan(h/2), y 2 tan(v/2), 1)``, normalised.

A pixel's solid angle is that of the spherical quadrilateral of its four corner directions,
two triangles by Van Oosterom & Strackee's formula
``tan(Omega / 2) = |a . (b x c)| / (1 + a.b + b.c + c.a)`` (unit vectors a, b, c; IEEE Trans.
Biomed. Eng. 30(2), 1983); pixels whose centre lies outside the projection's circle (fisheye
corners) have no direction and zero solid angle. Checked against the closed forms: a
180-degree angular fisheye covers 2 pi sr, a perspective view of half-angle a and b covers
``4 asin(sin a sin b)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.core.errors import InputError

__all__ = ["View", "parse_view", "pixel_directions", "pixel_solid_angles"]

_TYPES = {"a": "angular fisheye", "h": "hemispherical fisheye", "v": "perspective"}


@dataclass(frozen=True)
class View:
    """A Radiance view: ``kind`` ``"a"`` / ``"h"`` / ``"v"`` (``-vta``, ``-vth``, ``-vtv``),
    full horizontal and vertical angles in degrees, image-centre shifts (``-vs``, ``-vl``)."""

    kind: str = "v"
    horizontal: float = 45.0
    vertical: float = 45.0
    shift: float = 0.0
    lift: float = 0.0

    def header(self) -> str:
        """The view as Radiance writes it after ``VIEW=``."""
        text = f"-vt{self.kind} -vh {self.horizontal:g} -vv {self.vertical:g}"
        if self.shift or self.lift:
            text += f" -vs {self.shift:g} -vl {self.lift:g}"
        return text


def parse_view(text: str) -> View:
    """A :class:`View` from Radiance view options (``"-vta -vh 180 -vv 180"``; Radiance's
    defaults ``-vtv -vh 45 -vv 45`` for what is not given). The direction options ``-vp``,
    ``-vd``, ``-vu`` (3 numbers each) and ``-vo``/``-va`` are accepted and do not change the
    pixel geometry in the view frame. An option derender cannot honour is an :class:`InputError`."""
    words = str(text).split()
    values = {"kind": "v", "horizontal": 45.0, "vertical": 45.0, "shift": 0.0, "lift": 0.0}
    i = 0

    def number(k: int) -> float:
        try:
            return float(words[k])
        except (IndexError, ValueError):
            raise InputError(f"view {text!r}: {words[k - 1]} needs a number") from None

    while i < len(words):
        w = words[i]
        if w.startswith("-vt") and len(w) == 4:
            if w[3] not in _TYPES:
                raise InputError(f"view {text!r}: type {w} is not supported (use -vta, -vth or -vtv)")
            values["kind"] = w[3]
            i += 1
        elif w in ("-vh", "-vv", "-vs", "-vl", "-vo", "-va"):
            v = number(i + 1)
            key = {"-vh": "horizontal", "-vv": "vertical", "-vs": "shift", "-vl": "lift"}.get(w)
            if key is not None:
                values[key] = v
            i += 2
        elif w in ("-vp", "-vd", "-vu"):
            for k in range(1, 4):
                number(i + k)
            i += 4
        else:
            raise InputError(f"view {text!r}: {w!r} is not a Radiance view option")
    view = View(**values)
    limit = 360.0 if view.kind in "ah" else 180.0
    if not (0.0 < view.horizontal < limit + 1e-9 and 0.0 < view.vertical < limit + 1e-9):
        raise InputError(f"view {text!r}: angles must be in (0, {limit:g}) degrees for {_TYPES[view.kind]}")
    if view.kind == "h" and (view.horizontal > 180.0 or view.vertical > 180.0):
        raise InputError(f"view {text!r}: a hemispherical fisheye covers at most 180 degrees")
    if view.kind == "v" and (view.horizontal >= 180.0 or view.vertical >= 180.0):
        raise InputError(f"view {text!r}: a perspective view covers less than 180 degrees")
    return view


def _directions(view: View, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (..., 3) (x right, y up, z along the view) for image coordinates and a
    validity mask, as Radiance's viewray."""
    x, y = np.broadcast_arrays(x + view.shift, y + view.lift)
    h, v = np.radians(view.horizontal), np.radians(view.vertical)
    if view.kind == "a":
        px, py = x * h, y * v
        theta = np.hypot(px, py)
        ok = theta <= np.pi
        s = np.where(theta > 0, np.sin(theta) / np.where(theta > 0, theta, 1.0), 1.0)
        d = np.stack([px * s, py * s, np.cos(theta)], axis=-1)
    elif view.kind == "h":
        px, py = x * 2.0 * np.sin(h / 2.0), y * 2.0 * np.sin(v / 2.0)
        r2 = px * px + py * py
        ok = r2 <= 1.0
        d = np.stack([px, py, np.sqrt(np.clip(1.0 - r2, 0.0, None))], axis=-1)
    else:
        px, py = x * 2.0 * np.tan(h / 2.0), y * 2.0 * np.tan(v / 2.0)
        d = np.stack([px, py, np.ones_like(px)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        ok = np.ones(px.shape, bool)
    return d, ok


def pixel_directions(view: View, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit view-frame direction (H, W, 3) of each pixel centre (row 0 at the top) and the
    (H, W) mask of pixels inside the projection."""
    x = (np.arange(width) + 0.5) / width - 0.5
    y = 0.5 - (np.arange(height) + 0.5) / height
    return _directions(view, x[None, :], y[:, None])


def _triangle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    num = np.abs(np.einsum("...i,...i->...", a, np.cross(b, c)))
    den = 1.0 + np.einsum("...i,...i->...", a, b) + np.einsum("...i,...i->...", b, c) \
        + np.einsum("...i,...i->...", c, a)
    return 2.0 * np.arctan2(num, den)


def pixel_solid_angles(view: View, height: int, width: int) -> np.ndarray:
    """Solid angle (sr, (H, W) float64) of each pixel: the spherical quadrilateral of its
    corner directions (module docstring); 0 outside the projection."""
    xc = np.arange(width + 1) / width - 0.5
    yc = 0.5 - np.arange(height + 1) / height
    corners, ok_c = _directions(view, xc[None, :], yc[:, None])
    a, b = corners[:-1, :-1], corners[:-1, 1:]
    c, d = corners[1:, 1:], corners[1:, :-1]
    omega = _triangle(a, b, c) + _triangle(a, c, d)
    _, inside = pixel_directions(view, height, width)
    if view.kind in "ah":
        # a pixel cut by the circle: keep its centre's decision, its corners clamped to the rim
        omega = np.where(inside, omega, 0.0)
    return omega
