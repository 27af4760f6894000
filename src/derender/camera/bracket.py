"""Brackets from the simulator: exposure times, noisy mosaics, in-camera renderings, files with truth.

:func:`simulate_bracket` chooses the exposure times (:func:`bracket_times`), exposes the
scene's camera RGB onto Bayer mosaics with noise (:mod:`derender.camera.sensor`), renders
each frame in camera (:mod:`derender.camera.rendering`, per-exposure pipeline settings) and
keeps the exact truth; :func:`write_bracket` writes ``raw/NN.dng`` (with the sensor's true
NoiseProfile), ``jpeg/NN.jpg`` (EXIF
``ExposureTime``), ``truth.exr`` and ``scene.json``. See :mod:`derender.camera` for the
pipelines and rendering styles.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any, Callable

import numpy as np

from derender.camera.rendering import (
    RenderSettings,
    camera_rgb_from_mosaic,
    fit_xyz_to_camera,
    isp_render,
    pipeline_settings,
    white_balance_for,
)
from derender.camera.scene import SpectralScene, make_scene, scene_camera_rgb
from derender.camera.sensor import CFA_PATTERN, expose_mosaic, mosaic_signal
from derender.camera.spectral import (
    WAVELENGTHS,
    CameraSpectral,
    load_camera,
)
from derender.camera.stages import FrameSettings, prepare_frame, render_frame, settings_from_dict, settings_to_dict
from derender.core.colorimetry import camera_to_linear_srgb_matrix
from derender.core.errors import InputError

__all__ = [
    "SimulatedBracket",
    "bracket_times",
    "simulate_bracket",
    "write_jpeg",
    "write_bracket",
    "load_scene_json",
    "load_frame_settings",
    "bracket_paths",
    "simulate_to_folder",
]


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
    frames: list[FrameSettings] = field(default_factory=list)   # every parameter of every frame
    family: str | None = None          # pipeline family (derender.camera.families) or None
    motion_zones: np.ndarray | None = None   # (H, W) uint8 static/swept/object (derender.camera.motion)


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


def _bracket_params(*, camera, scene, seed: int, size: tuple[int, int], pipeline: str, style: str, tone_curve: bool,
                    noise: bool, times, scale: float, peak_percentile: float, xyz_to_camera, camera_to_srgb,
                    wb_true, wb_preset, family, settings, frames, plan, motion) -> tuple[dict, Any]:
    """What :func:`simulate_bracket` records of a bracket (``scene.json``), and the motion zones."""
    params = {
        "generator": "derender.camera.simulate_bracket",
        "seed": int(seed),
        "camera": {"name": camera.name, "make": camera.make, "model": camera.model, "source": camera.source,
                   "bits": camera.bits, "black_level": camera.black_level, "white_level": camera.white_level,
                   "full_well_electrons": camera.full_well, "read_noise_dn": camera.read_noise,
                   "cfa_pattern": CFA_PATTERN},
        "scene": {"kind": scene.kind, "size": list(size), "illuminants": list(scene.illuminant_names),
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
        "family": family,
        "exposures": ([asdict(s) | {"exponent": s.exponent} for s in settings] if family is None
                      else [settings_to_dict(f) for f in frames]),
        "frames": [settings_to_dict(f) for f in frames],
        "truth": "linear sRGB (Rec. 709, D65) per second: camera_to_linear_srgb @ (wb_as_shot * camera_rgb), "
                 "noise-free, unclipped",
    }
    zones = None
    if plan is not None:
        from derender.camera.motion import motion_zones

        zones = motion_zones(plan)
        params["motion"] = {"objects": int(motion.objects), "radius_px": plan.radius, "travel": float(motion.travel),
                            "shake_px": int(motion.shake), "canvas_margin": plan.margin,
                            "reference": plan.reference, "shifts_dy_dx": plan.shifts.tolist(),
                            "object_paths_yx": plan.paths.tolist(),
                            "truth": "the reference frame's instant, on its pixel grid; scene regions are in "
                                     "canvas coordinates (frame = canvas shifted by margin + shift)"}
    return params, zones


def simulate_bracket(
    camera: CameraSpectral | str = "nikon-d5100",
    *, kind: str = "outdoor",
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
    family: str | None = None,
    motion=None,
    exposure: tuple[np.ndarray, float] | None = None,
    falloff: np.ndarray | None = None,
) -> SimulatedBracket:
    """Simulate a bracket: spectral scene -> noisy RAW mosaics -> in-camera 8-bit renderings.

    ``wb_preset`` (a CIE illuminant name, e.g. ``"D65"`` for a daylight preset) makes the
    JPEG engine white-balance for that illuminant instead of the scene's, as a camera set
    to a fixed white-balance mode does (the mode :func:`derender.chart.chart_pairs` uses).
    ``peak_percentile`` is passed to :func:`bracket_times` (100: the shortest exposure keeps
    the whole scene below 60 % of white in RAW).

    ``family`` (one of :data:`derender.camera.families.FAMILIES`) overrides ``pipeline``,
    ``style`` and ``tone_curve``: ``"paper"`` and ``"camera"`` give byte for byte the codes of
    ``style="simple"`` / ``style="camera"`` with ``pipeline="auto"``. Every frame's parameters
    are in ``frames`` (and ``scene.json``'s ``"frames"``).

    ``motion`` (a :class:`derender.camera.motion.MotionSpec`): objects move and the camera
    shakes between the exposures; the truth is the reference frame's instant on its pixel
    grid, ``motion_zones`` (H, W) labels its pixels static / swept / object and
    ``params["motion"]`` records the shifts and paths (:mod:`derender.camera.motion`). The
    scene is then rendered on a canvas larger by the motion's margin on every side.

    ``exposure = (times, scale)`` replaces :func:`bracket_times` (the luminance family,
    :mod:`derender.camera.luminance`, sets its exposures from EXIF t S / N^2); ``falloff``
    (H, W) multiplies the sensor signal (lens vignetting) but not the truth.

    Parameters
    ----------
    camera : str or CameraSpectral
        A camera of the spectral library by name, a rawtoaces JSON file
        (:func:`~derender.camera.spectral.load_camera`), or a loaded camera.
    kind : str
        The scene: ``"outdoor"``, ``"indoor"`` or ``"night"``
        (:data:`~derender.camera.scene.SCENE_KINDS`).
    size : (int, int)
        Width and height in pixels (at least 32x32).
    exposures : int
        Frames in the bracket.
    pipeline : str
        ``"auto"`` (per-frame auto exposure, white balance and gamma) or ``"fixed"``.
    style : str
        Rendering style (:data:`~derender.camera.stages.STYLES`).
    seed : int
        Seeds the scene, the rendering parameters and the noise.
    tone_curve : bool
        Apply a tone curve after the gamma.
    stops : float, optional
        Stops between exposures (default: the bracket spans the scene).
    noise : bool
        Photon and read noise in the mosaics.
    scene : SpectralScene, optional
        A scene instead of ``kind``.
    wb_preset : str, optional
        A fixed white-balance preset (above).
    progress : callable, optional
        ``progress(done, total)`` after each frame.
    peak_percentile : float
        The scene percentile that sets the shortest exposure (above).
    family : str, optional
        A pipeline family (above).
    motion : MotionSpec, optional
        Moving objects and camera shake (above).
    exposure : (array, float), optional
        Exposure times and scene scale (above).
    falloff : numpy.ndarray, optional
        (H, W) lens falloff (above).

    Returns
    -------
    SimulatedBracket
        ``jpeg_codes`` (N, H, W, 3) uint8, ``mosaics`` (N, H, W) uint16, ``times`` (N,)
        seconds, ``truth_linear_srgb`` (H, W, 3) float32 radiance per second, the camera's
        matrices and white balance, and every frame's parameters.

    Raises
    ------
    InputError
        An unknown camera, scene kind, pipeline, style or family, a size below 32x32, fewer
        than one exposure, inconsistent ``exposure`` or ``scene``.

    Examples
    --------
    A 32x32 bracket of three frames in the ``paper`` family (paper 1's eq. 4), merged:

    >>> import numpy as np
    >>> import derender
    >>> bracket = derender.simulate_bracket(size=(32, 32), exposures=3, family="paper", seed=0)
    >>> bracket.jpeg_codes.shape, bracket.jpeg_codes.dtype, bracket.mosaics.shape
    ((3, 32, 32, 3), dtype('uint8'), (3, 32, 32))
    >>> bracket.truth_linear_srgb.shape, bool(np.all(np.diff(bracket.times) > 0))
    ((32, 32, 3), True)
    >>> stack = derender.Stack(bracket.jpeg_codes / 255, bracket.times)
    >>> derender.merge(stack, "debevec").radiance.shape
    (32, 32, 3)
    """
    if family is not None:
        from derender.camera.families import check_family

        check_family(family)
    if exposures < 1:
        raise InputError("--exposures must be at least 1")
    if isinstance(camera, str):
        camera = load_camera(camera)
    ss = np.random.SeedSequence(int(seed))
    rng_pipe, rng_noise = (np.random.default_rng(s) for s in ss.spawn(2))
    plan = frames_unit = None
    if motion is not None:
        from derender.camera.motion import compose_frames, plan_motion

        plan = plan_motion(motion, exposures, size, seed)
        canvas_size = (int(size[0]) + 2 * plan.margin, int(size[1]) + 2 * plan.margin)
        if scene is None:
            scene = make_scene(kind, canvas_size, seed)
        elif scene.shape != (canvas_size[1], canvas_size[0]):
            raise InputError(f"a scene for a moving bracket must be {canvas_size[0]}x{canvas_size[1]} (the margin)")
        frames_unit = compose_frames(scene_camera_rgb(scene, camera), plan)
        cam_unit = frames_unit[plan.reference]
    else:
        if scene is None:
            scene = make_scene(kind, size, seed)
        cam_unit = scene_camera_rgb(scene, camera)
    if exposure is None:
        times, scale = bracket_times(cam_unit, exposures, stops=stops, peak_percentile=peak_percentile)
    else:
        times, scale = np.asarray(exposure[0], dtype=np.float64), float(exposure[1])
        if times.shape != (exposures,):
            raise InputError(f"exposure times {times.shape} do not match exposures={exposures}")
    cam_per_s = cam_unit * scale
    xyz_to_camera = fit_xyz_to_camera(camera)
    camera_to_srgb = camera_to_linear_srgb_matrix(xyz_to_camera)
    wb_true = white_balance_for(camera, scene.key_illuminant)
    truth = (cam_per_s * wb_true) @ camera_to_srgb.T
    wb_render = wb_true if wb_preset is None else white_balance_for(camera, wb_preset)
    if family is None:
        settings = pipeline_settings(pipeline, exposures, wb_render, style, rng_pipe, tone_curve)
        frames = [FrameSettings.from_render_settings(s, wb_true, camera_to_srgb) for s in settings]
    else:
        from derender.camera.families import family_settings

        frames = family_settings(family, exposures, rng_pipe, wb_render, wb_true, camera_to_srgb)
        pipeline = "auto" if family in ("paper", "camera") else family
        style = frames[0].style
        tone_curve = False
    vig = 1.0 if falloff is None else np.asarray(falloff, dtype=np.float64)[..., None]
    signal = mosaic_signal(cam_per_s * vig) if frames_unit is None else None
    h, w = cam_unit.shape[:2]
    mosaics = np.empty((exposures, h, w), dtype=np.uint16)
    codes = np.empty((exposures, h, w, 3), dtype=np.uint8)
    noise_rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(rng_noise.integers(2**63)).spawn(exposures)]
    if family is not None:
        settings = [f.render_settings() if f.style in ("simple", "camera") else f for f in frames]
    for j, t in enumerate(times):
        sig = signal if frames_unit is None else mosaic_signal(frames_unit[j] * scale * vig)
        mosaics[j] = expose_mosaic(sig, camera, float(t), noise_rngs[j] if noise else None)
        if family is None:
            codes[j] = isp_render(mosaics[j], camera, camera_to_srgb, settings[j])
        else:
            rgb = camera_rgb_from_mosaic(mosaics[j], camera)
            frames[j] = prepare_frame(frames[j], rgb)
            codes[j] = render_frame(rgb, frames[j])
        if progress is not None:
            progress(j + 1, exposures)
    params, zones = _bracket_params(camera=camera, scene=scene, seed=seed, size=(w, h), pipeline=pipeline,
                                    style=style, tone_curve=tone_curve, noise=noise, times=times, scale=scale,
                                    peak_percentile=peak_percentile, xyz_to_camera=xyz_to_camera,
                                    camera_to_srgb=camera_to_srgb, wb_true=wb_true, wb_preset=wb_preset,
                                    family=family, settings=settings, frames=frames, plan=plan, motion=motion)
    return SimulatedBracket(camera=camera, scene=scene, times=times, mosaics=mosaics, jpeg_codes=codes,
                            settings=settings, truth_linear_srgb=truth.astype(np.float32),
                            camera_rgb_per_s=cam_per_s, xyz_to_camera=xyz_to_camera, wb_true=wb_true,
                            camera_to_srgb=camera_to_srgb, params=params, frames=frames, family=family,
                            motion_zones=zones)


# --------------------------------------------------------------------------- files
def write_jpeg(path: str | os.PathLike, codes: np.ndarray, exposure_time: float, make: str, model: str, *,
               quality: int = 95, fnumber: float | None = None, iso: int | None = None,
               sensitivity_type: int | None = None) -> Path:
    """Write 8-bit RGB codes as a JPEG (4:2:2, like most cameras) with EXIF Make/Model/ExposureTime
    (and ``FNumber`` / ``ISOSpeedRatings`` when given; ``sensitivity_type``: EXIF 2.3's
    ``SensitivityType``, 3 for an ISO speed from saturation, which then also goes to ``ISOSpeed``)."""
    from PIL import Image, TiffImagePlugin

    from derender.io.files import atomic_output

    img = Image.fromarray(np.ascontiguousarray(codes), mode="RGB")
    exif = Image.Exif()
    exif[0x010F] = make
    exif[0x0110] = model
    exif[0x0131] = "derender simulator"
    f = Fraction(float(exposure_time)).limit_denominator(1_000_000)
    exif.get_ifd(0x8769)[0x829A] = TiffImagePlugin.IFDRational(f.numerator, f.denominator)
    if fnumber is not None:
        fn = Fraction(float(fnumber)).limit_denominator(1000)
        exif.get_ifd(0x8769)[0x829D] = TiffImagePlugin.IFDRational(fn.numerator, fn.denominator)
    if iso is not None:
        exif.get_ifd(0x8769)[0x8827] = int(iso)
    if sensitivity_type is not None:
        exif.get_ifd(0x8769)[0x8830] = int(sensitivity_type)
        if int(sensitivity_type) == 3 and iso is not None:
            exif.get_ifd(0x8769)[0x8833] = int(iso)
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
    lum = bracket.params.get("luminance") or {}
    span = float(cam.white_level - cam.black_level)
    noise_profile = (1.0 / cam.full_well, (cam.read_noise ** 2 + 1.0 / 12.0) / span ** 2)   # S, O of x
    for j, t in enumerate(bracket.times):
        t_exif = float(lum["exif_times"][j]) if lum else float(t)
        dng = write_dng(outdir / "raw" / f"{j:02d}.dng", bracket.mosaics[j], cfa_pattern=CFA_PATTERN,
                        black_level=cam.black_level, white_level=cam.white_level,
                        xyz_to_camera=bracket.xyz_to_camera, as_shot_neutral=neutral, exposure_time=t_exif,
                        make=cam.make, model=cam.model, bits=cam.bits, noise_profile=noise_profile,
                        fnumber=lum["fnumbers"][j] if lum else None, iso=lum["isos"][j] if lum else None,
                        sensitivity_type=3 if lum else None)      # the sensor's white is the ISO's saturation
        jpg = write_jpeg(outdir / "jpeg" / f"{j:02d}.jpg", bracket.jpeg_codes[j],
                         t_exif, cam.make, cam.model, quality=jpeg_quality,
                         fnumber=lum["fnumbers"][j] if lum else None, iso=lum["isos"][j] if lum else None,
                         sensitivity_type=3 if lum else None)     # the family's ISO follows saturation
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


def load_frame_settings(outdir: str | os.PathLike | dict) -> list[FrameSettings]:
    """Every frame's :class:`~derender.camera.stages.FrameSettings` from ``scene.json`` (a folder or
    its parsed dict): with :func:`derender.camera.stages.render_frame` they re-render the
    bracket's codes from its mosaics exactly. Older files without ``"frames"`` are read from
    their ``"exposures"``."""
    params = outdir if isinstance(outdir, dict) else load_scene_json(outdir)
    if "frames" in params:
        return [settings_from_dict(d) for d in params["frames"]]
    keys = ("wb", "gain", "gamma", "saturation", "style", "tone_curve")
    return [FrameSettings.from_render_settings(RenderSettings(**{k: e[k] for k in keys if k in e}),
                                               params["wb_as_shot"], params["camera_to_linear_srgb"])
            for e in params["exposures"]]


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


_ = WAVELENGTHS  # re-exported for users of the simulator
