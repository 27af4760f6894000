"""OpenEXR files: reading (OpenEXR bindings) and two writers.

* :func:`write_exr` / :func:`read_exr` -- whole images through the ``OpenEXR`` package.
* :func:`write_exr_fast` / :func:`write_exr_lines` -- our own scanline writer, used for
  every radiance and variance the CLI writes. Why our own: it compresses blocks of 16
  lines (ZIP) in parallel threads and takes the pixels block by block from a callback,
  so a 24-megapixel float image is never copied whole (the OpenEXR bindings need the
  full interleaved array; measured in ``benchmarks/README.md``: 0.45-0.8 s per 24 MP
  image, against 2-3 s through the bindings with ZIP). The files are standard OpenEXR
  2 scanline images (tested by reading them back with the ``OpenEXR`` package).
"""

from __future__ import annotations

import os
import struct
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import thread_count
from derender.io.files import atomic_output

__all__ = [
    "write_exr",
    "read_exr",
    "EXR_COMPRESSION",
    "write_exr_fast",
    "write_exr_lines",
    "SRGB_CHROMATICITIES",
    "colour_attributes",
    "exr_attributes",
    "read_exr_attributes",
    "fill_exr_attribute",
    "reserved_text",
    "SUMMARY_BYTES",
]

#: OpenEXR ``chromaticities`` of linear sRGB / Rec. 709 (x, y of red, green, blue, white D65).
SRGB_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def colour_attributes(colour_space: str | None = "linear_srgb", white_luminance: float | None = None) -> dict:
    """The standard OpenEXR attributes that say what a map's RGB is: ``chromaticities`` (linear
    sRGB / Rec. 709 primaries, D65 white; CIE XYZ's for ``xyz``; none for camera RGB, which has
    no stated primaries)
    and ``whiteLuminance`` (cd/m2 of RGB = (1, 1, 1); for an absolute map in Radiance's units,
    ``L = 179 w·RGB``, it is 179), as typed values for :func:`write_exr_fast`'s ``attributes``."""
    out: dict = {}
    if colour_space in (None, "linear_srgb"):
        out["chromaticities"] = Chromaticities(SRGB_CHROMATICITIES)
    elif colour_space == "xyz":     # CIE XYZ as OpenEXR states it: primaries at X, Y, Z, white E
        out["chromaticities"] = Chromaticities((1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0 / 3.0, 1.0 / 3.0))
    if white_luminance is not None:
        out["whiteLuminance"] = float(white_luminance)
    return out


def exr_attributes(info: dict) -> dict:
    """A merge result's attributes from its ``info``: :func:`colour_attributes` (``chromaticities``
    unless ``info["colour_space"]`` is camera RGB, ``whiteLuminance`` when ``info`` holds a
    ``white_luminance``, set by an absolute calibration), the merge's summary record
    (``derender:summary``, :class:`derender.hdr.summary.MergeSummary` as JSON; spaces reserved
    for it while it is not made yet) and any ``info["exr_attributes"]``."""
    summary = info.get("summary")
    return {**colour_attributes(info.get("colour_space", "linear_srgb"), info.get("white_luminance")),
            "derender:summary": summary.to_json() if summary is not None else reserved_text(SUMMARY_BYTES),
            **dict(info.get("exr_attributes") or {})}


#: Bytes reserved for a merge's summary record (``derender:summary``: JSON, about 110 bytes a
#: frame, so about 140 frames) in an EXR written before the record exists; filled by
#: :func:`fill_exr_attribute` (a record that does not fit is left out of that file).
SUMMARY_BYTES = 16384


class Chromaticities(tuple):
    """Eight floats written as an OpenEXR ``chromaticities`` attribute (red, green, blue, white x y)."""



