"""A RAW+JPEG bracket in one call: paper 1's protocol (Sec. 4, Table 1) for the user's own camera.

Paper 1 scores a merge of a camera's JPEGs against a ground truth made from the RAW files of
the same shots. :func:`score_raw_jpeg` does that for one bracket shot as RAW+JPEG:

1. **Pairing** (:func:`pair_raw_jpeg`): as many RAW files as JPEGs, from one camera (RAW make
   and model against the JPEGs' EXIF), of one size, and the same exposure times: both sorted by
   time, each JPEG's EXIF ``ExposureTime`` within :data:`TIME_TOLERANCE` of its RAW frame's
   (a JPEG without one takes the time of the RAW file of the same name). Anything else is one
   :class:`~derender.core.errors.InputError`.
2. **Ground truth**: the RAW merge, as ``derender groundtruth`` makes it
   (:func:`derender.hdr.raw.merge_raw`: the noise-optimal estimator, or paper 1's eq. 11 with
   ``truth_method="paper1"``), in linear sRGB through the files' own colour matrix and as-shot
   white balance. No registration: the JPEG and RAW frames of one shot are the same exposure on
   the same sensor (a camera whose JPEG crops the sensor differently is refused by the size check).
3. **The merge** of the JPEGs with any registered method (:func:`derender.hdr.registry.merge_seeded`).
4. **Scores** as ``derender evaluate`` gives them (:func:`derender.evaluation.metrics.hdr_scores`:
   PSNR on R, G, B and luminance after one scale per plane, relative error after a 3x3 matrix or
   one scale, log-luminance PSNR), over the pixels the RAW merge measured (mask 0: a pixel
   over-exposed in every RAW frame is only a bound and is not scored).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult, RawFrame

__all__ = [
    "TIME_TOLERANCE",
    "RawJpegScore",
    "split_raw_rendered",
    "pair_raw_jpeg",
    "score_raw_jpeg",
]

#: Largest relative difference between a JPEG's EXIF exposure time and its RAW frame's.
TIME_TOLERANCE = 0.03


@dataclass
class RawJpegScore:
    """What :func:`score_raw_jpeg` returns: the RAW merge (``truth``), the JPEG merge
    (``result``), ``scores`` (:func:`~derender.evaluation.metrics.hdr_scores`), the pairs
    ``(raw name, jpeg name, seconds)`` shortest first, and the pixels scored / left out."""

    truth: HDRResult
    result: HDRResult
    scores: dict
    pairs: list
    n_scored: int
    n_unscored: int


def split_raw_rendered(paths: Sequence[str | os.PathLike]) -> tuple[list[Path], list[Path]]:
    """The RAW files and the rendered images among ``paths`` (files, or folders: a folder with
    ``raw/`` and ``jpeg/`` subfolders, the simulator's and paper 1's layout, stands for both;
    any other folder for the RAW files and images in it)."""
    from derender.io.files import RAW_SUFFIXES, folder_images, folder_raw_files

    raws: list[Path] = []
    rendered: list[Path] = []
    for p in map(Path, paths):
        if not p.exists():
            raise InputError(f"no such file or folder: {p}")
        if p.is_dir():
            if (p / "raw").is_dir() and (p / "jpeg").is_dir():
                raws += folder_raw_files(p / "raw")
                rendered += folder_images(p / "jpeg")
            else:
                raws += folder_raw_files(p)
                rendered += folder_images(p)
        elif p.suffix.lower() in RAW_SUFFIXES:
            raws.append(p)
        else:
            rendered.append(p)
    if not raws or not rendered:
        raise InputError(f"a RAW+JPEG bracket needs both: got {len(raws)} RAW file(s) and {len(rendered)} "
                         "rendered image(s)")
    return raws, rendered


def _camera(make: str | None, model: str | None) -> str:
    return " ".join(str(v).strip("\x00 ") for v in (make, model) if v).strip()


def pair_raw_jpeg(frames: Sequence[RawFrame], jpegs: Sequence[str | os.PathLike]) -> tuple[list[Path], list[float]]:
    """The JPEGs in the order of ``frames`` (RAW frames sorted by time, :func:`derender.read_raw_stack`)
    and their exposure times (module docstring, step 1); one error line for a mismatch."""
    from derender.io.exif import read_exif

    jpegs = [Path(p) for p in jpegs]
    if len(jpegs) != len(frames):
        raise InputError(f"the bracket has {len(frames)} RAW file(s) and {len(jpegs)} rendered image(s); "
                         "give the JPEG of every RAW shot")
    exifs = [read_exif(p) for p in jpegs]
    raw_cam = _camera(frames[0].make, frames[0].model)
    for p, e in zip(jpegs, exifs):
        cam = _camera(e.get("Make"), e.get("Model"))
        if raw_cam and cam and cam.lower() != raw_cam.lower():
            raise InputError(f"the RAW files are from {raw_cam}, {p.name} from {cam}")
    times = [e.get("ExposureTime") for e in exifs]
    if all(t for t in times):
        order = sorted(range(len(jpegs)), key=lambda i: times[i])
        jpegs, times = [jpegs[i] for i in order], [float(times[i]) for i in order]
    else:
        by_stem = {Path(f.path).stem: i for i, f in enumerate(frames)}
        slot: dict = {}
        for p, t in zip(jpegs, times):
            i = by_stem.get(p.stem)
            if i is None or i in slot:
                raise InputError(f"no exposure time in {p.name} and no RAW file of the same name to take it from")
            slot[i] = p
        jpegs = [slot[i] for i in range(len(frames))]
        times = [float(read_exif(p).get("ExposureTime") or frames[i].exposure_time) for i, p in enumerate(jpegs)]
    for f, p, t in zip(frames, jpegs, times):
        if f.exposure_time and abs(t / f.exposure_time - 1.0) > TIME_TOLERANCE:
            raise InputError(f"the RAW and JPEG exposures differ: {Path(f.path).name} {f.exposure_time:.6g} s, "
                             f"{p.name} {t:.6g} s")
    return jpegs, times


def score_raw_jpeg(raws: Sequence[str | os.PathLike], jpegs: Sequence[str | os.PathLike], method: str = "debevec", *,
                   truth_method: str = "optimal", seed: int = 0, remap: str = "lstsq", fit: str = "matrix",
                   options: Any = None) -> RawJpegScore:
    """Merge the RAW files (the truth) and the JPEGs (``method``, its ``options`` record or a
    mapping of them) and score the JPEG merge against the RAW merge (module docstring)."""
    from derender.evaluation.metrics import hdr_scores
    from derender.hdr.raw import merge_raw
    from derender.hdr.registry import merge_seeded, method_spec
    from derender.io.images import read_stack
    from derender.io.raw import read_raw_stack

    if truth_method not in ("optimal", "paper1"):
        raise InputError(f"truth_method must be optimal or paper1, got {truth_method!r}")
    method_spec(method)                         # an unknown method is an error before any work
    frames = read_raw_stack(raws)
    if len(frames) < 2:
        raise InputError("a RAW+JPEG bracket needs at least two shots")
    jpegs, times = pair_raw_jpeg(frames, jpegs)
    stack = read_stack(jpegs, times=times)
    if stack.images.shape[1:3] != frames[0].mosaic.shape:
        h, w = frames[0].mosaic.shape
        raise InputError(f"the RAW frames are {w}x{h}, the JPEGs {stack.images.shape[2]}x{stack.images.shape[1]}: "
                         "the protocol needs the JPEG of the whole sensor (no registration)")
    truth = merge_raw(frames, {"estimator": truth_method})
    result = merge_seeded(stack, method, seed, options)
    keep = np.asarray(truth.mask) == 0
    if not keep.any():
        raise InputError("every pixel is over-exposed in every RAW frame: nothing to score")
    scores = hdr_scores(result.radiance, truth.radiance, remap=remap, mask=keep, fit=fit)
    pairs = [(Path(f.path).name, p.name, float(t)) for f, p, t in zip(frames, jpegs, times)]
    return RawJpegScore(truth=truth, result=result, scores=scores, pairs=pairs, n_scored=int(keep.sum()),
                        n_unscored=int((~keep).sum()))
