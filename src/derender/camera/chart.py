"""Calibration pairs for de-rendering models (paper 2, Sec. 4): a simulated chart session.

Paper 2 photographs a 140-patch ColorChecker SG under a tungsten lamp filtered by 16 gels,
at exposures from all-black to all-white, in RAW+JPEG, and averages RAW and JPEG values
per patch. :func:`chart_pairs` does the same with the camera simulator:

* reflectances: the 140 ColorChecker SG patches, spectra recovered from colour-science's
  published chromaticities (``CCS_COLOURCHECKERS['ColorCheckerSG - After November 2014']``,
  D50) with Otsu et al. (2018) reflectance recovery;
* illuminants: CIE A (tungsten) bare, through 5 colour-temperature-blue gels and through 10
  coloured gels (:func:`gel_illuminants`);
* exposures: ``n_exposures`` (22 as in the paper) log-spaced from nearly black to all-white
  (:func:`chart_exposures`);
* each exposure of the chart is a noisy Bayer mosaic rendered by the camera's JPEG engine
  (fixed pipeline, daylight white-balance preset as a camera set to a fixed WB would);
  RAW and JPEG are averaged over each patch's core: patches are 16 px with a 1 px black
  margin, and only pixels at least ``core`` = 4 px inside a patch count. Bilinear
  demosaicking (1 px) and the JPEG engine's 7x7 chroma blur (3 px) mix the black margin
  into the pixels next to it; the previous 8 px patches averaged over their 6x6 interior
  had JPEG codes up to ~15 % too dark, so a GP trained on them over-predicted RAW on
  ordinary scene pixels by +0.17..+0.21 in log (nikon-d5100, 12 simulated brackets);
* the RAW value stored is the *unclipped* linear camera RGB of the patch (the paper
  replaces saturated RAW values by extrapolation from shorter exposures; the simulator knows
  the exact value), in camera space without white balance ("white balance fixed").

The result has 140 x 16 x 22 = 49,280 pairs, within the paper's 30,000-50,000.

``family`` (one of :data:`derender.camera.families.FAMILIES`) renders the chart JPEGs
through that pipeline family instead: one camera is drawn per family from the seed
(:func:`derender.camera.families.family_settings` with the chart's ``n_exposures`` as the
bracket, the daylight preset as the render white balance) and exposure ``e`` of every
illuminant is rendered with frame ``e``'s settings (:func:`derender.camera.stages.render_frame`;
``phone-local`` frames get their gain map from the chart frame itself). ``"paper"`` and
``"camera"`` are the fixed pipelines of ``style="simple"`` / ``style="camera"``, byte for
byte. The RAW side (the truth) and the noise are the same for every family.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from derender.camera.spectral import WAVELENGTHS, CameraSpectral, illuminant_spd, load_camera
from derender.core.errors import InputError

__all__ = [
    "PAIRS_FORMAT",
    "PAIRS_VERSION",
    "colorchecker_sg_reflectances",
    "gel_illuminants",
    "chart_exposures",
    "ChartPairs",
    "chart_pairs",
    "save_pairs",
    "load_pairs",
]


#: ``format`` field of a pairs ``.npz`` file (:func:`save_pairs`, :func:`load_pairs`).
PAIRS_FORMAT = "derender-pairs"


#: ``format_version`` field of a pairs ``.npz`` file.
PAIRS_VERSION = 1


@functools.lru_cache(maxsize=None)
def colorchecker_sg_reflectances() -> np.ndarray:
    """(140, n_wl) reflectances of the ColorChecker SG (Otsu 2018 recovery from its xyY, D50)."""
    import colour

    cc = colour.CCS_COLOURCHECKERS["ColorCheckerSG - After November 2014"]
    xyy = np.array(list(cc.data.values()), dtype=np.float64)
    xyz = colour.xyY_to_XYZ(xyy)
    out = []
    for x in xyz:
        sd = colour.XYZ_to_sd(x, method="Otsu 2018", illuminant=colour.SDS_ILLUMINANTS["D50"])
        out.append(np.interp(WAVELENGTHS, np.asarray(sd.wavelengths), np.asarray(sd.values)))
    return np.clip(np.stack(out), 0.005, 1.0)


def gel_illuminants(n: int = 16, seed: int = 0) -> np.ndarray:
    """(n, n_wl) spectra: CIE A (tungsten) through ``n`` gel filters (Y = 1).

    The first is the bare lamp; the next five are colour-temperature-blue gels of rising
    strength (transmission ``exp(-s (lambda - 380) / 400)``, s up to 2.2, which takes the
    lamp to about daylight and beyond, so that neutral colours under daylight-like light
    are covered); the rest are coloured gels: two Gaussian pass bands plus a floor,
    drawn from a seeded generator.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    lamp = illuminant_spd("A")
    from derender.camera.spectral import cmfs_xyz

    ybar = cmfs_xyz()[:, 1]
    wl = WAVELENGTHS
    filters = [np.ones(wl.size)]
    for strength in np.linspace(0.5, 2.2, 5):
        filters.append(np.exp(-strength * (wl - 380.0) / 400.0))
    while len(filters) < n:
        t = np.full(wl.size, rng.uniform(0.02, 0.2))
        for _ in range(2):
            centre = rng.uniform(400, 700)
            width = rng.uniform(25, 90)
            t += rng.uniform(0.3, 1.0) * np.exp(-0.5 * ((wl - centre) / width) ** 2)
        filters.append(np.clip(t, 0, 1))
    out = [lamp * f for f in filters[:n]]
    return np.stack([spd / float(ybar @ spd) for spd in out])


