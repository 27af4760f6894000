"""The matrix kernel of the engine: per-frame tables, a 3x3 matrix per frame, integer shifts.

:func:`merge_matrix_frames` runs :func:`derender.engine.kernels.stabilized_merge_rows`
(numba, rows in ``prange``): image ``j`` contributes ``max(M_j L_j(z), 0)`` (per-channel table
``L_j`` on the 256 codes, 3x3 ``M_j``; the estimate projected onto the non-negative orthant,
so that no radiance is negative) read through its registration shift, with one weight
for all channels (the smallest channel weight where some exposure has all channels
usable, else the weight of the brightest channel) optionally times an inverse-variance
table. Launches are serialised by :data:`KERNEL_LOCK` (numba's fallback thread pool
cannot run two parallel kernels at once).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from derender.core.memory import N_CODES, populated_zeros, thread_count
from derender.core.types import HDRResult
from derender.engine.plans import MatrixPlan
from derender.engine.tables import code_values

__all__ = [
    "merge_matrix_frames",
    "matrix_output_bytes",
    "KERNEL_LOCK",
    "set_numba_threads",
    "warm_up_kernels",
]


def matrix_output_bytes(h: int, w: int) -> int:
    """Bytes of the matrix kernel's outputs: planar float32 radiance and a uint8 mask."""
    return 13 * int(h) * int(w)


#: Serialises launches of the parallel numba kernels (see :mod:`derender.engine.kernels`).
KERNEL_LOCK = threading.Lock()


def set_numba_threads(threads: int | None) -> None:
    """Threads of numba's parallel kernels: ``threads`` (all CPUs when None), at most numba's maximum."""
    import numba

    numba.set_num_threads(max(1, min(thread_count(threads), int(numba.config.NUMBA_NUM_THREADS))))


def warm_up_kernels() -> threading.Thread:
    """Import numba and load the MTB and merge kernels from its cache (0.5-1 s) in a
    background thread while the frames decode: the import holds the GIL, decoding
    (libjpeg-turbo) does not. Failures are left for the real calls to report."""
    def run() -> None:
        try:
            from derender.engine.kernels import mtb_band_counts, stabilized_merge_rows

            mtb_band_counts(np.zeros((1, 1), np.uint8), np.zeros((1, 1), np.uint8), 0, 0, 4, np.zeros(1, np.int64),
                            1, 0, np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((1, 2), np.int64))

            f32 = np.float32
            with KERNEL_LOCK:
                stabilized_merge_rows(np.zeros((1, 1, 1, 3), np.uint8), np.zeros((1, 2), np.int64),
                                      np.ones((1, 1, 1), np.uint8), -1, np.zeros((1, N_CODES, 3), f32),
                                      np.zeros((1, 3, 3), f32), np.zeros((1, 3, 3)), np.zeros((N_CODES, 3), f32),
                                      np.zeros((1, N_CODES, 3), f32), np.ones(1, f32), True,
                                      np.ones(1, f32), False, 0, 0,
                                      np.zeros(N_CODES, bool), 0, 1, 0, np.zeros((3, 1, 1), f32),
                                      np.zeros((1, 1), np.uint8))
        except Exception:  # noqa: BLE001
            pass

    th = threading.Thread(target=run, name="derender-warm-up", daemon=True)
    th.start()
    return th


