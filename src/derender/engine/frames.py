"""Frames for the engine: where they come from, how they are decoded and how held frames are merged.

* :class:`FileFrames`, :class:`ArrayFrames` -- the engine's frame sources: image files
  (decoded with :func:`derender.io.images.read_codes`) and in-memory 8-bit stacks, both
  sorted by exposure time, so that the two give the same numbers by construction.
* :func:`clipped_pixels`, :func:`frame_brightness` -- what every path counts on the frames
  (the over-exposed pixels of the shortest exposure, the brightness order check).
* :func:`merge_held` -- a method's plan on held (N, H, W, 3) uint8 frames: the one dispatch
  on the plan type (:class:`~derender.engine.plans.MatrixPlan`,
  :class:`~derender.engine.plans.GaussianPlan`, :class:`~derender.engine.plans.TablePlan`)
  that the plain run (:func:`derender.engine.run.run`) and the motion run
  (:func:`derender.engine.motion.run.run_motion`) share.
* :func:`read_frames` -- decode a bracket into one (N, H, W, 3) uint8 array (and, on
  request, Ward's grey images made in the decoding threads).
* :func:`prefetch` -- ``fn(item)`` for each item in order, the next ones computed ahead.
* :class:`FramePool` -- recycles frame buffers between decodes (no fresh page faults).
"""

from __future__ import annotations

import os
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from derender.core.errors import InputError, StackError
from derender.core.memory import check_memory, populated_zeros, thread_count
from derender.core.types import HDRResult
from derender.io.headers import DEFAULT_MAX_MEGAPIXELS, probe_images
from derender.io.images import read_codes

__all__ = [
    "NotStreamable",
    "prefetch",
    "FramePool",
    "read_frames",
    "FileFrames",
    "ArrayFrames",
    "clipped_pixels",
    "frame_brightness",
    "merge_held",
    "STREAMED_BYTES_PER_PIXEL",
]

#: The least memory a streamed merge needs per pixel: the float32 RGB result and its
#: weight sums (24 bytes) and the frame being decoded (3 bytes), rounded up; checked
#: against the available memory before any frame is decoded.
STREAMED_BYTES_PER_PIXEL = 32


class NotStreamable(Exception):
    """The input or method needs the in-memory reference path."""


def prefetch(fn: Callable[[Any], Any], items: Sequence[Any], depth: int = 1, workers: int = 1) -> Iterator[Any]:
    """``fn(item)`` for each item in order, with up to ``depth`` further items computed ahead by ``workers`` threads."""
    items = list(items)
    if not items:
        return
    with ThreadPoolExecutor(max(1, workers), thread_name_prefix="derender-decode") as ex:
        futs: deque = deque()
        nxt = 0
        while nxt < len(items) and len(futs) < max(1, depth):
            futs.append(ex.submit(fn, items[nxt]))
            nxt += 1
        while futs:
            res = futs.popleft().result()
            if nxt < len(items):
                futs.append(ex.submit(fn, items[nxt]))
                nxt += 1
            yield res
            del res


class FramePool:
    """Recycles frame buffers: fresh memory costs page faults (~1 ms/MB on some VMs), a reused buffer none."""

    def __init__(self, max_free: int = 2):
        self.shape: tuple | None = None
        self.max_free = max_free
        self.free: deque = deque()

    def get(self) -> np.ndarray | None:
        if self.shape is None:
            return None
        try:
            return self.free.pop()
        except IndexError:
            return populated_zeros(self.shape, dtype=np.uint8)

    def put(self, buf: np.ndarray | None) -> None:
        if (buf is not None and self.shape is not None and buf.shape == self.shape and buf.dtype == np.uint8
                and buf.flags.c_contiguous and len(self.free) < self.max_free):
            self.free.append(buf)