def chart_exposures(n: int = 22) -> np.ndarray:
    """Relative exposures of the session: 2^-7 .. 2^4.5 of the white-patch exposure, log-spaced.

    At the shortest the white patch renders near code 40 and the darkest patches at 0-2
    (a nearly black frame); at the longest every patch is clipped (an all-white frame).
    """
    return np.logspace(-7 * np.log10(2.0), 4.5 * np.log10(2.0), n)


@dataclass
class ChartPairs:
    """RAW/JPEG colour pairs: ``jpeg`` (N, 3) uint8, ``raw`` (N, 3) linear camera RGB (unclipped)."""

    jpeg: np.ndarray
    raw: np.ndarray
    illuminant: np.ndarray   # (N,) index of the illuminant
    exposure: np.ndarray     # (N,) index of the exposure
    patch: np.ndarray        # (N,) index of the patch
    out_of_gamut: np.ndarray  # (N,) bool: linear sRGB of the white-balanced colour has a negative component
    camera: str
    make: str
    model: str
    camera_to_srgb: np.ndarray  # (3, 3) for white-balanced camera RGB
    wb: np.ndarray               # (3,) the in-camera white balance used
    family: str | None = None    # pipeline family of the JPEGs (None: ``style``'s fixed pipeline)


def chart_pairs(camera: CameraSpectral | str = "nikon-d5100", *, n_illuminants: int = 16, n_exposures: int = 22,
                style: str = "camera", patch_px: int = 16, seed: int = 0, core: int = 4,
                progress: Callable[[int, int], None] | None = None, family: str | None = None) -> ChartPairs:
    """Simulate the paper-2 calibration session for one camera (see module doc; ``family``
    overrides ``style``)."""
    from derender.camera import (
        CFA_PATTERN,
        RenderSettings,
        camera_rgb_from_mosaic,
        expose_mosaic,
        fit_xyz_to_camera,
        isp_render,
        mosaic_signal,
        white_balance_for,
    )
    from derender.camera.stages import prepare_frame, render_frame
    from derender.core.colorimetry import camera_to_linear_srgb_matrix

    frames = None
    if family is not None:
        from derender.camera.families import FAMILIES, check_family

        check_family(family)
        if family in ("paper", "camera"):
            style = "simple" if family == "paper" else "camera"
    if isinstance(camera, str):
        camera = load_camera(camera)
    if n_illuminants < 1 or n_exposures < 2:
        raise InputError("need at least 1 illuminant and 2 exposures")
    refl = colorchecker_sg_reflectances()
    illums = gel_illuminants(n_illuminants, seed)
    xyz_to_cam = fit_xyz_to_camera(camera)
    cam_to_srgb = camera_to_linear_srgb_matrix(xyz_to_cam)
    wb = white_balance_for(camera, "D65")  # daylight preset
    settings = RenderSettings(wb=[float(v) for v in wb], style=style)
    if family is not None and family not in ("paper", "camera"):
        from derender.camera.families import family_settings

        # one camera per family (its own stream: the noise stays that of the other families)
        rng_fam = np.random.default_rng(np.random.SeedSequence([int(seed), 13, list(FAMILIES).index(family)]))
        frames = family_settings(family, n_exposures, rng_fam, wb, wb, cam_to_srgb)
    n_patch = refl.shape[0]
    fill, pidx = _chart_layout(n_patch, patch_px, core)
    h, w = fill.shape
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
    exposures = chart_exposures(n_exposures)
    jpeg_rows, raw_rows, il_rows, ex_rows, pa_rows = [], [], [], [], []
    valid = pidx >= 0
    flat_idx = pidx[valid]
    counts = np.bincount(flat_idx, minlength=n_patch).astype(np.float64)
    for k, spd in enumerate(illums):
        cam = (refl * spd) @ camera.sensitivities           # (140, 3) per unit exposure
        white = float((spd @ camera.sensitivities).max())   # perfect white's largest channel
        cam = cam / white
        img = np.zeros((h, w, 3))
        img[fill >= 0] = cam[fill[fill >= 0]]
        signal = mosaic_signal(img, CFA_PATTERN)
        for e, t in enumerate(exposures):
            mosaic = expose_mosaic(signal, camera, float(t), rng)
            if frames is None:
                codes = isp_render(mosaic, camera, cam_to_srgb, settings)
            else:
                rgb = camera_rgb_from_mosaic(mosaic, camera)
                codes = render_frame(rgb, prepare_frame(frames[e], rgb))
            jpeg_rows.append(_patch_codes(codes, valid, flat_idx, counts))
            raw_rows.append(cam * t)
            il_rows.append(np.full(n_patch, k))
            ex_rows.append(np.full(n_patch, e))
            pa_rows.append(np.arange(n_patch))
        if progress is not None:
            progress(k + 1, len(illums))
    raw = np.concatenate(raw_rows)
    srgb = (raw * wb) @ cam_to_srgb.T
    return ChartPairs(
        jpeg=np.concatenate(jpeg_rows), raw=raw, illuminant=np.concatenate(il_rows),
        exposure=np.concatenate(ex_rows), patch=np.concatenate(pa_rows),
        out_of_gamut=np.any(srgb < -1e-6 * np.maximum(srgb.max(axis=1, keepdims=True), 1e-12), axis=1),
        camera=camera.name, make=camera.make, model=camera.model, camera_to_srgb=cam_to_srgb, wb=wb, family=family,
    )


