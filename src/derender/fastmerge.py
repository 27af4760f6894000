"""Fast HDR merging of 8-bit brackets: 256-entry tables, row blocks, threads, streaming.

An 8-bit image has 256 code values per channel, so every per-channel linearisation
(Debevec & Malik 1997, eq. 6: ``g(z) - ln t_j``; or ``f^-1(z) / t_j`` in the linear
domain) and every weight ``w(z)`` is a 256-entry table per channel and exposure. The
merge of :func:`derender.merge.merge_linear` then becomes table look-ups and
multiply-adds into float64 (log domain) or float32 accumulators (OpenCV's ``LUT``,
``accumulate`` and ``accumulateProduct``, which release the GIL), run on blocks of rows
by a thread pool.

* :class:`TableMerge` -- the engine: ``add(codes, values, weights)`` per exposure,
  ``finish()`` applies the saturation policy of ``DESIGN.md`` exactly as
  :func:`~derender.merge.merge_linear` does and returns an :class:`HDRResult`.
  An optional per-image 3x3 matrix is applied to the linearised values per block
  (for methods that mix channels, e.g. the stabilised merge of paper 1, eq. 10).
* :func:`merge_curves_table` -- the table path for an in-memory 8-bit
  :class:`~derender.stack.Stack` and per-channel response curves (used by
  ``merge(..., method="debevec"/"robertson")``); ``None`` when the stack is not 8-bit.
* :func:`merge_files_fast` -- streaming merge of image files (``derender merge``):
  every frame is decoded at most twice, one at a time. Pass 1 takes the calibration
  samples (the same grid positions as :func:`derender.response.sample_pixels`, so the
  curves equal :func:`~derender.response.calibrate_debevec` on the full stack), pass 2
  accumulates. Memory: the accumulators (32 bytes per pixel for Debevec's defaults),
  the mask and a few frames, whatever the number of exposures.
* :func:`write_exr_fast` -- OpenEXR writer (scanline, ZIP, float32 or half) that
  compresses blocks of 16 lines in parallel and never copies the whole image.
* :func:`run_bench` -- the side-by-side benchmark (OpenCV, colour-hdri, ``derender
  merge``) on generated full-resolution brackets; ``benchmarks/bench_merge.py`` is its
  command line.

Results equal the reference engine (:func:`~derender.merge.merge_linear`) to about
1e-6 relative (the value tables are float32; tested to 1e-5). Measurements:
``benchmarks/README.md``.
"""

from __future__ import annotations

import inspect
import json
import mmap
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from .errors import InputError, StackError
from .stack import HDRResult, Stack

__all__ = [
    "code_values",
    "weight_table",
    "curve_value_tables",
    "stack_codes_exact",
    "TableMerge",
    "merge_codes",
    "merge_curves_table",
    "merge_stabilized_table",
    "read_codes",
    "file_times",
    "STREAMING_METHODS",
    "merge_files_fast",
    "write_exr_fast",
    "write_exr_lines",
    "generate_bench_bracket",
    "run_bench",
    "format_bench",
]

_F32_MAX = float(np.finfo(np.float32).max)
_CHANNELS = "RGB"
N_CODES = 256


def _cv2():
    import cv2

    return cv2


_CV2_THREADS_LOCK = threading.Lock()
_CV2_SINGLE_DEPTH = [0, 0]   # nesting depth, OpenCV's thread count outside


@contextmanager
def _cv2_single_thread():
    """OpenCV's own threads off inside (process-wide setting; nested and concurrent uses
    from several of our threads are counted, the outermost restores the user's value)."""
    cv2 = _cv2()
    with _CV2_THREADS_LOCK:
        if _CV2_SINGLE_DEPTH[0] == 0:
            _CV2_SINGLE_DEPTH[1] = cv2.getNumThreads()
            cv2.setNumThreads(1)
        _CV2_SINGLE_DEPTH[0] += 1
    try:
        yield
    finally:
        with _CV2_THREADS_LOCK:
            _CV2_SINGLE_DEPTH[0] -= 1
            if _CV2_SINGLE_DEPTH[0] == 0:
                cv2.setNumThreads(_CV2_SINGLE_DEPTH[1])


def _n_threads(threads: int | None) -> int:
    if threads is None:
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except AttributeError:  # pragma: no cover - non-Linux
            return max(1, os.cpu_count() or 1)
    return max(1, int(threads))


# --------------------------------------------------------------------------- tables
#: Arrays at least this large are mapped with their pages populated up front (:func:`populated_zeros`).
POPULATE_BYTES = 8 << 20


def populated_zeros(shape: tuple[int, ...] | int, dtype: Any = np.float32) -> np.ndarray:
    """``np.zeros(shape, dtype)`` whose memory is mapped with all pages present (anonymous
    ``mmap`` with ``MAP_POPULATE``; zero-filled by the kernel).

    Fresh memory normally costs a page fault at first touch of every page, ~2-4 ms per MB
    on this project's 2-core VMs (a 650 MB stack of frames: 1.3-2.9 s); populating the
    mapping in one call costs ~0.5 ms per MB (0.33-0.35 s). Small arrays, and systems
    without ``MAP_POPULATE``, get ``np.zeros``. The array owns the mapping (unmapped when
    the last view goes)."""
    dt = np.dtype(dtype)
    shape = (int(shape),) if np.isscalar(shape) else tuple(int(v) for v in shape)
    count = int(np.prod(shape, dtype=np.int64))
    nbytes = count * dt.itemsize
    flag = getattr(mmap, "MAP_POPULATE", None)
    if nbytes < POPULATE_BYTES or flag is None:
        return np.zeros(shape, dtype=dt)
    try:
        m = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | flag)
    except (OSError, ValueError):
        return np.zeros(shape, dtype=dt)
    return np.frombuffer(m, dtype=dt, count=count).reshape(shape)


def code_values() -> np.ndarray:
    """The 256 normalised values of 8-bit codes, float32 ``k * float32(1/255)`` (as :func:`derender.io.read_image`)."""
    return np.arange(N_CODES, dtype=np.float32) * np.float32(1.0 / 255.0)


