"""File input and output: rendered stacks, RAW/DNG frames, OpenEXR, Radiance HDR, previews.

Every reader raises :class:`~derender.errors.InputError` with a one-line message for a
user mistake (missing, corrupt or inconsistent files); every writer is atomic (write to
a temporary file in the destination folder, then rename) and refuses to overwrite one of
the inputs it was given.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from fractions import Fraction
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from .errors import InputError
from .stack import RawFrame, Stack, validate_times

__all__ = [
    "read_image",
    "read_exif",
    "read_exposure_time",
    "parse_times",
    "read_times_file",
    "read_stack",
    "file_times",
    "read_raw",
    "read_raw_stack",
    "write_exr",
    "read_exr",
    "read_hdr",
    "read_radiance",
    "write_png",
    "write_preview",
    "atomic_output",
    "check_not_input",
]

RASTER_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}
RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".raw"}


# --------------------------------------------------------------------------- outputs
@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, inputs: Iterable[str | os.PathLike] = ()):
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    Nothing is left behind on failure, and ``path`` may not be one of ``inputs``.
    The temporary name keeps the suffix so that format-sniffing writers work.
    """
    path = Path(path)
    check_output(path, inputs)
    parent = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def check_output(path: str | os.PathLike, inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Raise :class:`InputError` unless ``path`` can be written as a new or replaced file:
    its folder exists, it is not a folder, and it is none of ``inputs`` (checked before any
    work, so a user mistake costs nothing)."""
    path = Path(path)
    check_not_input(path, inputs)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"output folder does not exist: {parent}")
    if path.is_dir():
        raise InputError(f"output {path} is a folder; give a file name")


def check_not_input(path: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """Raise :class:`InputError` if ``path`` names the same file as one of ``inputs``."""
    out = Path(path).resolve()
    for p in inputs:
        if Path(p).resolve() == out:
            raise InputError(f"refusing to overwrite input file {p}")


# --------------------------------------------------------------------------- rasters
def read_bytes(path: str | os.PathLike) -> np.ndarray:
    """The bytes of an existing, non-empty file as uint8 (clear errors otherwise)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise InputError(f"empty file: {path}")
    return data


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


def _ratio_to_float(value) -> float | None:
    try:
        if hasattr(value, "num") and hasattr(value, "den"):
            return float(value.num) / float(value.den) if value.den else None
        if hasattr(value, "numerator") and hasattr(value, "denominator"):
            return float(value.numerator) / float(value.denominator) if value.denominator else None
        return float(Fraction(str(value)))
    except (ValueError, ZeroDivisionError, TypeError):
        return None


def read_exif(path: str | os.PathLike) -> dict:
    """EXIF fields we use: ``ExposureTime`` (s), ``Make``, ``Model``, ``ISO``, ``FNumber``.

    Missing fields are absent from the dict; unreadable EXIF gives an empty dict.
    """
    info: dict = {}
    try:
        import logging

        import exifread

        logging.getLogger("exifread").setLevel(logging.ERROR)   # "PNG file does not have exif data." etc.

        with open(path, "rb") as fh:
            tags = exifread.process_file(fh, details=False)
        mapping = {
            "EXIF ExposureTime": "ExposureTime",
            "Image ExposureTime": "ExposureTime",
            "EXIF FNumber": "FNumber",
            "EXIF ISOSpeedRatings": "ISO",
            "Image Make": "Make",
            "Image Model": "Model",
        }
        for key, name in mapping.items():
            if key in tags and name not in info:
                val = tags[key]
                if name in ("Make", "Model"):
                    info[name] = str(val.printable).strip().strip("\x00")
                else:
                    v = _ratio_to_float(val.values[0] if getattr(val, "values", None) else val)
                    if v is not None and np.isfinite(v) and v > 0:
                        info[name] = v
    except Exception:  # noqa: BLE001 - any EXIF parser failure means "no EXIF"
        pass
    if "ExposureTime" not in info:
        try:
            from PIL import Image

            with Image.open(path) as im:
                exif = im.getexif()
                sub = exif.get_ifd(0x8769) if exif else {}
                for src in (sub, exif):
                    if src and 0x829A in src:
                        v = _ratio_to_float(src[0x829A])
                        if v is not None and np.isfinite(v) and v > 0:
                            info["ExposureTime"] = v
                            break
                if exif:
                    info.setdefault("Make", str(exif.get(0x010F, "")).strip("\x00 ") or None)
                    info.setdefault("Model", str(exif.get(0x0110, "")).strip("\x00 ") or None)
        except Exception:  # noqa: BLE001
            pass
    return {k: v for k, v in info.items() if v is not None}


def read_exposure_time(path: str | os.PathLike) -> float | None:
    """EXIF ``ExposureTime`` of a file in seconds, or None."""
    return read_exif(path).get("ExposureTime")


_NUMBER = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)(?:\s*/\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?))?\s*$")


