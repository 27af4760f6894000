"""File-level de-rendering: pairs from registered RAW/JPEG images, model libraries, images.

* :func:`pairs_from_images` turns registered RAW + JPEG files of the same shot into
  calibration pairs (``derender calibrate --raw ... --jpeg ...``).
* :func:`resolve_model` loads a model file, or picks from a *folder* of models the one
  whose camera make/model matches the image's EXIF (paper 2 imagines such per-camera
  libraries looked up by the metadata of an Internet image).
* :func:`derender_image` predicts per-pixel mean and variance of the linear RAW colour.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import InputError, ModelFileError

__all__ = ["pairs_from_images", "resolve_model", "derender_image", "check_8bit_rgb"]


def check_8bit_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read an 8-bit RGB image as uint8 codes (H, W, 3); refuse alpha channels and 16-bit files."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    if path.suffix.lower() in (".jpg", ".jpeg"):
        # JPEG is always 8-bit without alpha: the fast libjpeg-turbo decoder of fastmerge
        from .fastmerge import read_codes

        codes = read_codes(path)
        if codes is not None:
            return codes
    img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise InputError(f"not a readable image (corrupt or unsupported format): {path}")
    if img.dtype != np.uint8:
        raise InputError(f"{path} is {img.dtype.itemsize * 8}-bit; de-rendering models map 8-bit rendered colours")
    if img.ndim == 3 and img.shape[2] == 4:
        raise InputError(f"{path} has an alpha channel; de-rendering needs plain RGB (flatten it first)")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] != 3:
        raise InputError(f"{path} has {img.shape[2]} channels; expected RGB")
    else:
        img = img[:, :, ::-1]
    return np.ascontiguousarray(img)


def pairs_from_images(raw_paths: Sequence[str | os.PathLike], jpeg_paths: Sequence[str | os.PathLike],
                      saturation: float = 0.92, max_pairs_per_image: int = 200_000, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Pairs (jpeg codes, raw camera RGB) from registered RAW/JPEG shots of the same scene.

    Each RAW is demosaiced (Malvar) without white balance or colour matrix, normalised by
    its black and white level (sensor units, not divided by the exposure time); pixels with
    a RAW channel above ``saturation`` are left out (one shot cannot extrapolate them);
    the JPEG must have the RAW's visible size. Metadata (make/model) comes from the RAW.
    """
    from .groundtruth import raw_to_camera_rgb
    from .io import read_raw

    if len(raw_paths) != len(jpeg_paths) or not raw_paths:
        raise InputError(f"give one --jpeg per --raw ({len(raw_paths)} RAW, {len(jpeg_paths)} JPEG)")
    rng = np.random.default_rng(seed)
    jp_all, rw_all = [], []
    make = model = ""
    for rp, jpth in zip(raw_paths, jpeg_paths):
        frame = read_raw(rp)
        make, model = make or frame.make, model or frame.model
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
    return jp, rw, {"camera": {"name": "", "make": make, "model": model}}


def _norm(s: str) -> str:
    return re.sub(r"[^a-z0-9]+", " ", s.lower()).strip()


def _camera_matches(meta_cam: dict, exif: dict) -> bool:
    em = _norm(str(exif.get("Model", "")))
    mm = _norm(str(meta_cam.get("model", "")))
    if not em or not mm:
        return False
    return em == mm or em in mm or mm in em


def resolve_model(model_path: str | os.PathLike, image_path: str | os.PathLike | None = None):
    """Load ``model_path``; if it is a folder, pick the model matching the image's EXIF camera.

    Returns ``(model, description)``; raises :class:`InputError` when no model matches.
    """
    from .derendering import load_model
    from .io import read_exif

    p = Path(model_path)
    if p.is_file():
        m = load_model(p)
        return m, p.name
    if not p.is_dir():
        raise InputError(f"no such model file or folder: {p}")
    exif = read_exif(image_path) if image_path is not None else {}
    candidates = []
    for f in sorted(p.glob("*.npz")):
        try:
            m = load_model(f)
        except (ModelFileError, InputError):
            continue
        cam = m.metadata.get("camera", {}) if isinstance(m.metadata, dict) else {}
        candidates.append((f, m, cam))
        if _camera_matches(cam, exif):
            return m, f"{f.name} (camera {cam.get('make', '')} {cam.get('model', '')} matches the image EXIF)"
    known = ", ".join(f"{f.name}: {c.get('model', '?')}" for f, _, c in candidates) or "none"
    who = f"{exif.get('Make', '?')} {exif.get('Model', '?')}" if exif else "unknown (no EXIF)"
    raise InputError(f"no model in {p} for camera {who}; models: {known}")


def derender_image(image_path: str | os.PathLike, model_path: str | os.PathLike, srgb: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, str]:
    """Mean and variance (float32 (H, W, 3)) of the linear colour of every pixel, and the model used."""
    codes = check_8bit_rgb(image_path)
    model, used = resolve_model(model_path, image_path)
    mean, var = model.predict(codes)
    if srgb:
        from .probabilistic import model_camera_to_srgb

        a = model_camera_to_srgb(model)
        if a is None:
            raise InputError("the model has no camera colour metadata; drop --srgb to get camera RGB")
        mean = mean @ a.T.astype(np.float32)
        var = var @ (a * a).T.astype(np.float32)
        big = np.float32(np.finfo(np.float32).max / 4)
        mean = np.nan_to_num(mean, nan=0.0, posinf=big, neginf=-big).astype(np.float32)
        var = np.nan_to_num(np.clip(var, 0, big), nan=big).astype(np.float32)
    # model.predict already returns finite float32 (DerenderModel.predict guarantees it)
    return mean, var, used
