"""Radiance RGBE (``.hdr``) files: read by our own parser, written with Radiance's header conventions.

Reading, why our own: Debevec's own ``memorial.hdr`` starts with a ``VIEW=`` line before
``#?RADIANCE``, which OpenCV's and imageio's strict readers refuse; the parser accepts
the header lines in any order, flat and run-length-encoded scanlines and the ``-Y +X``
orientation. :func:`read_radiance` reads either format by suffix.

Writing (:func:`write_hdr`): the pixels are encoded by OpenCV's RGBE writer (new-style
run-length scanlines, as Radiance writes them); only the header is ours, because OpenCV's
is fixed and carries none of the lines Radiance's programs read: ``FORMAT=32-bit_rle_rgbe``,
``EXPOSURE=`` (the factor the stored values were multiplied by, so that ``value / EXPOSURE``
is the radiance; Radiance's ``pvalue -o`` undoes it), ``PRIMARIES=`` (the chromaticities of
R, G, B and white: Rec. 709 / sRGB for derender's linear sRGB maps) and an optional
``VIEW=`` (the lens projection that ``evalglare`` and ``getinfo`` read, e.g.
``-vta -vh 180 -vv 180`` for an equidistant 180-degree fisheye). Files are checked against
Radiance's own ``getinfo`` and ``pvalue`` in the tests.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from derender.core.errors import InputError
from derender.io.exr import read_exr

__all__ = [
    "read_hdr",
    "read_radiance",
    "write_hdr",
    "read_hdr_header",
    "check_view",
    "SRGB_PRIMARIES",
]

#: Rec. 709 / sRGB primaries and D65 white (x, y of R, G, B, W), as ``PRIMARIES=`` writes them.
SRGB_PRIMARIES = (0.640, 0.330, 0.300, 0.600, 0.150, 0.060, 0.3127, 0.3290)


def write_hdr(path: str | os.PathLike, image: np.ndarray, *, exposure: float = 1.0, view: str | None = None,
              primaries: tuple[float, ...] | None = SRGB_PRIMARIES, software: str = "derender",
              inputs=(), header_lines: tuple[str, ...] | list[str] = ()) -> Path:
    """Write a linear (H, W, 3) RGB image as a Radiance RGBE file (module docstring).

    Stored values are ``image * exposure`` and the header says ``EXPOSURE=exposure``;
    ``view`` is written as ``VIEW= <view>`` after a check that it only holds Radiance view
    options (``-vt?``, ``-vp``, ``-vd``, ``-vu``, ``-vh``, ``-vv``, ``-vo``, ``-va``,
    ``-vs``, ``-vl`` and numbers). Negative or non-finite values are refused: a radiance map
    has neither. ``header_lines``: more lines of the header (``NAME= value``: getinfo prints
    them), one line each, printable ASCII. Written atomically (:func:`derender.io.files.atomic_output`)."""
    from derender.core.memory import import_cv2
    from derender.io.files import atomic_output

    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"write_hdr needs an (H, W, 3) image, got shape {img.shape}")
    if not np.all(np.isfinite(img)) or float(img.min(initial=0.0)) < 0.0:
        raise InputError("a Radiance file holds finite non-negative values; the image has others")
    if not (np.isfinite(exposure) and exposure > 0):
        raise InputError(f"EXPOSURE must be a positive number, got {exposure!r}")
    lines = ["#?RADIANCE", f"SOFTWARE= {software}", "FORMAT=32-bit_rle_rgbe", f"EXPOSURE={exposure:.9g}"]
    if primaries is not None:
        if len(primaries) != 8:
            raise InputError("PRIMARIES needs 8 numbers: x y of R, G, B and white")
        lines.append("PRIMARIES= " + " ".join(f"{v:.4f}" for v in primaries))
    if view is not None:
        lines.append("VIEW= " + check_view(view))
    for line in header_lines:
        if not line.isascii() or not line.isprintable() or not line.strip():
            raise InputError(f"a Radiance header line is one line of printable ASCII, got {line!r}")
        lines.append(line)
    cv2 = import_cv2()
    scaled = img * np.float32(exposure) if exposure != 1.0 else img
    ok, buf = cv2.imencode(".hdr", np.ascontiguousarray(scaled[:, :, ::-1]))
    if not ok:  # pragma: no cover - OpenCV's RGBE encoder does not fail on finite float32
        raise InputError("OpenCV could not encode the RGBE data")
    data = buf.tobytes()
    end = data.find(b"\n\n")
    if end < 0 or not data[end + 2:].startswith(b"-Y "):
        raise InputError("unexpected RGBE stream from OpenCV (no header end before -Y)")  # pragma: no cover
    header = ("\n".join(lines) + "\n\n").encode("ascii")
    with atomic_output(path, inputs) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(data[end + 2:])
    return Path(path)


_VIEW_WORDS = {"-vtv", "-vtl", "-vta", "-vth", "-vts", "-vtc", "-vp", "-vd", "-vu", "-vh", "-vv", "-vo", "-va",
               "-vs", "-vl"}


def check_view(view: str) -> str:
    """``view`` with its words re-joined, after a check that it holds only Radiance view
    options and numbers (what may follow ``VIEW=`` in a header; an :class:`InputError` otherwise)."""
    words = view.split()
    for w in words:
        if w in _VIEW_WORDS:
            continue
        try:
            float(w)
        except ValueError:
            raise InputError(f"--view {view!r}: {w!r} is not a Radiance view option (e.g. '-vta -vh 180 -vv 180')") \
                from None
    if not words:
        raise InputError("--view is empty")
    return " ".join(words)


def read_hdr(path: str | os.PathLike) -> np.ndarray:
    """Read a Radiance RGBE ``.hdr`` file tolerantly as float32 (H, W, 3), decoded as
    Radiance decodes it (``pvalue -o``: mantissa + 0.5, divided by ``EXPOSURE``).

    Accepts header lines before ``#?RADIANCE`` (Debevec's ``memorial.hdr`` starts
    with ``VIEW=``), flat and new-style run-length encoded scanlines, and the
    ``-Y H +X W`` orientation (others are flipped into it).

    Parameters
    ----------
    path : path-like
        A Radiance ``.hdr`` (RGBE) file.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) float32 linear RGB, finite and non-negative.

    Raises
    ------
    InputError
        A missing, truncated or malformed file, or an unsupported format (XYZE).

    Examples
    --------
    A file written by :func:`derender.io.rgbe.write_hdr`; RGBE keeps 8 bits of mantissa
    with one exponent per pixel, so each value comes back to within about 0.4 % of its
    pixel's largest channel:

    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> from derender.io.rgbe import write_hdr
    >>> radiance = np.array([[[0.01, 0.1, 1.0], [10.0, 100.0, 1000.0]]], np.float32)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     back = derender.read_hdr(write_hdr(os.path.join(folder, "scene.hdr"), radiance))
    >>> back.shape, back.dtype
    ((1, 2, 3), dtype('float32'))
    >>> bool(np.all(np.abs(back - radiance).max(axis=2) <= 0.004 * radiance.max(axis=2)))
    True
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    data = path.read_bytes()
    header_lines, pos = _rgbe_header(data, path)
    exposure = 1.0
    for h in header_lines:
        if h.startswith(b"EXPOSURE="):
            with contextlib.suppress(ValueError):
                exposure *= float(h.split(b"=", 1)[1])
    nl = data.find(b"\n", pos)
    res = data[pos:nl].decode("ascii", "replace").split()
    pos = nl + 1
    if len(res) != 4:
        raise InputError(f"{path}: bad resolution line {' '.join(res)!r}")
    try:
        dims = {res[0][1]: (res[0][0], int(res[1])), res[2][1]: (res[2][0], int(res[3]))}
        height, width = dims["Y"][1], dims["X"][1]
    except (KeyError, ValueError, IndexError):
        raise InputError(f"{path}: bad resolution line {' '.join(res)!r}") from None
    if height <= 0 or width <= 0 or height * width > 2**31:
        raise InputError(f"{path}: bad image size {width}x{height}")
    rgbe = _rgbe_scanlines(np.frombuffer(data, dtype=np.uint8, offset=pos), height, width, path)
    e = rgbe[:, :, 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0).astype(np.float32)
    # Radiance's own decoding (colr_color): the mantissa's centre, (m + 0.5) 2^(e - 136); a
    # zero exponent is black. OpenCV and imageio drop the 0.5 (0.2-0.4 % low on the largest
    # channel); pvalue is the format's definition.
    img = (rgbe[:, :, :3].astype(np.float32) + np.float32(0.5)) * scale[:, :, None]
    # orientation to -Y +X (top row first, left to right)
    if dims["Y"][0] == "+":
        img = img[::-1]
    if dims["X"][0] == "-":
        img = img[:, ::-1]
    if res[0][1] == "X":  # X major: transpose
        img = np.transpose(img, (1, 0, 2))
    img /= np.float32(exposure)
    return np.ascontiguousarray(img, dtype=np.float32)