def _parse_number(text: str, what: str) -> float:
    m = _NUMBER.match(text)
    if not m:
        raise InputError(f"cannot read {what} {text!r}: use numbers like 0.01 or 1/60")
    num = float(m.group(1))
    if m.group(2) is not None:
        den = float(m.group(2))
        if den == 0:
            raise InputError(f"cannot read {what} {text!r}: division by zero")
        num /= den
    return num


def parse_times(text: str) -> list[float]:
    """Parse ``"0.01,0.1,1/30"`` into seconds."""
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    if not parts:
        raise InputError("--times is empty")
    return [_parse_number(p, "exposure time") for p in parts]


def read_times_file(path: str | os.PathLike, inverse: bool = False) -> dict[str, float]:
    """Read ``FILENAME SECONDS`` lines (``#`` comments allowed) into ``{name: seconds}``.

    With ``inverse=True`` the second column is 1/time, as in HDRShop/Debevec image
    lists such as ``memorial.hdr_image_list.txt``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such times file: {path}")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        raise InputError(f"times file is not text: {path}") from None
    out: dict[str, float] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) < 2:
            raise InputError(f"{path}:{lineno}: expected 'FILENAME SECONDS', got {line!r}")
        value = _parse_number(fields[1], f"time on line {lineno} of {path.name}")
        if value <= 0:
            raise InputError(f"{path}:{lineno}: exposure value must be positive")
        name = Path(fields[0]).name
        if name in out:
            raise InputError(f"{path}:{lineno}: {name} listed twice")
        out[name] = 1.0 / value if inverse else value
    if not out:
        raise InputError(f"times file lists no images: {path}")
    return out


def file_times(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
               times_file: str | os.PathLike | None = None, times_file_inverse: bool = False) -> np.ndarray:
    """Exposure times of image files without decoding them, in the order of ``paths``.

    From ``times`` (one per path), else ``times_file`` (matched by file name), else each
    file's EXIF ``ExposureTime``; checks the paths exist, are distinct and not RAW files.
    """
    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise InputError("an exposure stack needs at least two images")
    seen: set[Path] = set()
    for p in paths:
        r = p.resolve()
        if r in seen:
            raise InputError(f"the same file is given twice: {p}")
        seen.add(r)
    for p in paths:
        if not p.is_file():
            raise InputError(f"no such file: {p}")
        if p.suffix.lower() in RAW_SUFFIXES:
            raise InputError(f"{p} is a RAW file; use 'derender groundtruth' for RAW brackets")
    if times is not None:
        t = [float(x) for x in times]
        if len(t) != len(paths):
            raise InputError(f"{len(t)} exposure time(s) given for {len(paths)} image(s)")
    elif times_file is not None:
        table = read_times_file(times_file, inverse=times_file_inverse)
        missing = [p.name for p in paths if p.name not in table]
        if missing:
            raise InputError(f"times file {times_file} has no entry for: {', '.join(missing)}")
        t = [table[p.name] for p in paths]
    else:
        t, missing = [], []
        for p in paths:
            v = read_exposure_time(p)
            if v is None:
                missing.append(p.name)
            t.append(v if v is not None else 0.0)
        if missing:
            raise InputError(f"no EXIF ExposureTime in {', '.join(missing)}; give --times or --times-file")
    return validate_times(t, len(paths))


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


# --------------------------------------------------------------------------- RAW
def _dng_tags(path: Path) -> dict:
    """Colour tags of a DNG read directly (LibRaw does not expose ColorMatrix1 for all DNGs)."""
    import tifffile

    tags: dict = {}
    try:
        with tifffile.TiffFile(path) as tif:
            for page in tif.pages:
                for tag in page.tags.values():
                    if tag.name in ("ColorMatrix1", "ColorMatrix2", "AsShotNeutral", "CalibrationIlluminant1",
                                    "CalibrationIlluminant2", "ExposureTime", "Make", "Model", "UniqueCameraModel"):
                        tags.setdefault(tag.name, tag.value)
                exif = page.tags.get("ExifTag")
                if exif is not None and isinstance(exif.value, dict) and "ExposureTime" in exif.value:
                    tags.setdefault("ExposureTime", exif.value["ExposureTime"])
                break
    except Exception:  # noqa: BLE001
        return {}
    return tags


def _rationals(values) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size % 2 == 0 and v.size >= 2:
        num, den = v[0::2], v[1::2]
        if np.all(den != 0):
            return num / den
    return v


def read_raw(path: str | os.PathLike) -> RawFrame:
    """Read a RAW/DNG file with rawpy (LibRaw): mosaic, CFA, levels, WB, colour matrix, time."""
    import rawpy

    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    try:
        with rawpy.imread(str(path)) as raw:
            mosaic = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            desc = raw.color_desc.decode("ascii", "replace")
            pattern = np.asarray(raw.raw_pattern)
            if raw.num_colors != 3 or pattern.shape != (2, 2) or mosaic.ndim != 2:
                raise InputError(f"{path}: only 2x2 Bayer RAW files are supported")
            cfa = "".join(desc[int(c)] for c in pattern.reshape(-1))
            cfa = cfa.replace("g", "G")
            black_ch = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            black = black_ch[pattern]
            white = float(raw.white_level)
            wb4 = np.asarray(raw.camera_whitebalance, dtype=np.float64)
            xyz_cam = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3, :3]
            cmat = np.asarray(raw.color_matrix, dtype=np.float64)[:3, :3]
            shutter = float(raw.other.shutter_speed) if hasattr(raw, "other") else 0.0
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - LibRaw raises many types
        raise InputError(f"cannot read RAW file {path}: {type(exc).__name__}: {exc}".rstrip(": ")) from None
    if set(cfa) != {"R", "G", "B"}:
        raise InputError(f"{path}: unsupported CFA pattern {cfa}")
    tags = _dng_tags(path) if path.suffix.lower() == ".dng" else {}
    # white balance multipliers as R, G, B with G = 1
    if "AsShotNeutral" in tags:
        neutral = _rationals(tags["AsShotNeutral"])[:3]
        wb = neutral[1] / neutral if np.all(neutral > 0) else np.ones(3)
    else:
        g = wb4[1] if wb4[1] > 0 else 1.0
        wb = np.array([wb4[0], g, wb4[2]]) / g
        if not np.all(wb > 0):
            wb = np.ones(3)
    # XYZ -> camera matrix (DNG ColorMatrix semantics)
    if "ColorMatrix1" in tags:
        xyz_to_camera = _rationals(tags["ColorMatrix1"])[:9].reshape(3, 3)
    elif np.any(xyz_cam != 0):
        xyz_to_camera = xyz_cam
    elif np.any(cmat != 0) and abs(np.linalg.det(cmat)) > 1e-9:
        from .colorimetry import LINEAR_SRGB_TO_XYZ

        xyz_to_camera = np.linalg.inv(LINEAR_SRGB_TO_XYZ @ cmat)
    else:
        xyz_to_camera = None
    exposure = None
    if "ExposureTime" in tags:
        v = _rationals(tags["ExposureTime"])
        if v.size and v[0] > 0:
            exposure = float(v[0])
    if exposure is None and shutter > 0 and shutter != 1.0:
        exposure = shutter
    if exposure is None:
        exposure = read_exposure_time(path)
    make = str(tags.get("Make", "")).strip("\x00 ")
    model = str(tags.get("Model", tags.get("UniqueCameraModel", ""))).strip("\x00 ")
    return RawFrame(
        mosaic=mosaic,
        cfa_pattern=cfa,
        black_level=black,
        white_level=white,
        as_shot_wb=wb,
        xyz_to_camera=xyz_to_camera,
        exposure_time=exposure,
        path=str(path),
        make=make,
        model=model,
    )


def read_raw_stack(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None) -> list[RawFrame]:
    """Read RAW frames sorted by exposure time (times from the files unless given)."""
    frames = [read_raw(p) for p in paths]
    if not frames:
        raise InputError("no RAW files given")
    if times is not None:
        t = validate_times(times, len(frames))
        for f, v in zip(frames, t):
            f.exposure_time = float(v)
    shapes = {f.mosaic.shape for f in frames}
    if len(shapes) > 1:
        raise InputError(f"RAW frames differ in size: {sorted(shapes)}")
    if len(frames) > 1:
        missing = [Path(f.path).name for f in frames if f.exposure_time is None]
        if missing:
            raise InputError(f"no exposure time in {', '.join(missing)}; give --times")
        validate_times([f.exposure_time for f in frames], len(frames))
        frames.sort(key=lambda f: f.exposure_time)
    return frames


# --------------------------------------------------------------------------- EXR / HDR
def write_exr(path: str | os.PathLike, image: np.ndarray, half: bool = False,
              inputs: Iterable[str | os.PathLike] = (), channels: str = "RGB") -> Path:
    """Write an (H, W, 3) or (H, W) float image to OpenEXR atomically (ZIP compression).

    Non-finite values are refused: no result of this library may hold NaN or inf.
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
    """Read an OpenEXR file as float32 (H, W, 3) (RGB) or (H, W) (single channel)."""
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


