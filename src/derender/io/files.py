"""Safe file handling shared by every reader and writer: suffix sets, atomic outputs, input guards.

Every writer goes through :func:`atomic_output` (write to a temporary file in the
destination folder, then rename), which refuses to overwrite one of the inputs it was
given (:func:`check_not_input`, symlinks resolved). Readers raise
:class:`~derender.core.errors.InputError` with a one-line message for a user mistake.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterable

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "RASTER_SUFFIXES",
    "RAW_SUFFIXES",
    "atomic_output",
    "check_output",
    "check_not_input",
    "read_bytes",
]


#: Suffixes of rendered images read with OpenCV (8- or 16-bit).
RASTER_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}


#: Suffixes taken as RAW files (read with rawpy / LibRaw).
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
