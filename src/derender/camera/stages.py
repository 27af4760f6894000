"""Stages of the simulator's JPEG engines, per frame: :class:`FrameSettings` and :func:`render_frame`.

Every pipeline family (:mod:`derender.camera.families`) renders a frame as

1. white balance ``wb`` on camera RGB (demosaiced, in [0, 1]) with the highlight clip at 1,
2. the 3x3 colour-space transform ``gain * S(saturation) @ camera_to_srgb`` (the white
   balance is inside it in Kim et al.'s model: ``T_s T_w``),
3. a style-specific rendering to display values:

   * ``simple`` / ``camera``: :func:`derender.camera.rendering.render_style` (paper 1's power
     law; the filmic picture style),
   * ``dslr``: hue-dependent saturation (:func:`hue_saturation`), clip to [0, 1], a smooth
     non-linear 3D gamut map applied as a 3D LUT with trilinear interpolation
     (:func:`gamut_lut`, :func:`apply_lut`), per-channel tone curves (:func:`channel_curve`),
   * ``local``: a spatially varying gain map (low-resolution grid, bilinear upsampling,
     :func:`local_gain_grid`, :func:`upsample_gain`) sets the shadow gain of a tone curve that
     keeps white at white (:func:`local_curve`), then the display gamma with a linear toe,

4. 8-bit rounding.

Every parameter lives in :class:`FrameSettings` (plain numbers and lists, so
:func:`settings_to_dict` / :func:`settings_from_dict` round-trip them through ``scene.json``
exactly); content-dependent ones (the ``local`` gain map, computed from the frame itself as a
phone does) are filled in by :func:`prepare_frame` before rendering. The exact inverse is
:func:`derender.camera.oracle.invert_frame_codes`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np

from derender.camera.rendering import (
    RenderSettings,
    encode_gamma_with_toe,
    render_style,
    s_curve,
    saturation_matrix,
)
from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709
from derender.core.errors import InputError

__all__ = [
    "STYLES",
    "FrameSettings",
    "frame_matrix",
    "hue_angle",
    "hue_saturation_factor",
    "hue_saturation",
    "gamut_lut",
    "apply_lut",
    "channel_curve",
    "local_gain_grid",
    "local_curve",
    "inverse_local_curve",
    "upsample_gain",
    "prepare_frame",
    "render_frame",
    "settings_to_dict",
    "settings_from_dict",
]

#: Rendering styles a :class:`FrameSettings` can name.
STYLES = ("simple", "camera", "dslr", "local")


@dataclass
class FrameSettings:
    """Every parameter of one frame's in-camera rendering (see the module doc for the stages).

    ``wb``: render white balance (R, G, B multipliers on camera RGB); ``wb_as_shot``: the
    scene's (the truth's) white balance; ``camera_to_srgb``: normalised white-balanced
    camera RGB -> linear sRGB. ``gamut``: parameters of the ``dslr`` gamut map (``centers``
    (K, 3), ``amplitudes`` (K, 3), ``width``, ``neutral``, ``nodes``; see
    :func:`gamut_lut`). ``hue_sat``: ``[s0, a1, p1, a2, p2]`` of :func:`hue_saturation_factor`.
    ``curves``: per channel ``[gamma, blend, strength]`` of :func:`channel_curve`. ``local``:
    ``{"strength", "sigma", "grid"}`` of :func:`local_gain_grid`; ``gain_map``: the
    gain grid itself (rows x columns), filled by :func:`prepare_frame`.
    """

    style: str
    wb: list[float]
    wb_as_shot: list[float]
    camera_to_srgb: list[list[float]]
    gain: float = 1.0
    gamma: float = 2.2
    saturation: float = 1.0
    tone_curve: bool = False
    wb_preset: str | None = None
    hue_sat: list[float] | None = None
    gamut: dict[str, Any] | None = None
    curves: list[list[float]] | None = None
    local: dict[str, Any] | None = None
    gain_map: list[list[float]] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def render_settings(self) -> RenderSettings:
        """The :class:`~derender.camera.rendering.RenderSettings` of a ``simple``/``camera`` frame."""
        return RenderSettings(wb=list(self.wb), gain=self.gain, gamma=self.gamma, saturation=self.saturation,
                              style=self.style, tone_curve=self.tone_curve)

    @classmethod
    def from_render_settings(cls, rs: RenderSettings, wb_as_shot: Any, camera_to_srgb: Any) -> "FrameSettings":
        """Wrap the settings of the ``fixed``/``auto`` pipelines (same numbers, same rendering)."""
        return cls(style=rs.style, wb=[float(v) for v in rs.wb], wb_as_shot=[float(v) for v in wb_as_shot],
                   camera_to_srgb=np.asarray(camera_to_srgb, dtype=np.float64).tolist(), gain=float(rs.gain),
                   gamma=float(rs.gamma), saturation=float(rs.saturation), tone_curve=bool(rs.tone_curve))


def frame_matrix(settings: FrameSettings) -> np.ndarray:
    """The colour transform ``gain * S(saturation) @ camera_to_srgb`` (white-balanced camera RGB -> linear sRGB)."""
    return settings.gain * saturation_matrix(settings.saturation) @ np.asarray(settings.camera_to_srgb, dtype=np.float64)


# --------------------------------------------------------------------------- hue-dependent saturation
def hue_angle(rgb: np.ndarray) -> np.ndarray:
    """Opponent hue angle ``atan2(sqrt(3) (G - B), 2R - G - B)`` (radians); unchanged by scaling chroma."""
    return np.arctan2(np.sqrt(3.0) * (rgb[..., 1] - rgb[..., 2]), 2.0 * rgb[..., 0] - rgb[..., 1] - rgb[..., 2])


def hue_saturation_factor(h: np.ndarray, params: Any) -> np.ndarray:
    """``s(h) = s0 exp(a1 cos(h - p1) + a2 cos(2h - p2))`` (always positive)."""
    s0, a1, p1, a2, p2 = (float(v) for v in params)
    return s0 * np.exp(a1 * np.cos(h - p1) + a2 * np.cos(2.0 * h - p2))


def hue_saturation(lin: np.ndarray, params: Any) -> np.ndarray:
    """Hue-dependent saturation: chroma ``x - L`` (Rec. 709 luminance ``L``) scaled by ``s(hue)``.

    Luminance and hue are kept, so the stage is exactly invertible
    (divide the chroma by ``s`` of the output's hue).
    """
    lum = (lin @ LUMINANCE_WEIGHTS_REC709)[..., None]
    s = hue_saturation_factor(hue_angle(lin), params)[..., None]
    return lum + s * (lin - lum)


# --------------------------------------------------------------------------- 3D gamut map
def gamut_lut(gamut: dict[str, Any]) -> np.ndarray:
    """The 3D LUT (nodes^3, 3) of the ``dslr`` gamut map's displacement, over ``u = sqrt(linear)``.

    ``d(u) = P (sum_k a_k exp(-|u - c_k|^2 / (2 width^2))) q(u) t(u)``: a sum of Gaussian
    radial basis functions with vector amplitudes ``a_k``, ``P`` removes the component along
    the neutral axis (the map moves colours, not their level), ``q = |c|^2 / (|c|^2 +
    neutral^2)`` (``c`` = chroma of ``u``) keeps neutrals exactly neutral, and ``t =
    prod_c sin(pi u_c)`` keeps the cube's faces (black, clipped channels) in place. The map is
    ``u -> u + d(u)``; the generator keeps ``d``'s slope small, so it is monotone and invertible.
    """
    n = int(gamut["nodes"])
    g = np.linspace(0.0, 1.0, n)
    u = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    c = np.asarray(gamut["centers"], dtype=np.float64)
    a = np.asarray(gamut["amplitudes"], dtype=np.float64)
    w = float(gamut["width"])
    r2 = ((u[:, None, :] - c[None]) ** 2).sum(-1)
    d = np.exp(-r2 / (2.0 * w * w)) @ a
    d -= d.mean(axis=1, keepdims=True)                      # perpendicular to the neutral axis
    chroma = u - u.mean(axis=1, keepdims=True)
    cc = (chroma ** 2).sum(axis=1)
    q = cc / (cc + float(gamut["neutral"]) ** 2)
    t = np.prod(np.sin(np.pi * u), axis=1)
    return d * (q * t)[:, None]


def apply_lut(lut: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of a (n^3, 3) LUT (``indexing="ij"`` over [0, 1]^3) at ``u`` (..., 3)."""
    n = round(lut.shape[0] ** (1 / 3))
    shape = u.shape
    p = np.clip(u.reshape(-1, 3), 0.0, 1.0) * (n - 1)
    i0 = np.minimum(np.floor(p).astype(np.int64), n - 2)
    f = p - i0
    out = np.zeros((p.shape[0], lut.shape[1]), dtype=np.float64)
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1.0 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1.0 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1.0 - f[:, 2]
                idx = ((i0[:, 0] + dx) * n + (i0[:, 1] + dy)) * n + (i0[:, 2] + dz)
                out += (wx * wy * wz)[:, None] * lut[idx]
    return out.reshape(shape[:-1] + (lut.shape[1],))


# --------------------------------------------------------------------------- tone curves
def channel_curve(x: np.ndarray, params: Any) -> np.ndarray:
    """One channel's tone curve: ``(1 - blend) g + blend s_curve(g, strength)``, ``g`` the
    display gamma ``gamma`` with a linear toe; monotone from 0 -> 0 to 1 -> 1."""
    gamma, blend, strength = (float(v) for v in params)
    g = encode_gamma_with_toe(x, gamma)
    return (1.0 - blend) * g + blend * s_curve(g, strength)


# --------------------------------------------------------------------------- local tone map
def local_gain_grid(lin: np.ndarray, local: dict[str, Any]) -> np.ndarray:
    """A phone's local tone map: gain grid (rows x columns) from the frame's blurred luminance.

    ``log gain = -strength (log B - mean(log B))``, ``B`` the luminance blurred with a Gaussian of
    ``sigma`` (fraction of the image diagonal) and averaged over ``grid = [rows, cols]`` cells:
    shadows are lifted and highlights held back relative to the frame's mean (the gains' geometric
    mean is 1, so the frame's overall exposure is left to the global gain); gains limited to [1/4, 4].
    """
    import cv2

    h, w = lin.shape[:2]
    lum = np.maximum(lin @ LUMINANCE_WEIGHTS_REC709, 0.0)
    loglum = np.log(lum + 1e-3).astype(np.float64)
    sigma = float(local["sigma"]) * float(np.hypot(h, w))
    k = int(6 * sigma) | 1
    blurred = cv2.GaussianBlur(loglum, (k, k), sigma, borderType=cv2.BORDER_REFLECT)
    rows, cols = (int(v) for v in local["grid"])
    cells = cv2.resize(blurred, (cols, rows), interpolation=cv2.INTER_AREA)
    log_gain = -float(local["strength"]) * (cells - cells.mean())
    return np.exp(np.clip(log_gain, -np.log(4.0), np.log(4.0)))


def local_curve(x: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """The ``local`` style's tone curve with shadow gain ``g`` per pixel: ``g x / (1 + (g - 1) x)``.

    Slope ``g`` at black, 0 -> 0 and 1 -> 1 whatever ``g`` (a saturated pixel stays white, as in
    a real camera), increasing; ``g > 1`` lifts, ``g < 1`` holds back. ``x`` is clipped to [0, 1].
    """
    x = np.clip(x, 0.0, 1.0)
    return gain * x / (1.0 + (gain - 1.0) * x)


def inverse_local_curve(r: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Inverse of :func:`local_curve`: ``x = r / (g - (g - 1) r)``."""
    r = np.clip(r, 0.0, 1.0)
    return r / (gain - (gain - 1.0) * r)


def upsample_gain(grid: Any, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling of a gain grid to an (H, W) map (cell centres aligned, edges held)."""
    g = np.asarray(grid, dtype=np.float64)
    h, w = shape
    rows, cols = g.shape

    def coords(n_out: int, n_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0.0, n_in - 1.0)
        i0 = np.minimum(np.floor(x).astype(np.int64), max(n_in - 2, 0))
        return i0, np.minimum(i0 + 1, n_in - 1), x - i0

    r0, r1, fr = coords(h, rows)
    c0, c1, fc = coords(w, cols)
    top = g[r0][:, c0] * (1 - fc) + g[r0][:, c1] * fc
    bot = g[r1][:, c0] * (1 - fc) + g[r1][:, c1] * fc
    return top * (1 - fr)[:, None] + bot * fr[:, None]


# --------------------------------------------------------------------------- rendering
def _linear(camera_rgb: np.ndarray, settings: FrameSettings) -> np.ndarray:
    rgb = np.minimum(camera_rgb * np.asarray(settings.wb), 1.0)   # white balance + highlight clip
    return rgb @ frame_matrix(settings).T


def prepare_frame(settings: FrameSettings, camera_rgb: np.ndarray) -> FrameSettings:
    """Fill the content-dependent parameters (the ``local`` gain map, from this frame's
    linear image) of ``settings``; other settings are returned unchanged."""
    if settings.style != "local" or settings.gain_map is not None:
        return settings
    grid = local_gain_grid(_linear(np.asarray(camera_rgb, dtype=np.float64), settings), settings.local or {})
    return replace(settings, gain_map=grid.tolist())


def render_frame(camera_rgb: np.ndarray, settings: FrameSettings) -> np.ndarray:
    """Render camera RGB (demosaiced, normalised, in [0, 1]; (H, W, 3)) to 8-bit codes.

    For ``simple``/``camera`` frames this is exactly :func:`derender.camera.rendering.isp_render`
    after its demosaicing. ``local`` frames need their gain map (:func:`prepare_frame`).
    """
    lin = _linear(np.asarray(camera_rgb, dtype=np.float64), settings)
    if settings.style in ("simple", "camera"):
        y = render_style(lin, settings.render_settings())
    elif settings.style == "dslr":
        lin = np.clip(hue_saturation(lin, settings.hue_sat), 0.0, 1.0)
        u = np.sqrt(lin)
        u = np.clip(u + apply_lut(gamut_lut(settings.gamut), u), 0.0, 1.0)
        lin = u * u
        y = np.stack([channel_curve(lin[..., c], settings.curves[c]) for c in range(3)], axis=-1)
    elif settings.style == "local":
        if settings.gain_map is None:
            raise InputError("a 'local' frame needs its gain map: call prepare_frame first")
        gain = upsample_gain(settings.gain_map, lin.shape[:2])
        y = encode_gamma_with_toe(local_curve(lin, gain[..., None]), settings.gamma)
    else:
        raise InputError(f"unknown render style {settings.style!r}: use one of {', '.join(STYLES)}")
    return np.clip(np.rint(y * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- scene.json
def settings_to_dict(settings: FrameSettings) -> dict[str, Any]:
    """Plain-JSON dict of every parameter (floats round-trip exactly through ``json``)."""
    d = asdict(settings)
    d["exponent"] = 1.0 / settings.gamma
    return d


def settings_from_dict(d: dict[str, Any]) -> FrameSettings:
    """Inverse of :func:`settings_to_dict` (unknown keys are ignored)."""
    names = {f.name for f in fields(FrameSettings)}
    if "style" not in d or "wb" not in d:
        raise InputError("frame settings need at least 'style' and 'wb'")
    return FrameSettings(**{k: v for k, v in d.items() if k in names})
