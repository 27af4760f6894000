"""The one merge engine: every method runs through :func:`run`.

A method (:class:`~derender.engine.plans.EngineMethod`) says how it needs the frames and
returns a plan; :func:`run` does the rest, for files (:class:`FileFrames`, decoded with
:func:`derender.io.images.read_codes`) and in-memory 8-bit stacks (:class:`ArrayFrames`)
alike, so the two give the same numbers by construction:

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
  threads); the plan then runs on the held codes
  (:func:`~derender.engine.matrix.merge_matrix_frames`,
  :func:`~derender.engine.gaussian.merge_gaussian_frames`, or the table engine).

:func:`run` writes the radiance (and the variance) to OpenEXR when asked
(:func:`derender.io.exr.write_exr_fast`, blocks of lines compressed in threads).
"""

from __future__ import annotations

import functools
import os
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from derender.core.errors import InputError, StackError
from derender.core.memory import N_CODES, check_memory, populated_zeros, thread_count
from derender.core.types import HDRResult, Stack, check_brightness_order
from derender.engine.frames import FramePool, NotStreamable, prefetch, read_frames
from derender.engine.motion import motion_attributes
from derender.engine.overlap import RowsDone
from derender.engine.plans import EngineMethod, FrameAccess, GaussianPlan, MatrixPlan, TablePlan
from derender.engine.table_kernel import table_kernel_merge, warm_up_kernel
from derender.engine.tables import TableMerge, code_histograms, stack_codes_exact
from derender.io.exr import exr_attributes, write_exr_fast
from derender.io.headers import DEFAULT_MAX_MEGAPIXELS, probe_images
from derender.io.images import read_codes

__all__ = ["FileFrames", "ArrayFrames", "run", "run_stack", "write_outputs", "clipped_pixels",
           "frame_brightness", "ENGINES"]

#: ``engine=`` choices of the in-memory merge methods.
ENGINES = ("auto", "table", "reference")

#: The least memory a streamed merge needs per pixel: the float32 RGB result and its
#: weight sums (24 bytes) and the frame being decoded (3 bytes), rounded up; checked
#: against the available memory before any frame is decoded.
STREAMED_BYTES_PER_PIXEL = 32

#: Default budget of a streamed method's held frames (8-bit codes of the whole bracket):
#: within it every frame is decoded once and merged by a compiled kernel (13 frames of
#: 24 MP); above it the frames stream in two passes (memory independent of their number).
HOLD_BYTES = 1 << 30

#: Pixels x frames from which a held table merge runs the compiled kernel: below, OpenCV's
#: table engine on the held frames is faster, as importing numba and loading the kernel
#: (0.3-0.5 CPU s) outweighs the kernel's gain. Measured in-process, Debevec, 3 + 2
#: alternating pairs: 9 x 6 MP TableMerge 0.61-1.09 s (1.0-1.1 CPU s) against the kernel
#: 0.81-1.43 s (1.3-1.5 CPU s); 9 x 24 MP equal (3.0-3.1 s both, 2.9-3.0 CPU s), the
#: kernel without TableMerge's 768 MB of float64 accumulators.
KERNEL_MIN_PIXEL_FRAMES = 150_000_000


class FileFrames:
    """8-bit frames of image files, sorted by exposure time (``times`` in the order of ``paths``).

    Decoding a 16-bit file raises :class:`~derender.engine.frames.NotStreamable` (the caller
    falls back to the float reference engine)."""

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


def _size_error(source, shape: tuple, j: int, got: tuple) -> InputError:
    return InputError(f"images differ in size: {source.name(0)} is {shape[1]}x{shape[0]}, "
                      f"{source.name(j)} is {got[1]}x{got[0]}")


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
    if isinstance(plan, MatrixPlan):
        from derender.engine.matrix import merge_matrix_frames

        res = merge_matrix_frames(frames, plan, source.times, threads=threads, buffer=buffer, write=write, ring=ring)
        res.info["overlapped_write"] = write is not None
    elif isinstance(plan, GaussianPlan):
        from derender.engine.gaussian import merge_gaussian_frames

        res = merge_gaussian_frames(frames, plan, threads=threads, write=write,
                                    outputs=tuple(outputs) if len(outputs) == 2 else None, ring=ring)
        res.info["overlapped_write"] = write is not None
    elif isinstance(plan, TablePlan):
        from derender.engine.tables import merge_codes

        res = merge_codes(frames, source.times, plan.values, plan.weights, image_weights=plan.image_weights,
                          channel_weights=plan.channel_weights, domain=plan.domain, threads=threads,
                          block_rows=plan.block_rows, contiguous=False)
    else:
        raise TypeError(f"{method.name} returned an unknown plan {type(plan).__name__}")
    del buffer
    t3 = time.perf_counter()
    res.info.setdefault("timings", {}).update({"decode_s": t1 - t0, "plan_s": t2 - t1, "merge_s": t3 - t2})
    res.info["streaming"] = {"frames_kept": source.n, "decodes": source.n if isinstance(source, FileFrames) else 0}
    res.info["n_clipped"] = n_clipped
    method.finish(res, access)
    return res


