"""Image headers read before any pixel is decoded: size, bit depth, orientation, completeness.

Every reader probes its files first (:func:`probe_image`), so that a decompression bomb, a
forged header or a truncated file is refused with one line naming the file *before* any
memory is committed to it ("budget before work"):

* JPEG: the marker segments are walked from SOI to the first SOS; the frame header (SOFn)
  gives the size and precision, APP1 ``Exif`` the orientation (tag 0x0112). The file is
  *complete* when an EOI marker (``FF D9``) follows the first scan: libjpeg-turbo, the
  engine's decoder, silently fills the rows of a truncated file with grey (code 128), so
  completeness is checked here, on the bytes.
* PNG: the IHDR chunk (width, height, bit depth, colour type) and an ``IEND`` chunk at the
  end (a truncated PNG has none; OpenCV refuses it too, but only after allocating it).
* TIFF, HEIC/HEIF and AVIF: Pillow's lazy ``Image.open`` (header only), with its own
  decompression-bomb guard turned into the same error as ours. HEIC/HEIF (the iPhone's
  default format) is opened through the kept ``pillow-heif`` plugin (libheif), registered
  by :func:`pillow_image`; AVIF by Pillow itself (libavif, Pillow >= 11.3). libheif applies
  the container's rotation (``irot``/``imir``) when decoding and reports EXIF orientation 1,
  so a HEIC's size here is already the displayed one; Pillow's AVIF reader keeps the stored
  orientation in EXIF, which :func:`orient` applies as for a JPEG.

Our own parser for JPEG/PNG rather than Pillow's: Pillow refuses images above
2 x ``Image.MAX_IMAGE_PIXELS`` (179 MP) itself, a process-wide setting a library should not
change, and does not report a JPEG's completeness without decoding it. The walk reads only
the header bytes (a few kB, 3-10 us per file).

Orientation follows EXIF/TIFF: 1 upright, 2 mirrored, 3 rotated 180, 4 flipped, 5-8 the
transposed cases (6: rotate 90 degrees clockwise to display). :func:`orient` applies it to a
decoded (H, W, C) array as a view; :attr:`ImageInfo.width` and ``height`` are the *displayed*
size (after orientation).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.io.files import check_input_file

__all__ = [
    "DEFAULT_MAX_MEGAPIXELS",
    "ImageInfo",
    "probe_image",
    "probe_images",
    "orient",
    "jpeg_header",
    "pillow_image",
    "PILLOW_DECODED",
]

#: Formats (as :class:`ImageInfo` names them) decoded through Pillow rather than OpenCV,
#: which reads neither: HEIC/HEIF (pillow-heif) and AVIF (Pillow's own plugin).
PILLOW_DECODED = frozenset({"heif", "avif"})

#: Largest decoded image accepted by default (megapixels): above the 200 MP of today's
#: largest phone sensors, below a 16000 x 16000 decompression bomb (256 MP).
DEFAULT_MAX_MEGAPIXELS = 250.0

_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_STANDALONE = {0x01, *range(0xD0, 0xD8)}


@dataclass(frozen=True)
class ImageInfo:
    """What a file's header says (``width``/``height`` as displayed, after ``orientation``)."""

    path: Path
    format: str            # "jpeg" | "png" | "tiff" | Pillow's format name
    width: int
    height: int
    bit_depth: int         # 8 or 16 (other depths are refused when decoding)
    channels: int
    orientation: int = 1   # EXIF orientation, 1..8
    complete: bool = True  # the byte stream ends properly (JPEG EOI after the scan, PNG IEND)

    @property
    def megapixels(self) -> float:
        return self.width * self.height / 1e6

    @property
    def stored_shape(self) -> tuple[int, int]:
        """(rows, columns) as stored in the file, before orientation."""
        return (self.width, self.height) if self.orientation >= 5 else (self.height, self.width)


def _exif_orientation(app1: bytes) -> int:
    """EXIF orientation (tag 0x0112 of IFD0) from an APP1 payload, 1 when absent or malformed."""
    if not app1.startswith(b"Exif\x00\x00") or len(app1) < 14:
        return 1
    tiff = app1[6:]
    order = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    if order is None:
        return 1
    try:
        (ifd,) = struct.unpack_from(order + "I", tiff, 4)
        (count,) = struct.unpack_from(order + "H", tiff, ifd)
        for k in range(min(count, 512)):
            tag, typ, _n = struct.unpack_from(order + "HHI", tiff, ifd + 2 + 12 * k)
            if tag == 0x0112 and typ == 3:
                (value,) = struct.unpack_from(order + "H", tiff, ifd + 2 + 12 * k + 8)
                return int(value) if 1 <= value <= 8 else 1
    except struct.error:
        return 1
    return 1


