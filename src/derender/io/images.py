"""Rendered 8-bit/16-bit images (JPEG, PNG, TIFF) and exposure stacks.

* :func:`read_image` -- one image as float32 ``value / (2^bits - 1)`` plus its bit depth.
* :func:`read_codes` -- the 8-bit codes of an image (uint8), the decoder of the streaming
  merge engine (libjpeg-turbo through ``imagecodecs`` for JPEGs, OpenCV otherwise).
* :func:`read_stack` -- a bracket sorted by exposure time (times from the caller, a times
  file or EXIF, see :mod:`derender.io.exif`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import import_cv2
from derender.core.types import Stack
from derender.io.exif import file_times, read_exif
from derender.io.files import read_bytes

__all__ = [
    "read_image",
    "read_stack",
    "read_codes",
]


def read_image(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """Read an 8- or 16-bit JPEG/PNG/TIFF as float32 (H, W, 3) RGB in [0, 1].

    Returns ``(image, bit_depth)``. Grey images are replicated to three channels; an
    alpha channel is dropped only when fully opaque, otherwise refused.
    """
    import cv2

    path = Path(path)
    data = read_bytes(path)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise InputError(f"not a readable image (corrupt or unsupported format): {path}")
    if img.dtype == np.uint8:
        depth, scale = 8, 255.0
    elif img.dtype == np.uint16:
        depth, scale = 16, 65535.0
    else:
        raise InputError(f"unsupported sample type {img.dtype} in {path}: use 8- or 16-bit images")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        alpha = img[:, :, 3]
        if np.any(alpha != (255 if depth == 8 else 65535)):
            raise InputError(f"{path} has a transparent alpha channel; flatten it first")
        img = img[:, :, 2::-1]
    elif img.shape[2] == 3:
        img = img[:, :, ::-1]
    else:
        raise InputError(f"{path} has {img.shape[2]} channels; expected grey, RGB or RGBA")
    if img.shape[0] < 1 or img.shape[1] < 1:
        raise InputError(f"empty image: {path}")
    out = np.empty(img.shape, dtype=np.float32)
    np.multiply(img, np.float32(1.0 / scale), out=out, casting="unsafe")
    return out, depth


def read_stack(
    paths: Sequence[str | os.PathLike],
    times: Sequence[float] | None = None,
    times_file: str | os.PathLike | None = None,
    times_file_inverse: bool = False,
) -> Stack:
    """Read a bracketed stack of rendered images, sorted by exposure time.

    Times come from ``times`` (one per path, in the given order), else ``times_file``
    (matched by file name), else each file's EXIF ``ExposureTime``.
    """
    paths = [Path(p) for p in paths]
    t = file_times(paths, times, times_file, times_file_inverse)

    images: list[np.ndarray] = []
    depths: list[int] = []
    metadata: list[dict] = []
    for p in paths:
        img, depth = read_image(p)
        if images and img.shape != images[0].shape:
            raise InputError(
                f"images differ in size: {paths[0].name} is {images[0].shape[1]}x{images[0].shape[0]}, "
                f"{p.name} is {img.shape[1]}x{img.shape[0]}"
            )
        images.append(img)
        depths.append(depth)
        meta = read_exif(p)
        meta["bit_depth"] = depth
        metadata.append(meta)
    if len(set(depths)) > 1:
        raise InputError("images mix 8-bit and 16-bit files; use one bit depth per stack")
    return Stack(
        images=np.stack(images),
        times=np.asarray(t),
        bit_depth=depths[0],
        paths=tuple(str(p) for p in paths),
        metadata=tuple(metadata),
    )


# --------------------------------------------------------------------------- files
_JPEG_SUFFIXES = {".jpg", ".jpeg", ".jpe", ".jfif"}


def read_codes(path: str | os.PathLike, out: np.ndarray | None = None) -> np.ndarray | None:
    """8-bit RGB codes (H, W, 3) uint8 of a JPEG/PNG/TIFF file, or None if the file is 16-bit.

    Same conventions as :func:`derender.io.read_image` (EXIF orientation ignored, grey
    replicated, opaque alpha dropped); JPEGs are decoded with libjpeg-turbo through
    ``imagecodecs`` when available (the same decoder OpenCV bundles; ~1.6x faster here),
    into ``out`` when it has the right shape (reusing memory avoids page faults).
    """
    from derender.io.files import read_bytes

    path = Path(path)
    data = read_bytes(path)
    img = None
    if path.suffix.lower() in _JPEG_SUFFIXES or (data.size > 2 and data[0] == 0xFF and data[1] == 0xD8):
        try:
            import imagecodecs

            img = None
            if out is not None:
                try:
                    img = imagecodecs.jpeg8_decode(data, out=out)
                except Exception:  # noqa: BLE001 - wrong shape for this file: decode afresh
                    img = None
            if img is None:
                img = imagecodecs.jpeg8_decode(data)
            if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
                img = None
        except Exception:  # noqa: BLE001 - any failure: let OpenCV decide (and report)
            img = None
        if img is not None:
            if img.ndim == 2:
                img = np.repeat(img[:, :, None], 3, axis=2)
            return np.ascontiguousarray(img)
    cv2 = import_cv2()
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise InputError(f"not a readable image (corrupt or unsupported format): {path}")
    if img.dtype == np.uint16:
        return None
    if img.dtype != np.uint8:
        raise InputError(f"unsupported sample type {img.dtype} in {path}: use 8- or 16-bit images")
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.shape[2] == 4:
        if np.any(img[:, :, 3] != 255):
            raise InputError(f"{path} has a transparent alpha channel; flatten it first")
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise InputError(f"{path} has {img.shape[2]} channels; expected grey, RGB or RGBA")
