"""The table merge of held frames in one compiled pass per pixel (moved out of :mod:`derender.engine.run`).

:func:`table_kernel_merge` runs a :class:`~derender.engine.plans.TablePlan` (modes ``"mean"`` and
``"independent"``) with :func:`derender.engine.kernels.table_merge_rows` (the numbers of
:class:`~derender.engine.tables.TableMerge`, eq. 6 of Debevec & Malik in the log domain,
Robertson's weighted mean in the linear one), or, when the plan carries a
:class:`~derender.engine.variance.VarianceModel`, with
:func:`derender.engine.variance_kernels.table_merge_var_rows` (same radiance, and its variance).
"""

from __future__ import annotations

import numpy as np

from derender.core.memory import N_CODES, populated_zeros, thread_count
from derender.core.types import HDRResult
from derender.engine.overlap import OVERLAP_ROWS, OutputRing, merge_writing, run_bands
from derender.engine.plans import TablePlan
from derender.engine.tables import code_table
from derender.engine.weights import F32_MAX

__all__ = ["table_kernel_merge", "warm_up_kernel"]


def _table_kernel_tables(plan: TablePlan, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame value and weight tables (N, 256, 3) float32 of a plan, the weights scaled
    as :meth:`TableMerge.add` scales them (image weight, then 1/3 in the ``"mean"`` mode)."""
    values = np.ascontiguousarray(plan.values, dtype=np.float32)
    iw = np.ones(n) if plan.image_weights is None else np.asarray(plan.image_weights, dtype=np.float64)
    weights = np.empty((n, N_CODES, 3), dtype=np.float32)
    for j in range(n):
        wt = code_table(plan.weight_of(j), "weight").astype(np.float64) * float(iw[j])
        if plan.channel_weights == "mean":
            wt = wt / 3.0
        weights[j] = wt.astype(np.float32)
    for j in range(n):
        code_table(values[j], "value")
    return values, weights


def table_kernel_merge(frames: np.ndarray, plan: TablePlan, order: list[int], threads: int | None,
                        *, bright_threshold: float = 0.5, write=None, ring: int = 0,
                        valid: np.ndarray | None = None, ref: int = -1) -> HDRResult:
    """A table plan (modes ``"mean"`` / ``"independent"``) on held frames with the compiled
    kernel :func:`derender.engine.kernels.table_merge_rows`: the numbers of
    :class:`TableMerge` (frames added in ``order``; the log domain's exponential by OpenCV
    on the engine's row blocks), no accumulator planes.

    ``write(result, rows_done)``, if given, runs in a thread while the kernel merges bands of
    :data:`OVERLAP_ROWS` rows; it must read row ``y`` of the result only after
    ``rows_done.wait(y + 1)`` (the EXR writer compresses finished bands meanwhile). ``ring``
    (with ``write``): the radiance goes through an :class:`~derender.engine.overlap.OutputRing`
    of band buffers into the file, the result's ``radiance`` is None. ``valid`` (N, H, W) uint8:
    frame ``j`` takes part only where ``valid[j]`` is non-zero, and where none with weight does,
    the reference frame ``ref`` decides the saturation policy (:mod:`derender.engine.motion`).

    With ``plan.variance`` (a :class:`~derender.engine.variance.VarianceModel`) the kernel is
    :func:`~derender.engine.variance_kernels.table_merge_var_rows`: the same radiance and its
    variance (``result.variance``; through the ring's second buffer with ``ring`` 2), split by
    source in ``info["variance_sources"]``."""
    from concurrent.futures import ThreadPoolExecutor

    from derender.core.memory import import_cv2, opencv_single_thread
    from derender.engine.kernels import table_merge_rows
    from derender.engine.matrix import KERNEL_LOCK, set_numba_threads
    from derender.engine.tables import code_values

    cv2 = import_cv2()
    n, h, w = frames.shape[:3]
    values, weights = _table_kernel_tables(plan, n)
    log = plan.domain == "log"
    mask = populated_zeros((h, w), dtype=np.uint8)
    bright = code_values() >= np.float32(bright_threshold)
    br = plan.block_rows if plan.block_rows is not None else max(1, (1 << 16) // max(w, 1))
    # bands of whole engine blocks (the exponential's blocks are the engine's: same bytes)
    step = max(br, (OVERLAP_ROWS // br) * br)
    vm = plan.variance
    parts = None
    out_ring, out, var = _table_kernel_outputs(h, w, step, vm is not None, write, ring)
    if vm is not None:
        from derender.engine.variance import SOURCE_STRIDE, VAR_CAP, new_parts
        from derender.engine.variance_kernels import table_merge_var_rows, variance_finish_rows

        parts = new_parts(h, w)
        tn = np.ascontiguousarray(vm.noise, dtype=np.float32)
        tq = np.ascontiguousarray(vm.quant, dtype=np.float32)
        kv = vm.constants()
        edge2 = float(np.float32(vm.edge * vm.edge)) if vm.edge > 0 else 0.0
    order_a = np.asarray(order, dtype=np.int64)
    valid_k = np.ones((n, 1, 1), dtype=np.uint8) if valid is None else np.ascontiguousarray(valid, dtype=np.uint8)
    independent = plan.channel_weights == "independent"
    info = {"channel_weights": plan.channel_weights, "domain": plan.domain, "engine": "table",
            "accumulator": "float64" if log else "float32", "kernel": "table_merge_rows"}
    res = HDRResult(radiance=None if out_ring is not None else out.transpose(1, 2, 0), mask=mask,
                    variance=None if var is None else var.transpose(1, 2, 0), info=info)
    nthreads = thread_count(threads)
    with opencv_single_thread(), ThreadPoolExecutor(max(1, nthreads), thread_name_prefix="derender-exp") as ex:
        def band(y0: int, y1: int) -> None:
            if out_ring is not None:
                bufs, row0 = out_ring.slot(y0)
                dst, vdst = bufs[0], bufs[-1]
            else:
                dst, vdst, row0 = out, var, 0

            def finish(r0: int, r1: int) -> None:
                _finish_rows(cv2, dst[:, r0 - row0:r1 - row0], log)

            with KERNEL_LOCK:
                set_numba_threads(threads)
                if vm is None:
                    table_merge_rows(frames, valid_k, int(ref), order_a, values, weights, independent, log, values[0],
                                     values[n - 1], 0, n - 1, bright, y0, y1, row0, dst, mask)
                else:
                    table_merge_var_rows(frames, valid_k, int(ref), order_a, values, weights, independent, log,
                                         values[0], values[n - 1], 0, n - 1, bright, y0, y1, row0, dst, mask,
                                         tn, tq, kv, vdst, parts, SOURCE_STRIDE)
            run_bands(ex, nthreads, finish, [(r0, min(y1, r0 + br)) for r0 in range(y0, y1, br)])
            if vm is not None:      # log domain: the kernel's relative variance times r^2; the edge term
                with KERNEL_LOCK:
                    set_numba_threads(threads)
                    variance_finish_rows(dst, vdst, parts, edge2, log, y0, y1, row0, SOURCE_STRIDE, VAR_CAP)

        merge_writing(h, step, band, res, write, ring=out_ring)
    info["n_bright"] = int(np.count_nonzero(mask == HDRResult.MASK_BRIGHT))
    info["n_dark"] = int(np.count_nonzero(mask == HDRResult.MASK_DARK))
    if vm is not None:
        from derender.engine.variance import source_shares

        info["kernel"] = "table_merge_var_rows"
        info["variance_sources"] = source_shares(parts)
        info["variance_shared"] = float(vm.shared)
        info["variance_inflate"] = float(vm.inflate)
        if vm.curve_sd is not None:
            info["variance_curve_sd"] = float(vm.curve_sd)
    return res


def _table_kernel_outputs(h: int, w: int, step: int, with_variance: bool, write, ring: int) -> tuple:
    """``(out_ring, radiance, variance)``: a ring of ``step``-row planar band buffers (one, or two
    with the variance; radiance and variance None) when writing through one, else planar (3, H, W)
    float32 radiance (and variance, or None)."""
    nout = 2 if with_variance else 1
    if ring and write is not None:
        out_ring = OutputRing(h, w, step, lambda: tuple(populated_zeros((3, step, w), dtype=np.float32)
                                                   for _ in range(nout)), writers=min(int(ring), nout))
        return out_ring, None, None
    out = populated_zeros((3, h, w), dtype=np.float32)
    var = populated_zeros((3, h, w), dtype=np.float32) if with_variance else None
    return None, out, var


def _finish_rows(cv2, rows: np.ndarray, log: bool) -> None:
    """The kernel's sums of planar rows (3, r, W) made radiance in place: ``exp`` in the log domain
    (OpenCV's, on the engine's row blocks), non-finite values clipped to float32's range."""
    for c in range(3):
        r = rows[c]
        if log:
            cv2.exp(r, dst=r)
        if not cv2.checkRange(r)[0]:
            np.nan_to_num(r, copy=False, nan=0.0, posinf=F32_MAX, neginf=-F32_MAX)


#: Why a background warm-up failed (it never raises: the merge itself then compiles the
#: kernel and raises what goes wrong); kept for diagnosis.
WARM_UP_ERRORS: list[str] = []


def warm_up_kernel(which: str = "table") -> None:
    """Import numba and load a kernel (``"table"``: :func:`table_merge_rows`, ``"gaussian"``:
    :func:`gaussian_band`, :func:`gaussian_moments_band`) from its cache in a background thread while the frames decode
    (0.5-1 s; the decoders release the GIL)."""
    import threading

    def go() -> None:
        try:
            from derender.engine.kernels import gaussian_band, gaussian_moments_band, table_merge_rows
            from derender.engine.matrix import KERNEL_LOCK

            f32 = np.float32
            if which == "gaussian":
                z = np.zeros((3, 1, 1))
                gaussian_band(np.zeros((1, 1, 1, 3), np.uint8), np.ones((1, 1, 1), np.uint8),
                              np.zeros(1 << 24, np.int32), np.zeros((9, 1)),
                              np.zeros(1), 0, 1, z, z.copy(), z.copy())
                o = np.zeros((1, 1, 3), np.float32)
                gaussian_moments_band(np.zeros((1, 1, 1, 3), np.uint8), np.ones((1, 1, 1), np.uint8),
                                      np.zeros(1 << 24, np.int32), np.zeros((9, 1)),
                                      np.zeros(1), 0, 1, True, 80.0, 60.0, np.eye(3), True, 0, o, o.copy())
                return
            with KERNEL_LOCK:
                table_merge_rows(np.zeros((1, 1, 1, 3), np.uint8), np.ones((1, 1, 1), np.uint8), -1, np.zeros(1, np.int64),
                                 np.zeros((1, N_CODES, 3), f32), np.zeros((1, N_CODES, 3), f32), False, True,
                                 np.zeros((N_CODES, 3), f32), np.zeros((N_CODES, 3), f32), 0, 0,
                                 np.zeros(N_CODES, bool), 0, 1, 0, np.zeros((3, 1, 1), f32), np.zeros((1, 1), np.uint8))
        except Exception as exc:  # noqa: BLE001 - a warm-up only: the merge compiles and reports for itself
            WARM_UP_ERRORS.append(f"{which}: {type(exc).__name__}: {exc}")

    threading.Thread(target=go, name="derender-warm-up", daemon=True).start()
