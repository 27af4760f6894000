"""Rendered 8-bit/16-bit images (JPEG, PNG, TIFF, HEIC/HEIF, AVIF) and exposure stacks.

* :func:`read_image` -- one image as float32 ``value / (2^bits - 1)`` plus its bit depth.
* :func:`read_codes` -- the 8-bit codes of an image (uint8), for the streaming merge engine.
* :func:`decode_image` -- the one decoder both use (header probed first, strict about
  truncation, EXIF orientation applied; libjpeg-turbo through ``imagecodecs`` for 8-bit
  JPEGs, Pillow with ``pillow-heif`` for HEIC/HEIF and Pillow for AVIF, which OpenCV does
  not read, OpenCV otherwise).
* :func:`read_stack` -- a bracket sorted by exposure time (times from the caller, a times
  file or EXIF, see :mod:`derender.io.exif`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import check_memory, import_cv2
from derender.core.types import Stack
from derender.io.exif import file_times, read_exif
from derender.io.files import expand_image_paths, read_bytes
from derender.io.headers import (
    DEFAULT_MAX_MEGAPIXELS,
    PILLOW_DECODED,
    ImageInfo,
    orient,
    pillow_image,
    probe_image,
    probe_images,
)

__all__ = [
    "read_image",
    "read_stack",
    "read_codes",
    "decode_image",
]


def read_image(path: str | os.PathLike, max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS,
               info: ImageInfo | None = None) -> tuple[np.ndarray, int]:
    """Read an 8- or 16-bit JPEG/PNG/TIFF/HEIC/AVIF as float32 (H, W, 3) RGB in [0, 1], upright.

    Decoded by :func:`decode_image` (the one decoder every reader uses): grey images are
    replicated to three channels, an alpha channel is dropped only when fully opaque, EXIF
    orientation is applied.

    Parameters
    ----------
    path : path-like
        The image file.
    max_megapixels : float or None
        The largest image accepted, checked from the header before decoding (None: no limit).
    info : ImageInfo, optional
        The file's header as :func:`derender.io.headers.probe_image` read it (read here when
        not given).

    Returns
    -------
    image : numpy.ndarray
        (H, W, 3) float32 rendered RGB, code values divided by 255 or 65535.
    bit_depth : int
        8 or 16.

    Raises
    ------
    InputError
        A missing, truncated, corrupt or too large file, or one with a transparent alpha
        channel.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> codes = np.arange(8 * 8 * 3, dtype=np.uint8).reshape(8, 8, 3)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = derender.write_png(os.path.join(folder, "ramp.png"), codes)
    ...     image, bit_depth = derender.read_image(path)
    >>> image.shape, image.dtype, bit_depth
    ((8, 8, 3), dtype('float32'), 8)
    >>> bool(np.array_equal(np.rint(image * 255), codes))
    True
    """
    img = decode_image(path, max_megapixels=max_megapixels, info=info)
    depth, scale = (8, 255.0) if img.dtype == np.uint8 else (16, 65535.0)
    out = np.empty(img.shape, dtype=np.float32)
    np.multiply(img, np.float32(1.0 / scale), out=out, casting="unsafe")
    return out, depth


def read_stack(
    paths: Sequence[str | os.PathLike],
    times: Sequence[float] | None = None,
    times_file: str | os.PathLike | None = None,
    times_file_inverse: bool = False,
    max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS,
) -> Stack:
    """Read a bracketed stack of rendered images, sorted by exposure time.

    Times come from ``times`` (one per path, in the given order), else ``times_file``
    (matched by file name), else each file's EXIF ``ExposureTime``. Every header is read
    first (:func:`derender.io.headers.probe_images`): sizes, the ``max_megapixels`` limit
    and the memory the float stack needs are checked before any pixel is decoded. A folder
    among ``paths`` stands for the images in it (:func:`derender.io.files.expand_image_paths`).

    Parameters
    ----------
    paths : sequence of path-like
        The bracket's images (JPEG, PNG, TIFF, HEIC, AVIF), in any order; a folder stands for
        the images in it.
    times : sequence of float, optional
        Exposure times in seconds, one per path in the order given.
    times_file : path-like, optional
        A text file of ``name time`` lines (used when ``times`` is not given).
    times_file_inverse : bool
        The file holds ``1/t`` (e.g. ``250`` for 1/250 s).
    max_megapixels : float or None
        The largest frame accepted (None: no limit).

    Returns
    -------
    Stack
        The images as float32 (N, H, W, 3) in [0, 1], sorted by exposure time, with their
        bit depth, paths and EXIF metadata.

    Raises
    ------
    InputError
        Missing or unreadable files, frames of different sizes or bit depths, missing,
        repeated or contradictory exposure times, too little memory.
    StackError
        Fewer than two images.

    Examples
    --------
    Two PNG exposures of a grey ramp written into a temporary folder, with the times given:

    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> radiance = np.linspace(0.05, 1.0, 64).reshape(8, 8, 1).repeat(3, axis=2)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     paths = [derender.write_png(os.path.join(folder, f"t{t}.png"),
    ...                                 np.round(255 * np.clip(radiance * t, 0, 1) ** (1 / 2.2)).astype(np.uint8))
    ...              for t in (1.0, 0.25)]
    ...     stack = derender.read_stack(paths, times=[1.0, 0.25])
    >>> stack.n, stack.shape, stack.bit_depth, stack.times.tolist()
    (2, (8, 8), 8, [0.25, 1.0])
    >>> [os.path.basename(p) for p in stack.paths]
    ['t0.25.png', 't1.0.png']
    """
    paths = expand_image_paths(paths)
    t = file_times(paths, times, times_file, times_file_inverse)
    infos = probe_images(paths, max_megapixels)
    check_memory(len(paths) * infos[0].width * infos[0].height * 3 * 4, "the stack as float32")

    images: list[np.ndarray] = []
    depths: list[int] = []
    metadata: list[dict] = []
    for p, info in zip(paths, infos):
        img, depth = read_image(p, max_megapixels, info)
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


# --------------------------------------------------------------------------- the decoder
def read_codes(path: str | os.PathLike, out: np.ndarray | None = None,
               max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS,
               info: ImageInfo | None = None) -> np.ndarray | None:
    """8-bit RGB codes (H, W, 3) uint8 of a JPEG/PNG/TIFF file, or None if the file is 16-bit.

    :func:`decode_image` (the decoder of :func:`read_image` too), into ``out`` when it has the
    right shape (reusing memory avoids page faults).

    Parameters
    ----------
    path : path-like
        The image file.
    out : numpy.ndarray, optional
        (H, W, 3) uint8 buffer to decode 8-bit JPEGs into (used when its shape fits).
    max_megapixels : float or None
        The largest image accepted (None: no limit).
    info : ImageInfo, optional
        The file's header, as :func:`derender.io.headers.probe_image` read it.

    Returns
    -------
    numpy.ndarray or None
        (H, W, 3) uint8 codes, or None for a 16-bit file.

    Raises
    ------
    InputError
        A missing, truncated, corrupt or too large file.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> codes = np.arange(8 * 8 * 3, dtype=np.uint8).reshape(8, 8, 3)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     eight = derender.read_codes(derender.write_png(os.path.join(folder, "a.png"), codes))
    ...     sixteen = derender.read_codes(derender.write_png(os.path.join(folder, "b.png"),
    ...                                                      codes.astype(np.uint16) * 257))
    >>> eight.dtype, bool(np.array_equal(eight, codes)), sixteen
    (dtype('uint8'), True, None)
    """
    img = decode_image(path, out=out, max_megapixels=max_megapixels, info=info)
    return None if img.dtype == np.uint16 else img


def decode_image(path: str | os.PathLike, out: np.ndarray | None = None,
                 max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS,
                 info: ImageInfo | None = None) -> np.ndarray:
    """The one decoder of every reader: (H, W, 3) uint8 or uint16 RGB, upright.

    The header is probed first (:func:`derender.io.headers.probe_image`, unless ``info`` is
    given): a truncated file, a forged size or one above ``max_megapixels`` is refused before
    decoding. 8-bit JPEGs are decoded with libjpeg-turbo through ``imagecodecs`` (the decoder
    OpenCV bundles; ~1.6x faster here), into ``out`` when it has the stored shape; the rest
    with OpenCV. Grey is replicated, an opaque alpha dropped (a transparent one refused),
    EXIF orientation applied (a copy, only for rotated files). Every decoder failure is an
    :class:`InputError` naming the file.
    """
    path = Path(path)
    if info is None:
        info = probe_image(path, max_megapixels)
    check_memory(info.width * info.height * 3 * (2 if info.bit_depth > 8 else 1), f"decoding {path.name}")
    img = None
    if info.format in PILLOW_DECODED:
        img = _decode_pillow(path)
    else:
        data = read_bytes(path)
        if info.format == "jpeg" and info.bit_depth == 8:
            img = _decode_jpeg8(data, out if info.orientation == 1 else None)
        if img is None:
            img = _decode_opencv(data, path)
    if img.shape[:2] != info.stored_shape:
        raise InputError(f"corrupt image (its header says {info.stored_shape[1]}x{info.stored_shape[0]}, "
                         f"the data {img.shape[1]}x{img.shape[0]}): {path}")
    if info.orientation != 1:
        img = orient(img, info.orientation)
        img = _copy_into(img, out)
    return img


def _copy_into(img: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    if out is not None and out.shape == img.shape and out.dtype == img.dtype:
        np.copyto(out, img)
        return out
    return np.ascontiguousarray(img)


def _decode_jpeg8(data: np.ndarray, out: np.ndarray | None) -> np.ndarray | None:
    """libjpeg-turbo through imagecodecs (None when it is missing or the layout is unusual)."""
    try:
        import imagecodecs
    except ImportError:  # pragma: no cover - a declared dependency
        return None
    img = None
    if out is not None:
        try:
            img = imagecodecs.jpeg8_decode(data, out=out)
        except Exception:  # noqa: BLE001 - wrong shape for this file: decode afresh
            img = None
    if img is None:
        try:
            img = imagecodecs.jpeg8_decode(data)
        except Exception:  # noqa: BLE001 - let OpenCV decide (and report)
            return None
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        return None
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img)


def _decode_pillow(path: Path) -> np.ndarray:
    """HEIC/HEIF (pillow-heif; high-bit-depth HEICs are delivered as 8-bit, as the phone's own
    viewer shows them) and AVIF through Pillow: (H, W, 3) uint8 as stored (the caller orients)."""
    import warnings

    Image = pillow_image()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                im.load()
                if im.mode in ("RGBA", "LA") and im.getchannel("A").getextrema()[0] < 255:
                    raise InputError(f"{path} has a transparent alpha channel; flatten it first")
                rgb = im.convert("RGB")
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - libheif/libavif raise assorted types for damaged files
        raise InputError(f"not a readable image ({str(exc).strip()[:120] or 'corrupt data'}): {path}") from None
    return np.ascontiguousarray(np.asarray(rgb, dtype=np.uint8))


def _decode_opencv(data: np.ndarray, path: Path) -> np.ndarray:
    cv2 = import_cv2()
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error as exc:
        raise InputError(f"not a readable image ({str(exc).strip().splitlines()[-1][:120]}): {path}") from None
    if img is None:
        raise InputError(f"not a readable image (corrupt or unsupported format): {path}")
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(f"unsupported sample type {img.dtype} in {path}: use 8- or 16-bit images")
    full = 255 if img.dtype == np.uint8 else 65535
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.shape[2] == 4:
        if np.any(img[:, :, 3] != full):
            raise InputError(f"{path} has a transparent alpha channel; flatten it first")
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise InputError(f"{path} has {img.shape[2]} channels; expected grey, RGB or RGBA")
