"""The engine's plain run: every method merges through :func:`run` (or, with a reference frame,
alignment or ghost removal, through :func:`derender.engine.motion.run.run_motion`; the caller
chooses, and this module knows nothing of motion).

A method (:class:`~derender.engine.plans.EngineMethod`) says how it needs the frames and
returns a plan; :func:`run` does the rest, for files
(:class:`~derender.engine.frames.FileFrames`, decoded with
:func:`derender.io.images.read_codes`) and in-memory 8-bit stacks
(:class:`~derender.engine.frames.ArrayFrames`) alike, so the two give the same numbers by
construction:

* **streamed** methods (``holds_frames=False``, e.g. Debevec & Malik, Robertson): pass 1
  decodes each frame (in threads, in time order), keeps the codes at the method's sample
  positions (and the frame histograms if asked) and holds on to the last frames that fit
  ``keep_bytes``; the method calibrates and returns a
  :class:`~derender.engine.plans.TablePlan`; pass 2 decodes the other frames again,
  longest exposure first, and accumulates them with
  :class:`~derender.engine.tables.TableMerge`. Memory: the accumulators (32 bytes per pixel
  for Debevec's defaults), the mask and a few frames, whatever the number of exposures.
* **held** methods (``holds_frames=True``: paper 1's stabiliser, which registers and
  samples the frames; paper 2's probabilistic merge, which de-renders every distinct
  colour once): every frame is decoded once into one (N, H, W, 3) uint8 array (plus the
  method's derived planes, e.g. grey images for registration, made in the decoding
  threads); the plan then runs on the held codes (:func:`~derender.engine.frames.merge_held`:
  :func:`~derender.engine.matrix.merge_matrix_frames`,
  :func:`~derender.engine.gaussian.merge_gaussian_frames`, or the table engine).

:func:`run` writes the radiance (and the variance) to OpenEXR when asked
(:mod:`derender.engine.outputs`: while merging where a compiled kernel merges, else after).
"""

from __future__ import annotations

import functools
import os
import threading
import time
from typing import Callable, Iterable

import numpy as np

from derender.core.errors import InputError, StackError
from derender.core.memory import N_CODES, populated_zeros, thread_count
from derender.core.types import HDRResult, check_brightness_order
from derender.engine.frames import (
    ArrayFrames,
    FileFrames,
    FramePool,
    clipped_pixels,
    frame_brightness,
    merge_held,
    prefetch,
)
from derender.engine.options import EngineOptions, OutputOptions
from derender.engine.outputs import write_outputs, write_while_merging
from derender.engine.plans import EngineMethod, FrameAccess, TablePlan
from derender.engine.table_kernel import table_kernel_merge, warm_up_kernel
from derender.engine.tables import TableMerge, code_histograms

__all__ = ["run", "ENGINES", "KERNEL_MIN_PIXEL_FRAMES"]

#: ``engine=`` choices of the classic merge methods (the registry reads them: ``"reference"`` asks for
#: the float reference engine, ``"table"`` insists on the engine).
ENGINES = ("auto", "table", "reference")

#: Pixels x frames from which a held table merge runs the compiled kernel: below, OpenCV's
#: table engine on the held frames is faster, as importing numba and loading the kernel
#: (0.3-0.5 CPU s) outweighs the kernel's gain. Measured in-process, Debevec, 3 + 2
#: alternating pairs: 9 x 6 MP TableMerge 0.61-1.09 s (1.0-1.1 CPU s) against the kernel
#: 0.81-1.43 s (1.3-1.5 CPU s); 9 x 24 MP equal (3.0-3.1 s both, 2.9-3.0 CPU s), the
#: kernel without TableMerge's 768 MB of float64 accumulators.
KERNEL_MIN_PIXEL_FRAMES = 150_000_000


def _size_error(source, shape: tuple, j: int, got: tuple) -> InputError:
    return InputError(f"images differ in size: {source.name(0)} is {shape[1]}x{shape[0]}, "
                      f"{source.name(j)} is {got[1]}x{got[0]}")


