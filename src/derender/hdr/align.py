"""Registration of an exposure bracket (paper 1, Algorithm 1 step 2).

* ``"mtb"`` (default): Ward's median threshold bitmap alignment (Ward 2003, *Fast,
  robust image registration for compositing high dynamic range photographs from
  handheld exposures*, J. Graphics Tools 8(2)): integer translations found on an image
  pyramid by XOR-ing median threshold bitmaps, with an exclusion bitmap that ignores
  pixels within ``exclusion`` grey levels of the median. Exposure-invariant because the
  median splits every exposure at the same scene radiance. In a bracket one image of a
  pair is often more than half clipped (its median is 255 or 0), so :func:`align_images`
  thresholds both bitmaps at several common percentiles inside both images' usable
  range (:func:`common_percentiles`; one percentile still splits both images at one
  radiance) and sums the bit errors.
* ``"homography"``: ORB features (on histogram-equalised grey images, so that different
  exposures match), Hamming matching with Lowe's ratio test and a seeded RANSAC on
  4-point homographies, refined by least squares on the inliers (handheld brackets).
  A pair with too few matches (a nearly black or white exposure) falls back to MTB
  (recorded in ``info["pairs"]``).
* ``"none"``: identity.

Every image is registered to its neighbour towards the reference (neighbouring
exposures look most alike) and the transforms are chained. ``transforms[j]`` maps
reference pixel coordinates ``(x, y, 1)`` to coordinates in image ``j``; the aligned image
samples image ``j`` there. Pixels that fall outside image ``j`` are filled with the
nearest border pixel (never NaN) and marked ``False`` in ``valid`` so that later fits and
weights leave them out.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from derender.core.errors import InputError, StackError

__all__ = [
    "ALIGN_METHODS",
    "Alignment",
    "to_grey8",
    "grey8_codes",
    "median_threshold_bitmaps",
    "common_percentiles",
    "MTB_PIXELS",
    "mtb_shift",
    "shift_into",
    "shift_image",
    "estimate_homography",
    "warp_image",
    "align_images",
    "transforms_to_shifts",
    "chain_transforms",
]


ALIGN_METHODS = ("none", "mtb", "homography")


@dataclass
class Alignment:
    """Result of :func:`align_images`.

    images : (N, H, W, 3) float32 aligned images (borders filled by replication).
    valid : (N, H, W) bool, True where the aligned pixel comes from inside image j.
    transforms : (N, 3, 3) float64, reference pixel coords -> image j pixel coords.
    shifts : (N, 2) int (dy, dx) for translation methods (image j content sits at
        reference position + (dy, dx)), else None.
    """

    images: np.ndarray
    valid: np.ndarray
    transforms: np.ndarray
    method: str
    reference: int
    shifts: np.ndarray | None = None
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- MTB
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


def _common_percentiles_hist(hist_a: np.ndarray, hist_b: np.ndarray, low: int = 5, high: int = 250,
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
    counts), by :func:`derender.kernels.mtb_band_counts`."""
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


def shift_into(out: np.ndarray, img: np.ndarray, dy: int, dx: int) -> None:
    """``out[y, x] = img[clip(y + dy), clip(x + dx)]`` by slices (no index arrays, one copy)."""
    h, w = img.shape[:2]
    dy, dx = int(np.clip(dy, -h + 1, h - 1)), int(np.clip(dx, -w + 1, w - 1))
    y0, y1 = max(0, -dy), min(h, h - dy)          # rows of out whose source row is inside
    x0, x1 = max(0, -dx), min(w, w - dx)
    out[y0:y1, x0:x1] = img[y0 + dy:y1 + dy, x0 + dx:x1 + dx]
    if x0 > 0:
        out[y0:y1, :x0] = out[y0:y1, x0:x0 + 1]
    if x1 < w:
        out[y0:y1, x1:] = out[y0:y1, x1 - 1:x1]
    if y0 > 0:
        out[:y0] = out[y0:y0 + 1]
    if y1 < h:
        out[y1:] = out[y1 - 1:y1]


def shift_image(image: np.ndarray, dy: int, dx: int) -> tuple[np.ndarray, np.ndarray]:
    """``out[y, x] = image[y + dy, x + dx]`` with border replication, and the (H, W) validity mask."""
    img = np.asarray(image)
    h, w = img.shape[:2]
    out = np.empty_like(img)
    shift_into(out, img, dy, dx)
    return out, _shift_valid(h, w, dy, dx)


def _shift_valid(h: int, w: int, dy: int, dx: int) -> np.ndarray:
    ys = np.arange(h) + int(dy)
    xs = np.arange(w) + int(dx)
    return ((ys >= 0) & (ys < h))[:, None] & ((xs >= 0) & (xs < w))[None, :]