def jpeg_header(data: bytes | np.ndarray) -> tuple[int, int, int, int, int, bool]:
    """(height, width, components, precision, orientation, complete) of a JPEG byte stream.

    Raises :class:`ValueError` when the markers before the first scan are malformed or
    there is no frame header (the caller names the file)."""
    buf = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
    n = len(buf)
    if n < 4 or buf[0] != 0xFF or buf[1] != 0xD8:
        raise ValueError("no JPEG start-of-image marker")
    i, frame, orientation = 2, None, 1
    while True:
        while i < n and buf[i] != 0xFF:   # tolerate stray bytes between segments, as libjpeg does
            i += 1
        while i < n and buf[i] == 0xFF:   # fill bytes
            i += 1
        if i + 2 >= n:
            raise ValueError("file ends inside the JPEG header")
        marker = buf[i]
        i += 1
        if marker in _STANDALONE:
            continue
        if marker == 0xD9:
            raise ValueError("end-of-image marker before any scan")
        (length,) = struct.unpack_from(">H", buf, i)
        if length < 2 or i + length > n:
            raise ValueError(f"segment 0x{marker:02X} runs past the end of the file")
        seg = buf[i + 2:i + length]
        if marker in _SOF:
            if len(seg) < 6:
                raise ValueError("short frame header")
            precision, height, width, comps = struct.unpack_from(">BHHB", seg, 0)
            frame = (height, width, comps, precision)
        elif marker == 0xE1 and orientation == 1:
            orientation = _exif_orientation(seg)
        elif marker == 0xDA:
            if frame is None:
                raise ValueError("scan before any frame header")
            scan_start = i + length
            complete = buf.rfind(b"\xff\xd9", scan_start) >= 0
            return (*frame, orientation, complete)
        i += length


def _png_header(buf: bytes) -> tuple[int, int, int, int, bool]:
    """(height, width, channels, bit depth, complete) from a PNG's IHDR and IEND chunks."""
    if len(buf) < 33 or buf[12:16] != b"IHDR":
        raise ValueError("no PNG IHDR chunk")
    width, height, depth, colour = struct.unpack_from(">IIBB", buf, 16)
    channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour)
    if channels is None:
        raise ValueError(f"unknown PNG colour type {colour}")
    complete = b"IEND\xaeB`\x82" in buf[-64:]
    return height, width, channels, (8 if colour == 3 else depth), complete


_HEIF_REGISTERED = False


def pillow_image():
    """Pillow's ``Image`` module with the HEIC/HEIF opener of ``pillow-heif`` registered
    (once per process; every Pillow use of derender goes through here, so EXIF times of a
    HEIC are read as a JPEG's are)."""
    global _HEIF_REGISTERED
    from PIL import Image

    if not _HEIF_REGISTERED:
        try:
            import pillow_heif
        except ImportError:  # pragma: no cover - a declared dependency
            pass
        else:
            pillow_heif.register_heif_opener()
        _HEIF_REGISTERED = True
    return Image


def _pillow_header(path: Path) -> tuple[str, int, int, int, int, int]:
    """(format, height, width, channels, bit depth, orientation) through Pillow's lazy open."""
    import warnings

    Image = pillow_image()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            with Image.open(path) as im:
                fmt, (width, height), mode = (im.format or "image").lower(), im.size, im.mode
                orientation = int(im.getexif().get(0x0112, 1) or 1)
        except Image.UnidentifiedImageError:
            raise ValueError("corrupt or unsupported format") from None
        except Image.DecompressionBombError:
            raise ValueError("the image is larger than Pillow's decompression-bomb limit "
                             f"({2 * Image.MAX_IMAGE_PIXELS / 1e6:.0f} MP)") from None
    depth = 16 if mode.startswith("I;16") or mode in ("I", "RGB;16", "RGBA;16") else 8
    channels = {"L": 1, "LA": 2, "RGB": 3, "RGBA": 4, "P": 3}.get(mode, 1 if mode.startswith("I") else 3)
    return fmt, height, width, channels, depth, orientation if 1 <= orientation <= 8 else 1


