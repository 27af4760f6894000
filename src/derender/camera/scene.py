"""Spectral scenes for the simulator: reflectance and illumination maps with an exact radiance.

:func:`make_scene` builds a scene of a kind (``outdoor``, ``indoor``, ``night``): a natural
photograph turned into reflectances with the Mallett-Yuksel sRGB basis, a ColorChecker 24,
training reflectances, CIE illuminants, and an illumination field spanning more than four
decades (shadow, sunlit or window area, light source). :func:`scene_camera_rgb` integrates
it against a camera's spectral sensitivities (camera RGB per second, noise-free) and
:func:`scene_xyz` against the CIE 1931 observer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from derender.camera.spectral import CameraSpectral, cmfs_xyz, illuminant_spd, reflectance_library
from derender.core.errors import InputError

__all__ = [
    "SCENE_KINDS",
    "SpectralScene",
    "make_scene",
    "scene_camera_rgb",
    "scene_xyz",
    "texture_rgb",
    "soft_mask",
]

#: Scene kinds of :func:`make_scene` (``derender simulate --scene``).
SCENE_KINDS = ("outdoor", "indoor", "night")


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


def texture_rgb(size: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
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


def soft_mask(mask: np.ndarray, sigma: float) -> np.ndarray:
    """``mask`` blurred by a Gaussian of ``sigma`` pixels: a soft-edged region."""
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
    tex = texture_rgb((w, h), rng)
    tex = 0.03 + 0.87 * tex
    idx = np.empty((h, w, 3), dtype=np.int32)
    idx[:] = np.arange(groups["mallett"].start, groups["mallett"].stop, dtype=np.int32)
    wts = tex.copy()
    regions = _place_charts(idx, wts, groups, rng)

    # --- illumination field
    light = _SceneLight.draw((w, h), rng)
    # the light source itself is a bright white emitter-like reflector
    lamp_hard = light.lamp > 0.5
    idx[lamp_hard] = groups["white"].start
    wts[lamp_hard] = np.array([1.0, 0.0, 0.0], dtype=np.float32)
    light.lamp = soft_mask(light.lamp, light.sigma * 0.7)
    fields, illum_names, key = _illumination_fields(kind, light, rng, regions)
    illumination = np.stack(fields, axis=-1).astype(np.float32)
    illumination = np.maximum(illumination, 0.0)
    spds = np.stack([illuminant_spd(n) for n in illum_names])
    regions["lamp"] = [float(light.lamp_x), float(light.lamp_y), float(light.lamp_r)]
    return SpectralScene(
        kind=kind, library=library, material_index=idx, material_weight=wts.astype(np.float32),
        illuminant_names=illum_names, illuminant_spds=spds, illumination=illumination,
        key_illuminant=key, regions=regions,
    )


def _place_charts(idx: np.ndarray, wts: np.ndarray, groups: dict, rng: np.random.Generator) -> dict:
    """Paint a ColorChecker 24 and the rawtoaces 190 grid into the material planes (in place); their
    regions (``[x, y, w, h]`` per ColorChecker patch, one for the grid)."""
    h, w = idx.shape[:2]

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
    return regions


@dataclass
class _SceneLight:
    """The geometry every scene kind lights with: pixel coordinates, a shading texture, the lamp
    (a disc, then softened) and its glow."""

    xx: np.ndarray
    yy: np.ndarray
    shading: np.ndarray
    sigma: float
    lamp_x: float
    lamp_y: float
    lamp_r: float
    lamp: np.ndarray
    glow: np.ndarray

    @classmethod
    def draw(cls, size: tuple[int, int], rng: np.random.Generator) -> "_SceneLight":
        """The shading and the lamp's place, drawn from ``rng`` (the lamp a hard disc)."""
        w, h = size
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        shading = np.exp(0.25 * _smooth_noise((h, w), rng, scale=max(8.0, w / 6)))
        sigma = max(1.5, w / 120)
        lamp_r = max(3.0, 0.035 * w)
        lamp_x, lamp_y = w * rng.uniform(0.6, 0.85), h * rng.uniform(0.12, 0.3)
        lamp = ((xx - lamp_x) ** 2 + (yy - lamp_y) ** 2 <= lamp_r * lamp_r).astype(np.float32)
        glow = np.exp(-(((xx - lamp_x) ** 2 + (yy - lamp_y) ** 2) / (2 * (4 * lamp_r) ** 2)))
        return cls(xx, yy, shading, sigma, lamp_x, lamp_y, lamp_r, lamp, glow)


def _illumination_fields(kind: str, light: _SceneLight, rng: np.random.Generator, regions: dict) -> tuple:
    """``(fields, illuminant names, key illuminant)``: the three irradiance planes of a scene kind
    (adds its window to ``regions``)."""
    xx, yy, shading, sigma, lamp, glow = light.xx, light.yy, light.shading, light.sigma, light.lamp, light.glow
    h, w = xx.shape
    if kind == "outdoor":
        illum_names = ("D75", "D50", "D55")
        shadow = soft_mask((xx < w * rng.uniform(0.3, 0.42)).astype(np.float32), sigma * 3)
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
        win = soft_mask(win, sigma)
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
        win = soft_mask(win, sigma)
        fields = [dark * shading + 150.0 * win, glow * 800.0 + 10.0 * glow ** 0.3, lamp * 3.0e4]
        key = "A"
    return fields, illum_names, key


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