def weight_table(weight: str | Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(256, 3) float32 table of a weight (name in :data:`~derender.merge.WEIGHTS` or pointwise callable) on the codes."""
    from .merge import get_weight

    fn = get_weight(weight)
    z = np.repeat(code_values()[:, None], 3, axis=1)
    w = np.asarray(fn(z), dtype=np.float32)
    if w.shape == (N_CODES,):
        w = np.repeat(w[:, None], 3, axis=1)
    if w.shape != (N_CODES, 3):
        raise InputError(f"weight function returned shape {w.shape} for (256, 3) codes")
    return np.ascontiguousarray(w)


def curve_value_tables(curves, times: Any, domain: str = "log") -> np.ndarray:
    """(N, 256, 3) float32: the value each code contributes for exposure ``j`` (merge_linear, eq. 6).

    ``domain="log"``: ``g(z) - ln t_j``; ``"linear"``: ``exp(g(z) - ln t_j)``, with
    ``g`` from :meth:`ResponseCurves.log_linearise` evaluated on the code values (the
    same float32 interpolation the reference applies to every pixel).
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    g = curves.log_linearise(np.repeat(code_values()[:, None], 3, axis=1)).astype(np.float64)
    v = g[None] - np.log(t)[:, None, None]
    if domain == "linear":
        v = np.exp(v)
    elif domain != "log":
        raise InputError(f"domain must be 'linear' or 'log', got {domain!r}")
    return np.ascontiguousarray(v, dtype=np.float32)


def stack_codes_exact(images: np.ndarray, tol: float = 1e-3) -> np.ndarray | None:
    """uint8 codes of an (N, H, W, 3) float stack in [0, 1] if every value is ``code / 255`` (to ``tol`` codes), else None.

    Works on blocks of rows (small temporaries: large fresh ones cost page faults).
    """
    images = np.asarray(images)
    if images.dtype == np.uint8:
        return images
    if images.ndim != 4 or images.dtype.kind != "f":
        return None
    n, h, w = images.shape[:3]
    out = np.empty(images.shape, dtype=np.uint8)
    rows = max(1, (1 << 16) // max(w, 1))
    x = np.empty((rows, w, 3), dtype=np.float32)
    r = np.empty_like(x)
    for j in range(n):
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            xb, rb = x[: r1 - r0], r[: r1 - r0]
            np.multiply(images[j, r0:r1], np.float32(255.0), out=xb, casting="unsafe")
            np.rint(xb, out=rb)
            if rb.min() < 0 or rb.max() > 255:
                return None
            np.subtract(xb, rb, out=xb)
            np.abs(xb, out=xb)
            if xb.max() > tol:
                return None
            out[j, r0:r1] = rb
    return out


# --------------------------------------------------------------------------- engine
_ENGINE_MODES = ("mean", "min", "independent", "brightest", "min_else_brightest")


class TableMerge:
    """Weighted merge of 8-bit exposures by table look-up (Debevec & Malik 1997, eq. 6), in row blocks.

    ``add(codes, values, weights)`` accumulates one exposure: ``codes`` (H, W, 3)
    uint8 RGB, ``values`` (256, 3) the per-channel value ``v_j(z)`` of each code (what
    :func:`~derender.merge.merge_linear` averages: ``g(z) - ln t_j`` in the log domain,
    ``lin(z) / t_j`` in the linear one), ``weights`` (256, 3) ``w(z)``. With ``matrix``
    (3, 3), ``values`` is a per-channel linearisation and the averaged value is
    ``matrix @ values(z)`` (linear domain only). ``image_weight`` multiplies the weights
    and ``pixel_weights`` ((H, W), e.g. a registration mask) multiplies them per pixel.

    ``channel_weights``: ``"mean"``, ``"min"`` or ``"independent"`` as in merge_linear;
    ``"brightest"``: every channel takes the weight of the pixel's largest code, and
    the saturation policy judges that code too; ``"min_else_brightest"``: the ``"min"``
    weights where some exposure has all channels usable, else the ``"brightest"`` ones
    (two sets of accumulators; the weights of the stabilised merge of paper 1, whose
    compiled form is :func:`merge_stabilized_table`). :meth:`finish` needs the codes and
    tables of the shortest and longest exposures for the saturation policy.

    Accumulators: float64 in the log domain (a float32 sum of ``w (g - ln t)`` would
    lose up to ``N * 6e-8 * |ln E|`` relative, ~1e-5 for 18 frames), float32 in the
    linear domain (sums of same-sign terms); ``accumulator`` overrides. The float32
    radiance is written in place into the accumulator memory, so a merge needs
    8 (or 16) bytes per pixel and channel plus the weight planes, and nothing more.
    """

    def __init__(self, shape: tuple[int, int], channel_weights: str = "mean", domain: str = "log",
                 bright_threshold: float = 0.5, threads: int | None = None, block_rows: int | None = None,
                 accumulator: str = "auto"):
        if channel_weights not in _ENGINE_MODES:
            raise InputError(f"channel_weights must be one of {', '.join(_ENGINE_MODES)}, got {channel_weights!r}")
        if domain not in ("linear", "log"):
            raise InputError(f"domain must be 'linear' or 'log', got {domain!r}")
        if accumulator not in ("auto", "float32", "float64"):
            raise InputError(f"accumulator must be 'auto', 'float32' or 'float64', got {accumulator!r}")
        if accumulator == "auto":
            accumulator = "float64" if domain == "log" else "float32"
        h, w = int(shape[0]), int(shape[1])
        self.shape = (h, w)
        self.mode = channel_weights
        self.domain = domain
        self.bright_threshold = float(bright_threshold)
        self.threads = _n_threads(threads)
        if block_rows is None:
            block_rows = max(1, (1 << 16) // max(w, 1))
        self.block_rows = max(1, int(block_rows))
        self.dtype = np.dtype(accumulator)
        self.sets = ("min", "brightest") if channel_weights == "min_else_brightest" else (channel_weights,)
        self.num = populated_zeros((3 * len(self.sets), h, w), dtype=self.dtype)
        self.den = populated_zeros(((3 if channel_weights == "independent" else 1) * len(self.sets), h, w),
                                   dtype=self.dtype)
        self.n_added = 0
        self._pool: ThreadPoolExecutor | None = None

    # -- threading
    def _bands(self) -> list[tuple[int, int]]:
        h = self.shape[0]
        step = self.block_rows * 8
        return [(r0, min(h, r0 + step)) for r0 in range(0, h, step)]

    def _run(self, fn: Callable[[int, int], Any]) -> list:
        """``fn(r0, r1)`` over bands of rows. OpenCV's own threads are off meanwhile: ours own the
        cores, and OpenCV's split of an array (SIMD body vs scalar tail, e.g. in ``exp``) must not
        depend on its thread count, so the bytes of a result never depend on the machine."""
        bands = self._bands()
        with _cv2_single_thread():
            if self.threads == 1 or len(bands) == 1:
                return [fn(a, b) for a, b in bands]
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="derender-merge")
            return list(self._pool.map(lambda ab: fn(*ab), bands))

    def close(self) -> None:
        """Stop the worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> "TableMerge":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- accumulate
    def _check_codes(self, codes: np.ndarray) -> np.ndarray:
        codes = np.asarray(codes)
        if codes.dtype != np.uint8 or codes.shape != (*self.shape, 3):
            raise InputError(f"codes must be uint8 of shape {(*self.shape, 3)}, got {codes.dtype} {codes.shape}")
        return np.ascontiguousarray(codes)

    @staticmethod
    def _table(t: Any, what: str) -> np.ndarray:
        t = np.asarray(t, dtype=np.float32)
        if t.shape == (N_CODES,):
            t = np.repeat(t[:, None], 3, axis=1)
        if t.shape != (N_CODES, 3):
            raise InputError(f"{what} table must have shape (256, 3), got {t.shape}")
        if not np.all(np.isfinite(t)):
            raise InputError(f"{what} table has non-finite entries")
        return t

    def add(self, codes: np.ndarray, values: Any, weights: Any, image_weight: float = 1.0,
            matrix: Any = None, pixel_weights: np.ndarray | None = None,
            inverse_variance: tuple[Any, float] | None = None) -> None:
        """Accumulate one exposure (see the class docstring).

        ``inverse_variance=(table, k)`` further multiplies every weight of a pixel by
        ``k / max(mean_c table[z_c, c], 1e-30)`` (e.g. ``t_j^2 / mean (dL/dJ)^2``: the
        inverse variance of the radiance estimate for equal code noise).
        """
        cv2 = _cv2()
        codes = self._check_codes(codes)
        vt = self._table(values, "value")
        wt = self._table(weights, "weight").astype(np.float64) * float(image_weight)
        if self.mode == "mean":
            wt = wt / 3.0
        wt = wt.astype(np.float32)
        vcol = [np.ascontiguousarray(vt[:, c]) for c in range(3)]
        wcol = [np.ascontiguousarray(wt[:, c]) for c in range(3)]
        m = None
        if matrix is not None:
            if self.domain != "linear":
                raise InputError("a colour matrix needs the linear domain")
            m = np.asarray(matrix, dtype=np.float64)
            if m.shape != (3, 3) or not np.all(np.isfinite(m)):
                raise InputError(f"matrix must be a finite 3x3 array, got shape {m.shape}")
        pw = None
        if pixel_weights is not None:
            pw = np.asarray(pixel_weights)
            if pw.shape != self.shape:
                raise InputError(f"pixel_weights must have shape {self.shape}, got {pw.shape}")
            pw = np.ascontiguousarray(pw, dtype=np.float32)
        ivt = None
        if inverse_variance is not None:
            itab = self._table(inverse_variance[0], "inverse-variance")
            ivt = ([np.ascontiguousarray(itab[:, c] / np.float32(3.0)) for c in range(3)], float(inverse_variance[1]))
        num, den, mode, br = self.num, self.den, self.mode, self.block_rows

        def acc(dst: np.ndarray, a: np.ndarray, b: np.ndarray | None = None) -> None:
            """dst += a (* b), float32 sources into a float32 or float64 accumulator."""
            if b is None:
                cv2.accumulate(a, dst)
            else:
                cv2.accumulateProduct(a, b, dst)

        def weights_of(mode: str, p: list, r0: int, r1: int) -> tuple:
            """Per-channel weight planes of one set (a tuple of 3, possibly the same plane)."""
            if mode == "independent":
                wc = [cv2.LUT(p[c], wcol[c]) for c in range(3)]
                if pw is not None:
                    for c in range(3):
                        cv2.multiply(wc[c], pw[r0:r1], dst=wc[c])
                return tuple(wc)
            if mode == "brightest":
                wsum = cv2.LUT(cv2.max(cv2.max(p[0], p[1]), p[2]), wcol[0])
            else:
                w0, w1, w2 = (cv2.LUT(p[c], wcol[c]) for c in range(3))
                if mode == "mean":
                    wsum = cv2.add(w0, w1)
                    cv2.add(wsum, w2, dst=wsum)
                else:
                    wsum = cv2.min(w0, w1)
                    cv2.min(wsum, w2, dst=wsum)
            if pw is not None:
                cv2.multiply(wsum, pw[r0:r1], dst=wsum)
            return (wsum, wsum, wsum)

        sets = self.sets
        nd = 3 if mode == "independent" else 1

        def band(b0: int, b1: int) -> None:
            for r0 in range(b0, b1, br):
                r1 = min(b1, r0 + br)
                p = cv2.split(codes[r0:r1])
                if m is None:
                    vals = [cv2.LUT(p[c], vcol[c]) for c in range(3)]
                else:
                    lin = [cv2.LUT(p[d], vcol[d]) for d in range(3)]
                    vals = []
                    for c in range(3):
                        v = cv2.addWeighted(lin[0], float(m[c, 0]), lin[1], float(m[c, 1]), 0.0)
                        cv2.scaleAdd(lin[2], float(m[c, 2]), v, dst=v)
                        vals.append(v)
                inv = None
                if ivt is not None:
                    d = cv2.add(cv2.LUT(p[0], ivt[0][0]), cv2.LUT(p[1], ivt[0][1]))
                    cv2.add(d, cv2.LUT(p[2], ivt[0][2]), dst=d)
                    np.maximum(d, np.float32(1e-30), out=d)
                    inv = cv2.divide(ivt[1], d)
                for k, smode in enumerate(sets):
                    wc = weights_of(smode, p, r0, r1)
                    if inv is not None:
                        wc = tuple(cv2.multiply(x, inv) for x in wc) if wc[0] is not wc[1] else \
                            (cv2.multiply(wc[0], inv),) * 3
                    for i in range(nd):
                        acc(den[k * nd + i, r0:r1], wc[i])
                    for c in range(3):
                        acc(num[k * 3 + c, r0:r1], vals[c], wc[c])

        self._run(band)
        self.n_added += 1

    # -- finish
    @staticmethod
    def _values_at(z: np.ndarray, vt: np.ndarray, matrix: Any) -> np.ndarray:
        v = np.stack([vt[z[:, c], c] for c in range(3)], axis=1).astype(np.float64)
        if matrix is not None:
            v = v @ np.asarray(matrix, dtype=np.float64).T
        return v

    def finish(self, short: tuple, long: tuple, contiguous: bool = False, info: dict | None = None) -> HDRResult:
        """Normalise, apply the saturation policy and return the result.

        ``short`` / ``long``: ``(codes, values[, matrix])`` of the shortest and the
        longest exposure. Where the total weight of a channel is 0 the value comes from
        the shortest exposure if its value of the channel (``"brightest"``: the pixel's
        largest code) is ``>= bright_threshold``, else from the longest; ``mask`` 1
        (bright) / 2 (dark) as in merge_linear. ``contiguous=False`` returns the
        radiance as an (H, W, 3) view of the accumulator memory (no copy).
        """
        cv2 = _cv2()
        if self.n_added == 0:
            raise InputError("no exposure was added")
        zs, zl = self._check_codes(short[0]), self._check_codes(long[0])
        vs, vl = self._table(short[1], "value"), self._table(long[1], "value")
        ms, ml = (short[2] if len(short) > 2 else None), (long[2] if len(long) > 2 else None)
        bright_tab = code_values() >= np.float32(self.bright_threshold)
        h, w = self.shape
        mask = populated_zeros((h, w), dtype=np.uint8)
        num, den, log = self.num, self.den, self.domain == "log"
        # float32 output planes: the first accumulator planes, or the first half of each float64 row
        out = num[:3] if self.dtype == np.float32 else num[:3].view(np.float32)[:, :, :w]

        def block(b0: int, b1: int) -> tuple[int, int]:
            nb = nd = 0
            d = den[:, b0:b1]
            with np.errstate(divide="ignore", invalid="ignore"):
                if len(self.sets) == 1:
                    ok = d > 0
                    res = [num[c, b0:b1] / d[0 if d.shape[0] == 1 else c] for c in range(3)]
                else:  # min_else_brightest: set 0 where it has weight, else set 1
                    use0 = d[0] > 0
                    ok = (use0 | (d[1] > 0))[None]
                    res = [np.where(use0, num[c, b0:b1] / d[0], num[3 + c, b0:b1] / d[1]) for c in range(3)]
            if not ok.all():
                bad = ~ok.reshape(ok.shape[0], -1)
                pix = np.flatnonzero(bad.any(axis=0))
                none = np.broadcast_to(bad[:, pix].T, (pix.size, 3))
                z_s = zs[b0:b1].reshape(-1, 3)[pix]
                z_l = zl[b0:b1].reshape(-1, 3)[pix]
                if self.mode in ("brightest", "min_else_brightest"):   # the fallback sees the brightest channel
                    bright = none & bright_tab[z_s.max(axis=1)][:, None]
                else:
                    bright = none & bright_tab[z_s]
                dark = none & ~bright
                fs = self._values_at(z_s, vs, ms)
                fl = self._values_at(z_l, vl, ml)
                for c in range(3):
                    flat = res[c].reshape(-1)
                    flat[pix] = np.where(bright[:, c], fs[:, c], np.where(dark[:, c], fl[:, c], flat[pix]))
                bpix = bright.any(axis=1)
                dpix = dark.any(axis=1) & ~bpix
                mflat = mask[b0:b1].reshape(-1)
                mflat[pix[bpix]] = HDRResult.MASK_BRIGHT
                mflat[pix[dpix]] = HDRResult.MASK_DARK
                nb, nd = int(bpix.sum()), int(dpix.sum())
            for c in range(3):
                r = res[c]
                if log:
                    np.minimum(r, 88.0, out=r)
                    r = r.astype(np.float32)
                    cv2.exp(r, dst=r)
                elif r.dtype != np.float32:
                    r = r.astype(np.float32)
                if not cv2.checkRange(r)[0]:
                    np.nan_to_num(r, copy=False, nan=0.0, posinf=_F32_MAX, neginf=-_F32_MAX)
                out[c, b0:b1] = r
            return nb, nd

        def band(b0: int, b1: int) -> tuple[int, int]:
            counts = [block(r0, min(b1, r0 + self.block_rows)) for r0 in range(b0, b1, self.block_rows)]
            return sum(c[0] for c in counts), sum(c[1] for c in counts)

        counts = self._run(band)
        self.close()
        n_bright = sum(c[0] for c in counts)
        n_dark = sum(c[1] for c in counts)
        radiance = out.transpose(1, 2, 0)
        if contiguous:
            radiance = np.ascontiguousarray(radiance)
        self.num = self.den = None  # the result owns the memory now
        out_info = {"channel_weights": self.mode, "domain": self.domain, "n_bright": n_bright, "n_dark": n_dark,
                    "engine": "table", "accumulator": self.dtype.name}
        if info:
            out_info.update(info)
        return HDRResult(radiance=radiance, mask=mask, variance=None, info=out_info)


def merge_codes(codes: Sequence[np.ndarray] | np.ndarray, times: Any, values: np.ndarray, weights: Any,
                *, image_weights: Any = None, matrices: Any = None, channel_weights: str = "mean",
                domain: str = "log", bright_threshold: float = 0.5, threads: int | None = None,
                block_rows: int | None = None, contiguous: bool = True) -> HDRResult:
    """Table merge of in-memory 8-bit exposures (N, H, W, 3) sorted or not by ``times``.

    ``values`` (N, 256, 3) per-exposure value tables, ``weights`` (256, 3) or (N, 256, 3),
    ``image_weights`` (N,), ``matrices`` (N, 3, 3) or None. Same result as
    :func:`~derender.merge.merge_linear` on the corresponding linearisation.
    """
    t0 = time.perf_counter()
    n = len(codes)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.size != n:
        raise InputError(f"{t.size} exposure time(s) for {n} image(s)")
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise InputError(f"exposure times must be positive finite seconds, got {t.tolist()}")
    values = np.asarray(values, dtype=np.float32)
    if values.shape != (n, N_CODES, 3):
        raise InputError(f"values must have shape ({n}, 256, 3), got {values.shape}")
    wts = np.asarray(weights, dtype=np.float32)
    if wts.shape == (N_CODES,):
        wts = np.repeat(wts[:, None], 3, axis=1)
    if wts.shape == (N_CODES, 3):
        wts = np.broadcast_to(wts, (n, N_CODES, 3))
    if wts.shape != (n, N_CODES, 3):
        raise InputError(f"weights must have shape (256, 3) or ({n}, 256, 3), got {wts.shape}")
    iw = np.ones(n) if image_weights is None else np.asarray(image_weights, dtype=np.float64).reshape(-1)
    if iw.size != n or not np.all(np.isfinite(iw)) or np.any(iw < 0):
        raise InputError("image_weights must be N finite non-negative numbers")
    mats = [None] * n if matrices is None else [np.asarray(m, dtype=np.float64) for m in matrices]
    shape = np.asarray(codes[0]).shape[:2]
    j_short, j_long = int(np.argmin(t)), int(np.argmax(t))
    with TableMerge(shape, channel_weights=channel_weights, domain=domain, bright_threshold=bright_threshold,
                    threads=threads, block_rows=block_rows) as eng:
        for j in range(n):
            eng.add(codes[j], values[j], wts[j], image_weight=float(iw[j]), matrix=mats[j])
        res = eng.finish((codes[j_short], values[j_short], mats[j_short]), (codes[j_long], values[j_long], mats[j_long]),
                         contiguous=contiguous)
    res.info["merge_seconds"] = time.perf_counter() - t0
    return res


def merge_curves_table(stack: Stack, curves, weight: Any = "gaussian", *, domain: str = "log",
                       channel_weights: str = "mean", image_weights: Any = None, bright_threshold: float = 0.5,
                       block_rows: int | None = None, threads: int | None = None) -> HDRResult | None:
    """The table path of :func:`~derender.merge.merge_linear` for per-channel response curves.

    Equivalent to ``merge_linear(lambda j, z: curves.log_linearise(z), stack.times,
    stack.images, weight, log_input=True, ...)``. Returns None when the stack is not
    8-bit (values not all ``code / 255``), so the caller falls back to the reference.
    """
    if stack.bit_depth == 16:
        return None
    codes = stack_codes_exact(stack.images)
    if codes is None:
        return None
    wt = weight_table(weight)
    values = curve_value_tables(curves, stack.times, domain)
    res = merge_codes(codes, stack.times, values, wt, image_weights=image_weights, channel_weights=channel_weights,
                      domain=domain, bright_threshold=bright_threshold, threads=threads, block_rows=block_rows,
                      contiguous=True)
    res.info["weight"] = weight if isinstance(weight, str) else "custom"
    return res


def merge_stabilized_table(stab, weight: Any = "trapezoid", noise_weighting: bool = True,
                           threads: int | None = None) -> HDRResult | None:
    """:func:`derender.stabilize.stabilized_merge` on 8-bit codes (paper 1, Algorithm 1 step 4).

    Image ``j`` contributes ``H'_j L_j(z) / t_j`` with the per-channel table
    ``L_j = stab.curves[j].lin`` on the 256 codes and the 3x3 matrix ``H'_j``
    (``H_j t_j / t_ref`` in reference mode, ``K_j`` in joint mode). One weight for all
    channels, times the registration mask: the smallest channel weight where some
    exposure has all channels usable, else the weight of the brightest channel; with
    ``noise_weighting`` times ``t_j^2 / mean_c (dL_j/dJ)^2`` (the reference also divides
    by the per-pixel maximum over images, a common factor that cancels). One compiled
    pass per pixel (:func:`derender.kernels.stabilized_merge_rows`), float32 sums (every
    sum is of a few same-sign weights; measured 2e-7 to 4e-7 relative to the float64
    reference engine). Returns None when the aligned images are not 8-bit codes
    (sub-pixel warps), so the caller keeps the reference path.
    """
    al = stab.alignment
    codes = stack_codes_exact(al.images)
    if codes is None:
        return None
    valid = getattr(al, "valid", None)
    if valid is not None:
        valid = np.asarray(valid)
        valid = None if valid.all() else np.ascontiguousarray(valid, dtype=np.uint8)
    return _merge_stabilized_frames(stab, codes, np.zeros((codes.shape[0], 2), dtype=np.int64), valid,
                                    weight, noise_weighting, threads)


def _stabilized_tables(stab, weight: Any, noise_weighting: bool):
    """Per image: linearisation table (256, 3), matrix ``H'_j / t_j`` and inverse-variance table; None if unsupported."""
    times = np.asarray(stab.times, dtype=np.float64)
    z3 = np.repeat(code_values()[:, None], 3, axis=1)
    curves = list(getattr(stab, "curves", None) or [])
    values, mats, ivs = [], [], []
    t2max = float(np.max(times ** 2))
    for j in range(times.shape[0]):
        if curves:
            lin = np.asarray(curves[j].lin(z3), dtype=np.float64)
        else:  # power law of the gamma estimate (paper 1, eq. 4)
            lin = np.clip(z3.astype(np.float64), 0.0, 1.0) ** float(stab.gammas.gammas[j])
        values.append(lin.astype(np.float32))
        m = np.asarray(stab.matrices[j], dtype=np.float64)
        if stab.mode == "reference":
            m = m * (times[j] / times[stab.reference])
        mats.append(m / times[j])
        if noise_weighting:
            if not curves:
                return None
            d2 = np.asarray(curves[j].dlin(z3), dtype=np.float64) ** 2
            ivs.append((d2.astype(np.float32), times[j] ** 2 / t2max))  # common 1/t2max keeps float32 in range
        else:
            ivs.append(None)
    return values, mats, ivs


def stabilized_output_bytes(h: int, w: int) -> int:
    """Bytes of the stabilised merge's outputs: planar float32 radiance and a uint8 mask."""
    return 13 * int(h) * int(w)


#: Serialises launches of the parallel numba kernels (see :mod:`derender.kernels`).
_KERNEL_LOCK = threading.Lock()


def _set_numba_threads(threads: int | None) -> None:
    import numba

    numba.set_num_threads(max(1, min(_n_threads(threads), int(numba.config.NUMBA_NUM_THREADS))))


def _warm_up_stabilized() -> threading.Thread:
    """Import numba and load the MTB and merge kernels from its cache (0.5-1 s) in a
    background thread while the frames decode: the import holds the GIL, decoding
    (libjpeg-turbo) does not. Failures are left for the real calls to report."""
    def run() -> None:
        try:
            from .kernels import mtb_band_counts, stabilized_merge_rows

            mtb_band_counts(np.zeros((1, 1), np.uint8), np.zeros((1, 1), np.uint8), 0, 0, 4, np.zeros(1, np.int64),
                            1, 0, np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 2), np.int64))

            f32 = np.float32
            with _KERNEL_LOCK:
                stabilized_merge_rows(np.zeros((1, 1, 1, 3), np.uint8), np.zeros((1, 2), np.int64),
                                      np.ones((1, 1, 1), np.uint8), np.zeros((1, N_CODES, 3), f32),
                                      np.zeros((1, 3, 3), f32), np.zeros((1, 3, 3)), np.zeros((N_CODES, 3), f32),
                                      np.zeros((1, N_CODES, 3), f32), np.ones(1, f32), True, 0, 0,
                                      np.zeros(N_CODES, bool), 0, 1, np.zeros((3, 1, 1), f32),
                                      np.zeros((1, 1), np.uint8))
        except Exception:  # noqa: BLE001
            pass

    th = threading.Thread(target=run, name="derender-warm-up", daemon=True)
    th.start()
    return th