# --------------------------------------------------------------------------- homography
def _features(grey: np.ndarray, n_features: int):
    import cv2

    eq = cv2.equalizeHist(grey)
    orb = cv2.ORB_create(nfeatures=int(n_features))
    kp, des = orb.detectAndCompute(eq, None)
    pts = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
    return pts, des


def estimate_homography(reference_grey: np.ndarray, image_grey: np.ndarray, seed: int = 0,
                        n_features: int = 2000, ratio: float = 0.75, threshold: float = 2.0,
                        n_iter: int = 2000, min_coverage: float = 0.5) -> tuple[np.ndarray, int]:
    """Homography mapping reference pixel coords to image coords (ORB + ratio test + seeded RANSAC).

    When the RANSAC inliers span less than ``min_coverage`` of the image width or height
    the homography is not determined away from them, and a pure translation (median
    displacement of the inliers) is returned instead.
    Returns ``(H, n_inliers)``. Raises :class:`StackError` when fewer than 8 consistent
    matches exist (too little texture or too different exposures).
    """
    import cv2

    pr, dr = _features(np.asarray(reference_grey), n_features)
    pi, di = _features(np.asarray(image_grey), n_features)
    if dr is None or di is None or len(pr) < 4 or len(pi) < 4:
        raise StackError("homography alignment found too few features; use --align mtb or none")
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = matcher.knnMatch(dr, di, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if len(good) < 8:
        raise StackError(f"homography alignment found only {len(good)} feature matches; use --align mtb or none")
    src = np.array([pr[m.queryIdx] for m in good])
    dst = np.array([pi[m.trainIdx] for m in good])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    src_h = np.c_[src, np.ones(len(src))]
    best_inl = None
    for _ in range(int(n_iter)):
        idx = rng.choice(len(src), size=4, replace=False)
        try:
            hm = cv2.getPerspectiveTransform(src[idx].astype(np.float32), dst[idx].astype(np.float32))
        except cv2.error:
            continue
        if not np.all(np.isfinite(hm)):
            continue
        p = src_h @ hm.T
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = p[:, :2] / p[:, 2:3]
        err = np.linalg.norm(proj - dst, axis=1)
        inl = np.isfinite(err) & (err < threshold)
        if best_inl is None or inl.sum() > best_inl.sum():
            best_inl = inl
    if best_inl is None or best_inl.sum() < 8:
        raise StackError("homography alignment: RANSAC found no consistent transform; use --align mtb or none")
    s_in, d_in = src[best_inl], dst[best_inl]
    h, w = np.asarray(reference_grey).shape
    span = np.ptp(s_in, axis=0)
    if span[0] < min_coverage * w or span[1] < min_coverage * h:
        # inliers in one corner only: a homography would extrapolate wildly; translate instead
        t = np.median(d_in - s_in, axis=0)
        return np.array([[1.0, 0.0, t[0]], [0.0, 1.0, t[1]], [0.0, 0.0, 1.0]]), int(best_inl.sum())
    hm, _ = cv2.findHomography(s_in, d_in, 0)
    if hm is None or not np.all(np.isfinite(hm)):
        raise StackError("homography alignment: least-squares refit failed; use --align mtb or none")
    return hm / hm[2, 2], int(best_inl.sum())


def warp_image(image: np.ndarray, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``image`` at ``transform @ (x, y, 1)`` for every reference pixel (bilinear,
    border replication); returns the warped float32 image and the (H, W) validity mask."""
    import cv2

    img = np.asarray(image, dtype=np.float32)
    h, w = img.shape[:2]
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    out = cv2.warpPerspective(img, np.asarray(transform, dtype=np.float64), (w, h), flags=flags,
                              borderMode=cv2.BORDER_REPLICATE)
    ones = np.ones((h, w), dtype=np.float32)
    cover = cv2.warpPerspective(ones, np.asarray(transform, dtype=np.float64), (w, h), flags=flags,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.ascontiguousarray(out, dtype=np.float32), cover > 0.999


# --------------------------------------------------------------------------- driver
def align_images(images: np.ndarray, method: str = "mtb", reference: int | None = None, seed: int = 0,
                 max_bits: int = 6, exclusion: int = 4) -> Alignment:
    """Register every image of a bracket to ``reference`` (default: the middle image).

    Neighbouring exposures are registered pairwise and the transforms chained towards
    the reference. Returns an :class:`Alignment` (aligned images, validity masks,
    transforms; integer ``shifts`` for ``"mtb"``/``"none"``).
    """
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"images must have shape (N, H, W, 3), got {arr.shape}")
    n, h, w, _ = arr.shape
    if method not in ALIGN_METHODS:
        raise InputError(f"unknown alignment {method!r}; use one of {', '.join(ALIGN_METHODS)}")
    ref = n // 2 if reference is None else int(reference)
    if not 0 <= ref < n:
        raise InputError(f"reference image {reference} is out of range 0..{n - 1}")
    eye = np.eye(3)
    if method == "none":
        return Alignment(images=np.ascontiguousarray(arr, dtype=np.float32), valid=np.ones((n, h, w), bool),
                         transforms=np.repeat(eye[None], n, axis=0), method=method, reference=ref,
                         shifts=np.zeros((n, 2), dtype=int))
    grey = [to_grey8(arr[j]) for j in range(n)]
    transforms, info = chain_transforms(grey, method, ref, seed=seed, max_bits=max_bits, exclusion=exclusion)
    out = np.empty((n, h, w, 3), dtype=np.float32)
    valid = np.empty((n, h, w), dtype=bool)
    shifts = None
    if method == "mtb":
        shifts = transforms_to_shifts(transforms)
        for j in range(n):              # written in place: no per-frame temporaries
            src = arr[j] if arr.dtype == np.float32 else arr[j].astype(np.float32)
            shift_into(out[j], src, shifts[j, 0], shifts[j, 1])
            valid[j] = _shift_valid(h, w, shifts[j, 0], shifts[j, 1])
    else:
        for j in range(n):
            if j == ref:
                out[j], valid[j] = arr[j], True
            else:
                out[j], valid[j] = warp_image(arr[j], transforms[j])
    return Alignment(images=out, valid=valid, transforms=transforms, method=method, reference=ref,
                     shifts=shifts, info=info)


def transforms_to_shifts(transforms: np.ndarray) -> np.ndarray:
    """(N, 3, 3) translation transforms -> (N, 2) integer shifts (dy, dx)."""
    return np.rint(np.asarray(transforms)[:, [1, 0], 2]).astype(int)


def chain_transforms(grey: Sequence[np.ndarray], method: str, ref: int, seed: int = 0, max_bits: int = 6,
                     exclusion: int = 4, threads: int | None = None) -> tuple[np.ndarray, dict]:
    """Pairwise registration of neighbouring uint8 grey frames (:func:`to_grey8`), chained
    towards ``ref``: (N, 3, 3) transforms (reference pixel coords -> image j coords) and
    the per-pair details. ``method`` is ``"mtb"`` or ``"homography"`` (falls back to MTB
    for frames too dark or bright for features). Pairs are registered in ``threads``
    threads (default: the usable cores) when the frames are large."""
    n = len(grey)
    h, w = grey[0].shape
    eye = np.eye(3)
    # grey histograms once per image (every k-th row above MTB_PIXELS) for common_percentiles
    hstep = max(1, -(-h * w // MTB_PIXELS))
    hists = [np.bincount(g[::hstep].ravel(), minlength=256) for g in grey]
    # pairwise transforms T_(a <- b): coords in image a (nearer the reference) -> coords in b
    transforms = np.repeat(eye[None], n, axis=0)
    info: dict = {"pairs": []}
    order = list(range(ref - 1, -1, -1)) + list(range(ref + 1, n))

    def translation(a: int, j: int) -> tuple[np.ndarray, list, list]:
        qs = _common_percentiles_hist(hists[a], hists[j])
        dy, dx = mtb_shift(grey[a], grey[j], max_bits=max_bits, exclusion=exclusion, percentiles=qs)
        return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]), [dy, dx], list(qs)

    def register(j: int) -> tuple[np.ndarray, dict]:
        """Transform T_(a <- j) of frame j against its neighbour a nearer the reference."""
        a = j + 1 if j < ref else j - 1
        if method == "mtb":
            t, shift, qs = translation(a, j)
            return t, {"from": a, "to": j, "shift": shift, "percentiles": qs}
        try:
            t, n_inl = estimate_homography(grey[a], grey[j], seed=seed + j)
            return t, {"from": a, "to": j, "inliers": n_inl}
        except StackError as exc:   # too dark/bright for features: translation instead
            t, shift, _ = translation(a, j)
            return t, {"from": a, "to": j, "fallback": "mtb", "shift": shift, "reason": str(exc)}

    # the pairs are independent (NumPy releases the GIL on the bitmaps): register them in
    # threads, then chain in order
    from concurrent.futures import ThreadPoolExecutor

    if threads is None:
        threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = min(len(order), max(1, int(threads)))
    if workers > 1 and h * w >= MTB_PIXELS:
        with ThreadPoolExecutor(workers, thread_name_prefix="derender-align") as ex:
            found = list(ex.map(register, order))
    else:
        found = [register(j) for j in order]
    for j, (t, pair) in zip(order, found):
        a = pair["from"]
        info["pairs"].append(pair)
        transforms[j] = t @ transforms[a]
    return transforms, info