def read_frames(paths: list[Path], threads: int | None,
                derive: Callable[[np.ndarray, np.ndarray], Any] | None = None,
                derive_alloc: Callable[[int, int, int], np.ndarray] | None = None,
                infos: list | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode 8-bit frames (in threads) into one (N, H, W, 3) uint8 array (pages populated
    up front, :func:`populated_zeros`) and, with ``derive(frame, out)``, one uint8 plane
    (N, H, W) per frame computed in the decoding threads (e.g. Ward's grey images for MTB
    registration, :func:`derender.engine.motion.ward2003.grey8_codes`). The first frame gives the size;
    the others are decoded straight into their slot. ``derive_alloc(H, W, nbytes)``, if
    given, returns the uint8 memory (at least ``nbytes``) the planes go to, so that a later
    stage can reuse it. ``infos`` are the files' probed headers
    (:func:`derender.io.headers.probe_images`), read here when not given."""

    nthreads = thread_count(threads)
    if infos is None:
        infos = probe_images(paths)
    first = read_codes(paths[0], info=infos[0])
    if first is None:
        raise NotStreamable("16-bit input")
    if len(paths) < 2:
        raise StackError("an exposure stack needs at least two images")
    frames = populated_zeros((len(paths), *first.shape), dtype=np.uint8)
    frames[0] = first
    del first
    planes = None
    if derive is not None:
        n_plane = int(np.prod(frames.shape[:3]))
        mem = populated_zeros(n_plane, np.uint8) if derive_alloc is None else derive_alloc(*frames.shape[1:3], n_plane)
        planes = mem.reshape(-1)[:n_plane].reshape(frames.shape[:3])

    def load(j: int):
        codes = read_codes(paths[j], out=frames[j], info=infos[j]) if j else frames[0]
        if codes is None:
            return False
        if codes.shape != frames.shape[1:]:
            raise InputError(f"images differ in size: {paths[0].name} is {frames.shape[2]}x{frames.shape[1]}, "
                             f"{paths[j].name} is {codes.shape[1]}x{codes.shape[0]}")
        if not np.shares_memory(codes, frames[j]):
            frames[j] = codes
        if planes is not None:
            derive(frames[j], planes[j])
        return True

    for ok in prefetch(load, range(len(paths)), depth=nthreads, workers=nthreads):
        if not ok:
            raise NotStreamable("16-bit input")
    return frames, planes


class FileFrames:
    """8-bit frames of image files, sorted by exposure time (``times`` in the order of ``paths``).

    Decoding a 16-bit file raises :class:`NotStreamable` (the caller falls back to the float
    reference engine)."""

    def __init__(self, paths: Sequence[str | os.PathLike], times: Sequence[float],
                 max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS):
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        order = np.argsort(t, kind="stable")
        self.order = order                   # frame k (by time) is paths[order[k]]
        self.paths = [Path(paths[i]) for i in order]
        self.times = t[order]
        # every header before any pixel: truncation, forged sizes, the megapixel and memory budgets
        self.infos = probe_images(self.paths, max_megapixels)
        w, h = self.infos[0].width, self.infos[0].height
        check_memory(w * h * STREAMED_BYTES_PER_PIXEL, f"merging {w}x{h} images")

    @property
    def n(self) -> int:
        return len(self.paths)

    def name(self, j: int) -> str:
        return self.paths[j].name

    def read(self, j: int, out: np.ndarray | None = None) -> np.ndarray:
        codes = read_codes(self.paths[j], out=out, info=self.infos[j])
        if codes is None:
            raise NotStreamable("16-bit input")
        return codes

    def read_all(self, threads: int | None, derive=None, derive_alloc=None) -> tuple[np.ndarray, np.ndarray | None]:
        return read_frames(self.paths, threads, derive=derive, derive_alloc=derive_alloc, infos=self.infos)


class ArrayFrames:
    """In-memory 8-bit frames (N, H, W, 3) uint8 with their times (sorted here by time)."""

    def __init__(self, codes: np.ndarray, times: Sequence[float]):
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        codes = np.asarray(codes)
        if codes.dtype != np.uint8 or codes.ndim != 4 or codes.shape[-1] != 3 or codes.shape[0] != t.size:
            raise InputError(f"frames must be (N, H, W, 3) uint8 with one time each, got {codes.dtype} {codes.shape}")
        order = np.argsort(t, kind="stable")
        self.order = order                   # frame k (by time) is codes[order[k]]
        self.codes = codes if np.all(order == np.arange(t.size)) else codes[order]
        self.times = t[order]

    @property
    def n(self) -> int:
        return int(self.codes.shape[0])

    def name(self, j: int) -> str:
        return f"frame {j}"

    def read(self, j: int, out: np.ndarray | None = None) -> np.ndarray:
        return self.codes[j]

    def read_all(self, threads: int | None, derive=None, derive_alloc=None) -> tuple[np.ndarray, np.ndarray | None]:
        frames = np.ascontiguousarray(self.codes)
        planes = None
        if derive is not None:
            n_plane = int(np.prod(frames.shape[:3]))
            mem = (populated_zeros(n_plane, np.uint8) if derive_alloc is None
                   else derive_alloc(*frames.shape[1:3], n_plane))
            planes = mem.reshape(-1)[:n_plane].reshape(frames.shape[:3])
            for j in range(self.n):
                derive(frames[j], planes[j])
        return frames, planes


def clipped_pixels(codes: np.ndarray) -> int:
    """Pixels of an (H, W, 3) uint8 frame with a channel at 255: in the shortest exposure, the
    pixels over-exposed in every frame. The engine counts them once, the same way for every
    method (``info["n_clipped"]``), whatever each method's weights make of them (its mask marks
    where *its* weights left no frame: ``info["n_bright"]``)."""
    full = np.uint8(255)
    return int(np.count_nonzero((codes[..., 0] == full) | (codes[..., 1] == full) | (codes[..., 2] == full)))


def frame_brightness(codes: np.ndarray) -> float:
    """Mean code of a frame on a 1/64 subsample (about 1 ms per 24 MP frame)."""
    return float(codes[::8, ::8].mean())


def merge_held(plan, frames: np.ndarray, times: np.ndarray, *, threads: int | None = None,
               valid: np.ndarray | None = None, ref: int = -1, compiled_tables: bool = True,
               buffer: np.ndarray | None = None, outputs: tuple[np.ndarray, np.ndarray] | None = None,
               write=None, ring: int = 0, name: str = "the method") -> HDRResult:
    """A method's plan on held frames (N, H, W, 3) uint8 sorted by ``times``: the engine's one
    dispatch on the plan type, for the plain and the motion run alike.

    * :class:`~derender.engine.plans.MatrixPlan`:
      :func:`~derender.engine.matrix.merge_matrix_frames` (``buffer``: memory to reuse for the
      outputs);
    * :class:`~derender.engine.plans.GaussianPlan`:
      :func:`~derender.engine.gaussian.merge_gaussian_frames` (``outputs``: the two float32
      output arrays, made ahead);
    * :class:`~derender.engine.plans.TablePlan`: the compiled kernel
      (:func:`~derender.engine.table_kernel.table_kernel_merge`, longest exposure first, modes
      ``"mean"`` and ``"independent"``) when ``compiled_tables``, else
      :func:`~derender.engine.tables.merge_codes` (every ``channel_weights`` mode; no ``valid``,
      no reference frame).

    ``valid`` ((N, H, W) uint8, 0 where frame j takes no part) and ``ref`` (the reference frame
    that decides the saturation policy, -1: the shortest and longest exposures) come from the
    motion run; ``write`` and ``ring`` let the compiled matrix and Gaussian merges write while
    merging (:mod:`derender.engine.overlap`). ``name`` names the method in errors."""
    from derender.engine.plans import GaussianPlan, MatrixPlan, TablePlan

    if isinstance(plan, MatrixPlan):
        from derender.engine.matrix import merge_matrix_frames

        return merge_matrix_frames(frames, plan, times, valid=valid, threads=threads, buffer=buffer, write=write,
                                   ring=ring, ref=ref)
    if isinstance(plan, GaussianPlan):
        from derender.engine.gaussian import merge_gaussian_frames

        return merge_gaussian_frames(frames, plan, threads=threads, write=write, outputs=outputs, ring=ring,
                                     valid=valid)
    if isinstance(plan, TablePlan):
        if compiled_tables:
            from derender.engine.table_kernel import table_kernel_merge

            if plan.channel_weights not in ("mean", "independent"):
                raise InputError(f"channel_weights={plan.channel_weights!r} cannot be merged with alignment or "
                                 "ghost removal; use 'mean' or 'independent'")
            return table_kernel_merge(frames, plan, list(range(frames.shape[0] - 1, -1, -1)), threads, valid=valid,
                                      ref=ref)
        if valid is not None or ref >= 0:
            raise ValueError("merge_codes takes no valid planes or reference frame: use compiled_tables=True")
        from derender.engine.tables import merge_codes

        return merge_codes(frames, times, plan.values, plan.weights, image_weights=plan.image_weights,
                           channel_weights=plan.channel_weights, domain=plan.domain, threads=threads,
                           block_rows=plan.block_rows, contiguous=False)
    raise TypeError(f"{name} returned an unknown plan {type(plan).__name__}")