class _FirstPass:
    """The first pass of a streamed method, frame by frame (both streamed paths): the codes at
    the method's sample positions, the histograms it wants, the frames' brightness for the
    order check and the clipped pixels of the shortest exposure; :meth:`plan` then makes the
    method's :class:`TablePlan`."""

    def __init__(self, method: EngineMethod, source, order_hint: str | None):
        self.method, self.source, self.order_hint = method, source, order_hint
        n = source.n
        self.shape: tuple | None = None
        self.samples = self.positions = None
        self.hists = np.zeros((n, 3, N_CODES), dtype=np.int64) if method.wants_histograms else None
        self.brightness = np.zeros(n)
        self.n_clipped = 0

    def add(self, j: int, codes: np.ndarray) -> None:
        """Read frame ``j`` (any order; the first one read sets the shape)."""
        if self.shape is None:
            self.shape = codes.shape
            self.positions = self.method.sample_positions(*codes.shape[:2])
            if self.positions is not None:
                size = self.positions[0].size
                self.samples = np.empty((self.source.n, size, 3), dtype=_sample_dtype(self.method))
        elif codes.shape != self.shape:
            raise _size_error(self.source, self.shape, j, codes.shape)
        if self.samples is not None:
            self.samples[j] = codes[self.positions]
        if j == 0:
            self.n_clipped = clipped_pixels(codes)
        if self.order_hint is not None:
            self.brightness[j] = frame_brightness(codes)
        if self.hists is not None:
            self.hists[j] = code_histograms(codes)

    def plan(self, histogram_fn: Callable[[], np.ndarray], threads: int | None) -> tuple[FrameAccess, TablePlan]:
        """The order check, then the method's plan from what the pass read (``histogram_fn``
        gives the histograms the pass did not keep)."""
        source, n = self.source, self.source.n
        if self.order_hint is not None:
            check_brightness_order(source.times, self.brightness, [source.name(j) for j in range(n)],
                                   self.order_hint)
        hists = self.hists
        access = FrameAccess(times=source.times, shape=self.shape[:2], samples=self.samples, threads=threads,
                             histogram_fn=(lambda: hists) if hists is not None else histogram_fn)
        plan = self.method.plan(access)
        if not isinstance(plan, TablePlan):
            raise TypeError(f"a streamed method must return a TablePlan, {self.method.name} returned "
                            f"{type(plan).__name__}")
        return access, plan


def _run_streamed_held(method: EngineMethod, source, threads: int | None, order_hint: str | None,
                       write=None, ring: int = 0) -> HDRResult:
    """A streamed method's merge when the bracket's codes fit in memory: every frame decoded
    once into one (N, H, W, 3) array, the first pass read from it (:class:`_FirstPass`), and
    the merge in one compiled pass per pixel (:func:`table_kernel_merge`) from
    :data:`KERNEL_MIN_PIXEL_FRAMES` on; smaller brackets, and modes the kernel lacks, run
    :class:`TableMerge` on the held frames. Same numbers as the two-pass stream."""
    n = source.n
    t0 = time.perf_counter()
    px = (source.infos[0].width * source.infos[0].height if isinstance(source, FileFrames)
          else int(np.prod(source.codes.shape[1:3])))
    compiled = n * px >= KERNEL_MIN_PIXEL_FRAMES
    if compiled:
        warm_up_kernel("table")
    frames, _ = source.read_all(threads)
    h, w = frames.shape[1:3]
    first = _FirstPass(method, source, order_hint)
    for j in range(n):
        first.add(j, frames[j])
    t1 = time.perf_counter()
    access, plan = first.plan(lambda: np.stack([code_histograms(f) for f in frames]), threads)
    t2 = time.perf_counter()
    order = list(range(n - 1, -1, -1))      # the stream's order: longest exposure first
    if plan.variance is not None and plan.channel_weights not in ("mean", "independent"):
        raise InputError(f"a variance needs channel_weights 'mean' or 'independent', got {plan.channel_weights!r}")
    if (compiled or plan.variance is not None) and plan.channel_weights in ("mean", "independent"):
        res = table_kernel_merge(frames, plan, order, threads, write=write, ring=ring)
        res.info["overlapped_write"] = write is not None
    else:
        iw = np.ones(n) if plan.image_weights is None else np.asarray(plan.image_weights, dtype=np.float64)
        with TableMerge((h, w), channel_weights=plan.channel_weights, domain=plan.domain, threads=threads,
                        block_rows=plan.block_rows) as eng:
            for j in order:
                eng.add(frames[j], plan.values[j], plan.weight_of(j), image_weight=float(iw[j]))
            res = eng.finish((frames[0], plan.values[0]), (frames[n - 1], plan.values[n - 1]))
    t3 = time.perf_counter()
    res.info.setdefault("timings", {}).update({"pass1_s": t1 - t0, "calibrate_s": t2 - t1, "merge_s": t3 - t2,
                                               "finish_s": 0.0})
    res.info.update({"merge_seconds": t3 - t2,
                     "streaming": {"frames_kept": n, "decodes": n if isinstance(source, FileFrames) else 0},
                     "n_clipped": first.n_clipped})
    res.plan = plan            # the forward model the map was merged with (evaluation.roundtrip)
    method.finish(res, access)
    return res


