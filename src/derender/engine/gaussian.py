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
from dataclasses import dataclass

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
    from derender.engine.overlap import OVERLAP_ROWS, merge_writing, run_bands

    t0 = time.perf_counter()
    h = frames.shape[1]
    fused = _fused_moments(frames, plan)
    nthreads = max(1, int(threads)) if threads else max(1, len(os.sched_getaffinity(0)))
    group = plan.band_rows * nthreads        # a chunk: whole rounds of bands over the threads
    step = group * max(1, OVERLAP_ROWS // group)
    bands = _GaussianBands.start(frames, plan, fused, valid, _gaussian_outputs(frames, fused, step, write,
                                                                               outputs, ring))
    res = HDRResult(radiance=bands.radiance, mask=bands.mask, variance=bands.variance, info={"engine": "gaussian"})
    with ThreadPoolExecutor(nthreads, thread_name_prefix="derender-gauss") as ex:
        def chunk(c0: int, c1: int) -> None:
            run_bands(ex, nthreads, bands.run,
                      [(y0, min(c1, y0 + plan.band_rows)) for y0 in range(c0, c1, plan.band_rows)])

        merge_writing(h, step, chunk, res, write, ring=bands.out_ring)
    if bands.hist is not None:
        res.info["variance_sources"] = variance_sources(bands.hist)
    res.info["merge_seconds"] = time.perf_counter() - t0
    return res


def _fused_moments(frames: np.ndarray, plan: GaussianPlan):
    """The plan's log-normal moments when sums and moments can run in one compiled pass per band
    (a colour-major float64 ``table`` of 8 columns, a colour look-up table, C-contiguous frames), else None."""
    lut = getattr(plan.index, "lut", None)
    table = plan.table
    return plan.lognormal if (lut is not None and table is not None and table.dtype == np.float64
                              and table.ndim == 2 and table.shape[1] == 8 and table.flags.c_contiguous
                              and frames.flags.c_contiguous) else None


def _gaussian_outputs(frames: np.ndarray, fused, step: int, write, outputs, ring: int) -> tuple:
    """``(out_ring, radiance, variance)``: an output ring of ``step``-row band buffers (radiance and
    variance None), the caller's ``outputs`` when they fit, or new (H, W, 3) float32 arrays."""
    from derender.core.memory import populated_zeros
    from derender.engine.overlap import OutputRing

    h, w = frames.shape[1:3]
    # outputs mapped with their pages present: first-touch faults inside the merge cost 2-4 ms
    # per MB here (576 MB at 24 MP), populating ~0.5 ms per MB (core.memory.populated_zeros)
    if ring and write is not None and fused is not None:
        out_ring = OutputRing(h, w, step, lambda: (populated_zeros((step, w, 3), np.float32),
                                                   populated_zeros((step, w, 3), np.float32)), writers=ring,
                              planar=False)
        return out_ring, None, None
    if outputs is not None and all(o.shape == (h, w, 3) and o.dtype == np.float32 and o.flags.c_contiguous
                                   and o.flags.writeable for o in outputs):
        return (None, *outputs)
    return None, populated_zeros((h, w, 3), np.float32), populated_zeros((h, w, 3), np.float32)


@dataclass
class _GaussianBands:
    """What every band of one Gaussian merge reads and writes; :meth:`run` merges rows ``y0:y1``."""

    frames: np.ndarray
    plan: GaussianPlan
    fused: object                   # the plan's LogNormalMoments when one compiled pass does it all
    valid: np.ndarray | None
    valid_k: np.ndarray             # (N, H, W) or (N, 1, 1) uint8 for the kernels
    out_ring: object
    radiance: np.ndarray | None
    variance: np.ndarray | None
    mask: np.ndarray
    planes: np.ndarray | None       # [mu; p; low] rows of the colours (not for the fused pass)
    compiled: bool
    log_scales: list
    scales: np.ndarray
    hist: np.ndarray | None         # per-row counts of the variance sources' shares
    a: np.ndarray | None = None     # the fused pass's colour matrix (identity when unused)
    use_a: bool = False

    @classmethod
    def start(cls, frames: np.ndarray, plan: GaussianPlan, fused, valid: np.ndarray | None,
              outputs: tuple) -> "_GaussianBands":
        """The bands' shared state: the kernels' inputs and the (ring or whole) outputs."""
        n, h, w = frames.shape[:3]
        out_ring, radiance, variance = outputs
        planes = None if fused is not None else plan.rows_planes()
        lut = getattr(plan.index, "lut", None)
        compiled = (fused is not None or (plan.shared is None and lut is not None and planes.dtype == np.float64
                                          and planes.flags.c_contiguous and frames.flags.c_contiguous))
        hist = None
        if plan.shared is not None:
            from derender.engine.gaussian_kernels import NBINS

            hist = np.zeros((h, 4, NBINS), dtype=np.int64)
        valid_k = np.ones((n, 1, 1), dtype=np.uint8) if valid is None else np.ascontiguousarray(valid, dtype=np.uint8)
        log_scales = [float(s) for s in plan.log_scales]
        bands = cls(frames, plan, fused, valid, valid_k, out_ring, radiance, variance,
                    np.empty((h, w), dtype=np.uint8), planes, compiled, log_scales,
                    np.asarray(log_scales, dtype=np.float64), hist)
        if fused is not None:
            bands.use_a = fused.matrix is not None
            bands.a = np.ascontiguousarray(fused.matrix if bands.use_a else np.eye(3), dtype=np.float64)
        return bands

    def run(self, y0: int, y1: int) -> None:
        """Merge rows ``y0:y1`` into the outputs and the saturation mask."""
        if self.fused is not None:    # sums and moments in one compiled pass, no float64 band arrays
            self._fused_band(y0, y1)
        else:
            self._summed_band(y0, y1)
        n = self.frames.shape[0]
        self.mask[y0:y1] = self.plan.mask(self.frames[0, y0:y1], self.frames[n - 1, y0:y1])

    def _fused_band(self, y0: int, y1: int) -> None:
        """Sums and log-normal moments of a band in one compiled pass."""
        from derender.engine.kernels import gaussian_moments_band

        fused, shared, lut = self.fused, self.plan.shared, self.plan.index.lut
        if self.out_ring is not None:
            (rad, var), row0 = self.out_ring.slot(y0)
        else:
            rad, var, row0 = self.radiance, self.variance, 0
        if shared is not None:
            from derender.engine.gaussian_kernels import gaussian_variance_band

            gaussian_variance_band(self.frames, self.valid_k, lut, self.plan.table, self.scales, y0, y1,
                                   bool(fused.censor), float(fused.max_log), float(fused.max_v), self.a,
                                   self.use_a, row0, rad, var, float(shared.k_model), float(shared.k_pipe),
                                   float(shared.k_spatial), float(shared.floor_share), self.hist)
        else:
            gaussian_moments_band(self.frames, self.valid_k, lut, self.plan.table, self.scales, y0, y1,
                                  bool(fused.censor), float(fused.max_log), float(fused.max_v), self.a,
                                  self.use_a, row0, rad, var)

    def _summed_band(self, y0: int, y1: int) -> None:
        """The product's sums of a band (compiled, or frame by frame), then the plan's moments."""
        frames, plan, w = self.frames, self.plan, self.frames.shape[2]
        prod = LogGaussianProduct((y1 - y0, w), shared=plan.shared is not None)
        if self.compiled:
            from derender.engine.kernels import gaussian_band

            gaussian_band(frames, self.valid_k, plan.index.lut, self.planes, self.scales, y0, y1,
                          prod.prec, prod.acc, prod.bound)
        else:
            for j in range(frames.shape[0]):
                prod.add_rows(self.planes, plan.index.rows(frames[j, y0:y1]), self.log_scales[j],
                              keep=None if self.valid is None else self.valid[j, y0:y1] != 0)
        if plan.shared is not None:
            self.radiance[y0:y1], self.variance[y0:y1] = plan.moments(prod.prec, prod.acc, prod.bound,
                                                                      (*prod.extra, self.hist[y0:y1]))
        else:
            self.radiance[y0:y1], self.variance[y0:y1] = plan.moments(prod.prec, prod.acc, prod.bound)


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
