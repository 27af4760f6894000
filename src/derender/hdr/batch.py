"""Merge many brackets (``derender merge-batch``), serially or on Dask.

A *stack folder* holds one bracket: its images directly or in a ``jpeg/`` subfolder
(as the simulator writes), with exposure times in EXIF or in a ``times.txt``
(``FILENAME SECONDS`` lines). Each stack becomes ``OUTDIR/<folder name>.exr``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable, Sequence

from derender.core.errors import DerenderError, InputError
from derender.core.types import HDRResult

__all__ = [
    "stack_files",
    "merge_one_stack",
    "merge_batch",
]


def stack_files(folder: str | os.PathLike) -> tuple[list[Path], Path | None]:
    """Image files of a stack folder (sorted) and its ``times.txt`` if present."""
    from derender.io.files import folder_images

    d = Path(folder)
    if not d.is_dir():
        raise InputError(f"no such stack folder: {d}")
    files = folder_images(d)
    if len(files) < 2:
        raise InputError(f"{d}: a stack folder needs at least two images")
    times = d / "times.txt"
    return files, (times if times.is_file() else None)


def merge_one_stack(folder: str, outdir: str, method: str, seed: int = 0, half: bool = False) -> dict:
    """Merge one stack folder into ``outdir/<name>.exr``; a user error is reported, not raised."""
    from derender.engine.options import EngineOptions, OutputOptions
    from derender.hdr.files import merge_files
    from derender.hdr.registry import seeded_options

    name = Path(folder).name
    out = Path(outdir) / f"{name}.exr"
    t0 = time.perf_counter()
    try:
        files, times_file = stack_files(folder)
        result = merge_files(files, None, method, seeded_options(method, seed), times_file=times_file,
                             output=OutputOptions(output=out, half=half, hold_outputs=False),   # written band by band
                             engine=EngineOptions(threads=1), inputs=files)
    except DerenderError as exc:
        return {"stack": name, "ok": False, "error": str(exc)}
    return {"stack": name, "ok": True, "output": str(out), "seconds": time.perf_counter() - t0,
            "shape": list(result.mask.shape[:2]), "over_exposed_px": int((result.mask == HDRResult.MASK_BRIGHT).sum()),
            "under_exposed_px": int((result.mask == HDRResult.MASK_DARK).sum())}


def merge_batch(folders: Sequence[str | os.PathLike], outdir: str | os.PathLike, method: str = "debevec",
                scheduler: str | None = "local", workers: int = 2, seed: int = 0, half: bool = False,
                progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Merge every stack folder; returns one status row per stack, in the given order."""
    from derender.core.parallel import run_tasks

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    names = [Path(f).name for f in folders]
    if len(set(names)) != len(names):
        raise InputError("stack folders must have distinct names (they name the outputs)")
    return run_tasks(merge_one_stack, [(str(f), str(outdir), method, seed, half) for f in folders],
                     scheduler=scheduler, workers=workers, progress=progress)
