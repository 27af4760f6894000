"""Merging image files: the product path of ``derender merge``.

:func:`merge_files` reads the exposure times without decoding, sorts the frames and runs
the method on the engine: 8-bit files stream (Debevec: two passes, a few frames held;
paper 1's and paper 2's methods: every frame held once as 8-bit codes), other inputs
(16-bit files, methods without a table form) go through :func:`derender.io.images.read_stack`
and :func:`derender.hdr.registry.merge`. ``info["engine_path"]`` says which ran.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import N_CODES, populated_zeros, thread_count
from derender.core.types import HDRResult
from derender.engine.frames import FramePool, NotStreamable, prefetch, read_frames
from derender.engine.matrix import stabilized_output_bytes, warm_up_kernels
from derender.engine.tables import TableMerge, code_values, curve_value_tables, weight_table
from derender.hdr.registry import get_method, method_options
from derender.hdr.stabilize import merge_stabilized_frames
from derender.hdr.ward2003 import grey8_codes
from derender.io.exif import file_times
from derender.io.exr import write_exr_fast
from derender.io.images import read_codes
from derender.response.curves import check_usable_histograms, code_histograms, histogram_samples
from derender.response.debevec1997 import calibrate_debevec_from_samples

__all__ = [
    "NotStreamable",
    "STREAMING_METHODS",
    "merge_files",
]




#: Methods :func:`merge_files` streams (others are read into memory and merged by :func:`derender.hdr.registry.merge`).
STREAMING_METHODS = ("debevec", "stabilized", "stabilized-joint", "probabilistic")


class _ShiftedFrames:
    """8-bit frames seen through integer registration shifts, as the float images
    :func:`derender.align.align_images` would produce (``out[y, x] = frame[clip(y + dy),
    clip(x + dx)]``, codes as ``k * float32(1/255)``), without making them: ``shape`` and
    ``pixels(j, ys, xs)`` for :func:`derender.stabilize.stabilize_aligned`; ``codes(j)``
    gives the aligned uint8 frame."""

    def __init__(self, frames: list[np.ndarray], shifts: np.ndarray):
        self.frames = frames
        self.shifts = np.asarray(shifts, dtype=int)
        h, w = frames[0].shape[:2]
        self.shape = (len(frames), h, w, 3)
        self.valid_view = _ShiftedValid(self)

    def _where(self, j: int, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.shape[1:3]
        dy, dx = self.shifts[j]
        return np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)

    def pixels(self, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        yy, xx = self._where(j, ys, xs)
        return code_values()[self.frames[j][yy, xx]]

    def code_pixels(self, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        yy, xx = self._where(j, ys, xs)
        return self.frames[j][yy, xx]

    def codes(self, j: int, out: np.ndarray | None = None) -> np.ndarray:
        from derender.hdr.align import shift_into

        dy, dx = self.shifts[j]
        if dy == 0 and dx == 0:
            return self.frames[j]
        out = np.empty_like(self.frames[j]) if out is None else out
        shift_into(out, self.frames[j], int(dy), int(dx))
        return out


class _ShiftedValid:
    """Registration masks of :class:`_ShiftedFrames` (``shape``, ``pixels``), never made whole."""

    def __init__(self, frames: _ShiftedFrames):
        self.f = frames
        self.shape = frames.shape[:3]

    def pixels(self, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        h, w = self.shape[1:3]
        dy, dx = self.f.shifts[j]
        return (ys + dy >= 0) & (ys + dy < h) & (xs + dx >= 0) & (xs + dx < w)


@dataclass
class _LazyAlignment:
    """What :func:`derender.stabilize.stabilize_aligned` and the table merge read of an Alignment."""

    images: _ShiftedFrames
    valid: _ShiftedValid
    transforms: np.ndarray
    method: str
    reference: int
    shifts: np.ndarray
    info: dict


def _stream_probabilistic(paths: list[Path], t: np.ndarray, opts: dict, threads: int | None) -> HDRResult:
    """:func:`derender.probabilistic.merge_probabilistic` on 8-bit files, band by band (same numbers)."""
    from derender.hdr.probabilistic import as_model, check_options, merge_probabilistic_frames

    model = as_model(opts.get("model"))
    space, _ = check_options(model, opts["target_time"], opts["colour_space"], opts["censor"], opts["space"],
                              opts["floor"], opts["clip_code"], opts["code_noise"])
    if space != "log":
        raise NotStreamable("raw-space product")
    t0 = time.perf_counter()
    frames, _ = read_frames(paths, threads)
    t1 = time.perf_counter()
    res = merge_probabilistic_frames(frames, t, model, target_time=opts["target_time"],
                                     colour_space=opts["colour_space"], censor=opts["censor"], space=opts["space"],
                                     floor=opts["floor"], clip_code=opts["clip_code"], threads=threads,
                                     code_noise=opts["code_noise"])
    res.info["timings"] = {"decode_s": t1 - t0, "merge_s": time.perf_counter() - t1}
    res.info["streaming"] = {"frames_kept": len(frames), "decodes": len(frames)}
    return res


def _stream_stabilized(paths: list[Path], t: np.ndarray, method: str, opts: dict,
                       threads: int | None) -> HDRResult:
    """:func:`derender.stabilize.merge_stabilized` (or ``-joint``) on 8-bit files, same result.

    Each frame is decoded once and kept as 8-bit codes (72 MB per 24 MP frame, a quarter
    of the float image the in-memory path holds, which also keeps an aligned copy); grey
    images are made in the decoding threads. Registration (MTB) works on the greys, the
    reference is chosen on the row-subsampled codes exactly as
    :func:`~derender.stabilize.select_reference` does, the gamma / matrix fits read only
    their sampled blocks through :class:`_ShiftedFrames`, the Debevec curve (filmic
    cameras) comes from grid samples of the aligned frames, and the merge takes bands of
    pass reads all frames through their shifts (:func:`merge_stabilized_frames`).
    """
    from derender.hdr.align import chain_transforms, transforms_to_shifts
    from derender.hdr.stabilize import select_reference, stabilize_aligned, unclipped_debevec
    from derender.response.curves import DEFAULT_LAMBDA, DEFAULT_SAMPLES, grid_positions

    align = opts["align"]
    if align not in ("mtb", "none"):
        raise NotStreamable(f"align={align!r} warps frames")
    n = len(paths)
    t0 = time.perf_counter()
    warm_up_kernels()
    # the greys' memory is reused for the merge's outputs once registration is done: fresh
    # memory costs 0.5-3 ms/MB here (page population), 216 MB of it per 24 MP bracket
    held: dict = {}

    def grey_alloc(h: int, w: int, nbytes: int) -> np.ndarray:
        held["buffer"] = populated_zeros(max(nbytes, stabilized_output_bytes(h, w)), np.uint8)
        return held["buffer"]

    frames, greys = read_frames(paths, threads, derive=(lambda f, out: grey8_codes(f, out=out)) if align == "mtb" else None,
                                derive_alloc=grey_alloc)
    out_buffer = held.pop("buffer", None)
    h, w = frames[0].shape[:2]
    # response.check_usable: grid samples settle it, unless some channel shows no usable code there
    ys, xs = grid_positions(h, w, DEFAULT_SAMPLES, int(opts["seed"]))
    probe = np.stack([f[ys, xs] for f in frames])
    if not np.all(((probe > 0) & (probe < N_CODES - 1)).any(axis=(0, 1))):
        check_usable_histograms(np.stack([code_histograms(f) for f in frames]))
    # reference (stabilize.select_reference reads every k-th row of the float frames)
    if opts["reference"] is None:
        ref = select_reference(frames)         # counts 8-bit codes against the code thresholds
    else:
        ref = int(opts["reference"])
        if not 0 <= ref < n:
            raise InputError(f"reference image {opts['reference']} is out of range 0..{n - 1}")
    t1 = time.perf_counter()
    if align == "mtb":
        transforms, ainfo = chain_transforms(greys, "mtb", ref, seed=int(opts["seed"]), threads=threads)
    else:
        transforms, ainfo = np.repeat(np.eye(3)[None], n, axis=0), {}
    del greys
    shifts = transforms_to_shifts(transforms)
    view = _ShiftedFrames(frames, shifts)
    al = _LazyAlignment(images=view, valid=view.valid_view, transforms=transforms, method=align, reference=ref,
                        shifts=shifts, info=ainfo)
    t2 = time.perf_counter()
    seed = int(opts["seed"])

    def calibrate():
        cur = unclipped_debevec(view.code_pixels, n, (h, w), t, seed)
        if cur is not None:
            return cur
        ys, xs = grid_positions(h, w, DEFAULT_SAMPLES, seed)
        samples = np.stack([view.code_pixels(j, ys, xs) for j in range(n)]).astype(np.int32)

        def aligned_hists() -> np.ndarray:
            return np.stack([code_histograms(np.ascontiguousarray(view.codes(j))) for j in range(n)])

        return calibrate_debevec_from_samples(samples, t, aligned_hists, DEFAULT_LAMBDA, DEFAULT_SAMPLES, "grid", seed)

    mode = "joint" if method == "stabilized-joint" else "reference"
    stab = stabilize_aligned(al, t, mode=mode, response=opts["response"], gammas=opts["gammas"],
                             use_times=opts["use_times"], path=opts.get("path", "auto"), block=opts["block"],
                             max_blocks=opts["max_blocks"], ransac_iter=opts["ransac_iter"], seed=seed,
                             calibrate=calibrate)
    t3 = time.perf_counter()
    res = merge_stabilized_frames(stab, frames, np.asarray(shifts, dtype=np.int64), None, opts["weight"],
                                   opts["noise_weighting"], threads, buffer=out_buffer)
    del out_buffer
    if res is None:
        raise NotStreamable("no table form for these curves")
    t4 = time.perf_counter()
    from derender.hdr.stabilize import stabilization_info

    res.info.update(stabilization_info(stab))
    res.info.update({"method": method,
                     "timings": {"decode_s": t1 - t0, "align_s": t2 - t1, **stab.info["timings"],
                                 "merge_s": t4 - t3},
                     "streaming": {"frames_kept": n, "decodes": n}})
    return res


def merge_files(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
                     method: str = "debevec", *, times_file: str | os.PathLike | None = None,
                     times_file_inverse: bool = False, output: str | os.PathLike | None = None,
                     half: bool = False, inputs: Iterable[str | os.PathLike] = (), threads: int | None = None,
                     keep_frames: int | None = None, keep_bytes: int = 256 << 20, compression: str = "zip",
                     **options: Any) -> HDRResult:
    """Merge image files into a radiance map, streaming 8-bit frames; optionally write ``output`` (.exr).

    Times as :func:`derender.io.read_stack` (``times`` in the order of ``paths``, else
    ``times_file``, else EXIF). For ``method="debevec"`` (options as
    :func:`~derender.merge.merge_debevec`) and 8-bit files: pass 1 decodes each frame
    and keeps only the calibration samples (and the last ``keep_frames`` frames; default
    as many as fit in ``keep_bytes``, at least 1), calibrates as
    :func:`~derender.response.calibrate_debevec` would on the whole stack, pass 2
    decodes the others again (longest exposure first, the next frame decoded while the
    current one is merged) and accumulates them with :class:`TableMerge`. The result
    equals ``merge(read_stack(paths), "debevec", ...)`` to ~1e-6 relative. Other
    methods and 16-bit files go through ``read_stack`` + :func:`~derender.merge.merge`
    (``info["engine"]`` says which path ran). The radiance is returned as an (H, W, 3)
    view of planar float32 memory. Writing uses :func:`write_exr_fast`.
    """
    t_start = time.perf_counter()
    get_method(method)   # an unknown method is an error before any file is read
    paths = [Path(p) for p in paths]
    t = file_times(paths, times, times_file, times_file_inverse)
    order = np.argsort(t, kind="stable")
    paths = [paths[i] for i in order]
    t = t[order]
    all_inputs = list(paths) + list(inputs) + ([Path(times_file)] if times_file else [])
    if output is not None:
        from derender.io.files import check_not_input

        if Path(output).suffix.lower() != ".exr":
            raise InputError(f"output must end in .exr, got {Path(output).name}")
        check_not_input(output, all_inputs)
    res = None
    if method in STREAMING_METHODS:
        opts = method_options(method, options)
        try:
            if opts.get("engine", "auto") == "reference":
                raise NotStreamable("reference engine requested")
            if method == "debevec":
                res = _stream_debevec(paths, t, opts, threads=threads, keep_frames=keep_frames,
                                      keep_bytes=keep_bytes)
            elif method == "probabilistic":
                res = _stream_probabilistic(paths, t, opts, threads=threads)
            else:
                res = _stream_stabilized(paths, t, method, opts, threads=threads)
        except NotStreamable:
            res = None
    if res is None:
        from derender.hdr.registry import merge_seeded
        from derender.io.images import read_stack

        seed = options.pop("seed", 0)
        stack = read_stack(paths, times=t)
        res = merge_seeded(stack, method, seed, **options)
        res.info.setdefault("engine", "stack")
        res.info["engine_path"] = "stack"
    else:
        res.info["engine_path"] = "streaming"
    if output is not None:
        tw = time.perf_counter()
        write_exr_fast(output, res.radiance, half=half, inputs=all_inputs, compression=compression, threads=threads)
        res.info.setdefault("timings", {})["write_s"] = time.perf_counter() - tw
    res.info["total_seconds"] = time.perf_counter() - t_start
    return res


def _stream_debevec(paths: list[Path], t: np.ndarray, opts: dict, threads: int | None,
                    keep_frames: int | None, keep_bytes: int) -> HDRResult:
    from derender.response.curves import DEFAULT_LAMBDA, DEFAULT_SAMPLES, grid_positions

    n = len(paths)
    lam = DEFAULT_LAMBDA if opts["lam"] is None else float(opts["lam"])
    n_samples = DEFAULT_SAMPLES if opts["n_samples"] is None else int(opts["n_samples"])
    sampling, seed = opts["sampling"], int(opts["seed"])
    if sampling not in ("grid", "histogram"):
        raise InputError(f"unknown sampling method {sampling!r}; use 'grid' or 'histogram'")
    if n_samples < 1:
        raise InputError(f"n_samples must be positive, got {n_samples}")
    wt = weight_table(opts["weight"])
    domain, cw = opts["domain"], opts["channel_weights"]
    t0 = time.perf_counter()

    # pass 1: samples (and histograms when needed), keep the last frames
    shape = None
    samples = None
    hists = np.zeros((n, 3, N_CODES), dtype=np.int64) if sampling == "histogram" else None
    kept: dict[int, np.ndarray] = {}
    keep = keep_frames
    ys = xs = None
    nthreads = thread_count(threads)
    pool = FramePool()
    for j, codes in enumerate(prefetch(lambda p: read_codes(p, out=pool.get()), paths, depth=nthreads,
                                        workers=nthreads)):
        if codes is None:
            raise NotStreamable("16-bit input")
        if shape is None:
            shape = pool.shape = codes.shape
            h, w = shape[:2]
            if keep is None:
                keep = int(keep_bytes // max(codes.nbytes, 1))
            keep = int(min(max(keep, 1), n))
            if sampling == "grid":
                ys, xs = grid_positions(h, w, n_samples, seed)
                samples = np.empty((n, ys.size, 3), dtype=np.int32)
        elif codes.shape != shape:
            raise InputError(f"images differ in size: {paths[0].name} is {shape[1]}x{shape[0]}, "
                             f"{paths[j].name} is {codes.shape[1]}x{codes.shape[0]}")
        if sampling == "grid":
            samples[j] = codes[ys, xs]
        else:
            hists[j] = code_histograms(codes)
        if j >= n - keep:
            kept[j] = codes
        else:
            pool.put(codes)
        del codes
    t1 = time.perf_counter()

    def get_hists() -> np.ndarray:
        nonlocal hists
        if hists is None:  # rare: a channel without usable grid samples
            hists = np.stack([code_histograms(kept[j] if j in kept else read_codes(paths[j])) for j in range(n)])
        return hists

    if sampling == "histogram":
        samples = histogram_samples(hists, n_samples)
    # response.check_usable on the whole stack; the samples settle it unless a channel has no usable sample
    if not np.all(((samples > 0) & (samples < N_CODES - 1)).any(axis=(0, 1))):
        check_usable_histograms(get_hists())
    curves = opts["curves"]
    if curves is None:
        curves = calibrate_debevec_from_samples(samples, t, get_hists, lam, n_samples, sampling, seed)
    t2 = time.perf_counter()

    # pass 2: longest exposure first (kept frames need no decoding), shortest last
    values = curve_value_tables(curves, t, domain)
    h, w = shape[:2]
    order = list(range(n - 1, -1, -1))
    long_codes = short_codes = None

    def load(j: int) -> np.ndarray:
        return kept[j] if j in kept else read_codes(paths[j], out=pool.get())

    with TableMerge((h, w), channel_weights=cw, domain=domain, threads=threads,
                    block_rows=opts.get("block_rows")) as eng:
        for j, codes in zip(order, prefetch(load, order)):
            if codes is None or codes.shape != shape:
                raise InputError(f"{paths[j]} changed while merging")
            eng.add(codes, values[j], wt)
            kept.pop(j, None)
            if j == n - 1:
                long_codes = codes
            elif j == 0:
                short_codes = codes
            else:
                pool.put(codes)
            del codes
        t3 = time.perf_counter()
        res = eng.finish((short_codes, values[0]), (long_codes, values[n - 1]))
    t4 = time.perf_counter()
    res.info.update({
        "method": "debevec",
        "weight": opts["weight"] if isinstance(opts["weight"], str) else "custom",
        "curves": curves,
        "merge_seconds": t4 - t2,
        "timings": {"pass1_s": t1 - t0, "calibrate_s": t2 - t1, "merge_s": t3 - t2, "finish_s": t4 - t3},
        "streaming": {"frames_kept": keep, "decodes": n + n - keep},
    })
    return res