def _rgbe_header(data: bytes, path: Path) -> tuple[list[bytes], int]:
    """The header lines of a Radiance file (up to the empty line) and the offset after them; an
    :class:`InputError` unless it is an RGBE Radiance file."""
    pos = 0
    header_lines = []
    while True:
        nl = data.find(b"\n", pos)
        if nl < 0:
            raise InputError(f"not a Radiance HDR file (no header end): {path}")
        line = data[pos:nl].rstrip(b"\r")
        pos = nl + 1
        if not line:
            break
        header_lines.append(line)
        if len(header_lines) > 1000:
            raise InputError(f"not a Radiance HDR file: {path}")
    if not any(h.startswith(b"#?") for h in header_lines) and not any(
        h.startswith(b"FORMAT=32-bit_rle_rgbe") for h in header_lines
    ):
        raise InputError(f"not a Radiance HDR file: {path}")
    if any(h.startswith(b"FORMAT=") and b"32-bit_rle_rgbe" not in h for h in header_lines):
        raise InputError(f"{path}: only RGBE Radiance files are supported (not XYZE)")
    return header_lines, pos


def _rgbe_scanlines(buf: np.ndarray, height: int, width: int, path: Path) -> np.ndarray:
    """Decode ``height`` scanlines (flat or new-style run-length encoded) into (H, W, 4) uint8 RGBE."""
    rgbe = np.zeros((height, width, 4), dtype=np.uint8)
    i = 0
    try:
        for y in range(height):
            if width >= 8 and width < 32768 and buf[i] == 2 and buf[i + 1] == 2 and (buf[i + 2] & 0x80) == 0:
                if (int(buf[i + 2]) << 8 | int(buf[i + 3])) != width:
                    raise InputError(f"{path}: scanline width mismatch")
                i += 4
                for c in range(4):
                    i = _rle_component(buf, i, rgbe[y, :, c], path)
            else:
                n = width * 4
                if i + n > buf.size:
                    raise InputError(f"{path}: file truncated")
                rgbe[y] = buf[i:i + n].reshape(width, 4)
                i += n
    except IndexError:
        raise InputError(f"{path}: file truncated") from None
    return rgbe