def merge_matrix_frames(frames: np.ndarray, plan: MatrixPlan, times: np.ndarray, *, valid: np.ndarray | None = None,
                        threads: int | None = None, buffer: np.ndarray | None = None, write=None,
                        ring: int = 0, ref: int = -1) -> HDRResult:
    """Run a :class:`~derender.engine.plans.MatrixPlan` on held frames (N, H, W, 3) uint8.

    Frame ``j`` is read through ``plan.shifts[j]`` and restricted to ``valid`` (N, H, W)
    uint8 (None: everywhere); ``ref`` (the engine's reference frame, -1 none) decides the
    saturation policy where frames are left out. ``times`` (sorted or not) name the shortest and the longest
    exposure for the saturation policy. ``buffer``: uint8 memory of at least
    :func:`matrix_output_bytes` to hold the radiance and mask (the kernel writes every
    pixel of both, so it need not be zero). The radiance is an (H, W, 3) view of planar
    float32 memory; sums are float32 (2e-7 to 4e-7 relative to the float64 reference).
    ``write(result, rows_done)``: written while merging (:func:`derender.engine.overlap.merge_writing`);
    with ``ring`` too the radiance goes through an :class:`~derender.engine.overlap.OutputRing` of
    band buffers into the file and the result's ``radiance`` is None (the mask is kept).
    With ``plan.variance`` (:class:`~derender.engine.variance.VarianceModel`) the kernel is
    :func:`~derender.engine.variance_kernels.stabilized_merge_var_rows`: the same radiance, its
    variance in ``result.variance`` (a second ring buffer with ``ring`` 2) and
    ``info["variance_sources"]``.
    """
    from derender.engine.kernels import stabilized_merge_rows
    from derender.engine.overlap import OVERLAP_ROWS, merge_writing

    times = np.asarray(times, dtype=np.float64)
    n = times.shape[0]
    h, w = int(frames.shape[1]), int(frames.shape[2])
    tables = _matrix_tables(plan, n)
    if valid is None:
        valid = np.ones((n, 1, 1), dtype=np.uint8)
    vm = plan.variance
    var = None
    out_ring, radiance, mask = _matrix_outputs(h, w, 1 if vm is None else 2, buffer, write, ring)
    if vm is not None:
        from derender.engine.variance import SOURCE_STRIDE, VAR_CAP, new_parts
        from derender.engine.variance_kernels import stabilized_merge_var_rows, variance_finish_rows

        edge2 = float(np.float32(vm.edge * vm.edge)) if vm.edge > 0 else 0.0

        parts = new_parts(h, w)
        vargs = (np.ascontiguousarray(vm.noise, dtype=np.float32), np.ascontiguousarray(vm.quant, dtype=np.float32),
                 vm.constants())
        if out_ring is None:
            var = populated_zeros((3, h, w), dtype=np.float32)
    t0 = time.perf_counter()
    info: dict = {}
    res = HDRResult(radiance=None if radiance is None else radiance.transpose(1, 2, 0), mask=mask,
                    variance=None if var is None else var.transpose(1, 2, 0), info=info)
    args = (np.ascontiguousarray(frames), np.ascontiguousarray(plan.shifts, dtype=np.int64),
            np.ascontiguousarray(valid, dtype=np.uint8), int(ref), *tables,
            int(np.argmin(times)), int(np.argmax(times)), code_values() >= np.float32(0.5))

    def band(y0: int, y1: int) -> None:
        if out_ring is not None:
            bufs, row0 = out_ring.slot(y0)
            dst, vdst = bufs[0], bufs[-1]
        else:
            dst, vdst, row0 = radiance, var, 0
        with KERNEL_LOCK:
            set_numba_threads(threads)
            if vm is None:
                stabilized_merge_rows(*args, y0, y1, row0, dst, mask)
            else:
                stabilized_merge_var_rows(*args, y0, y1, row0, dst, mask, *vargs, vdst, parts, SOURCE_STRIDE)
                if edge2 > 0.0:       # the edge term, one compiled pass over the band
                    variance_finish_rows(dst, vdst, parts, edge2, False, y0, y1, row0, SOURCE_STRIDE, VAR_CAP)

    merge_writing(h, OVERLAP_ROWS, band, res, write, ring=out_ring)
    info.update({"channel_weights": "min_else_brightest", "domain": "linear", "engine": "table",
            "accumulator": "float32", "n_bright": int(np.count_nonzero(mask == HDRResult.MASK_BRIGHT)),
            "n_dark": int(np.count_nonzero(mask == HDRResult.MASK_DARK)),
            "merge_seconds": time.perf_counter() - t0})
    if vm is not None:
        from derender.engine.variance import source_shares

        info["variance_sources"] = source_shares(parts)
        info["variance_shared"] = float(vm.shared)
        info["variance_inflate"] = float(vm.inflate)
        if vm.curve_sd is not None:
            info["variance_curve_sd"] = float(vm.curve_sd)
    return res


def _matrix_tables(plan: MatrixPlan, n: int) -> tuple:
    """The kernel's per-frame tables, in its argument order: ``lin`` (float32), the matrices (float32
    and float64), ``wt``, the inverse-variance tables and factors and their flag, the colour weights
    and their flag (zeros, ones and False when the plan has none)."""
    wt = np.ascontiguousarray(plan.weights, dtype=np.float32)
    lin = np.ascontiguousarray(plan.values, dtype=np.float32)
    mats64 = np.ascontiguousarray(plan.matrices, dtype=np.float64)
    use_iv = plan.inverse_variance is not None
    if use_iv:
        inv_var = np.ascontiguousarray(plan.inverse_variance, dtype=np.float32)
        inv_k = np.ascontiguousarray(plan.inverse_variance_k, dtype=np.float32)
    else:
        inv_var = np.zeros((n, N_CODES, 3), dtype=np.float32)
        inv_k = np.ones(n, dtype=np.float32)
    use_cw = plan.colour_weights is not None
    colour_w = (np.ascontiguousarray(plan.colour_weights, dtype=np.float32) if use_cw
                else np.ones(1, dtype=np.float32))
    if use_cw and colour_w.shape != (1 << 24,):
        raise ValueError(f"colour_weights must have 2**24 entries, got {colour_w.shape}")
    return lin, mats64.astype(np.float32), mats64, wt, inv_var, inv_k, use_iv, colour_w, use_cw


def _matrix_outputs(h: int, w: int, nout: int, buffer: np.ndarray | None, write, ring: int) -> tuple:
    """``(out_ring, radiance, mask)``: a ring of ``nout`` planar band buffers (radiance None) when
    writing through one, else planar (3, H, W) float32 radiance; in ``buffer`` when it is big enough."""
    from derender.engine.overlap import OVERLAP_ROWS, OutputRing

    if ring and write is not None:
        out_ring = OutputRing(h, w, OVERLAP_ROWS, lambda: tuple(populated_zeros((3, OVERLAP_ROWS, w), dtype=np.float32)
                                                           for _ in range(nout)), writers=min(int(ring), nout))
        mask = (buffer.reshape(-1)[:h * w].reshape(h, w) if buffer is not None and buffer.nbytes >= h * w
                else populated_zeros((h, w), dtype=np.uint8))
        return out_ring, None, mask
    if buffer is not None and buffer.nbytes >= matrix_output_bytes(h, w):
        flat = buffer.reshape(-1)
        return None, flat[:12 * h * w].view(np.float32).reshape(3, h, w), flat[12 * h * w:13 * h * w].reshape(h, w)
    # planar, like TableMerge's result
    return None, populated_zeros((3, h, w), dtype=np.float32), populated_zeros((h, w), dtype=np.uint8)
