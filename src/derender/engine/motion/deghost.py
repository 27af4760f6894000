"""Ghost removal by a per-pixel consistency test against the reference frame, with noise learnt from the bracket.

A moving object puts different radiance at a pixel in different frames. The engine tests each
frame against the reference frame and excludes the frames that disagree, per pixel (in the spirit
of Granados et al. 2013, *Automatic noise modeling for ghost-free HDR reconstruction*, whose
noise is estimated from the bracket itself).

Per frame ``j``, on a grid of at most :data:`DETECT_PIXELS` pixels (every ``s``-th row and
column):

* the two frames' **intensity mapping functions** (:mod:`derender.engine.intensity_mapping`):
  per channel and code, the median code the other frame shows at the pixels of that code, and
  its robust spread (MAD), read off the two frames' joint histogram (:class:`FrameAgreement`).
  Whatever the camera changed between the two exposures (exposure, white balance, gain, tone
  curve, a look-up table, film and scanner) maps a code the same way at every still pixel, so
  it is not a ghost; and the spread is the noise, quantisation and rendering variation these
  two frames really show at that code, not a model's;
* ``z^2`` per channel, the smaller of the two directions' squared residuals over their spread
  (plus what a half-pixel misregistration does on an edge: :data:`EDGE_SHIFT` times the
  codes' gradient); a code clipped in one frame predicts the other badly, but the other
  predicts it exactly, so clipping is never taken for motion;
* the statistic ``Q = mean over a (2k+1)^2 window of min(mean over channels of z^2,``
  :data:`Z2_CAP` ``)`` (a local chi-square per degree of freedom, about 1 where the frames
  agree; the cap keeps one wild pixel from rejecting its window) is compared with
  :data:`GHOST_THRESHOLD`; the rejections are cleaned into regions (a 3x3 opening removes
  specks, a dilation by :data:`GHOST_DILATE` covers the object's blurred edges) and brought
  to full resolution.

The test reads codes only, so every method gets the same ghost mask for a bracket (before this,
each method's own noise model and four-bin offsets rejected 1-25 % of still real brackets,
differently per method, and recoloured them: measured in ``docs/ghosts.md``). The method's plan
still gives each frame's log radiance and a per-code log offset against the reference
(:meth:`FrameAgreement.maps`), which the flow fill (:mod:`derender.engine.motion.compensation`) reads.

The reference frame always takes part. Where every other frame is rejected the reference
alone gives the value (its mask rule as usual: a clipped reference gives the bound).
A bracket in which almost nothing agrees with the reference is refused (:data:`MAX_REJECTED`;
and, before any of this, neighbouring frames whose structure disagrees:
:func:`derender.engine.motion.check_one_scene`).
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np

from derender.core.errors import StackError
from derender.engine.motion.intensity_mapping import MappingTables, mapping_tables, mapping_z2

__all__ = ["GHOST_THRESHOLD", "GHOST_WINDOW", "GHOST_DILATE", "CODE_SIGMA", "DETECT_PIXELS", "STAT_PIXELS", "MAX_REJECTED", "REFIT_MIN_REJECTED", "FLICKER_ELONGATION", "FLICKER_EXPLAINED", "FLICKER_REACH", "FLICKER_SIDES", "flicker_bands",
           "Z2_CAP", "EDGE_SHIFT", "AGREEMENT_MIN_PIXELS",
           "frame_estimates", "FrameAgreement", "ConsistencyTest", "upsample_mask", "map_frames", "detect_ghosts",
           "merge_valid"]

#: Window mean of z^2 per channel above which a frame is rejected at a pixel (chosen on the
#: tuning families ``paper`` and ``camera``, ``derender experiment ghosts``).
GHOST_THRESHOLD = 4.0

#: Half-width k of the pooling window (2k+1 pixels of the detection grid).
GHOST_WINDOW = 2

#: Dilation of the rejected regions, in pixels of the detection grid.
GHOST_DILATE = 2

#: Code noise (standard deviation, codes) besides quantisation: sensor read/shot noise and
#: JPEG error of a mid-grey 8-bit code.
CODE_SIGMA = 1.0

#: Each pixel's ``z^2`` counts at most this much in the window mean: a region is rejected
#: when a good part of the window disagrees, not when one pixel does.
Z2_CAP = 16.0

#: Misregistration (pixels) an edge may show between two exposures without a ghost:
#: sub-pixel alignment error, blur and JPEG ringing: ``(EDGE_SHIFT |grad mu|)^2`` is added to
#: the variance of both frames' log radiance.
EDGE_SHIFT = 0.5

#: The test runs on every s-th row and column so that at most about this many pixels remain.
DETECT_PIXELS = 1 << 19

#: The offsets and spreads are robust statistics of at most about this many pixels.
STAT_PIXELS = 1 << 16

#: A frame's offset and spread at a code are estimated from at least this many pixels (of the
#: nearest codes when that code alone has fewer).
AGREEMENT_MIN_PIXELS = 64

#: The codes at which :meth:`FrameAgreement.summary` reports a frame's offset and spread.
SUMMARY_CODES = (16, 64, 128, 192, 240)

#: The spread is read at this quantile of ``|d - median|`` (scaled to a normal's standard
#: deviation): below the median, so that ghosts filling a good part of a brightness bin do not
#: widen it (0.5 would be the MAD).
SPREAD_QUANTILE = 0.3
_HALF_NORMAL_QUANTILE = NormalDist().inv_cdf(0.5 + SPREAD_QUANTILE / 2)   # |N(0, 1)|'s quantile


#: A rejected region is flicker when at least this fraction of it passes the test once one
#: gain per position across the band (read off the band beyond the region) is removed
#: (:func:`flicker_bands`; synthetic bands 93-100 % explained, the ping-pong bracket's person at
#: most 46 %).
FLICKER_EXPLAINED = 0.9

#: A rejected region at least this many times longer than wide may be a whole band: its gains
#: may then be read on its own lines too (:func:`flicker_bands`).
FLICKER_ELONGATION = 3.0

#: The gains across a band are medians over a strip that reaches at least this many grid pixels
#: (and at least the region's own length) beyond each end of the rejected region, along the band:
#: a moving thing then fills at most a third of the strip, so its gains are the still
#: background's and do not explain it; a flicker band runs on beyond the region, with the same
#: gain per position.
FLICKER_REACH = 32

#: ... and the gains read on the two sides of the region (before and after it along the band)
#: differ by at most this (log; median over its lines): a band runs on at both ends with the same
#: gains. Measured (issue 36): the iPhone monitor's pieces given back differ by at most 0.46
#: (median 0.08); on the simulator's moving brackets the pieces of an object's path explained by
#: the object beside them by 1.0-2.0.
FLICKER_SIDES = 0.6

#: The method is calibrated again without the rejected pixels (fit, detect, refit) only when
#: at least this fraction of the other frames' pixels was rejected: a refit on a pixel set that
#: hardly differs cannot remove much of a ghost's pull on the fits, but it can move an
#: ill-conditioned fit (measured on Debevec's still Memorial bracket, stabilized, reference 8:
#: 1.3 % rejected, the refit recoloured the whole church by a chroma change p95 of 0.14; without
#: it 0.007).
REFIT_MIN_REJECTED = 0.05

#: A bracket is refused when more than this fraction of the non-reference frames' pixels
#: disagree with the reference.
MAX_REJECTED = 0.9

_LOG_FLOOR = -60.0


def _fill_nearest(values: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Per channel, entries where ``usable`` is False take the value of the nearest usable code."""
    out = values.copy()
    codes = np.arange(values.shape[0])
    for c in range(values.shape[1]):
        u = usable[:, c]
        if not u.any():
            continue
        idx = np.flatnonzero(u)
        nearest = idx[np.clip(np.searchsorted(idx, codes), 0, idx.size - 1)]
        lower = idx[np.clip(np.searchsorted(idx, codes) - 1, 0, idx.size - 1)]
        pick = np.where(np.abs(lower - codes) <= np.abs(nearest - codes), lower, nearest)
        out[~u, c] = values[pick[~u], c]
    return out