def _merge_stabilized_frames(stab, frames: np.ndarray, shifts: np.ndarray, valid: np.ndarray | None,
                             weight: Any, noise_weighting: bool, threads: int | None,
                             buffer: np.ndarray | None = None) -> HDRResult | None:
    """The stabilised merge of ``frames`` (N, H, W, 3) uint8, image ``j`` read shifted by
    ``shifts[j]`` (dy, dx) (outside the frame it does not take part) and restricted to
    ``valid`` (N, H, W) uint8 (None: everywhere), by :func:`derender.kernels.stabilized_merge_rows`.
    ``buffer``: uint8 memory of at least :func:`stabilized_output_bytes` to hold the radiance
    and mask (the kernel writes every pixel of both, so it need not be zero)."""
    tables = _stabilized_tables(stab, weight, noise_weighting)
    if tables is None:
        return None
    from .kernels import stabilized_merge_rows

    values, mats, ivs = tables
    al = stab.alignment
    times = np.asarray(stab.times, dtype=np.float64)
    n = times.shape[0]
    h, w = int(frames.shape[1]), int(frames.shape[2])
    wt = np.ascontiguousarray(weight_table(weight), dtype=np.float32)
    lin = np.ascontiguousarray(np.stack(values), dtype=np.float32)
    mats64 = np.ascontiguousarray(np.stack(mats), dtype=np.float64)
    use_iv = bool(noise_weighting)
    if use_iv:
        inv_var = np.ascontiguousarray(np.stack([iv[0] / np.float32(3.0) for iv in ivs]), dtype=np.float32)
        inv_k = np.array([iv[1] for iv in ivs], dtype=np.float32)
    else:
        inv_var = np.zeros((n, N_CODES, 3), dtype=np.float32)
        inv_k = np.ones(n, dtype=np.float32)
    bright = code_values() >= np.float32(0.5)
    if valid is None:
        valid = np.ones((n, 1, 1), dtype=np.uint8)
    if buffer is not None and buffer.nbytes >= stabilized_output_bytes(h, w):
        flat = buffer.reshape(-1)
        radiance = flat[:12 * h * w].view(np.float32).reshape(3, h, w)
        mask = flat[12 * h * w:13 * h * w].reshape(h, w)
    else:
        radiance = populated_zeros((3, h, w), dtype=np.float32)      # planar, like TableMerge's result
        mask = populated_zeros((h, w), dtype=np.uint8)
    t0 = time.perf_counter()
    with _KERNEL_LOCK:
        _set_numba_threads(threads)
        stabilized_merge_rows(np.ascontiguousarray(frames), np.ascontiguousarray(shifts, dtype=np.int64),
                              np.ascontiguousarray(valid, dtype=np.uint8), lin, mats64.astype(np.float32),
                              mats64, wt, inv_var, inv_k, use_iv, int(np.argmin(times)), int(np.argmax(times)),
                              bright, 0, h, radiance, mask)
    info = {"channel_weights": "min_else_brightest", "domain": "linear", "engine": "table",
            "accumulator": "float32", "n_bright": int(np.count_nonzero(mask == HDRResult.MASK_BRIGHT)),
            "n_dark": int(np.count_nonzero(mask == HDRResult.MASK_DARK)),
            "weight": weight if isinstance(weight, str) else "custom",
            "merge_seconds": time.perf_counter() - t0, "noise_weighting": bool(noise_weighting),
            "reference": stab.reference, "gammas": np.asarray(stab.gammas.gammas).tolist(),
            "gamma_method": getattr(stab.gammas, "method", None),
            "matrices": np.asarray(stab.matrices).tolist(), "mode": stab.mode, "how": stab.how,
            "align": getattr(al, "method", None)}
    if getattr(al, "shifts", None) is not None:
        info["shifts"] = np.asarray(al.shifts).tolist()
    return HDRResult(radiance=radiance.transpose(1, 2, 0), mask=mask, variance=None, info=info)