# --------------------------------------------------------------------------- EXR / HDR
def write_exr(path: str | os.PathLike, image: np.ndarray, half: bool = False,
              inputs: Iterable[str | os.PathLike] = (), channels: str = "RGB") -> Path:
    """Write an (H, W, 3) or (H, W) float image to OpenEXR atomically (ZIP compression).

    Non-finite values are refused: no result of this library may hold NaN or inf.

    Parameters
    ----------
    path : path-like
        The ``.exr`` file to write (replaced atomically: a reader never sees half a file).
    image : numpy.ndarray
        (H, W, 3) linear RGB, or (H, W) one channel (written as ``Y``); finite.
    half : bool
        Store 16-bit half floats instead of 32-bit floats.
    inputs : iterable of path-like
        Input files the output must not overwrite.
    channels : str
        The channel names of a 3-channel image.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    InputError
        An image of another shape, or ``path`` is one of ``inputs``.
    ValueError
        NaN or inf in ``image`` (a bug in the caller: no result may hold them).

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> radiance = np.linspace(0.0, 100.0, 4 * 6 * 3, dtype=np.float32).reshape(4, 6, 3)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = derender.write_exr(os.path.join(folder, "radiance.exr"), radiance)
    ...     back = derender.read_exr(path)
    >>> path.name, back.shape, back.dtype, bool(np.array_equal(back, radiance))
    ('radiance.exr', (4, 6, 3), dtype('float32'), True)
    """
    import OpenEXR

    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = arr[:, :, None]
        channels = "Y"
    if arr.ndim != 3 or arr.shape[2] != len(channels):
        raise InputError(f"cannot write image of shape {np.asarray(image).shape} to EXR")
    if not np.all(np.isfinite(arr)):
        raise ValueError("refusing to write NaN/inf to EXR (internal error)")
    dtype = np.float16 if half else np.float32
    chans = {c: np.ascontiguousarray(arr[:, :, i], dtype=dtype) for i, c in enumerate(channels)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        OpenEXR.File(header, chans).write(str(tmp))
    return path


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an OpenEXR file as float32 (H, W, 3) (RGB) or (H, W) (single channel).

    Parameters
    ----------
    path : path-like
        An OpenEXR file with R, G, B channels or a single channel (``Y`` is taken when there
        are others but no R, G, B).

    Returns
    -------
    numpy.ndarray
        (H, W, 3) float32 RGB, or (H, W) float32 for one channel.

    Raises
    ------
    InputError
        A missing or unreadable file, or one without R, G, B or a single channel.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     rgb = derender.read_exr(derender.write_exr(os.path.join(folder, "rgb.exr"),
    ...                                                np.full((2, 3, 3), 0.5, np.float32)))
    ...     grey = derender.read_exr(derender.write_exr(os.path.join(folder, "y.exr"),
    ...                                                 np.full((2, 3), 2.0, np.float32)))
    >>> rgb.shape, grey.shape, float(grey[0, 0])
    ((2, 3, 3), (2, 3), 2.0)
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            ch = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"not a readable OpenEXR file: {path} ({exc})") from None
    if all(c in ch for c in "RGB"):
        return np.stack([ch[c].astype(np.float32) for c in "RGB"], axis=-1)
    if len(ch) == 1:
        return next(iter(ch.values())).astype(np.float32)
    if "Y" in ch:
        return ch["Y"].astype(np.float32)
    raise InputError(f"{path}: expected R, G, B channels, found {sorted(ch)}")


