"""Physically based camera simulator with exact truth.

The simulator renders a *spectral* scene through a camera's measured spectral
sensitivities into a noisy Bayer mosaic (shot + read noise, black/white level, 12/14-bit
ADC), writes it as a real DNG, and renders the in-camera JPEG from that mosaic (demosaic,
white balance, camera-to-sRGB matrix, gain, tone rendering, gamut handling, 8-bit), with
EXIF ``ExposureTime``; the JPEG engine also applies a mild chroma noise reduction, as cameras
do before chroma subsampling. The scene radiance is known exactly, so every later stage is judged
against truth.

Data flow::

    make_scene(kind, size, seed)         -> SpectralScene (reflectance + illumination maps)
    scene_camera_rgb(scene, camera)      -> camera RGB per second, noise-free (H, W, 3)
    simulate_bracket(...)                -> SimulatedBracket (mosaics, JPEG codes, times, truth)
    write_bracket(bracket, outdir)       -> raw/NN.dng, jpeg/NN.jpg, truth.exr, scene.json

Truth (``truth.exr``) is the white-balanced, noise-free, unclipped camera RGB per second
mapped to linear sRGB by the same normalised colour matrix a RAW converter derives from the
DNG's ColorMatrix1 (:func:`derender.colorimetry.camera_to_linear_srgb_matrix`)
with the DNG's AsShotNeutral white balance: the quantity paper 1 (Sec. 4.2) builds from RAW.

Pipelines
---------
``fixed``: every exposure rendered identically (white balance of the scene illuminant,
gain 1, display gamma 2.2, no saturation change).

``auto`` (what auto modes do; magnitudes drawn from a seeded generator, stored in
``scene.json``): per exposure j the white-balance multipliers drift across the bracket by
up to +-10 % (R) and -+8 % (B) plus 4 % random jitter (log-normal); gain alpha_j =
exp(U(0, 0.3)), i.e. 1 to 1.35 (never below 1, so a saturated sensor still renders as
255, as in real cameras); display gamma gamma_j ~ U(1.8, 2.6) (encoding
exponent 1/gamma_j); a saturation matrix s_j ~ U(0.85, 1.15). The DNGs always carry the
scene's true white balance (AsShotNeutral), so the RAW ground truth is the same for both.

Rendering styles
----------------
``simple``: ``y = clip(alpha_j S_j M WB_j x, 0, 1) ** (1 / gamma_j)`` - exactly the model
of paper 1 (its eq. 4), optionally followed by a fixed S-shaped tone curve (``tone_curve``).

``camera`` (default, like a real picture style): saturation boost 1.2, soft hue-preserving
gamut compression (chroma scaled towards luminance so no channel goes negative, with a soft
knee), a per-channel filmic S-curve with highlight shoulder (Hable's curve, exposure bias 6,
white at linear 1 = sensor saturation), then the display gamma with a linear toe (as
sRGB: finite slope at black). The ``simple`` style keeps the pure power law of paper 1. No 3x3-plus-curve model contains it.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from derender.camera.spectral import (
    WAVELENGTHS,
    CameraSpectral,
    cmfs_xyz,
    illuminant_spd,
    load_camera,
    reflectance_library,
)
from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709, camera_to_linear_srgb_matrix
from derender.core.errors import InputError

__all__ = [
    "SCENE_KINDS",
    "CFA_PATTERN",
    "SpectralScene",
    "make_scene",
    "scene_camera_rgb",
    "scene_xyz",
    "fit_xyz_to_camera",
    "white_balance_for",
    "mosaic_signal",
    "expose_mosaic",
    "RenderSettings",
    "encode_gamma_with_toe",
    "saturation_matrix",
    "filmic_curve",
    "s_curve",
    "gamut_compress",
    "demosaic_bilinear",
    "chroma_denoise",
    "isp_render",
    "pipeline_settings",
    "SimulatedBracket",
    "bracket_times",
    "simulate_bracket",
    "write_jpeg",
    "write_bracket",
    "load_scene_json",
    "bracket_paths",
    "simulate_to_folder",
    "camera_names_for_search",
]


#: Scene kinds of :func:`make_scene` (``derender simulate --scene``).
SCENE_KINDS = ("outdoor", "indoor", "night")


#: Bayer pattern of the simulated sensor (top-left 2x2 block).
CFA_PATTERN = "RGGB"


# --------------------------------------------------------------------------- scene
@dataclass
class SpectralScene:
    """A spectral scene: per-pixel reflectance mixtures lit by a few illuminants.

    Reflectance at a pixel = sum_j material_weight[..., j] * library[material_index[..., j]].
    Spectral radiance = sum_k illumination[..., k] * illuminant_spds[k] * reflectance.
    """

    kind: str
    library: np.ndarray            # (L, n_wl) reflectances
    material_index: np.ndarray     # (H, W, 3) int32 rows of library
    material_weight: np.ndarray    # (H, W, 3) float32 mixture weights
    illuminant_names: tuple[str, ...]
    illuminant_spds: np.ndarray    # (K, n_wl), Y = 1
    illumination: np.ndarray       # (H, W, K) float32 relative irradiance
    key_illuminant: str            # the illuminant the camera white-balances for
    regions: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.material_index.shape[:2]


def _texture_rgb(size: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A natural texture (matplotlib's bundled photograph), randomly cropped/flipped, linear RGB in [0, 1]."""
    import cv2
    import matplotlib

    w, h = size
    sample = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    img = cv2.imread(str(sample), cv2.IMREAD_COLOR)
    if img is None:  # pragma: no cover - matplotlib always ships it
        base = rng.random((64, 64, 3)).astype(np.float32)
        img = (cv2.resize(base, (w, h), interpolation=cv2.INTER_CUBIC) * 255).astype(np.uint8)
    img = img[:, :, ::-1].astype(np.float32) / 255.0
    ih, iw = img.shape[:2]
    # random crop keeping >= 60 % of each side, random flip
    cw = int(iw * rng.uniform(0.6, 1.0))
    ch = int(ih * rng.uniform(0.6, 1.0))
    x0 = int(rng.integers(0, iw - cw + 1))
    y0 = int(rng.integers(0, ih - ch + 1))
    img = img[y0:y0 + ch, x0:x0 + cw]
    if rng.random() < 0.5:
        img = img[:, ::-1]
    img = cv2.resize(np.ascontiguousarray(img), (w, h), interpolation=cv2.INTER_AREA)
    lin = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4)
    return np.clip(lin, 0.0, 1.0).astype(np.float32)


