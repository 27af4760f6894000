"""Frames for the engine: decoding in threads, prefetching, recycled frame buffers.

* :func:`read_frames` -- decode a bracket into one (N, H, W, 3) uint8 array (and, on
  request, Ward's grey images made in the decoding threads).
* :func:`prefetch` -- ``fn(item)`` for each item in order, the next ones computed ahead.
* :class:`FramePool` -- recycles frame buffers between decodes (no fresh page faults).
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from derender.core.errors import InputError, StackError
from derender.core.memory import populated_zeros, thread_count
from derender.io.headers import probe_images
from derender.io.images import read_codes

__all__ = [
    "NotStreamable",
    "prefetch",
    "FramePool",
    "read_frames",
]


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
    registration, :func:`derender.engine.ward2003.grey8_codes`). The first frame gives the size;
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
