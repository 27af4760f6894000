"""Ward's (2003) median threshold bitmap (MTB) alignment: integer translations between exposures.

G. Ward, *Fast, robust image registration for compositing high dynamic range photographs
from handheld exposures*, J. Graphics Tools 8(2), 2003 (paper 1's ref. [26], Algorithm 1
step 2). Each image becomes an 8-bit grey image (:func:`to_grey8`, Ward's weights
``(54 R + 183 G + 19 B) / 256``), thresholded at its median: the *threshold bitmap*
``grey > median`` is exposure-invariant because the median splits every exposure at the
same scene radiance; the *exclusion bitmap* ``|grey - median| > exclusion`` leaves out the
noisy pixels near the threshold (:func:`median_threshold_bitmaps`). :func:`mtb_shift`
finds the shift on an image pyramid (2x2 box halving), coarse to fine: the nine offsets
around twice each coarser estimate are scored by XOR-ing the threshold bitmaps over the
pixels where neither exclusion bitmap is set.

Additions to Ward's method: thresholds at several percentiles common to both images'
usable range (:func:`common_percentiles`; a half-clipped exposure has no useful median),
a beam of survivors per level and a full-resolution refinement for nearly black or white
frames, a significance test against no shift, and the scoring on bit-packed rows (64
pixels per word, popcount); frames above :data:`MTB_PIXELS` are scored on bands of rows,
by the compiled :func:`derender.engine.kernels.mtb_band_counts` straight from the greys.
"""

from __future__ import annotations

import numpy as np

from derender.core.errors import InputError

__all__ = ["to_grey8", "grey8_codes", "median_threshold_bitmaps", "common_percentiles", "common_percentiles_hist",
           "MTB_PIXELS", "mtb_shift"]