def _chart_layout(n_patch: int, patch_px: int, core: int) -> tuple[np.ndarray, np.ndarray]:
    """The chart image's patch index per pixel, 14 patches a row of ``patch_px`` pixels: ``fill``
    (-1 in the 1 px black margin between patches) and ``pidx`` (-1 but ``core`` px inside a patch)."""
    cols = 14
    rows = int(np.ceil(n_patch / cols))
    p = int(patch_px)
    if p < 4:
        raise InputError("patch_px must be at least 4")
    if not 1 <= int(core) < p // 2:
        raise InputError("core must be in 1 .. patch_px // 2 - 1")
    h, w = rows * p, cols * p
    # per-pixel patch index (1 px black margin between patches); only pixels at least ``core`` px
    # inside a patch are averaged: bilinear demosaicking (1 px) and the 7x7 chroma blur (3 px) mix
    # the black margin into the pixels next to it (codes up to ~15 % too dark at 8 px / core 1)
    fill = -np.ones((h, w), dtype=np.int64)
    for i in range(n_patch):
        r, c = divmod(i, cols)
        fill[r * p + 1:(r + 1) * p - 1, c * p + 1:(c + 1) * p - 1] = i
    inner = np.zeros((h, w), dtype=bool)
    for i in range(n_patch):
        r, c = divmod(i, cols)
        inner[r * p + core:(r + 1) * p - core, c * p + core:(c + 1) * p - core] = True
    return fill, np.where(inner, fill, -1)


