"""The Gaussian-product kernel of the engine: per-colour Gaussians multiplied across exposures, band by band.

Paper 2, eq. 3: the radiance of a pixel is the product of the Gaussians its exposures
give, each scaled to a common exposure. In log space a frame's scale is an offset, so
frame ``j`` contributes, per channel, ``p`` (precision), ``p (mu + log s_j)`` and a
censoring bound ``low + log s_j`` (``-inf`` where measured); :class:`LogGaussianProduct`
accumulates ``sum p``, ``sum p (mu + log s_j)`` and ``max bound`` in float64. The method
tabulates ``[mu; p; low]`` once per distinct colour of the bracket
(:class:`~derender.engine.plans.GaussianPlan`) and turns the sums into moments; the
engine gathers the tables band by band (``band_rows`` rows, in threads), so no
full-size float image but the outputs exists. A plan with a colour-major ``table`` and
log-normal moments (:class:`~derender.engine.plans.LogNormalMoments`, the probabilistic
merge's) runs sums and moments in one compiled pass per band
(:func:`~derender.engine.kernels.gaussian_moments_band`), without float64 band arrays.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from derender.core.types import HDRResult
from derender.engine.plans import GaussianPlan

__all__ = ["LogGaussianProduct", "merge_gaussian_frames", "mark_colours_held", "variance_sources"]


def mark_colours_held(frames: np.ndarray, present: np.ndarray, threads: int | None = None) -> bool:
    """Mark the colours of held frames (N, H, W, 3) uint8 in a presence bitmap ``present``
    ((2**24,) bool, :class:`derender.derendering.apply.ColourIndexBuilder`'s) with the
    compiled :func:`derender.engine.kernels.mark_colours`, the frames split over ``threads``
    threads. Returns False (nothing marked) for frames it cannot take."""
    if (frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3 or not frames.flags.c_contiguous
            or present.dtype != np.bool_ or present.shape != (1 << 24,) or not present.flags.c_contiguous):
        return False
    from derender.core.memory import thread_count
    from derender.engine.kernels import mark_colours

    n = frames.shape[0]
    k = max(1, min(thread_count(threads), n))
    cuts = [n * i // k for i in range(k + 1)]
    if k == 1:
        mark_colours(frames, 0, n, present)
    else:
        with ThreadPoolExecutor(k, thread_name_prefix="derender-colours") as ex:
            list(ex.map(lambda i: mark_colours(frames, cuts[i], cuts[i + 1], present), range(k)))
    return True


class LogGaussianProduct:
    """Accumulators of the log-space product (eq. 3) for a block of pixels, channel planes (3, ...)."""

    def __init__(self, shape: tuple[int, ...], shared: bool = False):
        self.prec = np.zeros((3, *shape), dtype=np.float64)
        self.acc = np.zeros((3, *shape), dtype=np.float64)
        self.bound = np.full((3, *shape), -np.inf)
        # shared-error variance (planes (11, M), :class:`~derender.engine.plans.SharedVariance`):
        # sum p y^2, sum p sm, sum p^2 vn, sum p vn
        self.extra = tuple(np.zeros((3, *shape), dtype=np.float64) for _ in range(4)) if shared else None

    def add_rows(self, planes: np.ndarray, rows: np.ndarray, log_scale: float,
                 keep: np.ndarray | None = None) -> None:
        """One exposure: ``planes`` (9, M) = ``[mu; p; low]`` per channel of its colours,
        ``rows`` (...) the row of each pixel's colour, and the frame's ``log(t_0 / t_j)``;
        ``keep`` (bool, ``rows``' shape): the pixels where the frame takes part (all if None)."""
        t = np.empty(rows.shape, dtype=np.float64)
        p = np.empty(rows.shape, dtype=np.float64)
        for c in range(3):
            np.take(planes[3 + c], rows, out=p, mode="clip")       # clip: rows are valid; unbuffered out
            if keep is not None:
                p[~keep] = 0.0
            self.prec[c] += p
            np.take(planes[c], rows, out=t, mode="clip")
            t += log_scale
            t *= p
            self.acc[c] += t
            np.take(planes[6 + c], rows, out=t, mode="clip")
            t += log_scale
            if keep is not None:
                t[~keep] = -np.inf
            np.maximum(self.bound[c], t, out=self.bound[c])
            if self.extra is not None:
                sq, shm, noi, nw = self.extra
                yy = np.take(planes[c], rows, mode="clip") + log_scale
                vn = np.take(planes[10], rows, mode="clip")
                sq[c] += p * yy * yy
                shm[c] += p * np.take(planes[9], rows, mode="clip")
                noi[c] += p * p * vn
                nw[c] += p * vn


def merge_gaussian_frames(frames: np.ndarray, plan: GaussianPlan, threads: int | None = None,
                          write=None, outputs: tuple[np.ndarray, np.ndarray] | None = None,
                          ring: int = 0, valid: np.ndarray | None = None) -> HDRResult:
    """Run a :class:`~derender.engine.plans.GaussianPlan` on held frames (N, H, W, 3) uint8
    sorted by exposure time; bands of ``plan.band_rows`` rows in ``threads`` threads.
    ``write(result, rows_done)``: the radiance written while merging
    (:func:`derender.engine.overlap.merge_writing`). ``outputs``: radiance and variance arrays
    (H, W, 3) float32 to fill (allocated here when None). ``ring`` > 0 (with ``write`` and the
    fused compiled pass): radiance and variance go through an
    :class:`~derender.engine.overlap.OutputRing` of band buffers read by ``ring`` writers (1:
    the radiance file, 2: and the variance file); the result's ``radiance`` and ``variance``
    are None. ``valid`` (N, H, W) uint8: frame ``j`` takes part only where ``valid[j]`` is
    non-zero (the engine's alignment and ghost removal, :mod:`derender.engine.motion`)."""
    from derender.core.memory import populated_zeros
    from derender.engine.overlap import OVERLAP_ROWS, OutputRing, merge_writing, run_bands

    t0 = time.perf_counter()
    n, h, w = frames.shape[:3]
    # outputs mapped with their pages present: first-touch faults inside the merge cost 2-4 ms
    # per MB here (576 MB at 24 MP), populating ~0.5 ms per MB (core.memory.populated_zeros)
    log_scales = [float(s) for s in plan.log_scales]
    lut = getattr(plan.index, "lut", None)
    table = plan.table
    fused = plan.lognormal if (lut is not None and table is not None and table.dtype == np.float64
                               and table.ndim == 2 and table.shape[1] == 8 and table.flags.c_contiguous
                               and frames.flags.c_contiguous) else None
    nthreads = max(1, int(threads)) if threads else max(1, len(os.sched_getaffinity(0)))
    group = plan.band_rows * nthreads        # a chunk: whole rounds of bands over the threads
    step = group * max(1, OVERLAP_ROWS // group)
    out_ring = None
    if ring and write is not None and fused is not None:
        out_ring = OutputRing(h, w, step, lambda: (populated_zeros((step, w, 3), np.float32),
                                              populated_zeros((step, w, 3), np.float32)), writers=ring,
                         planar=False)
        radiance = variance = None
    elif outputs is not None and all(o.shape == (h, w, 3) and o.dtype == np.float32 and o.flags.c_contiguous
                                     and o.flags.writeable for o in outputs):
        radiance, variance = outputs
    else:
        radiance = populated_zeros((h, w, 3), np.float32)
        variance = populated_zeros((h, w, 3), np.float32)
    mask = np.empty((h, w), dtype=np.uint8)
    planes = None if fused is not None else plan.rows_planes()
    shared = plan.shared
    compiled = (fused is not None or (shared is None and lut is not None and planes.dtype == np.float64
                                      and planes.flags.c_contiguous and frames.flags.c_contiguous))
    hist = None
    if shared is not None:       # per-row counts of the variance sources' shares
        from derender.engine.gaussian_kernels import NBINS

        hist = np.zeros((h, 4, NBINS), dtype=np.int64)
    whole = valid is None
    valid_k = np.ones((n, 1, 1), dtype=np.uint8) if whole else np.ascontiguousarray(valid, dtype=np.uint8)
    if compiled:
        from derender.engine.kernels import gaussian_band

        scales = np.asarray(log_scales, dtype=np.float64)

    if fused is not None:
        from derender.engine.kernels import gaussian_moments_band

        if shared is not None:
            from derender.engine.gaussian_kernels import gaussian_variance_band

        use_a = fused.matrix is not None
        a = np.ascontiguousarray(fused.matrix if use_a else np.eye(3), dtype=np.float64)

    def run(y0: int, y1: int) -> None:
        if fused is not None:    # sums and moments in one compiled pass, no float64 band arrays
            if out_ring is not None:
                (rad, var), row0 = out_ring.slot(y0)
            else:
                rad, var, row0 = radiance, variance, 0
            if shared is not None:
                gaussian_variance_band(frames, valid_k, lut, table, scales, y0, y1, bool(fused.censor),
                                       float(fused.max_log), float(fused.max_v), a, use_a, row0, rad, var,
                                       float(shared.k_model), float(shared.k_pipe), float(shared.k_spatial),
                                       float(shared.floor_share), hist)
            else:
                gaussian_moments_band(frames, valid_k, lut, table, scales, y0, y1, bool(fused.censor),
                                      float(fused.max_log), float(fused.max_v), a, use_a, row0, rad, var)
            mask[y0:y1] = plan.mask(frames[0, y0:y1], frames[n - 1, y0:y1])
            return
        prod = LogGaussianProduct((y1 - y0, w), shared=shared is not None)
        if compiled:
            gaussian_band(frames, valid_k, lut, planes, scales, y0, y1, prod.prec, prod.acc, prod.bound)
        else:
            for j in range(n):
                prod.add_rows(planes, plan.index.rows(frames[j, y0:y1]), log_scales[j],
                              keep=None if whole else valid[j, y0:y1] != 0)
        if shared is not None:
            radiance[y0:y1], variance[y0:y1] = plan.moments(prod.prec, prod.acc, prod.bound,
                                                            (*prod.extra, hist[y0:y1]))
        else:
            radiance[y0:y1], variance[y0:y1] = plan.moments(prod.prec, prod.acc, prod.bound)
        mask[y0:y1] = plan.mask(frames[0, y0:y1], frames[n - 1, y0:y1])

    res = HDRResult(radiance=radiance, mask=mask, variance=variance, info={"engine": "gaussian"})
    with ThreadPoolExecutor(nthreads, thread_name_prefix="derender-gauss") as ex:
        def chunk(c0: int, c1: int) -> None:
            run_bands(ex, nthreads, run, [(y0, min(c1, y0 + plan.band_rows)) for y0 in range(c0, c1, plan.band_rows)])

        merge_writing(h, step, chunk, res, write, ring=out_ring)
    if hist is not None:
        res.info["variance_sources"] = variance_sources(hist)
    res.info["merge_seconds"] = time.perf_counter() - t0
    return res


def variance_sources(hist: np.ndarray) -> dict:
    """Median share of each source in the merged log variance (model shared, noise, pipeline
    change, spatial mixing) from per-row histograms (H, 4, NBINS) of the shares
    (:func:`~derender.engine.gaussian_kernels.gaussian_variance_band`), bin centres; with the
    number of pixel-channels counted."""
    tot = hist.sum(axis=0)                 # (4, NBINS)
    nb = tot.shape[1]
    n = int(tot[0].sum())
    out: dict = {"n": n}
    for k, name in enumerate(("model_shared", "noise", "pipeline_change", "spatial_mixing")):
        if n == 0:
            out[name] = float("nan")
            continue
        c = np.cumsum(tot[k])
        out[name] = float((np.searchsorted(c, 0.5 * n) + 0.5) / nb)
    return out