def _smooth_noise(shape: tuple[int, int], rng: np.random.Generator, scale: float) -> np.ndarray:
    import cv2

    h, w = shape
    small = rng.standard_normal((max(2, int(h / scale)), max(2, int(w / scale)))).astype(np.float32)
    up = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    return up / max(float(up.std()), 1e-6)


def _soft(mask: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    k = int(6 * sigma) | 1
    return cv2.GaussianBlur(mask.astype(np.float32), (k, k), sigma)


def make_scene(kind: str = "outdoor", size: tuple[int, int] = (384, 256), seed: int = 0) -> SpectralScene:
    """Build a spectral scene of ``size = (W, H)``.

    Content: a natural photograph turned into reflectances with the sRGB basis of
    Mallett & Yuksel (2019) (scaled into [0.03, 0.9]), a ColorChecker 24 (Ohta
    reflectances) and a grid of the 190 rawtoaces training reflectances. The
    illumination spans more than four decades: shadow (relative irradiance ~0.3-1),
    the main area (~10-30), a window or sunlit region (~300-1000) and a light source
    (~1e4-3e4), each with its own CIE illuminant, with soft boundaries.
    """
    if kind not in SCENE_KINDS:
        raise InputError(f"unknown scene kind {kind!r}: use one of {', '.join(SCENE_KINDS)}")
    w, h = int(size[0]), int(size[1])
    if w < 32 or h < 32:
        raise InputError(f"scene size {w}x{h} is too small (minimum 32x32)")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    names, library, groups = reflectance_library()

    # --- materials: texture via Mallett basis (3 weights = linear RGB), charts on top
    tex = _texture_rgb((w, h), rng)
    tex = 0.03 + 0.87 * tex
    idx = np.empty((h, w, 3), dtype=np.int32)
    idx[:] = np.arange(groups["mallett"].start, groups["mallett"].stop, dtype=np.int32)
    wts = tex.copy()

    def put_patch(x0, y0, x1, y1, row):
        idx[y0:y1, x0:x1, :] = row
        wts[y0:y1, x0:x1, :] = np.array([1.0, 0.0, 0.0], dtype=np.float32)

    # ColorChecker 24: 6 x 4 patches in the lower-left quarter
    cc = groups["colorchecker24"]
    pw = max(2, w // 18)
    gap = max(1, pw // 6)
    cx0 = int(w * rng.uniform(0.04, 0.10))
    cy0 = int(h * rng.uniform(0.52, 0.60))
    regions = {"colorchecker24": []}
    for i in range(24):
        r, c = divmod(i, 6)
        x0 = cx0 + c * (pw + gap)
        y0 = cy0 + r * (pw + gap)
        if x0 + pw <= w and y0 + pw <= h:
            put_patch(x0, y0, x0 + pw, y0 + pw, cc.start + i)
            regions["colorchecker24"].append([x0, y0, pw, pw])
    # rawtoaces 190: 19 x 10 grid in the lower-right part
    tr = groups["rawtoaces190"]
    gw = max(2, w // 48)
    gx0 = int(w * 0.55)
    gy0 = int(h * 0.55)
    regions["rawtoaces190"] = [gx0, gy0, 19 * gw, 10 * gw]
    for i in range(tr.stop - tr.start):
        r, c = divmod(i, 19)
        x0, y0 = gx0 + c * gw, gy0 + r * gw
        if x0 + gw <= w and y0 + gw <= h:
            put_patch(x0, y0, x0 + gw, y0 + gw, tr.start + i)

    # --- illumination field
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    shading = np.exp(0.25 * _smooth_noise((h, w), rng, scale=max(8.0, w / 6)))
    sigma = max(1.5, w / 120)

    def disc(cx, cy, r):
        return ((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r).astype(np.float32)

    lamp_r = max(3.0, 0.035 * w)
    lamp_x, lamp_y = w * rng.uniform(0.6, 0.85), h * rng.uniform(0.12, 0.3)
    lamp = disc(lamp_x, lamp_y, lamp_r)
    white_row = groups["white"].start
    # the light source itself is a bright white emitter-like reflector
    lamp_hard = lamp > 0.5
    idx[lamp_hard] = white_row
    wts[lamp_hard] = np.array([1.0, 0.0, 0.0], dtype=np.float32)
    lamp = _soft(lamp, sigma * 0.7)
    glow = np.exp(-(((xx - lamp_x) ** 2 + (yy - lamp_y) ** 2) / (2 * (4 * lamp_r) ** 2)))

    if kind == "outdoor":
        illum_names = ("D75", "D50", "D55")
        shadow = _soft((xx < w * rng.uniform(0.3, 0.42)).astype(np.float32), sigma * 3)
        sun = 1.0 - shadow
        base_shadow = 1.0 * shadow
        base_sun = 25.0 * sun
        bright = np.maximum(0.0, glow * 600.0) + lamp * 2.0e4
        fields = [base_shadow * shading, base_sun * shading, bright]
        key = "D50"
    elif kind == "indoor":
        illum_names = ("A", "D65", "A")
        win = np.zeros((h, w), np.float32)
        wx0, wx1 = int(w * 0.05), int(w * rng.uniform(0.3, 0.4))
        wy0, wy1 = int(h * 0.06), int(h * 0.42)
        win[wy0:wy1, wx0:wx1] = 1.0
        regions["window"] = [wx0, wy0, wx1 - wx0, wy1 - wy0]
        win = _soft(win, sigma)
        vignette = 0.25 + 0.75 * np.exp(-(((xx - w / 2) / (0.7 * w)) ** 2 + ((yy - h / 2) / (0.7 * h)) ** 2))
        room = 12.0 * vignette * (1 - win)
        fields = [room * shading, 500.0 * win * shading, glow * 300.0 + lamp * 1.5e4]
        key = "A"
    else:  # night
        illum_names = ("FL11", "A", "HP1")
        dark = 0.4 * (0.3 + 0.7 * np.exp(-((yy - h) / (0.6 * h)) ** 2))
        win = np.zeros((h, w), np.float32)
        wx0, wy0 = int(w * 0.1), int(h * 0.15)
        win[wy0:wy0 + h // 5, wx0:wx0 + w // 6] = 1.0
        regions["window"] = [wx0, wy0, w // 6, h // 5]
        win = _soft(win, sigma)
        fields = [dark * shading + 150.0 * win, glow * 800.0 + 10.0 * glow ** 0.3, lamp * 3.0e4]
        key = "A"
    illumination = np.stack(fields, axis=-1).astype(np.float32)
    illumination = np.maximum(illumination, 0.0)
    spds = np.stack([illuminant_spd(n) for n in illum_names])
    regions["lamp"] = [float(lamp_x), float(lamp_y), float(lamp_r)]
    return SpectralScene(
        kind=kind, library=library, material_index=idx, material_weight=wts.astype(np.float32),
        illuminant_names=illum_names, illuminant_spds=spds, illumination=illumination,
        key_illuminant=key, regions=regions,
    )


def _responses(scene: SpectralScene, observer: np.ndarray) -> np.ndarray:
    """(K, L, 3): response of ``observer`` (n_wl, 3) to every library reflectance under each illuminant."""
    return np.einsum("kw,lw,wc->klc", scene.illuminant_spds, scene.library, observer)


def _render_linear(scene: SpectralScene, observer: np.ndarray) -> np.ndarray:
    table = _responses(scene, observer).astype(np.float64)  # (K, L, 3)
    h, w = scene.shape
    out = np.zeros((h, w, 3), dtype=np.float64)
    for k in range(table.shape[0]):
        per_material = table[k][scene.material_index]          # (H, W, 3 mats, 3 ch)
        refl_resp = np.einsum("hwm,hwmc->hwc", scene.material_weight.astype(np.float64), per_material)
        out += scene.illumination[..., k:k + 1].astype(np.float64) * refl_resp
    return out


def scene_camera_rgb(scene: SpectralScene, camera: CameraSpectral) -> np.ndarray:
    """Noise-free camera RGB (relative, per unit exposure) at every pixel, (H, W, 3) float64."""
    return _render_linear(scene, camera.sensitivities)


def scene_xyz(scene: SpectralScene) -> np.ndarray:
    """CIE XYZ of the scene radiance (relative), (H, W, 3) float64."""
    return _render_linear(scene, cmfs_xyz())


def fit_xyz_to_camera(camera: CameraSpectral, illuminant: str = "D65") -> np.ndarray:
    """XYZ -> camera 3x3 matrix (DNG ColorMatrix semantics) by least squares on reflectances.

    Fits camera-to-XYZ on the 24 ColorChecker + 190 rawtoaces reflectances under
    ``illuminant`` (XYZ ~= M @ camera_rgb), and returns its inverse.
    """
    names, library, groups = reflectance_library()
    rows = np.r_[np.arange(groups["colorchecker24"].start, groups["colorchecker24"].stop),
                 np.arange(groups["rawtoaces190"].start, groups["rawtoaces190"].stop)]
    e = illuminant_spd(illuminant)
    refl = library[rows] * e[None, :]
    cam = refl @ camera.sensitivities
    xyz = refl @ cmfs_xyz()
    m, *_ = np.linalg.lstsq(cam, xyz, rcond=None)  # xyz = cam @ m
    cam_to_xyz = m.T
    return np.linalg.inv(cam_to_xyz)


def white_balance_for(camera: CameraSpectral, illuminant: str) -> np.ndarray:
    """White-balance multipliers (R, G, B; G = 1) that make a neutral under ``illuminant`` grey."""
    neutral = illuminant_spd(illuminant) @ camera.sensitivities
    return neutral[1] / neutral


# --------------------------------------------------------------------------- sensor
def _cfa_index(shape: tuple[int, int], pattern: str = CFA_PATTERN) -> np.ndarray:
    lut = {"R": 0, "G": 1, "B": 2}
    tile = np.array([[lut[pattern[0]], lut[pattern[1]]], [lut[pattern[2]], lut[pattern[3]]]])
    h, w = shape
    return np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def mosaic_signal(camera_rgb: np.ndarray, pattern: str = CFA_PATTERN) -> np.ndarray:
    """Pick each photosite's colour from an (H, W, 3) image: the Bayer sampling."""
    ci = _cfa_index(camera_rgb.shape[:2], pattern)
    return np.take_along_axis(camera_rgb, ci[..., None], axis=2)[..., 0]


def expose_mosaic(signal_per_s: np.ndarray, camera: CameraSpectral, time: float,
                  rng: np.random.Generator | None) -> np.ndarray:
    """Sensor model: normalised signal per second (1 = white level) -> uint16 mosaic in DN.

    electrons ~ Poisson(signal * t * full_well); DN = black + electrons * (white - black) /
    full_well + N(0, read_noise); rounded and clipped to [0, white]. ``rng=None`` gives
    the noise-free, rounded mosaic.
    """
    gain = (camera.white_level - camera.black_level) / camera.full_well
    lam = np.clip(signal_per_s * time * camera.full_well, 0.0, 4.0 * camera.full_well)
    if rng is None:
        dn = camera.black_level + lam * gain
    else:
        electrons = rng.poisson(lam).astype(np.float64)
        dn = camera.black_level + electrons * gain + rng.normal(0.0, camera.read_noise, lam.shape)
    return np.clip(np.rint(dn), 0, camera.white_level).astype(np.uint16)


# --------------------------------------------------------------------------- ISP
@dataclass
class RenderSettings:
    """In-camera rendering parameters of one exposure."""

    wb: list[float]                 # multipliers R, G, B
    gain: float = 1.0               # alpha_j
    gamma: float = 2.2              # display gamma; encoding exponent is 1 / gamma
    saturation: float = 1.0         # s_j of the saturation matrix S_j
    style: str = "camera"           # "simple" | "camera"
    tone_curve: bool = False        # simple style: extra fixed S-curve

    @property
    def exponent(self) -> float:
        return 1.0 / self.gamma


def encode_gamma_with_toe(y: np.ndarray, gamma: float, a: float = 0.055) -> np.ndarray:
    """Display encoding ``(1 + a) y^(1/gamma) - a`` with a linear toe (as sRGB / Rec. 709).

    The toe ``k y`` below ``y0 = (a / ((1 + a)(1 - 1/gamma)))^gamma`` joins the power law
    with matching value and slope (for gamma = 2.4 this is sRGB: y0 = 0.0030, k = 12.9).
    Real cameras' curves have a finite slope at black; a pure power law would amplify
    sensor noise in the shadows without bound.
    """
    inv = 1.0 / gamma
    y0 = (a / ((1.0 + a) * (1.0 - inv))) ** gamma
    k = (1.0 + a) * inv * y0 ** (inv - 1.0)
    y = np.clip(y, 0.0, 1.0)
    return np.where(y < y0, k * y, (1.0 + a) * np.power(np.maximum(y, y0), inv) - a)


def saturation_matrix(s: float) -> np.ndarray:
    """S = s I + (1 - s) 1 w^T with Rec. 709 luminance weights w (keeps luminance)."""
    w = LUMINANCE_WEIGHTS_REC709
    return s * np.eye(3) + (1.0 - s) * np.outer(np.ones(3), w)


def _hable(x: np.ndarray) -> np.ndarray:
    a, b, c, d, e, f = 0.15, 0.50, 0.10, 0.20, 0.02, 0.30
    return ((x * (a * x + c * b) + d * e) / (x * (a * x + b) + d * f)) - e / f


def filmic_curve(x: np.ndarray, exposure_bias: float = 6.0, white: float = 1.0) -> np.ndarray:
    """Hable's filmic curve (toe + highlight shoulder): ``hable(b x) / hable(b W)``, 0 -> 0, W -> 1.

    With W = 1 the sensor's saturation (linear 1 after white balance) renders as white, as
    in a real camera; mid grey 0.18 renders at about 0.385 display-linear.
    """
    x = np.minimum(np.maximum(x, 0.0), white)
    return np.clip(_hable(x * exposure_bias) / _hable(np.float64(white * exposure_bias)), 0.0, 1.0)


def s_curve(y: np.ndarray, strength: float = 2.0) -> np.ndarray:
    """Spatially uniform S-shaped tone curve on [0, 1] (0 -> 0, 1 -> 1)."""
    return 0.5 + 0.5 * np.tanh(strength * (y - 0.5)) / np.tanh(strength / 2)


def gamut_compress(linear_rgb: np.ndarray, knee: float = 0.8) -> np.ndarray:
    """Soft, hue-preserving gamut compression towards luminance.

    d = max_c (L - x_c) / L is the chroma distance (1 where a channel reaches 0);
    d above ``knee`` is compressed smoothly into [knee, 1) and the chroma vector
    x - L is scaled by d' / d, so hue (chroma direction) is kept and no channel is negative.
    """
    lum = linear_rgb @ LUMINANCE_WEIGHTS_REC709
    lum_safe = np.maximum(lum, 1e-12)[..., None]
    chroma = linear_rgb - lum[..., None]
    d = np.max(-chroma, axis=-1) / lum_safe[..., 0]
    d = np.maximum(d, 0.0)
    over = d > knee
    d_new = np.where(over, knee + (1 - knee) * np.tanh((d - knee) / (1 - knee)), d)
    factor = np.where(over, d_new / np.maximum(d, 1e-12), 1.0)
    out = lum[..., None] + chroma * factor[..., None]
    return np.where(lum[..., None] > 0, out, 0.0)


def demosaic_bilinear(normalised_mosaic: np.ndarray, pattern: str = CFA_PATTERN) -> np.ndarray:
    """In-camera demosaicing (bilinear, colour-demosaicing)."""
    from colour_demosaicing import demosaicing_CFA_Bayer_bilinear

    return np.asarray(demosaicing_CFA_Bayer_bilinear(normalised_mosaic, pattern), dtype=np.float64)


def chroma_denoise(rgb: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """In-camera chroma noise reduction: Gaussian blur (``sigma`` px) of ``rgb - mean(rgb)``."""
    import cv2

    lum = rgb.mean(axis=-1, keepdims=True)
    chroma = np.ascontiguousarray(rgb - lum, dtype=np.float64)
    k = int(6 * sigma) | 1
    chroma = cv2.GaussianBlur(chroma, (k, k), sigma, borderType=cv2.BORDER_REFLECT)
    return np.clip(lum + chroma, 0.0, 1.0)


def isp_render(mosaic: np.ndarray, camera: CameraSpectral, camera_to_srgb: np.ndarray,
               settings: RenderSettings, pattern: str = CFA_PATTERN) -> np.ndarray:
    """Render a RAW mosaic to 8-bit sRGB codes (H, W, 3) uint8 as the camera's JPEG engine does."""
    x = (mosaic.astype(np.float64) - camera.black_level) / (camera.white_level - camera.black_level)
    rgb = chroma_denoise(np.clip(demosaic_bilinear(x, pattern), 0.0, 1.0))
    rgb = np.minimum(rgb * np.asarray(settings.wb), 1.0)          # white balance + highlight clip
    m = settings.gain * saturation_matrix(settings.saturation) @ camera_to_srgb
    lin = rgb @ m.T                                                # linear sRGB (may leave the gamut)
    if settings.style == "simple":
        y = np.clip(lin, 0.0, 1.0) ** settings.exponent
        if settings.tone_curve:
            y = s_curve(y)
    elif settings.style == "camera":
        lum = lin @ LUMINANCE_WEIGHTS_REC709
        lin = lum[..., None] + 1.2 * (lin - lum[..., None])           # picture-style saturation boost
        lin = gamut_compress(lin)
        y = encode_gamma_with_toe(filmic_curve(lin), settings.gamma)
    else:
        raise InputError(f"unknown render style {settings.style!r}: use 'simple' or 'camera'")
    return np.clip(np.rint(y * 255.0), 0, 255).astype(np.uint8)


def pipeline_settings(pipeline: str, n: int, wb_true: np.ndarray, style: str, rng: np.random.Generator,
                      tone_curve: bool = False) -> list[RenderSettings]:
    """Per-exposure rendering parameters for the ``fixed`` or ``auto`` pipeline (see module doc)."""
    if pipeline == "fixed":
        return [RenderSettings(wb=[float(v) for v in wb_true], style=style, tone_curve=tone_curve) for _ in range(n)]
    if pipeline != "auto":
        raise InputError(f"unknown pipeline {pipeline!r}: use 'fixed' or 'auto'")
    out = []
    drift = np.linspace(-1.0, 1.0, n)
    for j in range(n):
        d_r = 0.10 * drift[j] + rng.normal(0.0, 0.04)
        d_b = -0.08 * drift[j] + rng.normal(0.0, 0.04)
        wb = np.asarray(wb_true, dtype=np.float64) * np.exp([d_r, 0.0, d_b])
        gain = float(np.exp(rng.uniform(0.0, 0.3)))
        gamma = float(rng.uniform(1.8, 2.6))
        sat = float(rng.uniform(0.85, 1.15))
        out.append(RenderSettings(wb=[float(v) for v in wb], gain=gain, gamma=gamma, saturation=sat,
                                  style=style, tone_curve=tone_curve))
    return out


# --------------------------------------------------------------------------- bracket
@dataclass
class SimulatedBracket:
    """Everything a simulated bracket holds, in memory (see :func:`write_bracket` for files)."""

    camera: CameraSpectral
    scene: SpectralScene
    times: np.ndarray                  # (N,) seconds, exactly representable as EXIF rationals
    mosaics: np.ndarray                # (N, H, W) uint16
    jpeg_codes: np.ndarray             # (N, H, W, 3) uint8 (before JPEG compression)
    settings: list[RenderSettings]
    truth_linear_srgb: np.ndarray      # (H, W, 3) float32, per second
    camera_rgb_per_s: np.ndarray       # (H, W, 3) float64, normalised sensor units per second
    xyz_to_camera: np.ndarray          # DNG ColorMatrix1
    wb_true: np.ndarray                # AsShotNeutral multipliers
    camera_to_srgb: np.ndarray         # normalised, for white-balanced camera RGB
    params: dict


def _exif_time(t: float) -> float:
    f = Fraction(float(t)).limit_denominator(1_000_000)
    return f.numerator / f.denominator


def bracket_times(camera_rgb_per_unit: np.ndarray, n: int, t_min: float = 1 / 2000,
                  stops: float | None = None, peak_percentile: float = 99.9,
                  peak_level: float = 0.6) -> tuple[np.ndarray, float]:
    """Exposure times (geometric) and the scene scale so the ``peak_percentile`` of the
    per-pixel maximum camera channel reaches ``peak_level`` of white (RAW) at ``t_min`` and
    the darkest 2 % reach 25 % at the longest exposure (or ``stops`` between exposures).

    With the default 99.9 a highlight smaller than 0.1 % of the frame may clip in every
    exposure; ``peak_percentile=100`` makes the shortest exposure hold the whole scene
    below ``peak_level`` (a bracket that covers the scene). On the built-in scenes the two
    differ by < 0.3 % (their brightest region, the lamp, is larger than 0.1 % and uniform).
    """
    if not (0.0 < peak_percentile <= 100.0) or not (0.0 < peak_level <= 1.0):
        raise InputError(f"bracket_times needs 0 < peak_percentile <= 100 and 0 < peak_level <= 1, "
                         f"got {peak_percentile}, {peak_level}")
    peak = float(np.percentile(camera_rgb_per_unit.max(axis=-1), peak_percentile))
    dark = float(np.percentile(camera_rgb_per_unit.mean(axis=-1), 2.0))
    scale = float(peak_level) / (t_min * max(peak, 1e-30))
    if n == 1:
        return np.array([_exif_time(t_min)]), scale
    if stops is None:
        t_max = 0.25 / (max(dark, 1e-30) * scale)
        ratio = max((t_max / t_min) ** (1.0 / (n - 1)), 2.0 ** 0.5)
    else:
        ratio = 2.0 ** float(stops)
    times = np.array([_exif_time(t_min * ratio**j) for j in range(n)])
    return times, scale


def simulate_bracket(
    camera: CameraSpectral | str = "nikon-d5100",
    kind: str = "outdoor",
    size: tuple[int, int] = (384, 256),
    exposures: int = 9,
    pipeline: str = "auto",
    style: str = "camera",
    seed: int = 0,
    tone_curve: bool = False,
    stops: float | None = None,
    noise: bool = True,
    scene: SpectralScene | None = None,
    wb_preset: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    peak_percentile: float = 99.9,
) -> SimulatedBracket:
    """Simulate a bracket: spectral scene -> noisy RAW mosaics -> in-camera 8-bit renderings.

    ``wb_preset`` (a CIE illuminant name, e.g. ``"D65"`` for a daylight preset) makes the
    JPEG engine white-balance for that illuminant instead of the scene's, as a camera set
    to a fixed white-balance mode does (the mode :func:`derender.chart.chart_pairs` uses).
    ``peak_percentile`` is passed to :func:`bracket_times` (100: the shortest exposure keeps
    the whole scene below 60 % of white in RAW).
    """
    if exposures < 1:
        raise InputError("--exposures must be at least 1")
    if isinstance(camera, str):
        camera = load_camera(camera)
    ss = np.random.SeedSequence(int(seed))
    rng_pipe, rng_noise = (np.random.default_rng(s) for s in ss.spawn(2))
    if scene is None:
        scene = make_scene(kind, size, seed)
    cam_unit = scene_camera_rgb(scene, camera)
    times, scale = bracket_times(cam_unit, exposures, stops=stops, peak_percentile=peak_percentile)
    cam_per_s = cam_unit * scale
    xyz_to_camera = fit_xyz_to_camera(camera)
    camera_to_srgb = camera_to_linear_srgb_matrix(xyz_to_camera)
    wb_true = white_balance_for(camera, scene.key_illuminant)
    truth = (cam_per_s * wb_true) @ camera_to_srgb.T
    wb_render = wb_true if wb_preset is None else white_balance_for(camera, wb_preset)
    settings = pipeline_settings(pipeline, exposures, wb_render, style, rng_pipe, tone_curve)
    signal = mosaic_signal(cam_per_s)
    h, w = scene.shape
    mosaics = np.empty((exposures, h, w), dtype=np.uint16)
    codes = np.empty((exposures, h, w, 3), dtype=np.uint8)
    noise_rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(rng_noise.integers(2**63)).spawn(exposures)]
    for j, t in enumerate(times):
        mosaics[j] = expose_mosaic(signal, camera, float(t), noise_rngs[j] if noise else None)
        codes[j] = isp_render(mosaics[j], camera, camera_to_srgb, settings[j])
        if progress is not None:
            progress(j + 1, exposures)
    params = {
        "generator": "derender.camera.simulate_bracket",
        "seed": int(seed),
        "camera": {"name": camera.name, "make": camera.make, "model": camera.model, "source": camera.source,
                   "bits": camera.bits, "black_level": camera.black_level, "white_level": camera.white_level,
                   "full_well_electrons": camera.full_well, "read_noise_dn": camera.read_noise,
                   "cfa_pattern": CFA_PATTERN},
        "scene": {"kind": scene.kind, "size": [w, h], "illuminants": list(scene.illuminant_names),
                  "key_illuminant": scene.key_illuminant, "regions": scene.regions,
                  "illumination_range": [float(np.percentile(scene.illumination.sum(-1), 1)),
                                         float(scene.illumination.sum(-1).max())]},
        "pipeline": pipeline,
        "style": style,
        "tone_curve": bool(tone_curve),
        "noise": bool(noise),
        "times": [float(t) for t in times],
        "scene_scale": float(scale),
        "peak_percentile": float(peak_percentile),
        "xyz_to_camera": xyz_to_camera.tolist(),
        "camera_to_linear_srgb": camera_to_srgb.tolist(),
        "wb_as_shot": [float(v) for v in wb_true],
        "wb_preset": wb_preset,
        "exposures": [asdict(s) | {"exponent": s.exponent} for s in settings],
        "truth": "linear sRGB (Rec. 709, D65) per second: camera_to_linear_srgb @ (wb_as_shot * camera_rgb), "
                 "noise-free, unclipped",
    }
    return SimulatedBracket(camera=camera, scene=scene, times=times, mosaics=mosaics, jpeg_codes=codes,
                            settings=settings, truth_linear_srgb=truth.astype(np.float32),
                            camera_rgb_per_s=cam_per_s, xyz_to_camera=xyz_to_camera, wb_true=wb_true,
                            camera_to_srgb=camera_to_srgb, params=params)


# --------------------------------------------------------------------------- files
def write_jpeg(path: str | os.PathLike, codes: np.ndarray, exposure_time: float, make: str, model: str,
               quality: int = 95) -> Path:
    """Write 8-bit RGB codes as a JPEG (4:2:2, like most cameras) with EXIF Make/Model/ExposureTime."""
    from PIL import Image, TiffImagePlugin

    from derender.io.files import atomic_output

    img = Image.fromarray(np.ascontiguousarray(codes), mode="RGB")
    exif = Image.Exif()
    exif[0x010F] = make
    exif[0x0110] = model
    exif[0x0131] = "derender simulator"
    f = Fraction(float(exposure_time)).limit_denominator(1_000_000)
    exif.get_ifd(0x8769)[0x829A] = TiffImagePlugin.IFDRational(f.numerator, f.denominator)
    path = Path(path)
    with atomic_output(path) as tmp:
        img.save(tmp, format="JPEG", quality=quality, subsampling=1, exif=exif.tobytes(), optimize=False)
    return path


def write_bracket(bracket: SimulatedBracket, outdir: str | os.PathLike, jpeg_quality: int = 95) -> dict:
    """Write ``raw/NN.dng``, ``jpeg/NN.jpg``, ``truth.exr`` and ``scene.json`` under ``outdir``."""
    from derender.camera.dng import write_dng
    from derender.io.exr import write_exr

    outdir = Path(outdir)
    (outdir / "raw").mkdir(parents=True, exist_ok=True)
    (outdir / "jpeg").mkdir(parents=True, exist_ok=True)
    cam = bracket.camera
    neutral = 1.0 / np.asarray(bracket.wb_true)
    files = {"raw": [], "jpeg": []}
    for j, t in enumerate(bracket.times):
        dng = write_dng(outdir / "raw" / f"{j:02d}.dng", bracket.mosaics[j], CFA_PATTERN, cam.black_level,
                        cam.white_level, bracket.xyz_to_camera, neutral, float(t), cam.make, cam.model, cam.bits)
        jpg = write_jpeg(outdir / "jpeg" / f"{j:02d}.jpg", bracket.jpeg_codes[j], float(t), cam.make, cam.model,
                         quality=jpeg_quality)
        files["raw"].append(str(dng.relative_to(outdir)))
        files["jpeg"].append(str(jpg.relative_to(outdir)))
    write_exr(outdir / "truth.exr", bracket.truth_linear_srgb)
    params = dict(bracket.params) | {"files": files, "jpeg_quality": jpeg_quality}
    from derender.io.files import atomic_output

    with atomic_output(outdir / "scene.json") as tmp:
        Path(tmp).write_text(json.dumps(params, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return params


def load_scene_json(outdir: str | os.PathLike) -> dict:
    """Read ``scene.json`` of a simulated bracket."""
    p = Path(outdir) / "scene.json"
    if not p.is_file():
        raise InputError(f"no scene.json in {outdir}")
    return json.loads(p.read_text(encoding="utf-8"))


def bracket_paths(outdir: str | os.PathLike, kind: str = "jpeg") -> list[Path]:
    """Sorted file paths of a simulated bracket folder (``kind`` = "jpeg" or "raw")."""
    d = Path(outdir) / kind
    pattern = "*.jpg" if kind == "jpeg" else "*.dng"
    files = sorted(d.glob(pattern))
    if not files:
        raise InputError(f"no {kind} files in {d}")
    return files


def simulate_to_folder(outdir: str | os.PathLike, **kwargs) -> dict:
    """:func:`simulate_bracket` then :func:`write_bracket`."""
    return write_bracket(simulate_bracket(**kwargs), outdir)


def camera_names_for_search(extra_dirs: Sequence[str | os.PathLike] = ()) -> list[str]:
    """Built-in camera names plus rawtoaces JSON names found in ``extra_dirs``."""
    from derender.camera.spectral import builtin_camera_names

    names = builtin_camera_names()
    for d in extra_dirs:
        for f in sorted(Path(d).glob("*.json")):
            names.append(f.stem)
    return names


_ = WAVELENGTHS  # re-exported for users of the simulator