def _patch_codes(codes: np.ndarray, valid: np.ndarray, flat_idx: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Each patch's mean code (rounded, uint8 (n_patch, 3)) over its ``valid`` core pixels, whose patch
    indices are ``flat_idx`` and per-patch numbers ``counts``."""
    n_patch = counts.shape[0]
    sums = np.stack([np.bincount(flat_idx, weights=codes[..., c][valid].astype(np.float64), minlength=n_patch)
                     for c in range(3)], axis=1)
    return np.clip(np.rint(sums / counts[:, None]), 0, 255).astype(np.uint8)


def save_pairs(pairs: ChartPairs, path: str | os.PathLike) -> Path:
    """Write pairs as ``.npz`` (arrays ``jpeg`` uint8 and ``raw`` float plus metadata), atomically."""
    from derender.io.files import atomic_output

    path = Path(path)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, format=np.array(PAIRS_FORMAT), format_version=np.array(PAIRS_VERSION),
                jpeg=pairs.jpeg, raw=pairs.raw.astype(np.float64), illuminant=pairs.illuminant,
                exposure=pairs.exposure, patch=pairs.patch, out_of_gamut=pairs.out_of_gamut,
                camera=np.array(pairs.camera), make=np.array(pairs.make), model=np.array(pairs.model),
                camera_to_srgb=pairs.camera_to_srgb, wb=pairs.wb, family=np.array(pairs.family or ""),
            )
    return path


def load_pairs(path: str | os.PathLike) -> ChartPairs:
    """Read a pairs ``.npz``; needs at least ``jpeg`` (N,3) uint8 and ``raw`` (N,3) finite floats."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such pairs file: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"not a readable pairs .npz file: {path} ({type(exc).__name__})") from None
    if "jpeg" not in data or "raw" not in data:
        raise InputError(f"{path}: a pairs file needs arrays 'jpeg' and 'raw'")
    jpeg, raw = data["jpeg"], data["raw"]
    if jpeg.ndim != 2 or jpeg.shape[1] != 3 or raw.shape != jpeg.shape:
        raise InputError(f"{path}: 'jpeg' and 'raw' must both be (N, 3), got {jpeg.shape} and {raw.shape}")
    if not np.issubdtype(raw.dtype, np.number) or not np.all(np.isfinite(raw)):
        raise InputError(f"{path}: 'raw' holds NaN or inf values")
    if jpeg.dtype != np.uint8:
        if not np.all(np.isfinite(jpeg)) or jpeg.min() < 0 or jpeg.max() > 255:
            raise InputError(f"{path}: 'jpeg' must hold 8-bit codes 0..255")
        jpeg = np.rint(jpeg).astype(np.uint8)
    n = jpeg.shape[0]

    def get(key, default):
        return data[key] if key in data else default

    return ChartPairs(
        jpeg=jpeg, raw=raw.astype(np.float64), illuminant=get("illuminant", np.zeros(n, int)),
        exposure=get("exposure", np.zeros(n, int)), patch=get("patch", np.arange(n)),
        out_of_gamut=get("out_of_gamut", np.zeros(n, bool)).astype(bool), camera=str(get("camera", "")),
        make=str(get("make", "")), model=str(get("model", "")), camera_to_srgb=get("camera_to_srgb", np.eye(3)),
        wb=get("wb", np.ones(3)), family=str(get("family", "")) or None,
    )