def to_grey8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float image in [0, 1] (or uint8) -> uint8 grey, Ward's weights (54 R + 183 G + 19 B) / 256."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise InputError(f"expected an (H, W, 3) image, got {img.shape}")
    if img.dtype == np.uint8:
        return grey8_codes(img)
    h, w = img.shape[:2]
    out = np.empty((h, w), dtype=np.uint8)
    rows = max(1, (1 << 16) // max(w, 1))          # row blocks: small float32 temporaries
    for r0 in range(0, h, rows):
        blk = img[r0:r0 + rows]
        if blk.dtype != np.uint8:
            c = np.clip(blk.astype(np.float32), 0.0, 1.0)
            c *= np.float32(255.0)
            np.rint(c, out=c)
        else:
            c = blk.astype(np.float32)
        # integer codes: the weighted sum and /256 are exact in float32, as in float64
        g = np.float32(54.0) * c[..., 0] + np.float32(183.0) * c[..., 1] + np.float32(19.0) * c[..., 2]
        g /= np.float32(256.0)
        out[r0:r0 + rows] = np.clip(np.rint(g), 0, 255)
    return out


#: Ward's grey weights as the 1x3 matrix of ``cv2.transform``: 54/256 etc. are exact in
#: float32, so OpenCV's sum of products is exact and its rounding (half to even) is ``np.rint``.
_WARD_GREY = np.array([[54.0 / 256.0, 183.0 / 256.0, 19.0 / 256.0]], dtype=np.float32)


def grey8_codes(codes: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """:func:`to_grey8` of (H, W, 3) uint8 codes in one OpenCV pass (the same bytes: tested on
    all 2^24 colours), into ``out`` ((H, W) uint8) if given."""
    import cv2

    codes = np.asarray(codes)
    if codes.dtype != np.uint8 or codes.ndim != 3 or codes.shape[-1] != 3:
        raise InputError(f"expected (H, W, 3) uint8 codes, got {codes.dtype} {codes.shape}")
    if out is None or out.shape != codes.shape[:2] or out.dtype != np.uint8 or not out.flags.c_contiguous:
        out = np.empty(codes.shape[:2], dtype=np.uint8)
    cv2.transform(np.ascontiguousarray(codes), _WARD_GREY, dst=out.reshape(*out.shape, 1))
    return out


def _grey_threshold(g: np.ndarray, percentile: float, cum: np.ndarray | None = None) -> int:
    """``int(np.median(g))`` (percentile 50) or ``np.percentile(g, q, method="lower")`` of a
    uint8 image, from its cumulative histogram ``cum`` (computed if None; no sort, same value)."""
    if cum is None:
        cum = np.cumsum(np.bincount(g.ravel(), minlength=256))
    n = int(cum[-1])

    def kth(k: int) -> int:            # k-th smallest value (0-based)
        return int(np.searchsorted(cum, k, side="right"))

    if percentile == 50.0:
        return kth(n // 2) if n % 2 else int((kth(n // 2 - 1) + kth(n // 2)) / 2.0)
    q = np.true_divide(float(percentile), 100)
    return kth(int(np.floor(q * (n - 1))))


def median_threshold_bitmaps(grey: np.ndarray, exclusion: int = 4, percentile: float = 50.0,
                             _cum: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ward's threshold bitmap ``grey > median`` and exclusion bitmap ``|grey - median| > exclusion``.

    ``percentile`` other than 50 thresholds at that percentile instead of the median
    (Ward's suggestion for very dark or very bright exposures)."""
    grey = np.asarray(grey)
    if grey.dtype == np.uint8 and grey.size:
        med = _grey_threshold(grey, percentile, _cum)
        lo, hi = med - exclusion, med + exclusion          # |g - med| > exclusion on uint8 without a widening copy
        return grey > med, (grey < lo) | (grey > hi) if lo >= 0 else grey > hi
    g = np.asarray(grey, dtype=np.int16)
    med = int(np.median(g)) if percentile == 50.0 else int(np.percentile(g, percentile, method="lower"))
    return g > med, np.abs(g - med) > exclusion


def common_percentiles(grey_a: np.ndarray, grey_b: np.ndarray, low: int = 5, high: int = 250,
                       count: int = 5) -> tuple[float, ...]:
    """``count`` percentiles spread over the range in which both grey images are inside
    (low, high) (the intersection of their well-exposed percentile ranges); ``(50,)``
    (Ward's median) when that range is empty."""
    def fracs(g: np.ndarray) -> tuple[float, float]:
        if g.dtype == np.uint8 and g.size and int(low) == low and int(high) == high and 0 <= low <= high <= 255:
            hist = np.bincount(g.ravel(), minlength=256)
            return float(hist[:int(low) + 1].sum()) / g.size, float(hist[int(high):].sum()) / g.size
        return float(np.mean(g <= low)), float(np.mean(g >= high))

    (la, ha), (lb, hb) = fracs(np.asarray(grey_a)), fracs(np.asarray(grey_b))
    lo = 100.0 * max(la, lb)
    hi = 100.0 * (1.0 - max(ha, hb))
    if hi - lo < 2.0:
        return (50.0,)
    return tuple(float(q) for q in np.linspace(lo, hi, int(count) + 2)[1:-1])


def common_percentiles_hist(hist_a: np.ndarray, hist_b: np.ndarray, low: int = 5, high: int = 250,
                            count: int = 5) -> tuple[float, ...]:
    """:func:`common_percentiles` from the two grey histograms (same result)."""
    def fracs(hist: np.ndarray) -> tuple[float, float]:
        tot = int(hist.sum())
        return float(hist[:low + 1].sum()) / tot, float(hist[high:].sum()) / tot

    (la, ha), (lb, hb) = fracs(hist_a), fracs(hist_b)
    lo = 100.0 * max(la, lb)
    hi = 100.0 * (1.0 - max(ha, hb))
    if hi - lo < 2.0:
        return (50.0,)
    return tuple(float(q) for q in np.linspace(lo, hi, int(count) + 2)[1:-1])


def _shift_bool(b: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``out[y, x] = b[y + dy, x + dx]`` with False outside."""
    h, w = b.shape
    out = np.zeros_like(b)
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    if abs(dy) < h and abs(dx) < w:
        out[yd, xd] = b[ys, xs]
    return out


def _half(grey: np.ndarray) -> np.ndarray:
    """Next MTB pyramid level: 2x2 box average ``(a + b + c + d + 2) // 4`` (odd edge dropped)."""
    grey = np.asarray(grey)
    h, w = grey.shape[0] // 2 * 2, grey.shape[1] // 2 * 2
    if grey.dtype == np.uint8 and h >= 2 and w >= 2:
        import cv2

        # OpenCV's area average for an exact factor 2 on uint8 is (a + b + c + d + 2) >> 2 (tested)
        return cv2.resize(np.ascontiguousarray(grey[:h, :w]), (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    g = grey[:h, :w].astype(np.uint16)
    return ((g[0::2, 0::2] + g[1::2, 0::2] + g[0::2, 1::2] + g[1::2, 1::2] + 2) // 4).astype(np.uint8)


def _bitmap_pairs(a: np.ndarray, b: np.ndarray, exclusion: int, percentiles, lazy: bool = False) -> list:
    """[(bitmaps of a, bitmaps of b)] per percentile; uint8 histograms computed once.

    Images above :data:`MTB_PIXELS` get lazy bitmaps (:class:`_RowBitmaps`: threshold
    now, bits only for the rows that are scored; thresholds from the histogram of every
    k-th row), and so do smaller uint8 images with ``lazy`` (the compiled scorer then
    counts them straight from the greys; same counts)."""
    h, w = a.shape
    step = -(-h * w // MTB_PIXELS)
    if (step > 1 or lazy) and h >= 64 and a.dtype == np.uint8 and b.dtype == np.uint8:
        ca = np.cumsum(np.bincount(a[::step].ravel(), minlength=256))
        cb = np.cumsum(np.bincount(b[::step].ravel(), minlength=256))
        return [(_RowBitmaps(a, _grey_threshold(a, q, ca), exclusion),
                 _RowBitmaps(b, _grey_threshold(b, q, cb), exclusion)) for q in percentiles]
    ca = np.cumsum(np.bincount(a.ravel(), minlength=256)) if a.dtype == np.uint8 and a.size else None
    cb = np.cumsum(np.bincount(b.ravel(), minlength=256)) if b.dtype == np.uint8 and b.size else None
    return [(median_threshold_bitmaps(a, exclusion, q, ca), median_threshold_bitmaps(b, exclusion, q, cb))
            for q in percentiles]


class _RowBitmaps:
    """Threshold and exclusion bitmaps of a uint8 grey image, computed for requested rows only."""

    def __init__(self, grey: np.ndarray, med: int, exclusion: int):
        self.grey, self.med, self.exclusion = grey, int(med), int(exclusion)
        self.shape = grey.shape

    def rows(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = self.grey[idx]
        lo, hi = self.med - self.exclusion, self.med + self.exclusion
        return g > self.med, ((g < lo) | (g > hi)) if lo >= 0 else g > hi


#: MTB scores each candidate shift on at most about this many pixels per pyramid level:
#: larger levels are scored on evenly spaced bands of rows (see :func:`_mtb_counts`).
MTB_PIXELS = 1 << 19


def _pack(b: np.ndarray) -> np.ndarray:
    """Bool (..., W) -> rows of 64-bit words (zero padded), 64 pixels per word."""
    p = np.packbits(b, axis=-1)
    pad = -p.shape[-1] % 8
    if pad:
        p = np.concatenate([p, np.zeros(p.shape[:-1] + (pad,), np.uint8)], axis=-1)
    return p.view(np.uint64)


def _mtb_counts(bitmaps: list, cands: list[tuple[int, int]],
                max_pixels: int | None = None) -> list[list[tuple[int, int]]]:
    """For every candidate shift and every bitmap pair: (differing threshold bits, pixels
    outside both exclusion bitmaps) over the overlap, as :func:`_shift_bool` would count them.

    Bit-packed along rows: one packing of the image's bitmaps per horizontal shift, the
    vertical shift is a row offset of the packed arrays (64 pixels per word, popcount).
    Images larger than ``max_pixels`` (default :data:`MTB_PIXELS`) are scored on every
    k-th band of rows of the reference (same bands for every candidate; the counts of a
    row subset rank shifts like the full counts)."""
    first = bitmaps[0][0]
    h, w = first.shape if isinstance(first, _RowBitmaps) else first[0].shape
    budget = MTB_PIXELS if max_pixels is None else int(max_pixels)
    step = -(-h * w // max(budget, 1))
    if (step > 1 and h >= 64) or isinstance(first, _RowBitmaps):
        return _mtb_counts_bands(bitmaps, cands, step)
    out = [[(0, 0)] * len(bitmaps) for _ in cands]
    pack = _pack

    for i, ((tb_a, eb_a), (tb_b, eb_b)) in enumerate(bitmaps):
        ta, ea = pack(tb_a), pack(eb_a)
        for sx in sorted({c[1] for c in cands}):
            tb, eb = pack(_shift_bool(tb_b, 0, sx)), pack(_shift_bool(eb_b, 0, sx))
            for ci, (sy, sx2) in enumerate(cands):
                if sx2 != sx:
                    continue
                if abs(sy) >= h:
                    out[ci][i] = (0, 0)
                    continue
                ya, yb = (slice(0, h - sy), slice(sy, h)) if sy >= 0 else (slice(-sy, h), slice(0, h + sy))
                both = ea[ya] & eb[yb]
                nb = int(np.bitwise_count(both).sum(dtype=np.int64))
                nd = int(np.bitwise_count((ta[ya] ^ tb[yb]) & both).sum(dtype=np.int64))
                out[ci][i] = (nd, nb)
    return out


def _mtb_counts_bands(bitmaps: list, cands: list[tuple[int, int]], step: int) -> list[list[tuple[int, int]]]:
    """:func:`_mtb_counts` on every ``step``-th band of reference rows (bands of at least
    32 rows, 4x the largest vertical shift): per band the image rows it meets under all
    candidate shifts are gathered and packed once per horizontal shift."""
    first = bitmaps[0][0]
    h, w = first.shape if isinstance(first, _RowBitmaps) else first[0].shape
    m = min(max(abs(c[0]) for c in cands), h)
    band = max(32, 4 * m)
    starts = np.arange(0, h, band)[::step]
    rows_a = starts[:, None] + np.arange(band)[None, :]                   # (nb, band), may pass h
    rows_b = starts[:, None] + np.arange(-m, band + m)[None, :]           # (nb, band + 2m)
    if all(isinstance(a, _RowBitmaps) and isinstance(b, _RowBitmaps) for a, b in bitmaps) \
            and max(abs(c[0]) for c in cands) <= m:
        return _mtb_counts_compiled(bitmaps, cands, starts, band, m)
    in_a, in_b = rows_a < h, (rows_b >= 0) & (rows_b < h)
    ra, rb = np.clip(rows_a, 0, h - 1), np.clip(rows_b, 0, h - 1)
    out = [[(0, 0)] * len(bitmaps) for _ in cands]

    def rows(bm, idx):
        if isinstance(bm, _RowBitmaps):
            return bm.rows(idx)
        return bm[0][idx], bm[1][idx]

    for i, (bm_a, bm_b) in enumerate(bitmaps):
        tba, eba = rows(bm_a, ra)
        ta = _pack(tba)
        ea = _pack(eba & in_a[..., None])                 # rows past the image count nowhere
        tbb, ebb = rows(bm_b, rb)
        for sx in sorted({c[1] for c in cands}):
            tbg = _shift_bool(tbb.reshape(-1, w), 0, sx).reshape(rb.shape + (w,))
            ebg = _shift_bool(ebb.reshape(-1, w), 0, sx).reshape(rb.shape + (w,)) & in_b[..., None]
            tb, eb = _pack(tbg), _pack(ebg)
            for ci, (sy, sx2) in enumerate(cands):
                if sx2 != sx:
                    continue
                sl = slice(m + sy, m + sy + band)
                both = ea & eb[:, sl]
                nb = int(np.bitwise_count(both).sum(dtype=np.int64))
                nd = int(np.bitwise_count((ta ^ tb[:, sl]) & both).sum(dtype=np.int64))
                out[ci][i] = (nd, nb)
    return out


def _mtb_counts_compiled(bitmaps: list, cands: list[tuple[int, int]], starts: np.ndarray, band: int,
                         margin: int) -> list[list[tuple[int, int]]]:
    """:func:`_mtb_counts_bands` straight from the greys of :class:`_RowBitmaps` (the same
    counts), by :func:`derender.engine.kernels.mtb_band_counts`."""
    from derender.engine.kernels import mtb_band_counts

    cy = np.array([c[0] for c in cands], dtype=np.int64)
    cx = np.array([c[1] for c in cands], dtype=np.int64)
    out = [[(0, 0)] * len(bitmaps) for _ in cands]
    for i, (bm_a, bm_b) in enumerate(bitmaps):
        counts = np.zeros((len(cands), 2), dtype=np.int64)
        mtb_band_counts(np.ascontiguousarray(bm_a.grey, dtype=np.uint8),
                        np.ascontiguousarray(bm_b.grey, dtype=np.uint8), int(bm_a.med), int(bm_b.med),
                        int(bm_a.exclusion), np.asarray(starts, dtype=np.int64), int(band), int(margin), cy, cx,
                        counts)
        for ci in range(len(cands)):
            out[ci][i] = (int(counts[ci, 0]), int(counts[ci, 1]))
    return out


def _mtb_errors(bitmaps: list, cands: list[tuple[int, int]]) -> list[float]:
    """Summed fraction of differing threshold bits (over the overlap of both exclusion
    bitmaps) for every candidate shift."""
    return [sum(nd / max(nb, 1) for nd, nb in row) for row in _mtb_counts(bitmaps, cands)]


def mtb_shift(reference_grey: np.ndarray, image_grey: np.ndarray, max_bits: int = 6,
              exclusion: int = 4, percentiles: tuple[float, ...] = (50.0,), beam: int = 3,
              refine: int = 2) -> tuple[int, int]:
    """Integer shift ``(dy, dx)`` of ``image_grey`` against ``reference_grey`` by Ward's MTB.

    The content of the reference at ``(y, x)`` is found in the image at ``(y + dy, x + dx)``;
    ``|dy|, |dx| < 2 ** max_bits``. On an image pyramid (coarse to fine) the nine offsets
    around twice each coarser estimate are scored by the fraction of differing threshold
    bits among the overlapping pixels where neither exclusion bitmap is set (Ward counts
    them; the fraction does not favour shifts that push pixels out of the frame), summed
    over the threshold ``percentiles`` (Ward: the median only). Two additions for nearly
    black or white frames, whose bitmaps hold few edges: the best ``beam`` offsets (Ward:
    1) survive each level, and at full resolution every offset within ``refine`` pixels
    of the survivors is scored. Ties keep the smaller offset, and a non-zero result must
    remove significantly many differing bits compared with no shift (more than 3 Poisson
    standard deviations of the counts), else the frame stays put.
    """
    ref = np.asarray(reference_grey)
    img = np.asarray(image_grey)
    if ref.shape != img.shape or ref.ndim != 2:
        raise InputError(f"MTB needs two grey images of equal shape, got {ref.shape} and {img.shape}")
    levels = max(0, int(max_bits) - 1)
    while levels > 0 and min(ref.shape) >> levels < 8:
        levels -= 1
    pyr = [(ref, img)]
    for _ in range(levels):
        a, b = pyr[-1]
        pyr.append((_half(a), _half(b)))
    survivors = [(0, 0)]
    # frames large enough for the compiled scorer score their coarse levels with it too
    # (24 MP bracket: MTB 0.67-0.71 -> 0.40-0.57 s on one thread, 0.65 -> 0.38 s on two)
    lazy = ref.size > MTB_PIXELS
    for lvl, (a, b) in enumerate(reversed(pyr)):
        finest = lvl == len(pyr) - 1
        bitmaps = _bitmap_pairs(a, b, exclusion, percentiles, lazy=lazy)
        reach = max(1, int(refine)) if finest else 1
        cands = sorted({(2 * sy + ddy, 2 * sx + ddx) if lvl > 0 else (sy + ddy, sx + ddx)
                        for sy, sx in survivors
                        for ddy in range(-reach, reach + 1) for ddx in range(-reach, reach + 1)})
        errs = _mtb_errors(bitmaps, cands)
        order = sorted(range(len(cands)), key=lambda i: (round(errs[i], 12), abs(cands[i][0]) + abs(cands[i][1]),
                                                         cands[i]))
        survivors = [cands[i] for i in order[:max(1, int(beam))]]
    dy, dx = survivors[0]
    if (dy, dx) != (0, 0):
        # keep the frame where it is unless the shift removes significantly many differing
        # bits (counts; 3 Poisson sigmas): nearly empty bitmaps must not move a tripod frame
        bitmaps = _bitmap_pairs(ref, img, exclusion, percentiles)
        c0, c1 = _mtb_counts(bitmaps, [(0, 0), (dy, dx)])
        n0, n1 = sum(nd for nd, _ in c0), sum(nd for nd, _ in c1)
        if n0 - n1 < 3.0 * np.sqrt(n0 + n1 + 1.0):
            dy, dx = 0, 0
    return int(dy), int(dx)