def probe_image(path: str | os.PathLike, max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS,
                head: bytes | None = None) -> ImageInfo:
    """The header of one image file (nothing decoded), refused with :class:`InputError` when
    it is not an image, is truncated, or decodes to more than ``max_megapixels``."""
    path = check_input_file(path)
    try:
        if head is None:
            with open(path, "rb") as f:
                head = f.read(1 << 16)
        if not head:
            raise InputError(f"empty file: {path}")
        if head[:2] == b"\xff\xd8":
            buf = head
            try:
                h, w, comps, precision, orientation, complete = jpeg_header(buf)
            except ValueError:
                buf = path.read_bytes()         # header larger than 64 kB (big EXIF/ICC blocks)
                h, w, comps, precision, orientation, complete = jpeg_header(buf)
            if not complete and len(buf) < path.stat().st_size:
                with open(path, "rb") as f:
                    f.seek(-min(path.stat().st_size, 1 << 16), os.SEEK_END)
                    complete = b"\xff\xd9" in f.read()
            info = ImageInfo(path, "jpeg", w, h, 16 if precision > 8 else 8, comps, orientation, complete)
        elif head[:8] == b"\x89PNG\r\n\x1a\n":
            with open(path, "rb") as f:
                f.seek(-min(path.stat().st_size, 64), os.SEEK_END)
                tail = f.read()
            h, w, comps, depth, _ = _png_header(head)
            complete = b"IEND\xaeB`\x82" in tail
            info = ImageInfo(path, "png", w, h, depth, comps, 1, complete)
        else:
            fmt, h, w, comps, depth, orientation = _pillow_header(path)
            if orientation >= 5:
                h, w = w, h
            info = ImageInfo(path, fmt, w, h, depth, comps, orientation, True)
            return _check_budget(info, max_megapixels)
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    except (ValueError, struct.error, SyntaxError) as exc:
        raise InputError(f"not a readable image ({exc}): {path}") from None
    except Exception as exc:  # noqa: BLE001 - Pillow raises assorted types for unknown formats
        raise InputError(f"not a readable image (corrupt or unsupported format): {path}") from exc
    if info.orientation >= 5:
        info = ImageInfo(info.path, info.format, info.height, info.width, info.bit_depth, info.channels,
                         info.orientation, info.complete)
    if not info.complete:
        raise InputError(f"truncated image (the file ends before the image data does): {path}")
    info = _check_budget(info, max_megapixels)
    _check_plausible(info, path.stat().st_size)
    return info


#: Most pixels one byte of a file can encode: a JPEG needs at least one bit per 8x8 block
#: (Huffman-coded DC; progressive end-of-band runs make AC free): 512 pixels per byte, with
#: 8x margin for arithmetic coding; deflate (PNG) expands at most 1032:1.
_MAX_PIXELS_PER_BYTE = {"jpeg": 4096.0}
_MAX_DEFLATE_RATIO = 1100.0


def _check_plausible(info: ImageInfo, size: int) -> None:
    """Refuse a header whose size the file cannot hold (a forged or corrupted header)."""
    pixels = info.width * info.height
    if info.format == "jpeg":
        possible = size * _MAX_PIXELS_PER_BYTE["jpeg"]
    elif info.format == "png":
        possible = size * _MAX_DEFLATE_RATIO / max(info.channels * info.bit_depth / 8.0, 1.0 / 8.0)
    else:
        return
    if pixels > possible:
        raise InputError(f"corrupt image: its header claims {info.width}x{info.height}, more than "
                         f"{size} bytes can encode: {info.path}")


def _check_budget(info: ImageInfo, max_megapixels: float | None) -> ImageInfo:
    if info.width < 1 or info.height < 1:
        raise InputError(f"empty image ({info.width}x{info.height}): {info.path}")
    if max_megapixels is not None and info.megapixels > max_megapixels:
        raise InputError(f"{info.path} is {info.width}x{info.height} ({info.megapixels:.0f} MP), above the "
                         f"{max_megapixels:g} MP limit; raise it with --max-megapixels if the image is real")
    return info


def probe_images(paths: Sequence[str | os.PathLike], max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS,
                 same_size: bool = True) -> list[ImageInfo]:
    """:func:`probe_image` on every path, and (``same_size``) one displayed size and bit depth for all."""
    infos = [probe_image(p, max_megapixels) for p in paths]
    if same_size:
        for info in infos[1:]:
            if (info.width, info.height) != (infos[0].width, infos[0].height):
                raise InputError(f"images differ in size: {infos[0].path.name} is {infos[0].width}x{infos[0].height}, "
                                 f"{info.path.name} is {info.width}x{info.height}")
    return infos


def orient(img: np.ndarray, orientation: int) -> np.ndarray:
    """The displayed image of a decoded (H, W, ...) array stored with EXIF ``orientation`` (a view)."""
    if orientation == 2:
        return img[:, ::-1]
    if orientation == 3:
        return img[::-1, ::-1]
    if orientation == 4:
        return img[::-1]
    if orientation == 5:
        return img.swapaxes(0, 1)
    if orientation == 6:
        return img.swapaxes(0, 1)[:, ::-1]
    if orientation == 7:
        return img.swapaxes(0, 1)[::-1, ::-1]
    if orientation == 8:
        return img.swapaxes(0, 1)[::-1]
    return img