def _rle_component(buf: np.ndarray, i: int, row: np.ndarray, path: Path) -> int:
    """Decode one component of a run-length encoded scanline from ``buf[i:]`` into ``row``; the
    offset after it."""
    width = row.shape[0]
    x = 0
    while x < width:
        count = int(buf[i])
        i += 1
        if count > 128:
            count -= 128
            if x + count > width:
                raise InputError(f"{path}: corrupt run length data")
            row[x:x + count] = buf[i]
            i += 1
        else:
            if count == 0 or x + count > width or i + count > buf.size:
                raise InputError(f"{path}: corrupt or truncated run length data")
            row[x:x + count] = buf[i:i + count]
            i += count
        x += count
    return i


def read_hdr_header(path: str | os.PathLike) -> dict[str, str]:
    """The ``NAME=value`` lines of a Radiance file's header (``VIEW``, ``EXPOSURE``,
    ``PRIMARIES``, ``FORMAT``, ...), values stripped; a repeated ``EXPOSURE`` is multiplied
    out as Radiance does, a repeated ``VIEW`` appended. Lines before ``#?RADIANCE`` count
    (Debevec's ``memorial.hdr``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    out: dict[str, str] = {}
    with open(path, "rb") as fh:
        for _ in range(1000):
            line = fh.readline()
            if not line or not line.strip():
                break
            text = line.decode("latin-1").strip()
            name, sep, value = text.partition("=")
            if not sep or " " in name or name.startswith("#"):
                continue
            value = value.strip()
            if name == "EXPOSURE" and "EXPOSURE" in out:
                with contextlib.suppress(ValueError):
                    value = f"{float(out['EXPOSURE']) * float(value):.9g}"
            elif name == "VIEW" and "VIEW" in out:
                value = out["VIEW"] + " " + value
            out[name] = value
    return out


def read_radiance(path: str | os.PathLike) -> np.ndarray:
    """Read a linear radiance map from ``.exr`` or ``.hdr`` as float32 (H, W, 3).

    Parameters
    ----------
    path : path-like
        An OpenEXR (``.exr``) or Radiance (``.hdr``, ``.pic``, ``.rgbe``) file, told apart by
        the suffix.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) float32; a single-channel EXR is replicated to three channels.

    Raises
    ------
    InputError
        Another suffix, or a file the reader (:func:`read_exr`, :func:`read_hdr`) refuses.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = derender.write_exr(os.path.join(folder, "luminance.exr"), np.ones((2, 3), np.float32))
    ...     derender.read_radiance(path).shape
    (2, 3, 3)
    >>> try:
    ...     derender.read_radiance("radiance.tiff")
    ... except derender.InputError as error:
    ...     print(error)
    unknown radiance file type '.tiff': use .exr or .hdr
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".exr":
        img = read_exr(path)
    elif suffix in (".hdr", ".pic", ".rgbe"):
        img = read_hdr(path)
    else:
        raise InputError(f"unknown radiance file type {suffix!r}: use .exr or .hdr")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return img