def _write_radiance_while_merging(res: HDRResult, done: RowsDone, output, *, half: bool, compression: str,
                                  inputs, threads: int | None, arr: np.ndarray | None = None, k: int = 0) -> None:
    """:func:`write_outputs`' radiance file (or ``arr``, e.g. the variance), each block of lines
    read once the merge has finished it; from ``done.ring`` (output ``k``: 0 radiance, 1
    variance) when the merge fills band slots instead of whole arrays."""
    from derender.io.exr import write_exr_lines

    ring = done.ring
    if ring is None:
        arr = res.radiance if arr is None else arr
        h, w = arr.shape[:2]
    else:
        h, w = ring.h, ring.w

    def bgr_lines(y0: int, y1: int, buf: np.ndarray) -> None:
        done.wait(y1)
        if ring is None:
            for kk, c in enumerate((2, 1, 0)):  # channels in alphabetical order: B, G, R
                buf[:, kk, :] = arr[y0:y1, :, c]
            return
        for ya, yb, view in ring.segments(k, y0, y1):
            for kk, c in enumerate((2, 1, 0)):
                buf[ya - y0:yb - y0, kk, :] = view[:, :, c]

    write_exr_lines(output, w, h, bgr_lines, half=half, inputs=list(inputs), compression=compression, threads=threads,
                    rows_read=None if ring is None else (lambda y: ring.read(k, y)), attributes=exr_attributes(res.info))


def _write_while_merging(res: HDRResult, done: RowsDone, *, output, variance_output, half: bool, compression: str,
                         inputs: list, threads: int | None) -> None:
    """The writer a compiled merge runs in a thread (``write(result, rows_done)``): the radiance
    to ``output`` band by band as rows are done and, when the result has a variance from the
    start (or the ring carries one), the variance to ``variance_output`` in a second thread."""
    tw = time.perf_counter()
    var_thread, var_error = None, []
    has_variance = res.variance is not None or (done.ring is not None and len(done.ring.rows_read) > 1)
    if variance_output is not None and has_variance:
        def write_variance() -> None:
            try:
                _write_radiance_while_merging(res, done, variance_output, half=half, compression=compression,
                                              inputs=inputs + [output], threads=threads, arr=res.variance, k=1)
            except BaseException as exc:  # noqa: BLE001 - re-raised below, after the radiance's writer
                var_error.append(exc)
                if done.ring is not None:
                    done.ring.fail()      # the merge waits for this writer's rows

        var_thread = threading.Thread(target=write_variance, name="derender-exr-variance", daemon=True)
        var_thread.start()
    try:
        _write_radiance_while_merging(res, done, output, half=half, compression=compression, inputs=inputs,
                                      threads=threads)
    finally:
        if var_thread is not None:
            var_thread.join()
    if var_error:
        raise var_error[0]
    if var_thread is not None:
        res.info["overlapped_variance_write"] = True
    res.info.setdefault("timings", {})["write_s"] = time.perf_counter() - tw


def write_outputs(res: HDRResult, output: str | os.PathLike | None = None,
                  variance_output: str | os.PathLike | None = None, *, half: bool = False, compression: str = "zip",
                  inputs: Iterable[str | os.PathLike] = (), threads: int | None = None, name: str = "this method") -> None:
    """Write a result's radiance (and variance) to OpenEXR (:func:`derender.io.exr.write_exr_fast`)."""
    inputs = list(inputs)
    if variance_output is not None and res.variance is None:
        raise InputError(f"method {name!r} gives no variance")
    attributes = {**exr_attributes(res.info), **motion_attributes(res.info)}
    if output is not None:
        tw = time.perf_counter()
        write_exr_fast(output, res.radiance, half=half, inputs=inputs, compression=compression, threads=threads,
                       attributes=attributes)
        res.info.setdefault("timings", {})["write_s"] = time.perf_counter() - tw
    if variance_output is not None:
        write_exr_fast(variance_output, res.variance, half=half, inputs=inputs + ([output] if output else []),
                       compression=compression, threads=threads, attributes=dict(attributes, whiteLuminance=None))