def _sample_dtype(method: EngineMethod) -> type:
    """The codes at the sample positions: int32 as the calibrations take them, or uint8 for a
    method whose positions come in clusters (many more of them; it keeps a few and converts)."""
    return np.uint8 if method.sample_cluster > 1 else np.int32


def _hold(source, keep_frames: int | None, hold_bytes: int) -> bool:
    """Whether a streamed method holds every frame (decoded once): no explicit frame budget,
    the codes within ``hold_bytes`` and, with the outputs, within half the available memory."""
    from derender.core.memory import available_memory

    if keep_frames is not None:
        return False
    if isinstance(source, ArrayFrames):
        return True
    info = source.infos[0]
    px = int(info.width) * int(info.height)
    codes = source.n * px * 3
    if codes > hold_bytes:
        return False
    avail = available_memory()
    return avail is None or codes + 13 * px <= avail // 2


def _run_streamed(method: EngineMethod, source, threads: int | None, keep_frames: int | None,
                  keep_bytes: int, order_hint: str | None = None) -> HDRResult:
    """A streamed method's merge in two passes: the first (:class:`_FirstPass`) keeps
    ``keep_frames`` frames (default: as many as fit in ``keep_bytes``), the second decodes the
    others again and adds every frame to a :class:`TableMerge`."""
    n = source.n
    t0 = time.perf_counter()
    kept: dict[int, np.ndarray] = {}
    keep = keep_frames
    nthreads = thread_count(threads)
    pool = FramePool()
    first = _FirstPass(method, source, order_hint)
    for j, codes in enumerate(prefetch(lambda i: source.read(i, out=pool.get()), range(n), depth=nthreads,
                                       workers=nthreads)):
        if first.shape is None:
            pool.shape = codes.shape
            if keep is None:
                keep = int(keep_bytes // max(codes.nbytes, 1))
            keep = int(min(max(keep, 1), n))
        first.add(j, codes)
        if j >= n - keep:
            kept[j] = codes
        else:
            pool.put(codes)
        del codes
    t1 = time.perf_counter()
    access, plan = first.plan(lambda: np.stack([code_histograms(kept[j] if j in kept else source.read(j))
                                                for j in range(n)]), threads)
    t2 = time.perf_counter()
    shape = first.shape
    h, w = shape[:2]
    order = list(range(n - 1, -1, -1))      # longest exposure first: kept frames need no decoding
    long_codes = short_codes = None
    iw = np.ones(n) if plan.image_weights is None else np.asarray(plan.image_weights, dtype=np.float64)

    def load(j: int) -> np.ndarray:
        return kept[j] if j in kept else source.read(j, out=pool.get())

    with TableMerge((h, w), channel_weights=plan.channel_weights, domain=plan.domain, threads=threads,
                    block_rows=plan.block_rows) as eng:
        for j, codes in zip(order, prefetch(load, order)):
            if codes.shape != shape:
                raise InputError(f"{source.name(j)} changed while merging")
            eng.add(codes, plan.values[j], plan.weight_of(j), image_weight=float(iw[j]))
            kept.pop(j, None)
            if j == n - 1:
                long_codes = codes
            elif j == 0:
                short_codes = codes
            else:
                pool.put(codes)
            del codes
        t3 = time.perf_counter()
        res = eng.finish((short_codes, plan.values[0]), (long_codes, plan.values[n - 1]))
    t4 = time.perf_counter()
    res.info.update({
        "merge_seconds": t4 - t2,
        "timings": {"pass1_s": t1 - t0, "calibrate_s": t2 - t1, "merge_s": t3 - t2, "finish_s": t4 - t3},
        "streaming": {"frames_kept": keep, "decodes": n + n - keep},
        "n_clipped": first.n_clipped,
    })
    res.plan = plan            # the forward model the map was merged with (evaluation.roundtrip)
    method.finish(res, access)
    return res


def _run_held(method: EngineMethod, source, threads: int | None, order_hint: str | None = None,
              write=None, ring: int = 0) -> HDRResult:
    t0 = time.perf_counter()
    held: dict = {}
    out_bytes = method.output_bytes

    def derive_alloc(h: int, w: int, nbytes: int) -> np.ndarray:
        # the derived planes' memory is reused for the outputs once the plan is made: fresh
        # memory costs 0.5-3 ms/MB here (page population), 216 MB of it per 24 MP bracket
        extra = out_bytes(h, w) if out_bytes is not None and not ring else 0
        held["buffer"] = populated_zeros(max(nbytes, extra), np.uint8)
        return held["buffer"]

    if method.warm_up == "gaussian":
        warm_up_kernel("gaussian")
    frames, planes = source.read_all(threads, derive=method.derive(), derive_alloc=derive_alloc)
    n_clipped = clipped_pixels(frames[0])
    if order_hint is not None:
        check_brightness_order(source.times, [frame_brightness(f) for f in frames],
                               [source.name(j) for j in range(source.n)], order_hint)
    t1 = time.perf_counter()
    access = FrameAccess(times=source.times, shape=frames.shape[1:3], frames=frames, planes=planes, threads=threads,
                         histogram_fn=lambda: np.stack([code_histograms(f) for f in frames]),
                         # outputs in band buffers: the derived planes' memory has no later use
                         release_fn=(lambda: held.pop("buffer", None)) if ring else None)
    del planes
    outputs: list = []
    prepare = None
    if method.warm_up == "gaussian" and not ring:
        # the Gaussian merge's float32 outputs, pages present, mapped in a thread while the
        # plan runs (its serial parts leave a core idle; populating 576 MB at 24 MP takes ~0.3 s)
        h, w = frames.shape[1:3]

        def alloc() -> None:
            outputs.extend(populated_zeros((h, w, 3), np.float32) for _ in range(2))

        prepare = threading.Thread(target=alloc, name="derender-outputs", daemon=True)
        prepare.start()
    try:
        plan = method.plan(access)
    finally:
        if prepare is not None:
            prepare.join()
    access.planes = None
    t2 = time.perf_counter()
    buffer = held.pop("buffer", None)
    if ring:
        buffer = None        # the derived planes' memory is released: the outputs are band buffers
    res = merge_held(plan, frames, source.times, threads=threads, compiled_tables=False, buffer=buffer,
                     outputs=tuple(outputs) if len(outputs) == 2 else None, write=write, ring=ring, name=method.name)
    if not isinstance(plan, TablePlan):      # the matrix and Gaussian merges write while merging
        res.info["overlapped_write"] = write is not None
    del buffer
    t3 = time.perf_counter()
    res.info.setdefault("timings", {}).update({"decode_s": t1 - t0, "plan_s": t2 - t1, "merge_s": t3 - t2})
    res.info["streaming"] = {"frames_kept": source.n, "decodes": source.n if isinstance(source, FileFrames) else 0}
    res.info["n_clipped"] = n_clipped
    res.plan = plan            # the forward model the map was merged with (evaluation.roundtrip)
    method.finish(res, access)
    return res

def run(method: EngineMethod, source: FileFrames | ArrayFrames, output: OutputOptions | None = None,
        engine: EngineOptions | None = None, *, inputs: Iterable[str | os.PathLike] = (),
        order_hint: str | None = None) -> HDRResult:
    """Merge ``source`` with ``method`` (see the module docstring); optionally write the
    radiance and the variance to the OpenEXR files of ``output``.

    Streamed methods hold every frame (decoded once, merged by a compiled kernel:
    :func:`_run_streamed_held`) when ``engine.keep_frames`` is None and the bracket's codes fit
    in ``engine.hold_bytes`` (and, with the outputs, in half the available memory); otherwise
    they stream in two passes. Held methods (:attr:`EngineMethod.holds_frames`) read every
    frame once (:func:`_run_held`).

    Parameters
    ----------
    method : EngineMethod
        What to merge with: its plan (tables, matrices or Gaussians) from the frames.
    source : FileFrames or ArrayFrames
        The bracket's 8-bit frames and exposure times.
    output : OutputOptions, optional
        The OpenEXR files (written atomically, never over one of ``inputs``), and whether the
        maps stay in memory: with ``hold_outputs=False``, where the merge writes while merging
        (held frames merged by a compiled kernel), the outputs go through a ring of band
        buffers (:class:`~derender.engine.overlap.OutputRing`) straight into the files and are
        never held whole (9 x 24 MP: 288 MB less memory per output); the result's
        ``radiance`` (and ``variance``) are then None. None: nothing written.
    engine : EngineOptions, optional
        Threads and the frame budgets (:class:`~derender.engine.options.EngineOptions`).
    inputs : iterable of path-like
        Files the outputs must not overwrite.
    order_hint : str, optional
        For user input: check while decoding that the images brighten with their exposure
        times (:func:`derender.core.types.check_brightness_order`); the hint ends the error.

    Returns
    -------
    HDRResult
        Radiance, mask, variance (Gaussian plans), info (timings, ``n_clipped``, the
        method's own entries).

    Raises
    ------
    NotStreamable
        Inputs without 8-bit codes, or a method with no engine form for them: the caller
        (:mod:`derender.hdr.registry`) falls back to the float reference engine.
    """
    t0 = time.perf_counter()
    if source.n < 2:
        raise StackError("an exposure stack needs at least two images")
    out = output or OutputOptions()
    engine = engine or EngineOptions()
    threads = engine.threads
    inputs = list(inputs)
    write = None
    if out.output is not None:
        write = functools.partial(write_while_merging, output=out.output, variance_output=out.variance_output,
                                  half=out.half, compression=out.compression, inputs=inputs, threads=threads)
    # outputs streamed through band buffers: how many files read them (the variance's too if asked)
    ring = 0 if write is None or out.held else 1 + (out.variance_output is not None)
    if method.holds_outputs:   # the method's finish() reads the merged radiance
        ring = 0
    if method.holds_frames:
        res = _run_held(method, source, threads, order_hint, write=write, ring=ring)
    elif _hold(source, engine.keep_frames, engine.hold_bytes) or method.variance:   # a variance: held
        res = _run_streamed_held(method, source, threads, order_hint, write=write, ring=ring)
    else:
        res = _run_streamed(method, source, threads, engine.keep_frames, engine.keep_bytes, order_hint)
    res.info["engine_path"] = "streaming"
    res.info["outputs_held"] = res.radiance is not None
    output_path, variance_path = out.output, out.variance_output
    if res.info.get("overlapped_write"):      # the radiance was written while merging
        inputs, output_path = inputs + [output_path], None
    if res.info.pop("overlapped_variance_write", False):     # ... and the variance
        variance_path = None
    write_outputs(res, output_path, variance_path, half=out.half, compression=out.compression, inputs=inputs,
                  threads=threads, name=method.name)
    res.info["total_seconds"] = time.perf_counter() - t0
    return res