# --------------------------------------------------------------------------- files
_JPEG_SUFFIXES = {".jpg", ".jpeg", ".jpe", ".jfif"}


def read_codes(path: str | os.PathLike, out: np.ndarray | None = None) -> np.ndarray | None:
    """8-bit RGB codes (H, W, 3) uint8 of a JPEG/PNG/TIFF file, or None if the file is 16-bit.

    Same conventions as :func:`derender.io.read_image` (EXIF orientation ignored, grey
    replicated, opaque alpha dropped); JPEGs are decoded with libjpeg-turbo through
    ``imagecodecs`` when available (the same decoder OpenCV bundles; ~1.6x faster here),
    into ``out`` when it has the right shape (reusing memory avoids page faults).
    """
    from .io import read_bytes

    path = Path(path)
    data = read_bytes(path)
    img = None
    if path.suffix.lower() in _JPEG_SUFFIXES or (data.size > 2 and data[0] == 0xFF and data[1] == 0xD8):
        try:
            import imagecodecs

            img = None
            if out is not None:
                try:
                    img = imagecodecs.jpeg8_decode(data, out=out)
                except Exception:  # noqa: BLE001 - wrong shape for this file: decode afresh
                    img = None
            if img is None:
                img = imagecodecs.jpeg8_decode(data)
            if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
                img = None
        except Exception:  # noqa: BLE001 - any failure: let OpenCV decide (and report)
            img = None
        if img is not None:
            if img.ndim == 2:
                img = np.repeat(img[:, :, None], 3, axis=2)
            return np.ascontiguousarray(img)
    cv2 = _cv2()
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise InputError(f"not a readable image (corrupt or unsupported format): {path}")
    if img.dtype == np.uint16:
        return None
    if img.dtype != np.uint8:
        raise InputError(f"unsupported sample type {img.dtype} in {path}: use 8- or 16-bit images")
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.shape[2] == 4:
        if np.any(img[:, :, 3] != 255):
            raise InputError(f"{path} has a transparent alpha channel; flatten it first")
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise InputError(f"{path} has {img.shape[2]} channels; expected grey, RGB or RGBA")


