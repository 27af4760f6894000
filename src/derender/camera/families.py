"""Families of in-camera pipelines: tune methods on some, report them on held-out others.

:data:`FAMILIES` names each family with a one-line description; :func:`family_settings`
draws a bracket's per-frame :class:`~derender.camera.stages.FrameSettings` from a seeded
generator (one "camera" per seed: its gamut map, curves, ... and the frame-to-frame changes).

* ``paper``: paper 1's eq. 4 (``simple`` style, ``auto`` pipeline), bit-identical to
  ``simulate_bracket(style="simple", pipeline="auto")``.
* ``camera``: the filmic picture style with the ``auto`` pipeline, bit-identical to
  ``simulate_bracket()``'s default.
* ``dslr-lut``: a DSLR JPEG engine after Kim et al. (PAMI 2012, "A new in-camera imaging
  model for color computer vision"): white balance inside the 3x3 colour transform, then
  hue-dependent saturation (``s0`` ~ U(1.0, 1.25), first/second hue harmonics up to 0.15), a
  smooth non-linear 3D gamut map (6 Gaussian RBFs with random centres and amplitudes over
  ``sqrt(linear)``, tabulated on a 17^3 LUT, trilinear; neutrals kept neutral, slope
  <= 0.2), per-channel tone curves that differ between channels (gamma ~ U(1.9, 2.6), S-curve
  blend ~ U(0.1, 0.5)), and a white balance that switches between discrete presets
  (:data:`WB_PRESETS`, at least two in a bracket of two or more exposures); exposure
  gain jitter exp(U(0, 0.1)).
* ``phone-local``: a phone's local tone map: a gain map (6 x 8 grid, bilinear) from the
  frame's blurred log luminance relative to its mean (strength ~ U(0.25, 0.5) per frame, so the
  map changes with the exposure; geometric mean 1, gains in [1/4, 4]) that sets the shadow
  gain of a tone curve keeping white at white, per-frame gain exp(U(0, 0.3)) and display
  gamma U(1.9, 2.6).
* ``drift``: the filmic style with a white balance drifting continuously across the
  bracket (log R +-25 %, log B -+20 %, plus a random walk of 5 % steps), gain as a random
  walk exp(clip(walk, 0, 0.6)), gamma U(1.8, 2.6), saturation U(0.8, 1.2): a harder ``auto``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from derender.core.errors import InputError

if TYPE_CHECKING:  # the CLI's help imports this module: keep it light
    from derender.camera.stages import FrameSettings

__all__ = [
    "FAMILIES",
    "WB_PRESETS",
    "check_family",
    "family_settings",
    "random_gamut",
]

#: Pipeline families (ordered) with a one-line description each.
FAMILIES: dict[str, str] = {
    "paper": "paper 1's eq. 4: WB, gain, saturation matrix, power-law gamma per frame (auto pipeline, simple style)",
    "camera": "filmic picture style (saturation boost, gamut compression, Hable curve, toe) with the auto pipeline",
    "dslr-lut": "DSLR engine (Kim et al. 2012): WB in a 3x3, hue-dependent saturation, random 3D gamut LUT, "
                "per-channel curves, WB switching between presets",
    "phone-local": "phone: local tone map (shadow gain map from blurred luminance, white kept), per-frame gain/gamma",
    "drift": "filmic style with white balance drifting continuously and gain random-walking across the bracket",
}

#: White-balance presets of the ``dslr-lut`` family: multipliers (R, G, B) relative to the scene's white balance.
WB_PRESETS: dict[str, tuple[float, float, float]] = {
    "daylight": (1.0, 1.0, 1.0),
    "cloudy": (1.10, 1.0, 0.90),
    "shade": (1.20, 1.0, 0.80),
    "tungsten": (0.72, 1.0, 1.45),
}


def check_family(family: str) -> str:
    """Return ``family`` if it is one of :data:`FAMILIES`, else raise :class:`InputError` naming them."""
    if family not in FAMILIES:
        raise InputError(f"unknown pipeline family {family!r}: choose from {', '.join(FAMILIES)}")
    return family


def random_gamut(rng: np.random.Generator, k: int = 6, nodes: int = 17, max_slope: float = 0.2) -> dict[str, Any]:
    """Random parameters of the ``dslr-lut`` gamut map (:func:`derender.camera.stages.gamut_lut`).

    Amplitudes are scaled down so that no LUT entry changes by more than ``max_slope``
    times the node spacing between neighbouring nodes (the map stays monotone and invertible).
    """
    from derender.camera.stages import gamut_lut

    centers = rng.uniform(0.15, 0.85, (k, 3))
    amplitudes = rng.normal(0.0, 0.05, (k, 3))
    g = {"nodes": nodes, "centers": centers.tolist(), "amplitudes": amplitudes.tolist(), "width": 0.25,
         "neutral": 0.12}
    lut = gamut_lut(g).reshape(nodes, nodes, nodes, 3)
    h = 1.0 / (nodes - 1)
    slope = max(float(np.abs(np.diff(lut, axis=ax)).max()) / h for ax in range(3))
    if slope > max_slope:
        g["amplitudes"] = (amplitudes * (max_slope / slope)).tolist()
    return g


def _dslr(n: int, wb: np.ndarray, rng: np.random.Generator, base: dict) -> list[FrameSettings]:
    from derender.camera.stages import FrameSettings

    hue_sat = [float(rng.uniform(1.0, 1.25)), float(rng.uniform(0.0, 0.15)), float(rng.uniform(-np.pi, np.pi)),
               float(rng.uniform(0.0, 0.1)), float(rng.uniform(-np.pi, np.pi))]
    gamut = random_gamut(rng)
    curves = [[float(rng.uniform(1.9, 2.6)), float(rng.uniform(0.1, 0.5)), float(rng.uniform(1.5, 3.0))]
              for _ in range(3)]
    names = list(WB_PRESETS)
    presets = [names[int(rng.integers(len(names)))]]
    for _ in range(1, n):
        presets.append(presets[-1] if rng.uniform() < 0.5 else names[int(rng.integers(len(names)))])
    if n >= 2 and len(set(presets)) == 1:   # the preset really switches within the bracket
        j = int(rng.integers(1, n))
        others = [p for p in names if p != presets[0]]
        presets[j:] = [others[int(rng.integers(len(others)))]] * (n - j)
    out = []
    for p in presets:
        out.append(FrameSettings(style="dslr", wb=[float(v) for v in wb * np.asarray(WB_PRESETS[p])], wb_preset=p,
                                 gain=float(np.exp(rng.uniform(0.0, 0.1))), hue_sat=hue_sat, gamut=gamut,
                                 curves=curves, **base))
    return out


def _phone(n: int, wb: np.ndarray, rng: np.random.Generator, base: dict) -> list[FrameSettings]:
    from derender.camera.stages import FrameSettings

    out = []
    for _ in range(n):
        local = {"strength": float(rng.uniform(0.25, 0.5)), "sigma": 0.08, "grid": [6, 8]}
        out.append(FrameSettings(style="local", wb=[float(v) for v in wb], gain=float(np.exp(rng.uniform(0.0, 0.3))),
                                 gamma=float(rng.uniform(1.9, 2.6)), local=local, **base))
    return out


def _drift(n: int, wb: np.ndarray, rng: np.random.Generator, base: dict) -> list[FrameSettings]:
    from derender.camera.stages import FrameSettings

    ramp = np.linspace(-1.0, 1.0, n)
    walk_r = np.cumsum(rng.normal(0.0, 0.05, n))
    walk_b = np.cumsum(rng.normal(0.0, 0.05, n))
    walk_g = rng.uniform(0.0, 0.2) + np.cumsum(rng.normal(0.0, 0.12, n))
    out = []
    for j in range(n):
        d = np.array([0.25 * ramp[j] + walk_r[j], 0.0, -0.20 * ramp[j] + walk_b[j]])
        out.append(FrameSettings(style="camera", wb=[float(v) for v in wb * np.exp(d)],
                                 gain=float(np.exp(np.clip(walk_g[j], 0.0, 0.6))), gamma=float(rng.uniform(1.8, 2.6)),
                                 saturation=float(rng.uniform(0.8, 1.2)), **base))
    return out


def family_settings(family: str, n_exposures: int, rng: np.random.Generator, wb_render: Any, wb_as_shot: Any,
                    camera_to_srgb: Any) -> list[FrameSettings]:
    """Per-frame settings of a bracket of ``n_exposures`` through ``family``, drawn from ``rng``.

    ``wb_render``: the white balance the camera would choose (the scene's, or a preset's);
    ``wb_as_shot`` and ``camera_to_srgb`` define the truth's space (recorded in every frame so
    that :func:`derender.camera.oracle.invert_frame_codes` needs nothing else). ``paper`` and
    ``camera`` draw exactly what :func:`derender.camera.rendering.pipeline_settings` draws.
    """
    check_family(family)
    wb = np.asarray(wb_render, dtype=np.float64)
    base = {"wb_as_shot": [float(v) for v in wb_as_shot],
            "camera_to_srgb": np.asarray(camera_to_srgb, dtype=np.float64).tolist()}
    if family in ("paper", "camera"):
        from derender.camera.rendering import pipeline_settings
        from derender.camera.stages import FrameSettings

        style = "simple" if family == "paper" else "camera"
        return [FrameSettings.from_render_settings(rs, wb_as_shot, camera_to_srgb)
                for rs in pipeline_settings("auto", n_exposures, wb, style, rng)]
    if family == "dslr-lut":
        return _dslr(n_exposures, wb, rng, base)
    if family == "phone-local":
        return _phone(n_exposures, wb, rng, base)
    return _drift(n_exposures, wb, rng, base)
