"""The luminance-truth family: absolute scene luminance (cd/m2) over 5 decades, EXIF t / N / ISO, a grey card.

Measurement-grade luminance maps need a bracket whose truth is in cd/m2. A
:func:`luminance_scene` is lit so that its luminance spans 1 .. 1e6 cd/m2: a textured room
(reflectances 0.03-0.9 from the natural texture, :mod:`derender.camera.scene`) under a
horizontal illumination gradient of 3.5 decades, a window (D65 sky, 1e4 .. 1e5 cd/m2) and three
lamps (1e5 .. 1e6 cd/m2, radial profile), and an 18 % grey card (flat spectrum, the
Mallett-Yuksel basis with equal weights) in the room at about 200 cd/m2.

Exposure is photometric, after ISO 12232's saturation-based speed: a neutral of luminance
``L`` reaches the sensor's white level at

    L t S / N^2 = 120 cd s m^-2            (H_sat = 78 / S lx s, H = 0.65 L t / N^2),

so the simulator's exposure of frame j is ``e_j = t_j S_j / N_j^2`` and its truth (linear sRGB
per unit ``e``, ``truth.exr``) has luminance ``L / 120``: the absolute luminance is
``120 (w . truth)`` cd/m2 (``w`` the Rec. 709 row), and Radiance RGB in cd/m2 / 179 units is
``truth * 120 / 179`` (``scene.json``: ``luminance.truth_to_cd_m2``). The JPEGs carry EXIF
``ExposureTime``, ``FNumber`` and ``ISOSpeedRatings`` (with ``SensitivityType`` 3 and ``ISOSpeed``:
a saturation-based speed, :func:`derender.photometry.calibration.sensitivity_rating`):

* ``mode="time"``: f/16, ISO 100, the time alone varies (2 stops a frame from 1/8000 s);
* ``mode="aperture-iso"``: the same exposures ``e_j`` reached with apertures f/4 .. f/16 and ISO
  100 .. 800 drawn per frame (seeded), so the times are out of order against brightness;
* ``mode="flat-field"``: a uniform 50 % grey surface under uniform light (a flat-field bracket
  for ``derender vignetting``).

``falloff`` (the corner transmission, e.g. 0.55) adds lens vignetting ``V(r) = 1 - (1 - c) r^2``
(``r`` over half the diagonal; the sensor signal only, not the truth), recorded in
``scene.json``. Every rendering of :data:`RENDERS` is available: ``gamma`` (a fixed pure
gamma-2.2 camera, the one the issue measured), and the pipeline families of
:mod:`derender.camera.families`; ``gamma``, ``paper`` and ``camera`` are tuning renderings,
``dslr-lut``, ``phone-local`` and ``drift`` held out (:data:`TUNING_RENDERS`).
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "LUMINANCE_MODES",
    "RENDERS",
    "TUNING_RENDERS",
    "SATURATION_EXPOSURE",
    "luminance_scene",
    "radial_falloff",
    "exif_triples",
    "simulate_luminance",
    "truth_luminance_cd_m2",
    "simulate_to_folder_cli",
]

#: Brackets of the family: the time alone, time + aperture + ISO, a flat field.
LUMINANCE_MODES = ("time", "aperture-iso", "flat-field")
#: Renderings: ``gamma`` (fixed pure gamma 2.2) and the pipeline families.
RENDERS = ("gamma", "paper", "camera", "dslr-lut", "phone-local", "drift")
#: Renderings methods may be tuned on; the others are held out.
TUNING_RENDERS = ("gamma", "paper", "camera")
#: L t S / N^2 (cd s m^-2) that brings a neutral to the sensor's white level (ISO 12232: 78 / 0.65).
SATURATION_EXPOSURE = 120.0
_APERTURES = (4.0, 5.6, 8.0, 11.0, 16.0)
_ISOS = (100, 200, 400, 800)


def luminance_scene(size: tuple[int, int] = (192, 128), seed: int = 0, *, flat: bool = False,
                    fisheye: bool = False):
    """The family's :class:`~derender.camera.scene.SpectralScene` (``regions`` records ``grey_card``
    ``[x, y, w, h]``, ``window`` and ``lamps``). ``fisheye``: a 180-degree circular fisheye
    framing, the scene inside the image circle (diameter the shorter side) and black outside,
    as a fisheye lens images it (Radiance view ``-vta -vh 180 -vv 180`` on a square image)."""
    from derender.camera.scene import SpectralScene, soft_mask, texture_rgb
    from derender.camera.spectral import illuminant_spd, reflectance_library

    w, h = int(size[0]), int(size[1])
    if w < 48 or h < 32:
        raise InputError(f"a luminance scene needs at least 48x32 pixels, got {w}x{h}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 28]))
    _, library, groups = reflectance_library()
    idx = np.empty((h, w, 3), dtype=np.int32)
    idx[:] = np.arange(groups["mallett"].start, groups["mallett"].stop, dtype=np.int32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    if flat:
        wts = np.full((h, w, 3), 0.5, np.float32)
        illum = np.full((h, w, 1), 400.0, np.float32)
        regions = {"flat_field": [0, 0, w, h]}
        return SpectralScene(kind="flat-field", library=library, material_index=idx, material_weight=wts,
                             illuminant_names=("D65",), illuminant_spds=illuminant_spd("D65")[None],
                             illumination=illum, key_illuminant="D65", regions=regions)
    tex = texture_rgb((w, h), rng)
    tex = tex.mean(-1, keepdims=True) + 0.5 * (tex - tex.mean(-1, keepdims=True))   # room surfaces: muted colours
    wts = (0.03 + 0.87 * tex).astype(np.float32)
    sigma = max(1.0, w / 150)
    # room: 10^(0.6 .. 4.1) across the width, smooth shading
    room = 10.0 ** (0.6 + 3.5 * xx / (w - 1)) * np.exp(0.15 * np.sin(yy / h * 3.0 + rng.uniform(0, 6)))
    # grey card (18 %, flat) where the room gives ~ 200 cd/m2 / 0.18
    cw, ch = max(10, w // 10), max(10, h // 7)
    cx = int(np.clip(np.rint((np.log10(1100.0) - 0.6) / 3.5 * (w - 1)) - cw // 2, 0, w - cw))
    cy = int(h * rng.uniform(0.62, 0.72))
    wts[cy:cy + ch, cx:cx + cw] = 0.18
    # window: top left, 1e4 .. 1e5 cd/m2 (vertical sky gradient), D65
    wx0, wx1, wy0, wy1 = int(0.06 * w), int(0.36 * w), int(0.08 * h), int(0.50 * h)
    win = np.zeros((h, w), np.float32)
    win[wy0:wy1, wx0:wx1] = 1.0
    win = soft_mask(win, sigma)
    sky = 10.0 ** (5.0 - 1.0 * (yy - wy0) / max(wy1 - wy0, 1))
    wts[wy0:wy1, wx0:wx1] = 0.9                     # a bright, neutral sky seen through the glass
    # lamps: 1e5 .. 1e6 cd/m2 from the rim to the centre
    lamps, lamp_field = [], np.zeros((h, w), np.float32)
    r = max(3.0, 0.07 * w)
    for k, (fx, fy) in enumerate(((0.55, 0.22), (0.75, 0.18), (0.90, 0.35))):
        lx, ly = w * (fx + rng.uniform(-0.02, 0.02)), h * (fy + rng.uniform(-0.03, 0.03))
        d = np.sqrt((xx - lx) ** 2 + (yy - ly) ** 2) / r
        inside = d <= 1.0
        lamp_field = np.where(inside, 10.0 ** (6.0 - d), lamp_field)
        wts[inside] = 0.9
        lamps.append([float(lx), float(ly), float(r)])
    lamp_mask = soft_mask((lamp_field > 0).astype(np.float32), 0.5 * sigma)
    room_part = room * (1.0 - win) * (1.0 - lamp_mask)
    illum = np.stack([room_part, sky * win * (1.0 - lamp_mask), lamp_field * lamp_mask], axis=-1)
    if fisheye:
        rad = min(w, h) / 2.0
        outside = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) > rad * rad
        illum[outside] = 0.0
    regions = {"grey_card": [cx, cy, cw, ch], "grey_card_reflectance": 0.18,
               "window": [wx0, wy0, wx1 - wx0, wy1 - wy0], "lamps": lamps}
    names = ("D50", "D65", "D50")
    spds = np.stack([illuminant_spd(n) for n in names])
    return SpectralScene(kind="luminance", library=library, material_index=idx, material_weight=wts,
                         illuminant_names=names, illuminant_spds=spds,
                         illumination=np.maximum(illum, 0.0).astype(np.float32), key_illuminant="D50",
                         regions=regions)


def radial_falloff(size: tuple[int, int], corner: float) -> np.ndarray:
    """Lens vignetting ``V(r) = 1 - (1 - corner) r^2``, ``r`` over half the diagonal: (H, W)."""
    w, h = int(size[0]), int(size[1])
    if not (0.05 <= corner <= 1.0):
        raise InputError(f"--lens-falloff is the corner transmission in [0.05, 1], got {corner}")
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    return 1.0 - (1.0 - corner) * r2


def _exif_rational(v: float, den: int) -> float:
    f = Fraction(float(v)).limit_denominator(den)
    return f.numerator / f.denominator


def exif_triples(exposures_e: np.ndarray, mode: str, rng: np.random.Generator) -> dict[str, list]:
    """EXIF ``(t, N, S)`` per frame for the target exposures ``e_j = t S / N^2``: f/16, ISO 100 for
    ``time``/``flat-field``; a seeded aperture and ISO per frame for ``aperture-iso``. The times
    are rounded to EXIF rationals and ``e`` recomputed from what the files say."""
    n = len(exposures_e)
    if mode == "aperture-iso":
        fn = [float(_APERTURES[int(rng.integers(len(_APERTURES)))]) for _ in range(n)]
        iso = [int(_ISOS[int(rng.integers(len(_ISOS)))]) for _ in range(n)]
        if n >= 2 and (len(set(fn)) == 1 or len(set(iso)) == 1):
            fn[0], iso[0] = 16.0, 100
            fn[-1], iso[-1] = 4.0, 800
    else:
        fn, iso = [16.0] * n, [100] * n
    t = [_exif_rational(e * N * N / S, 1_000_000) for e, N, S in zip(exposures_e, fn, iso)]
    e = [ti * S / (N * N) for ti, N, S in zip(t, fn, iso)]
    return {"exif_times": t, "fnumbers": fn, "isos": iso, "exposures_tS_N2": e}


def simulate_luminance(*, mode: str = "time", render: str = "gamma", size: tuple[int, int] = (192, 128),
                       exposures: int = 9, stops: float = 2.0, seed: int = 0, falloff: float | None = None,
                       camera: Any = "nikon-d5100", noise: bool = True, progress=None, fisheye: bool = False):
    """A bracket of the luminance family (module docstring): a
    :class:`~derender.camera.bracket.SimulatedBracket` whose ``times`` are ``e_j = t S / N^2``,
    whose truth has luminance ``L / 120`` and whose ``params["luminance"]`` records the EXIF
    triples, the grey card, the meter's spot on it (3 pixels inside its rim, where demosaicing
    and chroma noise reduction keep the card) with its luminance in cd/m2 and the ready
    ``--spot`` text, the falloff and the tuning/held-out role."""
    from derender.camera.bracket import simulate_bracket
    from derender.camera.scene import scene_camera_rgb
    from derender.camera.spectral import load_camera

    if mode not in LUMINANCE_MODES:
        raise InputError(f"unknown luminance mode {mode!r}: choose from {', '.join(LUMINANCE_MODES)}")
    if render not in RENDERS:
        raise InputError(f"unknown luminance rendering {render!r}: choose from {', '.join(RENDERS)}")
    if exposures < 2:
        raise InputError("a luminance bracket needs at least 2 exposures")
    cam = load_camera(camera) if isinstance(camera, str) else camera
    scene = luminance_scene(size, seed, flat=mode == "flat-field", fisheye=fisheye)
    from derender.camera.rendering import fit_xyz_to_camera, white_balance_for
    from derender.core.colorimetry import camera_to_linear_srgb_matrix

    cam_unit = scene_camera_rgb(scene, cam)
    m = camera_to_linear_srgb_matrix(fit_xyz_to_camera(cam))
    y_unit = truth_luminance_cd_m2((cam_unit * white_balance_for(cam, scene.key_illuminant)) @ m.T)
    design = (scene.illumination * scene.material_weight.mean(-1, keepdims=True)).sum(-1)
    if fisheye:   # the scale and the bracket as for the unframed scene (the black corners hold no light)
        design = np.where(design > 0, design, np.nan)
    # scale so that 120 times the truth's luminance (per unit e) is the design luminance in cd/m2
    ok = np.isfinite(design) & (design > 0)
    scale = float(np.median(design[ok] / np.maximum(y_unit[ok], 1e-30)))
    peak_l = float(np.percentile(design[ok], 99.9 if mode != "flat-field" else 50.0))
    e_min = 0.5 * SATURATION_EXPOSURE / peak_l if mode != "flat-field" else 0.05 * SATURATION_EXPOSURE / peak_l
    step = stops if mode != "flat-field" else 1.0
    target = e_min * 2.0 ** (step * np.arange(exposures))
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 2817]))
    ex = exif_triples(target, mode, rng)
    vig = None if falloff is None else radial_falloff(size, float(falloff))
    kwargs = {"family": render} if render != "gamma" else {"pipeline": "fixed", "style": "simple"}
    b = simulate_bracket(cam, size=size, exposures=exposures, seed=seed, scene=scene, noise=noise,
                         exposure=(np.asarray(ex["exposures_tS_N2"]), scale), falloff=vig, progress=progress,
                         **kwargs)
    lum = truth_luminance_cd_m2(b.truth_linear_srgb)
    card = scene.regions.get("grey_card") or [0, 0, size[0], size[1]]
    inset = 3 if mode != "flat-field" else 0          # the meter's spot stays off the card's blurred rim
    spot = [card[0] + inset, card[1] + inset, card[2] - 2 * inset, card[3] - 2 * inset]
    x, y, cw, ch = spot
    b.params["luminance"] = ex | {
        "mode": mode, "render": render, "framing": "fisheye -vta -vh 180 -vv 180" if fisheye else "rectilinear", "role": "tuning" if render in TUNING_RENDERS else "held-out",
        "truth_to_cd_m2": SATURATION_EXPOSURE,
        "truth": "absolute luminance = 120 * (0.2126 R + 0.7152 G + 0.0722 B) of truth.exr, cd/m2; Radiance RGB "
                 "= truth * 120 / 179; exposures e = t S / N^2 (ISO 12232 saturation: L e = 120 at white)",
        "grey_card": [int(v) for v in card], "spot": [int(v) for v in spot],
        "spot_cd_m2": float(lum[y:y + ch, x:x + cw].mean()),
        "spot_option": f"{x},{y},{cw},{ch}={float(lum[y:y + ch, x:x + cw].mean()):.6g}",
        "luminance_range_cd_m2": [float(lum.min()), float(lum.max())],
        "falloff_corner": None if falloff is None else float(falloff),
        "falloff_model": None if falloff is None else "V(r) = 1 - (1 - corner) r^2, r over half the diagonal",
    }
    return b


def truth_luminance_cd_m2(truth_linear_srgb: np.ndarray) -> np.ndarray:
    """Absolute luminance (cd/m2) of a luminance-family truth (Rec. 709 weights)."""
    from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709

    return SATURATION_EXPOSURE * (np.asarray(truth_linear_srgb, dtype=np.float64) @ LUMINANCE_WEIGHTS_REC709)


def simulate_to_folder_cli(outdir, *, mode: str | None, render: str, size: tuple[int, int], exposures: int,
                           stops: float | None, seed: int, camera: Any, falloff: float | None) -> None:
    """``derender simulate OUTDIR --luminance MODE [--lens-falloff C]``: check the options, simulate, write."""
    from pathlib import Path

    import typer

    from derender.camera.bracket import write_bracket

    if mode is None:
        raise InputError("--lens-falloff needs --luminance (time | aperture-iso | flat-field)")
    if mode not in LUMINANCE_MODES:
        raise InputError(f"--luminance must be one of {', '.join(LUMINANCE_MODES)}, got {mode!r}")
    render = "gamma" if render == "simple" else render
    if render not in RENDERS:
        raise InputError(f"--render with --luminance must be one of {', '.join(RENDERS)}, got {render!r}")
    if not 2 <= exposures <= 64:
        raise InputError("--exposures must be between 2 and 64 with --luminance")
    if falloff is not None:
        radial_falloff(size, falloff)                  # checks the range before any work
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"{outdir} exists and is not a folder")
    b = simulate_luminance(mode=mode, render=render, size=size, exposures=exposures,
                           stops=2.0 if stops is None else float(stops), seed=seed, falloff=falloff, camera=camera)
    outdir.mkdir(parents=True, exist_ok=True)
    params = write_bracket(b, outdir)
    lum = params["luminance"]
    typer.echo(f"wrote {exposures} DNG + JPEG exposures (EXIF t, N, ISO), truth.exr and scene.json to {outdir}; "
               f"luminance {lum['luminance_range_cd_m2'][0]:.3g}..{lum['luminance_range_cd_m2'][1]:.3g} cd/m2, "
               f"grey-card spot --spot {lum['spot_option']} ({lum['role']} rendering {render})")