def file_times(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
               times_file: str | os.PathLike | None = None, times_file_inverse: bool = False) -> np.ndarray:
    """Exposure times of image files without decoding them (see :func:`derender.io.file_times`)."""
    from .io import file_times as _file_times

    return _file_times(paths, times, times_file, times_file_inverse)


def _prefetch(fn: Callable[[Any], Any], items: Sequence[Any], depth: int = 1, workers: int = 1) -> Iterator[Any]:
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


class _FramePool:
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


class _NotStreamable(Exception):
    """The input or method needs the in-memory reference path."""


def _hist_samples(hists: np.ndarray, n_samples: int) -> np.ndarray:
    """Grossberg & Nayar histogram samples from per-image histograms (N, 3, 256): as ``sample_pixels(method="histogram")``."""
    n_img = hists.shape[0]
    u = np.linspace(0.0, 1.0, int(n_samples))
    out = np.empty((n_img, u.size, 3), dtype=np.int32)
    for j in range(n_img):
        for c in range(3):
            cdf = np.cumsum(hists[j, c]).astype(np.float64)
            cdf /= cdf[-1]
            out[j, :, c] = np.argmin(np.abs(cdf[None, :] - u[:, None]), axis=1)
    return out


def _histograms(codes: np.ndarray) -> np.ndarray:
    cv2 = _cv2()
    return np.stack([cv2.calcHist([codes], [c], None, [N_CODES], [0, N_CODES]).ravel().astype(np.int64)
                     for c in range(3)])


def _check_usable_hists(hists: np.ndarray) -> None:
    """:func:`derender.response.check_usable` from per-image histograms (N, 3, 256)."""
    from .response import raise_unusable

    raise_unusable(hists[:, :, 1:N_CODES - 1].sum(axis=(0, 2)) > 0)


def _calibrate_from_samples(samples: np.ndarray, times: np.ndarray, hists_fn: Callable[[], np.ndarray],
                            lam: float, n_samples: int, sampling: str, seed: int):
    """:func:`derender.response.calibrate_debevec` (hat weights, monotonic) from pre-drawn samples."""
    from .response import ResponseCurves, _monotonic, solve_debevec

    if lam < 0 or not np.isfinite(lam):
        raise InputError(f"lambda must be a non-negative number, got {lam}")
    log_t = np.log(times)
    g = np.empty((N_CODES, 3))
    fixed = []
    for c in range(3):
        zc = samples[:, :, c]
        if not np.any((zc > 0) & (zc < N_CODES - 1)):
            extra = _hist_samples(hists_fn(), n_samples)[:, :, c]
            zc = np.concatenate([zc, extra], axis=1)
        g[:, c], _ = solve_debevec(zc, log_t, lam=lam, weights="hat", n_levels=N_CODES)
        fixed.append(bool(np.any(np.diff(g[:, c]) < 0)))
    g = _monotonic(g)
    params = {"lambda": float(lam), "n_samples": int(n_samples), "sampling": sampling, "seed": int(seed),
              "weights": "hat", "monotonic_fixed": fixed}
    return ResponseCurves(log_inverse=g, method="debevec", params=params)


#: Methods :func:`merge_files_fast` streams (others are read into memory and merged by :func:`derender.merge.merge`).
STREAMING_METHODS = ("debevec", "stabilized", "stabilized-joint", "probabilistic")


def _method_options(method: str, options: dict) -> dict:
    """Options of merge ``method`` with its defaults filled in; unknown options are a user error."""
    from .merge import MERGE_METHODS, merge_debevec

    fn = merge_debevec if method == "debevec" else MERGE_METHODS[method]
    params = inspect.signature(fn).parameters
    bad = [k for k in options if k not in params or k == "stack"]
    if bad:
        accepted = ", ".join(p for p in params if p != "stack")
        raise InputError(f"merge method {method!r} does not accept option(s) {', '.join(bad)}; accepted: {accepted}")
    out = {k: p.default for k, p in params.items() if k != "stack"}
    out.update(options)
    return out


def _debevec_options(options: dict) -> dict:
    return _method_options("debevec", options)


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
        from .align import _shift_into

        dy, dx = self.shifts[j]
        if dy == 0 and dx == 0:
            return self.frames[j]
        out = np.empty_like(self.frames[j]) if out is None else out
        _shift_into(out, self.frames[j], int(dy), int(dx))
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