def read_hdr(path: str | os.PathLike) -> np.ndarray:
    """Read a Radiance RGBE ``.hdr`` file tolerantly as float32 (H, W, 3).

    Accepts header lines before ``#?RADIANCE`` (Debevec's ``memorial.hdr`` starts
    with ``VIEW=``), flat and new-style run-length encoded scanlines, and the
    ``-Y H +X W`` orientation (others are flipped into it).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such file: {path}")
    data = path.read_bytes()
    # header: lines up to an empty line
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
    buf = np.frombuffer(data, dtype=np.uint8, offset=pos)
    rgbe = np.zeros((height, width, 4), dtype=np.uint8)
    i = 0
    try:
        for y in range(height):
            if width >= 8 and width < 32768 and buf[i] == 2 and buf[i + 1] == 2 and (buf[i + 2] & 0x80) == 0:
                if (int(buf[i + 2]) << 8 | int(buf[i + 3])) != width:
                    raise InputError(f"{path}: scanline width mismatch")
                i += 4
                for c in range(4):
                    x = 0
                    row = rgbe[y, :, c]
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
            else:
                n = width * 4
                if i + n > buf.size:
                    raise InputError(f"{path}: file truncated")
                rgbe[y] = buf[i:i + n].reshape(width, 4)
                i += n
    except IndexError:
        raise InputError(f"{path}: file truncated") from None
    e = rgbe[:, :, 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0).astype(np.float32)
    img = rgbe[:, :, :3].astype(np.float32) * scale[:, :, None]
    # orientation to -Y +X (top row first, left to right)
    if dims["Y"][0] == "+":
        img = img[::-1]
    if dims["X"][0] == "-":
        img = img[:, ::-1]
    if res[0][1] == "X":  # X major: transpose
        img = np.transpose(img, (1, 0, 2))
    img /= np.float32(exposure)
    return np.ascontiguousarray(img, dtype=np.float32)


def read_radiance(path: str | os.PathLike) -> np.ndarray:
    """Read a linear radiance map from ``.exr`` or ``.hdr`` as float32 (H, W, 3)."""
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


# --------------------------------------------------------------------------- previews
def write_png(path: str | os.PathLike, image: np.ndarray, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Write an (H, W, 3) float image in [0, 1] (or uint8/uint16) to PNG atomically."""
    import cv2

    arr = np.asarray(image)
    if arr.dtype.kind == "f":
        arr = np.rint(np.clip(np.nan_to_num(arr), 0.0, 1.0) * 255.0).astype(np.uint8)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        ok, enc = cv2.imencode(".png", np.ascontiguousarray(arr))
        if not ok:
            raise InputError(f"could not encode PNG for {path}")
        enc.tofile(tmp)
    return path


def write_preview(path: str | os.PathLike, radiance: np.ndarray, inputs: Iterable[str | os.PathLike] = (),
                  key: float = 0.18) -> Path:
    """Tone-map a linear-sRGB radiance map (Reinhard et al. 2002) and write it as 8-bit sRGB PNG."""
    from .tonemap import reinhard_photographic, encode_srgb

    return write_png(path, encode_srgb(reinhard_photographic(radiance, key=key)), inputs)