def read_exr_attributes(path: str | os.PathLike) -> dict[str, Any]:
    """The header attributes of an OpenEXR file's first part, without its pixels: ``string``
    attributes as text, ``float`` ones as floats, ``chromaticities`` as 8 floats, others as
    their raw bytes (``whiteLuminance``, ``derender:photometry``, ``derender:summary``, ...)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    out: dict[str, Any] = {}
    with open(path, "rb") as fh:
        head = fh.read(1 << 20)
    if head[:4] != struct.pack("<i", 20000630):
        raise InputError(f"not an OpenEXR file: {path}")
    pos = 8
    try:
        while pos < len(head) and head[pos] != 0:
            end = head.index(b"\0", pos)
            name = head[pos:end].decode("utf-8", "replace")
            tend = head.index(b"\0", end + 1)
            typ = head[end + 1:tend].decode("ascii", "replace")
            (size,) = struct.unpack_from("<i", head, tend + 1)
            data = head[tend + 5:tend + 5 + size]
            if len(data) != size:
                break
            if typ == "string":
                out[name] = data.decode("utf-8", "replace")
            elif typ == "float":
                out[name] = struct.unpack("<f", data)[0]
            elif typ == "chromaticities":
                out[name] = struct.unpack("<8f", data)
            else:
                out[name] = data
            pos = tend + 5 + size
    except (ValueError, struct.error):
        raise InputError(f"not a readable OpenEXR header: {path}") from None
    return out


def fill_exr_attribute(path: str | os.PathLike, name: str, text: str) -> bool:
    """Write ``text`` into the reserved ``string`` attribute ``name`` of an EXR written with
    :func:`reserved_text` as its value, in place (padded with spaces to the reserved length;
    nothing else in the file moves). False when the file has no such attribute or ``text``
    does not fit."""
    raw = text.encode("utf-8")
    key = name.encode() + b"\0string\0"
    with open(path, "r+b") as fh:
        head = fh.read(1 << 20)
        at = head.find(key)
        if at < 0:
            return False
        (size,) = struct.unpack_from("<i", head, at + len(key))
        if len(raw) > size:
            return False
        fh.seek(at + len(key) + 4)
        fh.write(raw + b" " * (size - len(raw)))
    return True


class reserved_text(str):
    """An attribute value of :func:`_exr_header` that reserves ``size`` bytes of spaces, to be
    filled after the pixels are written (:func:`fill_exr_attribute`): a merge's summary, known
    only once the map is done, in a file written while merging."""

    def __new__(cls, size: int):
        return super().__new__(cls, " " * int(size))


# --------------------------------------------------------------------------- EXR
#: EXR compressions by name: (OpenEXR compression id, scan lines per block). ``"none"``
#: writes fastest; ``"zip"`` (deflate, 16-line blocks) is ~30 % smaller, ~3x slower to write.
EXR_COMPRESSION = {"none": (0, 1), "zip": (3, 16)}


def _exr_attr(name: str, typ: str, data: bytes) -> bytes:
    return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(data)) + data


def _exr_header(w: int, h: int, channels: Sequence[str], pixel_type: int, compression: int,
                attributes: dict[str, str] | None = None) -> bytes:
    ch = b"".join(c.encode() + b"\0" + struct.pack("<iB3xii", pixel_type, 0, 1, 1) for c in channels) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    attrs = [
        _exr_attr("channels", "chlist", ch),
        _exr_attr("compression", "compression", struct.pack("<B", compression)),
        _exr_attr("dataWindow", "box2i", box),
        _exr_attr("displayWindow", "box2i", box),
        _exr_attr("lineOrder", "lineOrder", struct.pack("<B", 0)),
        _exr_attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        _exr_attr("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
        _exr_attr("screenWindowWidth", "float", struct.pack("<f", 1.0)),
    ]
    for name, value in sorted((attributes or {}).items()):
        if value is None:       # an attribute left out (e.g. a variance file's whiteLuminance)
            continue
        if not name or "\0" in name or len(name) > 31:
            raise InputError(f"EXR attribute names are 1-31 characters, got {name!r}")
        if isinstance(value, Chromaticities):
            if len(value) != 8:
                raise InputError("chromaticities are 8 numbers")
            attrs.append(_exr_attr(name, "chromaticities", struct.pack("<8f", *(float(v) for v in value))))
        elif isinstance(value, float):
            attrs.append(_exr_attr(name, "float", struct.pack("<f", value)))
        else:
            attrs.append(_exr_attr(name, "string", str(value).encode("utf-8")))
    return struct.pack("<ii", 20000630, 2) + b"".join(attrs) + b"\0"


def _deflate(level: int) -> Callable[[bytes], bytes]:
    try:
        import imagecodecs

        imagecodecs.deflate_encode(b"x", level=level)
        return lambda b: imagecodecs.deflate_encode(b, level=level)  # libdeflate, zlib format
    except Exception:  # noqa: BLE001
        return lambda b: zlib.compress(b, level)


def _zip_chunk(raw: np.ndarray, deflate: Callable[[bytes], bytes]):
    """OpenEXR ZIP: split even/odd bytes, delta predictor (+128), zlib; ``raw`` itself when not smaller."""
    n = raw.size
    half = (n + 1) // 2
    tmp = np.empty(n, dtype=np.uint8)
    tmp[:half] = raw[0::2]
    tmp[half:] = raw[1::2]
    d = np.empty_like(tmp)
    d[0] = tmp[0]
    np.subtract(tmp[1:], tmp[:-1], out=d[1:])
    d[1:] += np.uint8(128)
    comp = deflate(d)
    return comp if len(comp) < n else raw


def write_exr_fast(path: str | os.PathLike, image: np.ndarray, *, half: bool = False,
                   inputs: Iterable[str | os.PathLike] = (), compression: str = "zip", level: int = 1,
                   threads: int | None = None, probe: int = 16, min_saving: float = 0.1,
                   attributes: dict[str, str] | None = None) -> Path:
    """Write an (H, W, 3) RGB float image as a scanline OpenEXR file (ZIP), atomically.

    Blocks of 16 lines are converted and compressed as OpenEXR's ZIP_COMPRESSION
    (even/odd byte split, delta predictor, zlib stream by libdeflate at ``level``) in a
    thread pool and written in order, so the image is never copied whole; planar views
    (``(3, H, W)`` memory transposed) are read without gathering. A ZIP file may store a
    block uncompressed (readers recognise it by its size), which this writer does when
    compression does not pay: in each group of ``probe`` blocks the first is compressed
    and the others only if it saved at least ``min_saving`` (float32 camera radiance
    hardly compresses: ~5 %; ``probe=1`` compresses every block). Deterministic bytes.
    ``compression="none"`` writes uncompressed lines. Non-finite values are refused
    (like :func:`derender.io.write_exr`); with ``half=True`` values beyond the half-float
    range are clipped to +-65504 instead of becoming inf. ``attributes``: extra string
    attributes of the header (e.g. ``derender:reference``): text, or a float (``float``
    attribute), or :class:`Chromaticities` (:func:`colour_attributes`); None leaves the name out. See :func:`write_exr_lines`
    for images produced block by block.
    """
    arr = image
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"cannot write image of shape {arr.shape} to EXR")

    def bgr_lines(y0: int, y1: int, buf: np.ndarray) -> None:
        for k, c in enumerate((2, 1, 0)):  # channels in alphabetical order: B, G, R
            buf[:, k, :] = arr[y0:y1, :, c]

    return write_exr_lines(path, arr.shape[1], arr.shape[0], bgr_lines, half=half, inputs=inputs,
                           compression=compression, level=level, threads=threads, probe=probe,
                           min_saving=min_saving, attributes=attributes)


def write_exr_lines(path: str | os.PathLike, width: int, height: int,
                    lines: Callable[[int, int, np.ndarray], None], *, half: bool = False,
                    inputs: Iterable[str | os.PathLike] = (), compression: str = "zip", level: int = 1,
                    threads: int | None = None, probe: int = 16, min_saving: float = 0.1,
                    rows_read: Callable[[int], None] | None = None,
                    attributes: dict[str, str] | None = None) -> Path:
    """:func:`write_exr_fast` for an image that exists only block by block.

    ``lines(y0, y1, buf)`` fills ``buf`` (float32, shape ``(y1 - y0, 3, width)``) with rows
    ``y0:y1`` in planar B, G, R order (the alphabetical channel order of the file). It is
    called from a thread pool on blocks of at most 16 rows, so it must be thread-safe and
    should release the GIL (NumPy gathers and arithmetic do). Non-finite values are
    refused; the other options are :func:`write_exr_fast`'s. ``rows_read(y)``, if given, is
    called (in the calling thread, ``y`` rising) once rows ``0:y`` have been read through
    ``lines``: their memory may be reused from then on.
    """
    from derender.io.files import atomic_output

    w, h = int(width), int(height)
    if w < 1 or h < 1:
        raise InputError(f"cannot write an empty {w}x{h} image to EXR")
    if compression not in EXR_COMPRESSION:
        raise InputError(f"compression must be one of {', '.join(EXR_COMPRESSION)}, got {compression!r}")
    comp_id = EXR_COMPRESSION[compression][0]
    n_blocks = (h + 15) // 16 if comp_id == 3 else h
    header = _exr_header(w, h, "BGR", 1 if half else 2, comp_id, attributes)
    chunks = _ExrChunks(w, h, lines, half=half, deflate=_deflate(level), probe=max(1, int(probe)),
                        min_saving=min_saving)
    nthreads = thread_count(threads)
    path = Path(path)
    with atomic_output(path, inputs) as tmp, open(tmp, "wb") as fh:
        fh.write(header)
        table_pos = len(header)
        fh.write(b"\0" * (8 * n_blocks))
        offsets = chunks.write(fh, len(header) + 8 * n_blocks, n_blocks, zipped=comp_id != 0,
                               nthreads=nthreads, rows_read=rows_read)
        fh.seek(table_pos)
        fh.write(offsets.tobytes())
    return path


class _ExrChunks:
    """The chunks of a scanline EXR made from ``lines(y0, y1, buf)`` (:func:`write_exr_lines`): uncompressed
    lines, or ZIP blocks of 16 lines stored raw when a group of ``probe`` blocks' first saves less
    than ``min_saving``."""

    def __init__(self, w: int, h: int, lines: Callable[[int, int, np.ndarray], None], *, half: bool,
                 deflate: Any, probe: int, min_saving: float):
        self.w, self.h, self.lines, self.half = w, h, lines, half
        self.dtype = np.dtype("<f2") if half else np.dtype("<f4")
        self.deflate, self.probe, self.min_saving = deflate, probe, min_saving
        self.firsts: dict[int, Future] = {}

    def raw_lines(self, y0: int, y1: int) -> np.ndarray:
        """Rows ``y0:y1`` from ``lines``, planar (rows, 3, W), checked finite, in the file's type."""
        import cv2

        w = self.w
        buf = np.empty((y1 - y0, 3, w), dtype=np.float32)
        self.lines(y0, y1, buf)
        if not cv2.checkRange(buf.reshape(-1, w))[0]:
            raise ValueError("refusing to write NaN/inf to EXR (internal error)")
        if self.half:
            return np.clip(buf, -65504.0, 65504.0).astype(self.dtype)
        return buf

    def lines_task(self, g: int) -> list[tuple[int, np.ndarray]]:
        """16 uncompressed lines from line ``16 g`` as (y, line) chunks."""
        y0, y1 = g * 16, min(self.h, g * 16 + 16)
        buf = self.raw_lines(y0, y1)
        return [(y, buf[y - y0].reshape(-1).view(np.uint8)) for y in range(y0, y1)]

    def block_task(self, b: int) -> tuple[list[tuple[int, object]], bool]:
        """ZIP block ``b`` (16 lines) as one chunk, and (first block of its group) whether
        compressing it saved ``min_saving``. The other blocks of the group are compressed
        only if it did: they wait for the group's first block, always submitted before them
        (the pool takes tasks in order, so no wait can block the block it waits for)."""
        y0, y1 = b * 16, min(self.h, b * 16 + 16)
        raw = self.raw_lines(y0, y1).reshape(-1).view(np.uint8)
        probe = self.probe
        first = (b // probe) * probe
        if b == first:
            data = _zip_chunk(raw, self.deflate)
            return [(y0, data)], not len(data) > (1.0 - self.min_saving) * raw.size
        squeeze = self.firsts[b // probe].result()[1]
        return [(y0, _zip_chunk(raw, self.deflate) if squeeze else raw)], False

    def write(self, fh: Any, pos: int, n_blocks: int, *, zipped: bool, nthreads: int,
              rows_read: Callable[[int], None] | None) -> np.ndarray:
        """Make the chunks in ``nthreads`` threads and write them in order to ``fh`` from offset
        ``pos``; their offsets (the file's offset table)."""
        h, probe, firsts = self.h, self.probe, self.firsts
        n_tasks = n_blocks if zipped else (h + 15) // 16
        offsets = np.empty(n_blocks, dtype="<u8")
        i = 0
        with ThreadPoolExecutor(nthreads, thread_name_prefix="derender-exr") as ex:
            futs: deque = deque()
            nxt = 0
            window = 2 * nthreads + 2
            for _ in range(n_tasks):
                while nxt < n_tasks and len(futs) < window:
                    if not zipped:
                        futs.append(ex.submit(self.lines_task, nxt))
                    else:
                        fut = ex.submit(self.block_task, nxt)
                        if nxt % probe == 0:
                            firsts[nxt // probe] = fut
                        futs.append(fut)
                    nxt += 1
                res = futs.popleft().result()
                y_end = 0
                for y, data in (res[0] if zipped else res):
                    offsets[i] = pos
                    size = len(data) if isinstance(data, bytes) else data.nbytes
                    fh.write(struct.pack("<ii", y, size))
                    fh.write(data)
                    pos += 8 + size
                    i += 1
                    y_end = y + (16 if zipped else 1)
                if rows_read is not None:      # this task's rows (and every earlier one's) are read
                    rows_read(min(h, y_end))
                if zipped and i % probe == 0:
                    firsts.pop(i // probe - 1, None)
        return offsets