def run(method: EngineMethod, source: FileFrames | ArrayFrames, *, threads: int | None = None,
        keep_frames: int | None = None, keep_bytes: int = 256 << 20, hold_bytes: int = HOLD_BYTES,
        output: str | os.PathLike | None = None,
        variance_output: str | os.PathLike | None = None, half: bool = False, compression: str = "zip",
        inputs: Iterable[str | os.PathLike] = (), order_hint: str | None = None,
        hold_outputs: bool = True, motion=None) -> HDRResult:
    """Merge ``source`` with ``method`` (see the module docstring); optionally write the
    radiance to ``output`` and the variance to ``variance_output`` (OpenEXR).

    Streamed methods hold every frame (decoded once, merged by a compiled kernel:
    :func:`_run_streamed_held`) when ``keep_frames`` is None and the bracket's codes fit in
    ``hold_bytes`` (and, with the outputs, in half the available memory); otherwise they
    stream in two passes. Held methods (:attr:`EngineMethod.holds_frames`) read every frame
    once (:func:`_run_held`).

    Parameters
    ----------
    method : EngineMethod
        What to merge with: its plan (tables, matrices or Gaussians) from the frames.
    source : FileFrames or ArrayFrames
        The bracket's 8-bit frames and exposure times.
    threads : int, optional
        Decoding and merging threads (None: every CPU).
    keep_frames, keep_bytes : int
        Frames a two-pass stream keeps between its passes (default: as many as fit in
        ``keep_bytes``, at least 1).
    hold_bytes : int
        The largest bracket of codes a streamed method holds whole.
    output, variance_output : path-like, optional
        OpenEXR files for the radiance and the variance (``half``, ``compression``), written
        atomically and never over one of ``inputs``.
    order_hint : str, optional
        For user input: check while decoding that the images brighten with their exposure
        times (:func:`derender.core.types.check_brightness_order`); the hint ends the error.
    hold_outputs : bool
        False (with ``output``): where the merge writes while merging (held frames merged by a
        compiled kernel), the outputs go through a ring of band buffers
        (:class:`~derender.engine.overlap.OutputRing`) straight into the files and are never
        held whole (9 x 24 MP: 288 MB less memory per output); the result's ``radiance``
        (and ``variance``) are then None.
    motion : MotionOptions, optional
        A reference frame, alignment or ghost removal
        (:class:`~derender.engine.motion.MotionOptions`); when it asks for any, every frame
        is held and :func:`derender.engine.motion.run_motion` merges
        (``info["engine_path"]`` ``"motion"``).

    Returns
    -------
    HDRResult
        Radiance, mask, variance (Gaussian plans), info (timings, ``n_clipped``, the
        method's own entries).

    Raises
    ------
    NotStreamable
        Inputs without 8-bit codes, or a method with no engine form for them: the caller
        falls back to the float reference engine.
    """
    t0 = time.perf_counter()
    if source.n < 2:
        raise StackError("an exposure stack needs at least two images")
    if motion is not None and motion.active:
        from derender.engine.motion import run_motion

        res = run_motion(method, source, motion, threads=threads, order_hint=order_hint)
        res.info["engine_path"] = "motion"
        res.info["reference_name"] = source.name(res.info["reference"])
        res.info["outputs_held"] = True
        write_outputs(res, output, variance_output, half=half, compression=compression, inputs=list(inputs),
                      threads=threads, name=method.name)
        res.info["total_seconds"] = time.perf_counter() - t0
        return res
    inputs = list(inputs)
    write = None
    if output is not None:
        write = functools.partial(_write_while_merging, output=output, variance_output=variance_output, half=half,
                                  compression=compression, inputs=inputs, threads=threads)
    # outputs streamed through band buffers: how many files read them (the variance's too if asked)
    ring = 0 if write is None or hold_outputs else 1 + (variance_output is not None)
    if method.holds_outputs:   # the method's finish() reads the merged radiance
        ring = 0
    if method.holds_frames:
        res = _run_held(method, source, threads, order_hint, write=write, ring=ring)
    elif _hold(source, keep_frames, hold_bytes) or method.variance:   # a variance: held
        res = _run_streamed_held(method, source, threads, order_hint, write=write, ring=ring)
    else:
        res = _run_streamed(method, source, threads, keep_frames, keep_bytes, order_hint)
    res.info["engine_path"] = "streaming"
    res.info["outputs_held"] = res.radiance is not None
    if res.info.get("overlapped_write"):      # the radiance was written while merging
        inputs, output = inputs + [output], None
    if res.info.pop("overlapped_variance_write", False):     # ... and the variance
        variance_output = None
    write_outputs(res, output, variance_output, half=half, compression=compression, inputs=inputs, threads=threads,
                  name=method.name)
    res.info["total_seconds"] = time.perf_counter() - t0
    return res


def run_stack(method, stack: Stack, engine: str = "auto") -> HDRResult:
    """Run an engine ``method`` on an in-memory stack whose values are 8-bit codes.

    The one way to fall back: :class:`~derender.engine.frames.NotStreamable` when the stack is
    not 8-bit codes (or ``engine="reference"``, or the method finds no engine form), and the
    caller then uses the float reference engine."""
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "reference":
        raise NotStreamable("engine='reference' asked for")
    codes = None if stack.bit_depth == 16 else stack_codes_exact(stack.images)
    if codes is None:
        if engine == "table":
            raise InputError("engine='table' needs an 8-bit stack (every value a code / 255)")
        raise NotStreamable("the stack's values are not 8-bit codes")
    return run(method, ArrayFrames(codes, stack.times))
