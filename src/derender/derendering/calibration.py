"""Calibration pairs (8-bit code, raw camera RGB) from registered RAW and JPEG files of one shot.

:func:`pairs_from_images` is ``derender calibrate --raw ... --jpeg ...``: the RAW gives the
training target ``x`` (demosaiced camera RGB, no white balance or colour matrix), the JPEG
the rendered code ``y`` of the same pixel; the pairs are what
:func:`derender.derendering.base.fit_model` learns p(x | y) from (paper 2, Sec. 4).
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.derendering.apply import check_8bit_rgb

__all__ = [
    "pairs_from_images",
]


def pairs_from_images(raw_paths: Sequence[str | os.PathLike], jpeg_paths: Sequence[str | os.PathLike],
                      saturation: float = 0.92, max_pairs_per_image: int = 200_000, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Pairs (jpeg codes, raw camera RGB) from registered RAW/JPEG shots of the same scene.

    Each RAW is demosaiced (Malvar) without white balance or colour matrix, normalised by
    its black and white level (sensor units, not divided by the exposure time); pixels with
    a RAW channel above ``saturation`` are left out (one shot cannot extrapolate them);
    the JPEG must have the RAW's visible size. Metadata comes from the first RAW: make and
    model, and, when it has a colour matrix (DNG ColorMatrix), ``camera_to_srgb`` (for
    white-balanced camera RGB, as :func:`derender.raw.groundtruth.raw_ground_truth` develops it)
    and its as-shot white balance ``wb``, so that a model of a real camera maps its camera RGB to
    linear sRGB as a chart-session model does (``derender derender --srgb``, the probabilistic
    merge's default output).
    """
    from derender.io.raw import read_raw
    from derender.raw.groundtruth import raw_to_camera_rgb

    if len(raw_paths) != len(jpeg_paths) or not raw_paths:
        raise InputError(f"give one --jpeg per --raw ({len(raw_paths)} RAW, {len(jpeg_paths)} JPEG)")
    rng = np.random.default_rng(seed)
    from derender.core.colorimetry import camera_to_linear_srgb_matrix

    jp_all, rw_all = [], []
    make = model = ""
    colour: dict = {}
    for rp, jpth in zip(raw_paths, jpeg_paths):
        frame = read_raw(rp)
        make, model = make or frame.make, model or frame.model
        if not colour and frame.xyz_to_camera is not None:
            colour = {"camera_to_srgb": camera_to_linear_srgb_matrix(frame.xyz_to_camera).tolist(),
                      "wb": np.asarray(frame.as_shot_wb, dtype=np.float64).reshape(3).tolist()}
        frame.exposure_time = None
        cam = raw_to_camera_rgb([frame], clip_negative=True).radiance
        codes = check_8bit_rgb(jpth)
        if codes.shape[:2] != cam.shape[:2]:
            raise InputError(f"{jpth} is {codes.shape[1]}x{codes.shape[0]} but {rp} is "
                             f"{cam.shape[1]}x{cam.shape[0]}: pairs must be registered at the RAW's size")
        ok = np.all(cam < saturation, axis=-1) & np.all(np.isfinite(cam), axis=-1)
        idx = np.flatnonzero(ok)
        if idx.size > max_pairs_per_image:
            idx = np.sort(rng.choice(idx, size=max_pairs_per_image, replace=False))
        jp_all.append(codes.reshape(-1, 3)[idx])
        rw_all.append(cam.reshape(-1, 3)[idx].astype(np.float64))
    jp = np.concatenate(jp_all)
    rw = np.concatenate(rw_all)
    if jp.shape[0] < 10:
        raise InputError("fewer than 10 usable (unsaturated) pixel pairs in the given images")
    return jp, rw, {"camera": {"name": "", "make": make, "model": model}, **colour}
