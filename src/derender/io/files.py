"""Safe file handling shared by every reader and writer: suffix sets, atomic outputs, input guards.

Every writer goes through :func:`atomic_output` (write to a temporary file in the
destination folder, then rename), which refuses to overwrite one of the inputs it was
given (:func:`check_not_input`, symlinks resolved). Readers raise
:class:`~derender.core.errors.InputError` with a one-line message for a user mistake.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from pathlib import Path
from typing import Iterable

import numpy as np

from derender.core.errors import InputError, interrupts_deferred

__all__ = [
    "RASTER_SUFFIXES",
    "RAW_SUFFIXES",
    "atomic_output",
    "check_output",
    "resolve_path",
    "OutputTransaction",
    "TEMP_PREFIX",
    "check_not_input",
    "check_input_file",
    "read_bytes",
    "folder_images",
    "folder_raw_files",
    "expand_image_paths",
]


#: Prefix of every temporary output (a short fixed name: a long output name still fits).
TEMP_PREFIX = ".derender-"


#: Suffixes of rendered images (8- or 16-bit; HEIC/HEIF and AVIF through Pillow).
RASTER_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".heic", ".heif", ".hif", ".avif"}


#: Suffixes taken as RAW files (read with rawpy / LibRaw).
RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".raw"}


# --------------------------------------------------------------------------- inputs given as folders
def folder_images(folder: str | os.PathLike) -> list[Path]:
    """The rendered images directly inside ``folder`` (or in its ``jpeg/`` subfolder, as
    ``derender simulate`` writes a bracket), by name: files whose suffix is one of
    :data:`RASTER_SUFFIXES` (any case), hidden files and derender's own temporaries left out.
    RAW files are not taken (a bracket is merged from its rendered images)."""
    d = Path(folder)
    src = d / "jpeg" if (d / "jpeg").is_dir() else d
    try:
        entries = sorted(src.iterdir())
    except OSError as exc:
        raise InputError(f"cannot list folder {d}: {exc.strerror or exc}") from None
    return [p for p in entries if p.suffix.lower() in RASTER_SUFFIXES and not p.name.startswith(".")
            and p.is_file()]


def folder_raw_files(folder: str | os.PathLike) -> list[Path]:
    """The RAW files (:data:`RAW_SUFFIXES`, any case) directly inside ``folder`` (or in its
    ``raw/`` subfolder, as ``derender simulate`` writes a bracket), by name."""
    d = Path(folder)
    src = d / "raw" if (d / "raw").is_dir() else d
    try:
        entries = sorted(src.iterdir())
    except OSError as exc:
        raise InputError(f"cannot list folder {d}: {exc.strerror or exc}") from None
    return [p for p in entries if p.suffix.lower() in RAW_SUFFIXES and not p.name.startswith(".") and p.is_file()]


def expand_image_paths(paths: Iterable[str | os.PathLike], raw: bool = False) -> list[Path]:
    """The image arguments of a command with every folder replaced by its images
    (:func:`folder_images`); files are kept as given. A folder without images is an error
    naming it and the suffixes looked for. The merge sorts the frames by exposure time
    afterwards, so a folder's name order does not matter. With ``raw``, a folder without
    rendered images stands for its RAW files (:func:`folder_raw_files`)."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if not p.exists() and not p.is_symlink():
            raise InputError(f"no such file or folder: {p}")
        if p.is_dir():
            found = folder_images(p)
            if not found and raw:
                found = folder_raw_files(p)
            if not found:
                looked = sorted(RASTER_SUFFIXES | (RAW_SUFFIXES if raw else set()))
                raise InputError(f"folder {p} holds no images (looked for {', '.join(looked)})")
            out.extend(found)
        else:
            out.append(p)
    return out


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
    umask = os.umask(0)
    os.umask(umask)
    tmp = None
    try:
        with interrupts_deferred():   # an interruption cannot fall between creating and owning the file
            fd, tmp = tempfile.mkstemp(prefix=TEMP_PREFIX, suffix=path.suffix, dir=parent)
            os.close(fd)
            os.chmod(tmp, 0o666 & ~umask)
        yield Path(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if exc.filename is None or str(exc.filename) == str(tmp):
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None   # name the output
        raise
    except BaseException:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        raise


def check_output(path: str | os.PathLike, inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Raise :class:`InputError` unless ``path`` can be written as a new or replaced file:
    its folder exists and is writable, its name fits the file system, it is not a folder
    nor a symlink loop, and it is none of ``inputs`` (also through symlinks). Checked before
    any work, so a user mistake costs nothing."""
    path = Path(path)
    check_not_input(path, inputs)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"output folder does not exist: {parent}")
    try:
        name_max = os.pathconf(parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    if len(os.fsencode(path.name)) > name_max:
        raise InputError(f"output file name too long ({len(os.fsencode(path.name))} bytes; the file system "
                         f"allows {name_max}): {path.name[:40]}...")
    if path.is_dir():
        raise InputError(f"output {path} is a folder; give a file name")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"permission denied: cannot write in the folder of {path}")
    if path.exists() and not os.access(path, os.W_OK) and not os.access(parent, os.W_OK):
        raise InputError(f"permission denied: cannot replace {path}")


def resolve_path(path: str | os.PathLike) -> Path:
    """``Path.resolve`` with a symlink loop reported as :class:`InputError`."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError):
        raise InputError(f"symbolic link loop: {path}") from None


def check_not_input(path: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """Raise :class:`InputError` if ``path`` names the same file as one of ``inputs``."""
    out = resolve_path(path)
    for p in inputs:
        if resolve_path(p) == out:
            raise InputError(f"refusing to overwrite input file {p}")


class OutputTransaction:
    """All outputs of one command, written as one transaction.

    :meth:`add` validates an output before any work (:func:`check_output`, its suffix, no
    two outputs the same file) and returns the temporary path the writer writes to (in the
    destination folder, so that the final rename is atomic). Leaving the ``with`` block
    normally renames every temporary into place; leaving it by an exception (a user error,
    ``OSError`` such as a full disk, or an interruption) removes them all, and an error that
    names a temporary is re-raised naming the user's path instead.
    """

    def __init__(self, inputs: Iterable[str | os.PathLike] = ()):
        self.inputs = [Path(p) for p in inputs]
        self.outputs: dict[Path, Path] = {}   # final path -> temporary path

    def add(self, path: str | os.PathLike | None, option: str = "output",
            suffixes: Iterable[str] | None = None) -> Path | None:
        if path is None:
            return None
        path = Path(path)
        allowed = tuple(s.lower() for s in suffixes) if suffixes else ()
        if allowed and path.suffix.lower() not in allowed:
            raise InputError(f"{option} must end in {' or '.join(allowed)}, got {path.name}")
        check_output(path, self.inputs)
        key = resolve_path(path)
        for other in self.outputs:
            if resolve_path(other) == key:
                raise InputError(f"two outputs are the same file: {path}")
        parent = path.parent if str(path.parent) else Path(".")
        with interrupts_deferred():   # an interruption here must not orphan the new temporary
            try:
                fd, tmp = tempfile.mkstemp(prefix=TEMP_PREFIX, suffix=path.suffix, dir=parent)
            except OSError as exc:
                self.rollback()
                raise InputError(f"cannot write {path}: {exc.strerror or exc}") from None
            os.close(fd)
            self.outputs[path] = Path(tmp)
        return Path(tmp)

    def rollback(self) -> None:
        with interrupts_deferred():
            for tmp in self.outputs.values():
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
            self.outputs = {}

    def commit(self) -> None:
        """Rename every temporary into place, with SIGINT/SIGTERM held back until all are
        (the permissions are set first, so the renames are the only step that can fail)."""
        umask = os.umask(0)
        os.umask(umask)
        with interrupts_deferred():   # all renames happen, or (on an OSError) the rest are rolled back
            for tmp in self.outputs.values():
                os.chmod(tmp, 0o666 & ~umask)
            for final, tmp in list(self.outputs.items()):
                os.replace(tmp, final)
                del self.outputs[final]

    def user_message(self, text: str) -> str:
        for final, tmp in self.outputs.items():
            text = text.replace(str(tmp), str(final)).replace(tmp.name, final.name)
        return text

    def __enter__(self) -> "OutputTransaction":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                self.commit()
            except OSError as err:
                message = self.user_message(f"cannot write outputs: {err.strerror or err}: {err.filename}")
                self.rollback()
                raise InputError(message) from None
            return False
        message = None
        if isinstance(exc, OSError):
            message = self.user_message(f"{exc.strerror or exc}: {exc.filename}" if exc.filename else
                                        f"{exc.strerror or exc}")
        elif isinstance(exc, InputError):
            message = self.user_message(str(exc))
        self.rollback()
        if message is not None and (isinstance(exc, OSError) or message != str(exc)):
            raise InputError(message) from None
        return False


# --------------------------------------------------------------------------- rasters
def check_input_file(path: str | os.PathLike) -> Path:
    """Raise :class:`InputError` with the accurate reason unless ``path`` is a readable file
    (missing, a folder, a symlink loop or dangling link, not readable)."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise InputError(f"broken symbolic link (its target does not exist): {path}") from None
        raise InputError(f"no such file: {path}") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(f"symbolic link loop: {path}") from None
        if exc.errno == errno.ENAMETOOLONG:
            raise InputError(f"file name too long: {path}") from None
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{path} is a folder, not a file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{path} is not a regular file")
    if not os.access(path, os.R_OK):
        raise InputError(f"permission denied reading {path}")
    return path


def read_bytes(path: str | os.PathLike) -> np.ndarray:
    """The bytes of an existing, non-empty file as uint8 (clear errors otherwise)."""
    path = check_input_file(path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    if data.size == 0:
        raise InputError(f"empty file: {path}")
    return data
