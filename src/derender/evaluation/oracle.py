"""The oracle HDR merge: invert each frame's *true* in-camera pipeline, then average.

No method can beat knowing the pipeline: :func:`oracle_merge` inverts every frame with
:func:`derender.camera.oracle.invert_frame_codes` (the simulator's recorded per-frame
settings), weights each channel with the engine's weights on its code (trapezoid by
default, :mod:`derender.engine.weights`) times the frame's validity mask (no clipped code,
no clipped sensor or white-balanced channel), divides by the exposure time and averages
with the float reference engine (:func:`derender.engine.float_merge.merge_linear`), whose
saturation policy gives pixels no frame exposes the shortest (bright) or longest (dark)
exposure's value and marks them in the mask; as in the table engine's ``"brightest"`` mode,
the choice looks at the pixel's largest code in the shortest exposure. The radiance is finite and never negative. Its
error against the truth is what is left: demosaicing and noise, 8-bit quantisation, clipping.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult

__all__ = [
    "oracle_merge",
    "oracle_merge_bracket",
]


def oracle_merge(codes: np.ndarray, times: Sequence[float], frame_settings: Sequence[Any],
                 weight: str = "trapezoid", clip_margin: float = 0.03,
                 quantisation_weights: bool = False) -> HDRResult:
    """Merge an (N, H, W, 3) uint8 bracket by inverting each frame's true pipeline.

    ``frame_settings``: one :class:`~derender.camera.stages.FrameSettings` per frame (as
    :func:`derender.camera.bracket.load_frame_settings` reads them), in the order of ``codes``.
    ``weight``: a name of :data:`derender.engine.weights.WEIGHTS`. ``quantisation_weights``:
    also divide each weight by the relative variance that one code's quantisation leaves
    after the frame's true inverse (its slope is known to the oracle), so that a frame
    whose code sits on a steep part of its inverse curve counts less: the better bound
    (``oracle-q`` in :mod:`derender.evaluation.families`). Returns an
    :class:`~derender.core.types.HDRResult` in the truth's space (linear sRGB per second).
    """
    from derender.camera.oracle import invert_frame_codes
    from derender.engine.float_merge import merge_linear
    from derender.engine.weights import get_weight

    codes = np.asarray(codes)
    if codes.ndim != 4 or codes.shape[-1] != 3 or codes.dtype != np.uint8:
        raise InputError(f"oracle_merge needs (N, H, W, 3) uint8 codes, got {codes.shape} {codes.dtype}")
    n, h = codes.shape[0], codes.shape[1]
    if len(frame_settings) != n:
        raise InputError(f"{len(frame_settings)} frame settings for {n} frames")
    wfun = get_weight(weight)
    linear = np.empty(codes.shape, dtype=np.float64)
    valid = np.empty(codes.shape[:3], dtype=bool)
    for j in range(n):
        linear[j], valid[j] = invert_frame_codes(codes[j], frame_settings[j], clip_margin=clip_margin)
    images = codes.astype(np.float32) * np.float32(1 / 255)
    weights = [wfun(images[j]) * valid[j][..., None] for j in range(n)]
    if quantisation_weights:
        for j in range(n):
            weights[j] = weights[j] / _relative_quantisation_variance(codes[j], linear[j], frame_settings[j],
                                                                      clip_margin)
    # the saturation policy sees each pixel's brightest channel (the table engine's "brightest" mode)
    brightest = np.repeat(images.max(axis=-1, keepdims=True), 3, axis=-1)

    def weight_fn(j: int, z: np.ndarray) -> np.ndarray:
        return weights[j]

    res = merge_linear(linear, times, brightest, weight_fn=weight_fn, block_rows=h,
                       info={"method": "oracle", "weight": weight, "quantisation_weights": bool(quantisation_weights),
                             "valid_fraction": [float(v.mean()) for v in valid]})
    res.radiance = np.maximum(res.radiance, np.float32(0.0))
    return res


def _relative_quantisation_variance(codes: np.ndarray, linear: np.ndarray, settings: Any,
                                    clip_margin: float) -> np.ndarray:
    """Per channel ``((x(z + 1/2) - x(z - 1/2)) / x)^2 / 12``: the relative variance of a uniform
    quantisation error of one code, through the frame's true inverse (floored at 1e-12)."""
    from derender.camera.oracle import invert_frame_values

    z = codes.astype(np.float64)
    up, _ = invert_frame_values(np.minimum(z + 0.5, 255.0) / 255.0, settings, clip_margin)
    dn, _ = invert_frame_values(np.maximum(z - 0.5, 0.0) / 255.0, settings, clip_margin)
    rel = np.minimum(np.abs(up - dn) / np.maximum(np.abs(linear), 1e-30), 1e6)
    return np.maximum(rel * rel / 12.0, 1e-12).astype(np.float32)


def oracle_merge_bracket(bracket: Any, weight: str = "trapezoid", quantisation_weights: bool = False) -> HDRResult:
    """:func:`oracle_merge` of a :class:`~derender.camera.bracket.SimulatedBracket` (its codes,
    times and recorded frame settings)."""
    frames = list(getattr(bracket, "frames", None) or [])
    if not frames:
        from derender.camera.stages import FrameSettings

        frames = [FrameSettings.from_render_settings(s, bracket.wb_true, bracket.camera_to_srgb)
                  for s in bracket.settings]
    return oracle_merge(bracket.jpeg_codes, bracket.times, frames, weight=weight,
                        quantisation_weights=quantisation_weights)