def _code_tables(log_values: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(256, 3) log radiance, its standard deviation and a censoring flag (0 observed, +1 a
    lower bound, -1 an upper bound) per code, from a frame's log-radiance table."""
    lv = np.asarray(log_values, dtype=np.float64)
    fin = np.isfinite(lv)
    usable = usable & fin
    lv = _fill_nearest(np.where(fin, lv, 0.0), fin)
    slope = np.abs(np.gradient(lv, axis=0))
    sd = slope * np.sqrt(CODE_SIGMA ** 2 + 1.0 / 12.0)
    sd = _fill_nearest(sd, usable)
    mu = _fill_nearest(lv, usable)          # a clipped code's bound: the nearest usable code's value
    codes = np.arange(lv.shape[0])[:, None]
    cens = np.where(usable, 0, np.where(codes >= lv.shape[0] // 2, 1, -1)).astype(np.int8)
    return mu, sd, cens


def _lut3(codes: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Per-channel look-up of a (256, 3) table on (h, w, 3) uint8 codes, float32 (OpenCV's LUT)."""
    import cv2

    lut = np.ascontiguousarray(np.asarray(table, dtype=np.float32).reshape(1, 256, 3))
    return cv2.LUT(np.ascontiguousarray(codes), lut)


def frame_estimates(plan, codes: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``j``'s log radiance, its standard deviation and censoring flags, each
    ``codes.shape`` ((h, w, 3)) float32, float32, int8, under ``plan`` (module docstring)."""
    import cv2

    from derender.engine.plans import GaussianPlan, MatrixPlan, TablePlan

    if isinstance(plan, TablePlan):
        vals = np.asarray(plan.values[j], dtype=np.float64)
        if plan.domain == "linear":
            with np.errstate(divide="ignore", invalid="ignore"):
                vals = np.where(vals > 0, np.log(vals), -np.inf)
        usable = np.asarray(plan.weight_of(j)) > 0
        mu, sd, cens = _code_tables(vals, usable)
        return (_lut3(codes, np.clip(mu, _LOG_FLOOR, -_LOG_FLOOR)), _lut3(codes, sd),
                _lut3(codes, cens).astype(np.int8))
    if isinstance(plan, MatrixPlan):
        lin = np.asarray(plan.values[j], dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            llin = np.where(lin > 0, np.log(lin), -np.inf)
        usable = np.asarray(plan.weights) > 0
        bound, sd, cens = _code_tables(llin, usable)
        # a clipped channel at its bound (nearest usable code), then the frame's 3x3 matrix
        e = cv2.transform(_lut3(codes, np.exp(bound)), np.asarray(plan.matrices[j], dtype=np.float32))
        np.maximum(e, np.float32(np.exp(_LOG_FLOOR)), out=e)
        return cv2.log(e), _lut3(codes, sd), _lut3(codes, cens).astype(np.int8)
    if isinstance(plan, GaussianPlan):
        packed = ((codes[..., 0].astype(np.int64) << 16) | (codes[..., 1].astype(np.int64) << 8)
                  | codes[..., 2].astype(np.int64))
        rows = plan.index.lut[packed]
        ls = float(plan.log_scales[j])
        if plan.table is not None:
            t = plan.table[rows]
            mean, p, low = t[..., 0:3], t[..., 3:4], t[..., 4:7]
            prec = np.where(np.isneginf(low), p, 0.0)
        else:
            pl = plan.rows_planes()[:, rows]
            mean, prec, low = np.moveaxis(pl[0:3], 0, -1), np.moveaxis(pl[3:6], 0, -1), np.moveaxis(pl[6:9], 0, -1)
        bound = np.isfinite(low)
        with np.errstate(divide="ignore"):
            sd = np.where(prec > 0, 1.0 / np.sqrt(np.maximum(prec, 1e-300)), np.inf)
        mu = np.where(bound, low, mean) + ls
        # a bound's own uncertainty: the spread of the observed channels of that colour (else 0.1)
        fallback = np.where(np.isfinite(sd), sd, np.inf).min(axis=-1, keepdims=True)
        fallback = np.where(np.isfinite(fallback), fallback, 0.1)
        sd = np.where(bound | ~np.isfinite(sd), fallback, sd)
        return (np.clip(mu, _LOG_FLOOR, -_LOG_FLOOR).astype(np.float32), sd.astype(np.float32),
                bound.astype(np.int8))
    raise TypeError(f"no noise model for a {type(plan).__name__}")


def _estimates32(plan, codes: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`frame_estimates` as C-contiguous arrays (what the kernel reads)."""
    return tuple(np.ascontiguousarray(a) for a in frame_estimates(plan, codes, j))


@dataclass(frozen=True)
class FrameAgreement:
    """How frame j departs from the reference where nothing moves, as a function of frame j's own
    code (its intensity mapping onto the reference): per code and channel, the median log
    offset ``offset`` (256, 3) of ``mu_j - mu_r`` and the variance the noise model leaves
    unexplained ``spread2`` (256, 3) (robust: median and a low quantile of ``|d - median|`` over
    the pixels whose frame-j code lies in a window of codes around it). A camera that changes
    its white balance, gain or tone curve between frames, or a response curve that fits some
    frames better than others, is not a ghost: whatever it does to a code, it does to every
    pixel of that code, so the offset absorbs it code by code."""

    offset: np.ndarray
    spread2: np.ndarray
    forward: MappingTables
    backward: MappingTables

    def maps(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel offset and extra variance (h, w, 3) float32 of frame j's (h, w, 3) uint8 ``codes``."""
        return _lut3(codes, self.offset), _lut3(codes, self.spread2)

    def summary(self) -> dict:
        """JSON-friendly: the offsets and spreads (their square roots) per channel at a few codes."""
        at = list(SUMMARY_CODES)
        return {"codes": at, "offset": np.round(self.offset[at].T, 4).tolist(),
                "spread": np.round(np.sqrt(self.spread2[at].T), 4).tolist()}


def _agreement(codes_j: np.ndarray, codes_r: np.ndarray, est_j: tuple, est_r: tuple, ok: np.ndarray) -> FrameAgreement:
    """:class:`FrameAgreement` from the pixels observed (not clipped) in both frames with
    ``sd < 0.5``: per channel and frame-j code, the pixels of the nearest codes until at least
    :data:`AGREEMENT_MIN_PIXELS` are pooled (codes without data take the nearest code's values;
    0 without data at all). ``est_j``, ``est_r``: each frame's ``(mu, sd, cens)``
    (:func:`frame_estimates`)."""
    (mu_j, sd_j, cens_j), (mu_r, sd_r, cens_r) = est_j, est_r
    both = (cens_j == 0) & (cens_r == 0) & (sd_j < 0.5) & (sd_r < 0.5) & (ok != 0)[..., None]
    off = np.zeros((256, 3))
    s2 = np.zeros((256, 3))
    has = np.zeros((256, 3), dtype=bool)
    for c in range(3):
        sel = both[..., c]
        m = int(np.count_nonzero(sel))
        if m < AGREEMENT_MIN_PIXELS:
            continue
        code = codes_j[..., c][sel].astype(np.intp)
        d = mu_j[..., c][sel].astype(np.float64) - mu_r[..., c][sel].astype(np.float64)
        v = sd_j[..., c][sel].astype(np.float64) ** 2 + sd_r[..., c][sel].astype(np.float64) ** 2
        order = np.argsort(code, kind="stable")
        code, d, v = code[order], d[order], v[order]
        counts = np.bincount(code, minlength=256)
        ends = np.cumsum(counts)
        starts = ends - counts
        for k in np.flatnonzero(counts):
            lo = hi = k
            n = counts[k]
            while n < AGREEMENT_MIN_PIXELS and (lo > 0 or hi < 255):   # widen towards the nearer data
                if lo > 0:
                    lo -= 1
                    n += counts[lo]
                if hi < 255 and n < AGREEMENT_MIN_PIXELS:
                    hi += 1
                    n += counts[hi]
            db = d[starts[lo]:ends[hi]]
            med = float(np.median(db))
            spread = float(np.quantile(np.abs(db - med), SPREAD_QUANTILE)) / _HALF_NORMAL_QUANTILE
            off[k, c] = med
            s2[k, c] = max(0.0, spread * spread - float(np.median(v[starts[lo]:ends[hi]])))
            has[k, c] = True
    sel = ok != 0
    forward = mapping_tables(codes_j[sel], codes_r[sel])
    backward = mapping_tables(codes_r[sel], codes_j[sel])
    return FrameAgreement(offset=_fill_nearest(off, has), spread2=_fill_nearest(s2, has), forward=forward,
                          backward=backward)


def _box_mean(a: np.ndarray, k: int) -> np.ndarray:
    import cv2

    return cv2.blur(a.astype(np.float32), (2 * k + 1, 2 * k + 1), borderType=cv2.BORDER_REFLECT)


def map_frames(fn, items: list, threads: int | None = None) -> list:
    """``[fn(item) for item in items]`` in a pool of ``threads`` threads (default: the usable
    cores): the per-frame work is NumPy, OpenCV and a GIL-free kernel. Results in order; the
    first exception is raised."""
    from concurrent.futures import ThreadPoolExecutor

    from derender.core.memory import thread_count

    k = max(1, min(thread_count(threads), len(items)))
    if k == 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(k, thread_name_prefix="derender-ghosts") as ex:
        return list(ex.map(fn, items))


def merge_valid(valid: np.ndarray | None, rejected: np.ndarray | None, *, in_place: bool = False) -> np.ndarray | None:
    """``valid`` (N, H, W) uint8 or None with the ``rejected`` (N, H, W) bool pixels removed
    (``in_place``: written over ``rejected``'s memory, which then holds the result, not the
    rejections: no new plane, whose first touch costs a page fault per 4 kB)."""
    if rejected is None:
        return valid
    if in_place:
        keep = np.logical_not(rejected, out=rejected).view(np.uint8)
    else:
        keep = np.logical_not(rejected).view(np.uint8)        # one new plane, its bytes 0/1
    if valid is not None:
        np.bitwise_and(keep, valid, out=keep)
    return keep


class ConsistencyTest:
    """The test of the module docstring against frame ``ref`` under ``plan``, on the detection
    grid of (H, W) frames (every ``step``-th row and column: at most about ``pixels``)."""

    def __init__(self, plan, ref_codes: np.ndarray, ref: int, threshold: float = GHOST_THRESHOLD,
                 window: int = GHOST_WINDOW, dilate: int = GHOST_DILATE, pixels: int = DETECT_PIXELS):
        import cv2

        self.plan, self.ref = plan, int(ref)
        self.threshold, self.window, self.dilate = float(threshold), int(window), int(dilate)
        self.h, self.w = ref_codes.shape[:2]
        self.step = max(1, int(np.ceil(np.sqrt(self.h * self.w / pixels))))
        self.codes_r = self.grid(ref_codes)
        self.mu_r, self.sd_r, self.cens_r = _estimates32(plan, self.codes_r, ref)
        self.hs, self.ws = self.mu_r.shape[:2]
        self.stat_step = max(1, int(np.ceil(np.sqrt(self.hs * self.ws / STAT_PIXELS))))
        self._open = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
        self._dilate = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1))

    def sub(self, a: np.ndarray) -> np.ndarray:
        """``a`` (H, W, ...) on the detection grid."""
        return a[::self.step, ::self.step]

    def grid(self, a: np.ndarray) -> np.ndarray:
        """:meth:`sub` gathered once into a C-contiguous array (the estimates read the codes
        several times: a strided view of a full frame would be gathered again each time)."""
        return np.ascontiguousarray(self.sub(a))

    def statistic(self, codes: np.ndarray, j: int, ok: np.ndarray | None = None,
                  agreement: "FrameAgreement | None" = None, on_grid: bool = False):
        """Frame ``j``'s capped ``z^2`` per pixel of the detection grid ((hs, ws) float32), its log
        radiance estimates (mu, sd, cens) and its :class:`FrameAgreement` (estimated here unless
        given). ``codes`` is the whole (H, W, 3) frame (``on_grid``: already the grid's (hs, ws, 3));
        ``ok`` (hs, ws) uint8 where it may be compared."""
        grid = codes if on_grid else self.grid(codes)
        mu_j, sd_j, cens_j = _estimates32(self.plan, grid, j)
        if ok is None:
            ok = np.ones((self.hs, self.ws), dtype=np.uint8)
        if agreement is None:
            k = self.stat_step
            agreement = _agreement(grid[::k, ::k], self.codes_r[::k, ::k],
                                   (mu_j[::k, ::k], sd_j[::k, ::k], cens_j[::k, ::k]),
                                   (self.mu_r[::k, ::k], self.sd_r[::k, ::k], self.cens_r[::k, ::k]), ok[::k, ::k])
        q = mapping_z2(np.ascontiguousarray(grid), self.codes_r, agreement.forward, agreement.backward,
                       float(EDGE_SHIFT), float(Z2_CAP), ok)
        return q, (mu_j, sd_j, cens_j), agreement

    def regions_grid(self, q: np.ndarray, dilate: bool = False) -> np.ndarray:
        """The pooled statistic above the threshold, cleaned into regions, on the grid ((hs, ws) bool)."""
        import cv2

        bad = (_box_mean(q, self.window) > self.threshold).astype(np.uint8)
        bad = cv2.morphologyEx(bad, cv2.MORPH_OPEN, self._open)
        if dilate and self.dilate > 0:
            bad = cv2.dilate(bad, self._dilate)
        return bad.astype(bool)

    def regions(self, q: np.ndarray, dilate: bool = True) -> np.ndarray:
        """:meth:`regions_grid` at full resolution ((H, W) bool)."""
        return upsample_mask(self.regions_grid(q, dilate).astype(np.uint8), self.step, self.h, self.w)


def _band_z2(cr, cj, pf, pb, gf, gb, axis: int, additive: bool) -> np.ndarray:
    """Capped ``z^2`` of a box of the grid (both directions, the smaller) once the gains ``gf`` (on
    the reference's side) and ``gb`` (on frame j's) are applied: one gain per column
    (``axis=0``, (w, 3)) or per row (``axis=1``, (h, 3)), a log gain on ``code + 1`` or
    (``additive``) an offset in codes. ``pf``, ``pb``: (median, variance) of each direction's
    prediction in the box."""
    gf = gf[None] if axis == 0 else gf[:, None]
    gb = gb[None] if axis == 0 else gb[:, None]
    if additive:
        mf, mb = pf[0] + gf, pb[0] + gb
    else:
        mf, mb = (pf[0] + 1.0) * np.exp(gf) - 1.0, (pb[0] + 1.0) * np.exp(gb) - 1.0
    z2 = np.minimum((cr - mf) ** 2 / pf[1], (cj - mb) ** 2 / pb[1]).mean(axis=-1)
    return np.minimum(z2, np.float32(Z2_CAP)).astype(np.float32)


def flicker_bands(test: "ConsistencyTest", grid_j: np.ndarray, agreement: FrameAgreement,
                  bad: np.ndarray) -> tuple[np.ndarray, int]:
    """``bad`` (hs, ws) bool without the rejected regions that are flicker, not motion, and the
    number of grid pixels given back.

    A light source that flickers (a monitor's or an LED's PWM) under a rolling shutter is
    brighter or darker in bands along the sensor's rows, in other places in each short frame:
    between two frames its pixels differ by one gain per position across the band, the same all
    along it, far beyond the pieces the test rejected (only where the band crosses texture: on
    the iPhone bracket, dotted along the monitor's bands, each piece about as long as wide).
    Per rejected region (8-connected) and orientation (one gain per column, or per row), the
    gain of a line is the median, over a strip that runs :data:`FLICKER_REACH` grid pixels (at
    least the region's own length) beyond both ends of the region *without the region's own
    lines*, of ``ln((c_r + 1) / (m(c_j) + 1))``: the reference's code against what frame j's
    code predicts (and the other direction likewise). The region is flicker when the gains read
    before and after it agree (within :data:`FLICKER_SIDES`: a band runs on at both ends) and,
    with these gains, at least :data:`FLICKER_EXPLAINED` of its pixels pass the test (the same
    pooled statistic and threshold). A region at least :data:`FLICKER_ELONGATION` times longer than wide
    (a whole band rejected) may also take its gains from the whole strip, its own lines
    included, or as one offset in codes per line of its own (the rule before issue 36's
    flicker work, which gave back Memorial's scanner bands).

    A moving thing is not explained so: its strip beyond it shows the still background, whose
    gains are about zero, and no gain per line makes a changed texture agree; a piece of an
    object's path with the object beside it, along its motion, sees other gains on its two
    sides. Measured
    (issue 36): the iPhone's monitor is given back (left out 0.83 % -> 0.18 % of the other
    frames' pixels; the green speckle on the monitor is gone); the ping-pong person and the
    sculpture garden's pedestrians stay left out (ping-pong 15.5 % -> 15.0 %, sculpture garden
    4.94 % -> 4.92 %)."""
    import cv2

    from derender.engine.motion.intensity_mapping import gradient2

    n, lab, stats, _ = cv2.connectedComponentsWithStats(bad.astype(np.uint8), connectivity=8)
    if n <= 1:
        return bad, 0
    hs, ws = bad.shape
    cr = test.codes_r.astype(np.float32)
    cj = np.asarray(grid_j).astype(np.float32)
    m_f, s_f = agreement.forward.predict(np.ascontiguousarray(grid_j))
    m_b, s_b = agreement.backward.predict(test.codes_r)
    e2 = np.float32(EDGE_SHIFT * EDGE_SHIFT)
    v_f = s_f * s_f + e2 * gradient2(test.codes_r)
    v_b = s_b * s_b + e2 * gradient2(np.ascontiguousarray(grid_j))
    with np.errstate(divide="ignore", invalid="ignore"):
        l_f = np.log((cr + 1.0) / np.maximum(m_f + 1.0, 1e-3))
        l_b = np.log((cj + 1.0) / np.maximum(m_b + 1.0, 1e-3))
    d_f, d_b = cr - m_f, cj - m_b
    win = test.window
    out = bad.copy()
    kept = 0
    for k in range(1, n):
        x, y, w, h, _ = (int(v) for v in stats[k])
        by0, by1, bx0, bx1 = max(0, y - win), min(hs, y + h + win), max(0, x - win), min(ws, x + w + win)
        box = (slice(by0, by1), slice(bx0, bx1))
        comp = lab[y:y + h, x:x + w] == k
        inner = (slice(y - by0, y - by0 + h), slice(x - bx0, x - bx0 + w))
        pf, pb = (m_f[box], v_f[box]), (m_b[box], v_b[box])
        explained = False
        for axis in (0, 1):
            # one gain per column (axis 0: the strip runs along the column, above and below the
            # region) or per row (axis 1: left and right of it)
            length, width = (h, w) if axis == 0 else (w, h)
            reach = max(length, FLICKER_REACH)
            if axis == 0:
                parts = [(slice(max(0, y - reach), y), slice(bx0, bx1)), (slice(y, y + h), slice(bx0, bx1)),
                         (slice(y + h, min(hs, y + h + reach)), slice(bx0, bx1))]
            else:
                parts = [(slice(by0, by1), slice(max(0, x - reach), x)), (slice(by0, by1), slice(x, x + w)),
                         (slice(by0, by1), slice(x + w, min(ws, x + w + reach)))]
            # the gains read beyond the region only (its own lines left out); a region itself
            # much longer than wide (a whole band rejected) may also read its own lines
            choices = []
            sides = [np.median(l_f[q], axis=axis) for q in (parts[0], parts[2]) if l_f[q].shape[axis] > 0]
            # a band runs on at both ends, with the same gains: a moving thing's path beside it
            # (the strip along its motion) shows other gains on its two sides
            if len(sides) == 2 and float(np.median(np.abs(sides[0] - sides[1]).mean(axis=-1))) <= FLICKER_SIDES:
                choices.append(((parts[0], parts[2]), False))
                if length >= FLICKER_ELONGATION * width:
                    choices.append((tuple(parts), False))
            if length >= FLICKER_ELONGATION * width:      # and, as codes, on its own lines alone
                choices.append(((parts[1],), True))
            for use, additive in choices:
                rf, rb = (d_f, d_b) if additive else (l_f, l_b)
                lf = np.concatenate([rf[q] for q in use], axis=axis)
                if lf.shape[axis] < min(FLICKER_REACH // 2, length):
                    continue
                gf = np.median(lf, axis=axis)
                gb = np.median(np.concatenate([rb[q] for q in use], axis=axis), axis=axis)
                z2 = _band_z2(cr[box], cj[box], pf, pb, gf, gb, axis, additive)
                pooled = _box_mean(z2, win)[inner]
                if float(np.mean(pooled[comp] <= test.threshold)) >= FLICKER_EXPLAINED:
                    explained = True
                    break
            if explained:
                break
        if explained:
            out[y:y + h, x:x + w][comp] = False
            kept += int(comp.sum())
    return out, kept


def upsample_mask(mask: np.ndarray, step: int, h: int, w: int) -> np.ndarray:
    """A detection-grid uint8 mask (every ``step``-th pixel) at full resolution (H, W) bool."""
    import cv2

    if step > 1:
        hs, ws = mask.shape
        mask = cv2.resize(mask, (ws * step, hs * step), interpolation=cv2.INTER_NEAREST)[:h, :w]
        if mask.shape != (h, w):
            mask = np.pad(mask, ((0, h - mask.shape[0]), (0, w - mask.shape[1])), mode="edge")
    return mask.astype(bool)


def detect_ghosts(frames: np.ndarray, plan, ref: int, valid: np.ndarray | None, *,
                  threshold: float = GHOST_THRESHOLD, window: int = GHOST_WINDOW, dilate: int = GHOST_DILATE,
                  threads: int | None = None, out: np.ndarray | None = None) -> tuple[np.ndarray | None, dict[str, Any]]:
    """Per frame and pixel, whether the frame disagrees with frame ``ref`` (module docstring).

    Returns ``rejected`` ((N, H, W) bool, False for the reference and, to the detection grid's
    resolution, where ``valid`` already excludes the pixel; None when nothing is rejected) and
    the details per frame (rejected
    fraction, log offset ``b`` and unexplained spread ``s`` at a few codes). Raises
    :class:`StackError` when more than :data:`MAX_REJECTED` of the other frames' pixels disagree.
    The per-pixel statistic is :func:`derender.engine.intensity_mapping.mapping_z2`; the mapping
    tables and offsets are robust statistics of at most :data:`STAT_PIXELS` pixels. ``out``: an (N, H, W)
    bool plane to write ``rejected`` into (e.g. the previous round's, no longer needed): the
    grid's rejections are written to full resolution in place
    (:func:`derender.engine.ghost_kernels.upsample_into`), no temporary planes."""
    from derender.core.memory import populated_zeros
    from derender.engine.motion.ghost_kernels import upsample_into

    n, h, w = frames.shape[:3]
    test = ConsistencyTest(plan, frames[ref], ref, threshold, window, dilate)
    vsub = None if valid is None else valid[:, ::test.step, ::test.step] != 0
    if out is not None and out.shape == (n, h, w) and out.dtype == np.bool_:
        rejected = out
        rejected[ref] = False
    else:
        rejected = populated_zeros((n, h, w), dtype=bool)
    agreements: dict[int, FrameAgreement] = {}

    def one(j: int) -> tuple[int, int, dict]:
        ok = None if vsub is None else (vsub[j] & vsub[ref]).astype(np.uint8)
        grid_j = test.grid(frames[j])
        q, _, agreement = test.statistic(grid_j, j, ok, on_grid=True)
        bad = test.regions_grid(q, dilate=True)
        bad, flicker = flicker_bands(test, grid_j, agreement, bad)
        if vsub is not None:
            bad &= vsub[j]
        upsample_into(bad.view(np.uint8), test.step, rejected[j])   # counted on the grid
        agreements[j] = agreement
        return int(bad.sum()), bad.size, {"frame": j, "rejected": float(bad.mean()), "flicker": flicker / bad.size,
                                          **agreement.summary()}

    others = [j for j in range(n) if j != ref]
    results = dict(zip(others, map_frames(one, others, threads)))          # frames in threads, in order
    per_frame = [{"frame": j, "reference": True} if j == ref else results[j][2] for j in range(n)]
    total = sum(results[j][0] for j in others)
    counted = sum(results[j][1] for j in others)
    info = {"threshold": float(threshold), "window": 2 * window + 1, "detect_step": test.step, "frames": per_frame,
            "rejected": total / max(counted, 1), "agreements": agreements}
    if counted and total / counted > MAX_REJECTED:
        raise StackError(f"{100 * total / counted:.0f}% of the pixels disagree with the reference frame: "
                         "these images do not show one scene (or their exposure times are wrong)")
    return (rejected if total else None), info