def _read_frames(paths: list[Path], threads: int | None, grey: bool = False,
                 grey_alloc: Callable[[int, int, int], np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode 8-bit frames (in threads) into one (N, H, W, 3) uint8 array (pages populated
    up front, :func:`populated_zeros`) and, with ``grey``, their Ward greys (N, H, W)
    (:func:`derender.align.grey8_codes`, made in the decoding threads). The first frame
    gives the size; the others are decoded straight into their slot. ``grey_alloc(H, W,
    nbytes)``, if given, returns the uint8 memory (at least ``nbytes``) the greys go to, so
    that a later stage can reuse it."""
    from .align import grey8_codes

    nthreads = _n_threads(threads)
    first = read_codes(paths[0])
    if first is None:
        raise _NotStreamable("16-bit input")
    if len(paths) < 2:
        raise StackError("an exposure stack needs at least two images")
    frames = populated_zeros((len(paths), *first.shape), dtype=np.uint8)
    frames[0] = first
    del first
    greys = None
    if grey:
        n_grey = int(np.prod(frames.shape[:3]))
        mem = populated_zeros(n_grey, np.uint8) if grey_alloc is None else grey_alloc(*frames.shape[1:3], n_grey)
        greys = mem.reshape(-1)[:n_grey].reshape(frames.shape[:3])

    def load(j: int):
        codes = read_codes(paths[j], out=frames[j]) if j else frames[0]
        if codes is None:
            return False
        if codes.shape != frames.shape[1:]:
            raise InputError(f"images differ in size: {paths[0].name} is {frames.shape[2]}x{frames.shape[1]}, "
                             f"{paths[j].name} is {codes.shape[1]}x{codes.shape[0]}")
        if not np.shares_memory(codes, frames[j]):
            frames[j] = codes
        if greys is not None:
            grey8_codes(frames[j], out=greys[j])
        return True

    for ok in _prefetch(load, range(len(paths)), depth=nthreads, workers=nthreads):
        if not ok:
            raise _NotStreamable("16-bit input")
    return frames, greys


def _stream_probabilistic(paths: list[Path], t: np.ndarray, opts: dict, threads: int | None) -> HDRResult:
    """:func:`derender.probabilistic.merge_probabilistic` on 8-bit files, band by band (same numbers)."""
    from .probabilistic import _check_options, _load, merge_probabilistic_frames

    model = _load(opts.get("model"))
    space, _ = _check_options(model, opts["target_time"], opts["colour_space"], opts["censor"], opts["space"],
                              opts["floor"], opts["clip_code"], opts["code_noise"])
    if space != "log":
        raise _NotStreamable("raw-space product")
    t0 = time.perf_counter()
    frames, _ = _read_frames(paths, threads)
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
    pass reads all frames through their shifts (:func:`_merge_stabilized_frames`).
    """
    from .align import chain_transforms, transforms_to_shifts
    from .response import DEFAULT_LAMBDA, DEFAULT_SAMPLES, _grid_positions
    from .stabilize import select_reference, stabilize_aligned, unclipped_debevec

    align = opts["align"]
    if align not in ("mtb", "none"):
        raise _NotStreamable(f"align={align!r} warps frames")
    n = len(paths)
    t0 = time.perf_counter()
    _warm_up_stabilized()
    # the greys' memory is reused for the merge's outputs once registration is done: fresh
    # memory costs 0.5-3 ms/MB here (page population), 216 MB of it per 24 MP bracket
    held: dict = {}

    def grey_alloc(h: int, w: int, nbytes: int) -> np.ndarray:
        held["buffer"] = populated_zeros(max(nbytes, stabilized_output_bytes(h, w)), np.uint8)
        return held["buffer"]

    frames, greys = _read_frames(paths, threads, grey=align == "mtb", grey_alloc=grey_alloc)
    out_buffer = held.pop("buffer", None)
    h, w = frames[0].shape[:2]
    # response.check_usable: grid samples settle it, unless some channel shows no usable code there
    ys, xs = _grid_positions(h, w, DEFAULT_SAMPLES, int(opts["seed"]))
    probe = np.stack([f[ys, xs] for f in frames])
    if not np.all(((probe > 0) & (probe < N_CODES - 1)).any(axis=(0, 1))):
        _check_usable_hists(np.stack([_histograms(f) for f in frames]))
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
        ys, xs = _grid_positions(h, w, DEFAULT_SAMPLES, seed)
        samples = np.stack([view.code_pixels(j, ys, xs) for j in range(n)]).astype(np.int32)

        def aligned_hists() -> np.ndarray:
            return np.stack([_histograms(np.ascontiguousarray(view.codes(j))) for j in range(n)])

        return _calibrate_from_samples(samples, t, aligned_hists, DEFAULT_LAMBDA, DEFAULT_SAMPLES, "grid", seed)

    mode = "joint" if method == "stabilized-joint" else "reference"
    stab = stabilize_aligned(al, t, mode=mode, response=opts["response"], gammas=opts["gammas"],
                             use_times=opts["use_times"], path=opts.get("path", "auto"), block=opts["block"],
                             max_blocks=opts["max_blocks"], ransac_iter=opts["ransac_iter"], seed=seed,
                             calibrate=calibrate)
    t3 = time.perf_counter()
    res = _merge_stabilized_frames(stab, frames, np.asarray(shifts, dtype=np.int64), None, opts["weight"],
                                   opts["noise_weighting"], threads, buffer=out_buffer)
    del out_buffer
    if res is None:
        raise _NotStreamable("no table form for these curves")
    t4 = time.perf_counter()
    from .stabilize import _stab_info

    res.info.update(_stab_info(stab))
    res.info.update({"method": method,
                     "timings": {"decode_s": t1 - t0, "align_s": t2 - t1, **stab.info["timings"],
                                 "merge_s": t4 - t3},
                     "streaming": {"frames_kept": n, "decodes": n}})
    return res


def merge_files_fast(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
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
    if not _method_registered(method):
        from .merge import MERGE_METHODS

        raise InputError(f"unknown merge method {method!r}; known: {', '.join(sorted(MERGE_METHODS))}")
    paths = [Path(p) for p in paths]
    t = file_times(paths, times, times_file, times_file_inverse)
    order = np.argsort(t, kind="stable")
    paths = [paths[i] for i in order]
    t = t[order]
    all_inputs = list(paths) + list(inputs) + ([Path(times_file)] if times_file else [])
    if output is not None:
        from .io import check_not_input

        if Path(output).suffix.lower() != ".exr":
            raise InputError(f"output must end in .exr, got {Path(output).name}")
        check_not_input(output, all_inputs)
    res = None
    if method in STREAMING_METHODS:
        opts = _method_options(method, options)
        try:
            if opts.get("engine", "auto") == "reference":
                raise _NotStreamable("reference engine requested")
            if method == "debevec":
                res = _stream_debevec(paths, t, opts, threads=threads, keep_frames=keep_frames,
                                      keep_bytes=keep_bytes)
            elif method == "probabilistic":
                res = _stream_probabilistic(paths, t, opts, threads=threads)
            else:
                res = _stream_stabilized(paths, t, method, opts, threads=threads)
        except _NotStreamable:
            res = None
    if res is None:
        from .benchmark import merge_seeded
        from .io import read_stack

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
    from .response import DEFAULT_LAMBDA, DEFAULT_SAMPLES, _grid_positions

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
    nthreads = _n_threads(threads)
    pool = _FramePool()
    for j, codes in enumerate(_prefetch(lambda p: read_codes(p, out=pool.get()), paths, depth=nthreads,
                                        workers=nthreads)):
        if codes is None:
            raise _NotStreamable("16-bit input")
        if shape is None:
            shape = pool.shape = codes.shape
            h, w = shape[:2]
            if keep is None:
                keep = int(keep_bytes // max(codes.nbytes, 1))
            keep = int(min(max(keep, 1), n))
            if sampling == "grid":
                ys, xs = _grid_positions(h, w, n_samples, seed)
                samples = np.empty((n, ys.size, 3), dtype=np.int32)
        elif codes.shape != shape:
            raise InputError(f"images differ in size: {paths[0].name} is {shape[1]}x{shape[0]}, "
                             f"{paths[j].name} is {codes.shape[1]}x{codes.shape[0]}")
        if sampling == "grid":
            samples[j] = codes[ys, xs]
        else:
            hists[j] = _histograms(codes)
        if j >= n - keep:
            kept[j] = codes
        else:
            pool.put(codes)
        del codes
    t1 = time.perf_counter()

    def get_hists() -> np.ndarray:
        nonlocal hists
        if hists is None:  # rare: a channel without usable grid samples
            hists = np.stack([_histograms(kept[j] if j in kept else read_codes(paths[j])) for j in range(n)])
        return hists

    if sampling == "histogram":
        samples = _hist_samples(hists, n_samples)
    # response.check_usable on the whole stack; the samples settle it unless a channel has no usable sample
    if not np.all(((samples > 0) & (samples < N_CODES - 1)).any(axis=(0, 1))):
        _check_usable_hists(get_hists())
    curves = opts["curves"]
    if curves is None:
        curves = _calibrate_from_samples(samples, t, get_hists, lam, n_samples, sampling, seed)
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
        for j, codes in zip(order, _prefetch(load, order)):
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


# --------------------------------------------------------------------------- EXR
_EXR_COMPRESSION = {"none": (0, 1), "zip": (3, 16)}


def _exr_attr(name: str, typ: str, data: bytes) -> bytes:
    return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(data)) + data


def _exr_header(w: int, h: int, channels: Sequence[str], pixel_type: int, compression: int) -> bytes:
    ch = b"".join(c.encode() + b"\0" + struct.pack("<iB3xii", pixel_type, 0, 1, 1) for c in channels) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    attrs = [
        _exr_attr("channels", "chlist", ch),
        _exr_attr("compression", "compression", struct.pack("<B", compression)),
        _exr_attr("dataWindow", "box2i", box),
        _exr_attr("displayWindow", "box2i", box),
        _exr_attr("lineOrder", "lineOrder", struct.pack("<B", 0)),
        _exr_attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        _exr_attr("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
        _exr_attr("screenWindowWidth", "float", struct.pack("<f", 1.0)),
    ]
    return struct.pack("<ii", 20000630, 2) + b"".join(attrs) + b"\0"


def _deflate(level: int) -> Callable[[bytes], bytes]:
    try:
        import imagecodecs

        imagecodecs.deflate_encode(b"x", level=level)
        return lambda b: imagecodecs.deflate_encode(b, level=level)  # libdeflate, zlib format
    except Exception:  # noqa: BLE001
        return lambda b: zlib.compress(b, level)


def _zip_chunk(raw: np.ndarray, deflate: Callable[[bytes], bytes]) -> bytes:
    """OpenEXR ZIP: split even/odd bytes, delta predictor (+128), zlib; raw when not smaller."""
    n = raw.size
    half = (n + 1) // 2
    tmp = np.empty(n, dtype=np.uint8)
    tmp[:half] = raw[0::2]
    tmp[half:] = raw[1::2]
    d = np.empty_like(tmp)
    d[0] = tmp[0]
    np.subtract(tmp[1:], tmp[:-1], out=d[1:])
    d[1:] += np.uint8(128)
    comp = deflate(d.tobytes())
    return comp if len(comp) < n else raw.tobytes()


def write_exr_fast(path: str | os.PathLike, image: np.ndarray, half: bool = False,
                   inputs: Iterable[str | os.PathLike] = (), compression: str = "zip", level: int = 1,
                   threads: int | None = None, probe: int = 16, min_saving: float = 0.1) -> Path:
    """Write an (H, W, 3) RGB float image as a scanline OpenEXR file (ZIP), atomically.

    Blocks of 16 lines are converted and compressed as OpenEXR's ZIP_COMPRESSION
    (even/odd byte split, delta predictor, zlib stream by libdeflate at ``level``) in a
    thread pool and written in order, so the image is never copied whole; planar views
    (``(3, H, W)`` memory transposed) are read without gathering. A ZIP file may store a
    block uncompressed (readers recognise it by its size), which this writer does when
    compression does not pay: in each group of ``probe`` blocks the first is compressed
    and the others only if it saved at least ``min_saving`` (float32 camera radiance
    hardly compresses: ~5 %; ``probe=1`` compresses every block). Deterministic bytes.
    ``compression="none"`` writes uncompressed lines. Non-finite values are refused
    (like :func:`derender.io.write_exr`); with ``half=True`` values beyond the half-float
    range are clipped to +-65504 instead of becoming inf. See :func:`write_exr_lines`
    for images produced block by block.
    """
    arr = image
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"cannot write image of shape {arr.shape} to EXR")

    def bgr_lines(y0: int, y1: int, buf: np.ndarray) -> None:
        for k, c in enumerate((2, 1, 0)):  # channels in alphabetical order: B, G, R
            buf[:, k, :] = arr[y0:y1, :, c]

    return write_exr_lines(path, arr.shape[1], arr.shape[0], bgr_lines, half=half, inputs=inputs,
                           compression=compression, level=level, threads=threads, probe=probe,
                           min_saving=min_saving)


def write_exr_lines(path: str | os.PathLike, width: int, height: int,
                    lines: Callable[[int, int, np.ndarray], None], half: bool = False,
                    inputs: Iterable[str | os.PathLike] = (), compression: str = "zip", level: int = 1,
                    threads: int | None = None, probe: int = 16, min_saving: float = 0.1) -> Path:
    """:func:`write_exr_fast` for an image that exists only block by block.

    ``lines(y0, y1, buf)`` fills ``buf`` (float32, shape ``(y1 - y0, 3, width)``) with rows
    ``y0:y1`` in planar B, G, R order (the alphabetical channel order of the file). It is
    called from a thread pool on blocks of at most 16 rows, so it must be thread-safe and
    should release the GIL (NumPy gathers and arithmetic do). Non-finite values are
    refused; the other options are :func:`write_exr_fast`'s.
    """
    import cv2

    from .io import atomic_output

    w, h = int(width), int(height)
    if w < 1 or h < 1:
        raise InputError(f"cannot write an empty {w}x{h} image to EXR")
    if compression not in _EXR_COMPRESSION:
        raise InputError(f"compression must be one of {', '.join(_EXR_COMPRESSION)}, got {compression!r}")
    comp_id = _EXR_COMPRESSION[compression][0]
    dtype = np.dtype("<f2") if half else np.dtype("<f4")
    deflate = _deflate(level)
    n_blocks = (h + 15) // 16 if comp_id == 3 else h
    header = _exr_header(w, h, "BGR", 1 if half else 2, comp_id)
    probe = max(1, int(probe))

    def raw_lines(y0: int, y1: int) -> np.ndarray:
        buf = np.empty((y1 - y0, 3, w), dtype=np.float32)
        lines(y0, y1, buf)
        if not cv2.checkRange(buf.reshape(-1, w))[0]:
            raise ValueError("refusing to write NaN/inf to EXR (internal error)")
        if half:
            return np.clip(buf, -65504.0, 65504.0).astype(dtype)
        return buf

    def group(g: int) -> list[bytes]:
        """Blocks of group ``g`` (``probe`` ZIP blocks, or 16 uncompressed lines) as chunk bytes."""
        out = []
        if comp_id == 0:
            y0, y1 = g * 16, min(h, g * 16 + 16)
            buf = raw_lines(y0, y1)
            for y in range(y0, y1):
                data = buf[y - y0].tobytes()
                out.append(struct.pack("<ii", y, len(data)) + data)
            return out
        squeeze = True
        for b in range(g * probe, min(n_blocks, (g + 1) * probe)):
            y0, y1 = b * 16, min(h, b * 16 + 16)
            raw = raw_lines(y0, y1).reshape(-1).view(np.uint8)
            if squeeze:
                data = _zip_chunk(raw, deflate)
                if b == g * probe and len(data) > (1.0 - min_saving) * raw.size:
                    squeeze = False
            else:
                data = raw.tobytes()
            out.append(struct.pack("<ii", y0, len(data)) + data)
        return out

    n_groups = (h + 15) // 16 if comp_id == 0 else (n_blocks + probe - 1) // probe
    nthreads = _n_threads(threads)
    path = Path(path)
    with atomic_output(path, inputs) as tmp, open(tmp, "wb") as fh:
        fh.write(header)
        table_pos = fh.tell()
        fh.write(b"\0" * (8 * n_blocks))
        offsets = np.empty(n_blocks, dtype="<u8")
        i = 0
        with ThreadPoolExecutor(nthreads, thread_name_prefix="derender-exr") as ex:
            futs: deque = deque()
            nxt = 0
            for _ in range(n_groups):
                while nxt < n_groups and len(futs) < 2 * nthreads:
                    futs.append(ex.submit(group, nxt))
                    nxt += 1
                for data in futs.popleft().result():
                    offsets[i] = fh.tell()
                    fh.write(data)
                    i += 1
        fh.seek(table_pos)
        fh.write(offsets.tobytes())
    return path


# --------------------------------------------------------------------------- benchmark
def generate_bench_bracket(workdir: str | os.PathLike, size: tuple[int, int] = (6000, 4000), frames: int = 9,
                           seed: int = 0, sim_width: int = 768, grain: int = 2, quality: int = 95,
                           camera: str = "nikon-d5100") -> list[Path]:
    """JPEG bracket of ``size`` (W, H): simulator frames (:func:`derender.camera.simulate_bracket`,
    ``sim_width`` wide) upscaled with bicubic interpolation, plus uniform grain of
    +-``grain`` codes (deterministic) so the files compress like photographs, written
    with EXIF times by :func:`derender.camera.write_jpeg`. Cached in
    ``workdir/bracket-WxH-N-sSEED`` (reused when complete).
    """
    import cv2

    from .camera import simulate_bracket, write_jpeg

    w, h = int(size[0]), int(size[1])
    if w < 16 or h < 16 or frames < 2:
        raise InputError("bench bracket needs at least 16x16 pixels and 2 frames")
    folder = Path(workdir) / f"bracket-{w}x{h}-{frames}-s{seed}"
    done = folder / "bracket.json"
    if done.is_file():
        meta = json.loads(done.read_text())
        paths = [folder / name for name in meta["files"]]
        if all(p.is_file() for p in paths):
            return paths
    folder.mkdir(parents=True, exist_ok=True)
    sw = min(sim_width, w)
    sh = max(16, int(round(sw * h / w)))
    bracket = simulate_bracket(camera=camera, size=(sw, sh), exposures=frames, seed=seed)
    rng = np.random.default_rng(seed + 12345)
    noise = rng.integers(-grain, grain + 1, size=(h, w, 3), dtype=np.int16) if grain > 0 else None
    paths = []
    for j, t in enumerate(bracket.times):
        big = cv2.resize(bracket.jpeg_codes[j], (w, h), interpolation=cv2.INTER_CUBIC)
        if noise is not None:
            big = np.clip(big.astype(np.int16) + np.roll(noise, 7 * j, axis=0), 0, 255).astype(np.uint8)
        paths.append(write_jpeg(folder / f"{j:02d}.jpg", big, float(t), bracket.camera.make, bracket.camera.model,
                                quality=quality))
        del big
    done.write_text(json.dumps({"size": [w, h], "frames": frames, "seed": seed, "grain": grain,
                                "times": [float(x) for x in bracket.times], "files": [p.name for p in paths]}))
    return paths


_OPENCV_WORKER = r"""
import json, sys, time
t0 = time.perf_counter()
import cv2, numpy as np
from derender.io import read_exposure_time
paths = sys.argv[1:]
times = np.array([read_exposure_time(p) for p in paths], dtype=np.float32)
t1 = time.perf_counter()
imgs = [cv2.imread(p) for p in paths]
t2 = time.perf_counter()
resp = cv2.createCalibrateDebevec().process(imgs, times)
t3 = time.perf_counter()
hdr = cv2.createMergeDebevec().process(imgs, times, resp)
t4 = time.perf_counter()
print(json.dumps({"inner_s": t4 - t1, "decode_s": t2 - t1, "calibrate_s": t3 - t2, "merge_s": t4 - t3,
                  "threads": cv2.getNumThreads(), "finite": bool(np.isfinite(hdr).all())}))
"""

_COLOUR_HDRI_WORKER = r"""
import json, sys, time
try:
    import colour_hdri
except ImportError as exc:
    print(json.dumps({"status": "skipped", "reason": f"colour_hdri not importable ({exc})"}))
    sys.exit(0)
t1 = time.perf_counter()
try:
    from colour_hdri import (ImageStack, camera_response_functions_Debevec1997, image_stack_to_HDRI,
                             weighting_function_Debevec1997)
    stack = ImageStack.from_files(sys.argv[1:])
    crfs = camera_response_functions_Debevec1997(stack)
    hdri = image_stack_to_HDRI(stack, weighting_function_Debevec1997, crfs)
except Exception as exc:
    print(json.dumps({"status": "error", "reason": f"{type(exc).__name__}: {exc}"}))
    sys.exit(0)
print(json.dumps({"inner_s": time.perf_counter() - t1}))
"""


def _run_measured(cmd: list[str], cwd: str | os.PathLike | None = None) -> dict:
    """Run ``cmd``; wall time, exit code, stdout/stderr tails and the child's peak RSS (``wait4``)."""
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=fo, stderr=fe, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out = fo.read().decode("utf-8", "replace")
        err = fe.read().decode("utf-8", "replace")
    return {"returncode": proc.returncode, "wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0,
            "cpu_s": usage.ru_utime + usage.ru_stime, "stdout": out[-2000:], "stderr": err[-2000:]}


def _last_json(text: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return {}


def _bench_one(name: str, paths: list[Path], outdir: Path, python: str) -> dict:
    files = [str(p) for p in paths]
    if name == "opencv":
        cmd = [python, "-c", _OPENCV_WORKER, *files]
    elif name == "colour-hdri":
        cmd = [python, "-c", _COLOUR_HDRI_WORKER, *files]
    elif name.startswith("derender-"):
        method = name[len("derender-"):]
        cmd = [python, "-m", "derender.cli", "merge", *files, "-o", str(outdir / f"{name}-{len(paths)}.exr"),
               "--method", method]
    else:
        raise InputError(f"unknown benchmark entry {name!r}")
    run = _run_measured(cmd)
    detail = _last_json(run["stdout"])
    status = detail.pop("status", "ok" if run["returncode"] == 0 else "error")
    row = {"status": status, "command": " ".join([Path(cmd[0]).name, *cmd[1:2]] if cmd[1] == "-c" else
                                                  [Path(cmd[0]).name, *cmd[1:5], "...", *cmd[-4:]]),
           "wall_s": run["wall_s"], "peak_rss_mb": run["peak_rss_mb"], "cpu_s": run["cpu_s"], **detail}
    if name.startswith("derender-") and run["returncode"] == 0:
        import re

        m = re.search(r"\(([0-9.]+) s;", run["stdout"])
        if m:
            row["inner_s"] = float(m.group(1))
    if status == "error":
        row["reason"] = (detail.get("reason") or run["stderr"].strip().splitlines()[-1:] or ["?"])
    return row


def _method_registered(method: str) -> bool:
    from .merge import MERGE_METHODS, _load_plugins

    if method in MERGE_METHODS:  # built-in methods need no plugin imports (they cost ~1 s of start-up)
        return True
    try:
        _load_plugins()
    except Exception:  # noqa: BLE001 - a broken plugin should not stop the benchmark
        pass
    return method in MERGE_METHODS


def run_bench(size: tuple[int, int] = (6000, 4000), frames: int = 9, workdir: str | os.PathLike | None = None,
              entries: Sequence[str] | None = None, memory_frames: int | None = None, seed: int = 0,
              repeat: int = 1, python: str | None = None, progress: Callable[[str], None] | None = None) -> dict:
    """Side-by-side benchmark on a generated bracket (:func:`generate_bench_bracket`), each run in a fresh process.

    ``entries`` (default all): ``"opencv"`` (cv2.imread x N + CalibrateDebevec +
    MergeDebevec, no file written), ``"colour-hdri"`` (``image_stack_to_HDRI``; skipped
    when not importable), ``"derender-debevec"`` and ``"derender-stabilized"`` (the
    ``derender merge`` command: decode, calibrate, merge and EXR write; stabilized only
    when the method is registered). With ``memory_frames`` (e.g. 18) ``derender merge
    --method debevec`` also runs on a bracket of that many frames, to compare peak RSS.
    Wall time is the whole process (interpreter start included); ``inner_s`` the
    tool's own timing; peak RSS from ``wait4``. ``repeat`` > 1 keeps the fastest run.
    Returns a dict (see :func:`format_bench`).
    """
    python = python or sys.executable
    workdir = Path(workdir) if workdir is not None else Path(tempfile.gettempdir()) / "derender-bench"
    workdir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda msg: None)
    if entries is None:
        entries = ["opencv", "colour-hdri", "derender-debevec", "derender-stabilized"]
    say(f"generating {frames} frames {size[0]}x{size[1]} in {workdir} (cached)")
    paths = generate_bench_bracket(workdir, size, frames, seed)
    outdir = workdir / "outputs"
    outdir.mkdir(exist_ok=True)
    runs: dict[str, dict] = {}
    for name in entries:
        if name == "derender-stabilized" and not _method_registered("stabilized"):
            runs[name] = {"status": "skipped", "reason": "method 'stabilized' is not registered"}
            continue
        best = None
        for _ in range(max(1, int(repeat))):
            say(f"running {name}")
            row = _bench_one(name, paths, outdir, python)
            if row["status"] != "ok":
                best = row
                break
            if best is None or row["wall_s"] < best["wall_s"]:
                best = row
        runs[name] = best
    result: dict[str, Any] = {
        "size": [int(size[0]), int(size[1])], "frames": int(frames), "workdir": str(workdir),
        "input_mb": sum(p.stat().st_size for p in paths) / 1e6,
        "cpus": _n_threads(None), "load_avg": list(os.getloadavg()), "runs": runs, "ratios": {},
    }
    ok = {k: v for k, v in runs.items() if v.get("status") == "ok"}
    if "opencv" in ok:
        for k, v in ok.items():
            if k != "opencv":
                result["ratios"][f"{k} / opencv"] = v["wall_s"] / ok["opencv"]["wall_s"]
    if "derender-stabilized" in ok and "derender-debevec" in ok:
        result["ratios"]["derender-stabilized / derender-debevec"] = (ok["derender-stabilized"]["wall_s"]
                                                                      / ok["derender-debevec"]["wall_s"])
    if memory_frames:
        say(f"generating {memory_frames} frames for the memory comparison")
        big = generate_bench_bracket(workdir, size, int(memory_frames), seed)
        say(f"running derender-debevec on {memory_frames} frames")
        row = _bench_one("derender-debevec", big, outdir, python)
        base = runs.get("derender-debevec") or _bench_one("derender-debevec", paths, outdir, python)
        result["memory"] = {"frames": [int(frames), int(memory_frames)],
                            "peak_rss_mb": [base.get("peak_rss_mb"), row.get("peak_rss_mb")],
                            "wall_s": [base.get("wall_s"), row.get("wall_s")], "status": row["status"]}
        if row["status"] == "ok" and base.get("status") == "ok":
            result["memory"]["rss_ratio"] = row["peak_rss_mb"] / base["peak_rss_mb"]
    return result


def format_bench(result: dict) -> str:
    """Markdown table of a :func:`run_bench` result."""
    w, h = result["size"]
    lines = [f"{result['frames']} JPEGs {w}x{h} ({w * h / 1e6:.1f} MP, {result['input_mb']:.0f} MB), "
             f"{result['cpus']} CPUs, load average {result['load_avg'][0]:.2f}", "",
             "| tool | status | wall s | inner s | peak RSS MB | CPU s | vs OpenCV |",
             "|---|---|---|---|---|---|---|"]
    ocv = result["runs"].get("opencv", {})
    for name, r in result["runs"].items():
        if r.get("status") != "ok":
            lines.append(f"| {name} | {r.get('status')}: {r.get('reason', '')} | | | | | |")
            continue
        ratio = f"{r['wall_s'] / ocv['wall_s']:.2f}x" if ocv.get("status") == "ok" else ""
        inner = f"{r['inner_s']:.2f}" if "inner_s" in r else ""
        lines.append(f"| {name} | ok | {r['wall_s']:.2f} | {inner} | {r['peak_rss_mb']:.0f} | {r['cpu_s']:.1f} | {ratio} |")
    for k, v in result.get("ratios", {}).items():
        lines.append(f"\n{k}: {v:.2f}")
    mem = result.get("memory")
    if mem:
        a, b = mem["frames"]
        ra, rb = mem["peak_rss_mb"]
        txt = f"\nmemory: derender-debevec peak RSS {a} frames {ra:.0f} MB, {b} frames {rb:.0f} MB"
        if "rss_ratio" in mem:
            txt += f" (ratio {mem['rss_ratio']:.2f})"
        lines.append(txt)
    return "\n".join(lines)
