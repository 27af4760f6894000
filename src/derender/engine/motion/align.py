"""Registration of an exposure bracket (paper 1, Sec. 3.1, Algorithm 1 step 2).

The paper registers the images with Ward's (2003) median threshold bitmaps (its ref.
[26]) "to get accurate one-to-one pixel correspondences" for the fits of eq. 9. Methods
(:func:`align_images`):

* ``"translation"`` (default): Ward's median threshold bitmap alignment, integer translations
  (:mod:`derender.engine.motion.ward2003`, :func:`~derender.engine.motion.ward2003.mtb_shift`). In a bracket
  one image of a pair is often more than half clipped (its median is 255 or 0), so the
  bitmaps are thresholded at several common percentiles inside both images' usable range
  (:func:`~derender.engine.motion.ward2003.common_percentiles`; one percentile still splits both
  images at one radiance) and the bit errors summed.
* ``"homography"``: ORB features (on histogram-equalised grey images, so that different
  exposures match), Hamming matching with Lowe's ratio test and a seeded RANSAC on
  4-point homographies, refined by least squares on the inliers (handheld brackets;
  :func:`estimate_homography`, :func:`warp_image`). A pair with too few matches (a nearly
  black or white exposure) falls back to MTB (recorded in ``info["pairs"]``).
* ``"flow"``: ``"translation"``, then each frame's dense residual flow against its neighbour
  nearer the reference (:func:`residual_flow`: OpenCV's DIS optical flow on the frames brought
  to one tone scale, trusted where both are well exposed, textured and the flows both ways
  agree, filled and pulled to zero elsewhere), applied by bilinear resampling
  (:func:`flow_warp`). For handheld brackets with parallax, where no single transform
  registers every depth: on the iPhone bracket of ``shared/data`` the two shortest frames'
  skyline is 2-8 px off the reference after the translation that registers the room in front
  of the window (measured by :func:`block_displacements` on 64 px tiles: 37 of 201 and 41 of
  177 tiles more than 1 px off), 1 of 192 and 1 of 179 after the flow
  (``tests/hdr/test_real_motion.py`` asks for at most a quarter). A frame keeps its integer translation (exact codes: a
  tripod bracket is left as it was) unless a well-correlated tile is more than
  :data:`FLOW_GATE_PX` off and the flow moves at least 1 % of the pixels by more than
  :data:`FLOW_MIN_PX`.
* ``"none"``: identity.

Every image is registered to its neighbour towards the reference (neighbouring
exposures look most alike) and the transforms are chained (:func:`chain_transforms`).
``transforms[j]`` maps reference pixel coordinates ``(x, y, 1)`` to coordinates in image
``j``; the aligned image samples image ``j`` there (:func:`shift_into` for integer shifts,
:func:`warp_image` otherwise). Pixels that fall outside image ``j`` are filled with the
nearest border pixel (never NaN) and marked ``False`` in ``valid`` so that later fits and
weights leave them out.
"""

from __future__ import annotations

import hashlib
import os
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from derender.core.errors import InputError, StackError
from derender.engine.motion import ward2003
from derender.engine.motion.ward2003 import common_percentiles_hist, mtb_shift, to_grey8

__all__ = [
    "ALIGNMENTS",
    "Alignment",
    "shift_into",
    "shift_valid",
    "shift_image",
    "estimate_homography",
    "warp_image",
    "align_images",
    "transforms_to_shifts",
    "chain_transforms",
    "exposure_lut",
    "block_displacements",
    "residual_flow",
    "flow_from_greys",
    "full_resolution_flow",
    "FLOW_CACHE_BYTES",
    "flow_warp",
    "FLOW_SIDE",
    "FLOW_CODES",
    "FLOW_MIN_GRADIENT",
    "FLOW_CONSISTENCY",
    "FLOW_SIGMA",
    "FLOW_PRIOR",
    "FLOW_MIN_PX",
    "FLOW_GATE_PX",
    "FLOW_MIN_PEAK",
    "FLOW_MAX_PX",
]


#: Registration methods of :func:`align_images`.
ALIGNMENTS = ("none", "translation", "homography", "flow")


@dataclass
class Alignment:
    """Result of :func:`align_images`.

    Attributes
    ----------
    images : numpy.ndarray
        (N, H, W, 3) float32 aligned images (borders filled by replication).
    valid : numpy.ndarray
        (N, H, W) bool, True where the aligned pixel comes from inside image j.
    transforms : numpy.ndarray
        (N, 3, 3) float64, reference pixel coords -> image j pixel coords.
    shifts : numpy.ndarray or None
        (N, 2) int (dy, dx) for translation methods (image j content sits at reference
        position + (dy, dx)), else None.
    """

    images: np.ndarray
    valid: np.ndarray
    transforms: np.ndarray
    method: str
    reference: int
    shifts: np.ndarray | None = None
    info: dict = field(default_factory=dict)


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
    return out, shift_valid(h, w, dy, dx)


def shift_valid(h: int, w: int, dy: int, dx: int) -> np.ndarray:
    """(H, W) bool: True where a frame read at ``(y + dy, x + dx)`` (:func:`shift_into`) is inside it."""
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


#: Longest side (pixels) of the grey images the residual flow (:func:`residual_flow`) is
#: computed on; larger frames are reduced by a power of two (area average).
FLOW_SIDE = 1632

#: The residual flow is trusted where both frames' grey codes are within
#: ``FLOW_CODES`` (neither dark nor clipped) ...
FLOW_CODES = (16, 250)

#: ... the reference's gradient magnitude (codes per working pixel, smoothed) is at least this ...
FLOW_MIN_GRADIENT = 6.0

#: ... and the forward and backward flows agree within this many working pixels.
FLOW_CONSISTENCY = 0.5

#: Where the flow is not trusted it is filled from the trusted flow around (normalised
#: convolution, Gaussian of this sigma in working pixels), pulled to zero (the translation)
#: where little trusted flow is near: ``sum(g w f) / (sum(g w) + FLOW_PRIOR)``.
FLOW_SIGMA = 24.0

#: Weight of the zero-flow prior in that fill (a fraction of a full Gaussian's support).
FLOW_PRIOR = 0.05

#: A frame is warped by its residual flow only when the flow moves at least 1 % of the pixels
#: by more than this many (full-resolution) pixels; otherwise it keeps its integer translation
#: (exact codes: a tripod bracket is left as it was).
FLOW_MIN_PX = 0.5

#: ... and when the residual is measured independently of the flow: one of the 32-pixel tiles
#: (working resolution) whose phase correlation peaks at :data:`FLOW_MIN_PEAK` or more is
#: displaced by more than this many full-resolution pixels (:func:`block_displacements`: a few
#: hundredths of a pixel apart on the frames a translation registers, where DIS's flow still
#: wanders by 1-2 px at its p99).
FLOW_GATE_PX = 1.0

#: Trusted flow is at most this many full-resolution pixels (the residual after a registration
#: is small; larger flows are DIS's mistakes, e.g. on a periodic facade or a flickering screen).
FLOW_MAX_PX = 16.0

#: Tiles whose phase correlation peak is below this take no part in that decision.
FLOW_MIN_PEAK = 0.3


def exposure_lut(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(256,) float32 monotone map of ``src``'s uint8 grey codes onto ``dst``'s by histogram
    (CDF) matching: two exposures of one scene brought to one tone scale."""
    src, dst = np.asarray(src), np.asarray(dst)
    hs = np.bincount(src.ravel(), minlength=256).cumsum() / src.size
    hd = np.bincount(dst.ravel(), minlength=256).cumsum() / dst.size
    return np.interp(hs, hd, np.arange(256.0)).astype(np.float32)


def _gradient(img: np.ndarray) -> np.ndarray:
    """Gradient magnitude (Sobel, Gaussian sigma 1) of a float32 grey image."""
    import cv2

    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.GaussianBlur(np.sqrt(gx * gx + gy * gy), (0, 0), 1.0)


def block_displacements(a: np.ndarray, b: np.ndarray, usable: np.ndarray, block: int) -> np.ndarray:
    """Displacement field between two float32 grey images of one size and tone scale, by phase
    correlation of their gradient magnitudes (zero where ``usable`` is False: clipping edges are
    not the scene's) on non-overlapping ``block x block`` tiles (Hann window, every tile in one
    batched FFT, sub-pixel by a parabola through the peak and its neighbours).

    Returns (K, 5) float64 rows ``(x, y, dx, dy, peak)``: tile centre, displacement such that
    ``a(x, y) ~ b(x + dx, y + dy)``, and the correlation peak (1 for one picture shifted, about
    ``1 / block`` for unrelated ones), for the tiles ``usable`` covers at least half of."""
    h, w = a.shape
    ga = np.where(usable, _gradient(np.asarray(a, np.float32)), np.float32(0.0))
    gb = np.where(usable, _gradient(np.asarray(b, np.float32)), np.float32(0.0))
    ny, nx = h // block, w // block
    if ny == 0 or nx == 0:
        return np.zeros((0, 5))

    def tiles(x: np.ndarray) -> np.ndarray:
        return x[:ny * block, :nx * block].reshape(ny, block, nx, block).swapaxes(1, 2).reshape(-1, block, block)

    ta, tb, tu = tiles(ga), tiles(gb), tiles(usable)
    keep = (tu.mean(axis=(1, 2)) >= 0.5) & (ta.std(axis=(1, 2)) > 1e-3) & (tb.std(axis=(1, 2)) > 1e-3)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return np.zeros((0, 5))
    win = np.outer(np.hanning(block), np.hanning(block)).astype(np.float32)
    fa = np.fft.rfft2((ta[idx] - ta[idx].mean(axis=(1, 2), keepdims=True)) * win)
    fb = np.fft.rfft2((tb[idx] - tb[idx].mean(axis=(1, 2), keepdims=True)) * win)
    cross = fb * np.conj(fa)
    cross /= np.maximum(np.abs(cross), 1e-12)
    corr = np.fft.irfft2(cross, s=(block, block))
    flat = corr.reshape(len(idx), -1)
    k = np.argmax(flat, axis=1)
    py, px = np.divmod(k, block)
    rows = np.arange(len(idx))
    peak = flat[rows, k]

    def parabola(m: np.ndarray, p: np.ndarray) -> np.ndarray:
        den = m - 2 * peak + p
        return np.clip(np.where(np.abs(den) > 1e-12, 0.5 * (m - p) / np.where(den == 0, 1, den), 0.0), -0.5, 0.5)

    sy = parabola(corr[rows, (py - 1) % block, px], corr[rows, (py + 1) % block, px])
    sx = parabola(corr[rows, py, (px - 1) % block], corr[rows, py, (px + 1) % block])
    dy = ((py + block // 2) % block - block // 2) + sy
    dx = ((px + block // 2) % block - block // 2) + sx
    cy, cx = np.divmod(idx, nx)
    return np.column_stack([cx * block + block / 2.0 - 0.5, cy * block + block / 2.0 - 0.5, dx, dy, peak])


#: Bytes of working-resolution residual flows (:func:`residual_flow`) a process keeps, keyed by a hash of the two grey
#: frames and the flow's constants: the same pair (a bracket merged again with another method, or
#: with and without ``--deghost``) is not computed twice. The flow is a deterministic function of
#: those inputs, so a kept one is the one that would be computed (measured: 6.5 s of a 9.3 s
#: ``--align flow`` merge of the iPhone bracket is the flow).
FLOW_CACHE_BYTES = 256 * 2 ** 20

_FLOW_CACHE: OrderedDict = OrderedDict()


def residual_flow(grey_ref: np.ndarray, grey_j: np.ndarray) -> tuple[np.ndarray | None, dict]:
    """:func:`flow_from_greys`, kept per process for a pair of frames seen before
    (:data:`FLOW_CACHE_BYTES`); returns a copy, so the caller may write into it."""
    gr, gj = np.ascontiguousarray(grey_ref), np.ascontiguousarray(grey_j)
    consts = (FLOW_SIDE, FLOW_CODES, FLOW_MIN_GRADIENT, FLOW_CONSISTENCY, FLOW_SIGMA, FLOW_PRIOR, FLOW_MIN_PX,
              FLOW_GATE_PX, FLOW_MAX_PX, FLOW_MIN_PEAK)
    h = hashlib.blake2b(repr((gr.shape, gr.dtype.str, gj.shape, gj.dtype.str, consts)).encode(), digest_size=20)
    h.update(gr.data)
    h.update(gj.data)
    key = h.hexdigest()
    if key not in _FLOW_CACHE:
        kept: list = []
        result = flow_from_greys(gr, gj, keep=kept)
        _FLOW_CACHE[key] = kept[0]
        while len(_FLOW_CACHE) > 1 and sum(0 if k[0] is None else k[0].nbytes for k in _FLOW_CACHE.values()) \
                > FLOW_CACHE_BYTES:
            _FLOW_CACHE.popitem(last=False)
        return result
    _FLOW_CACHE.move_to_end(key)
    work, s, shape, details = _FLOW_CACHE[key]
    if work is None:
        return None, dict(details)
    return full_resolution_flow(work.copy(), s, shape, details)


def flow_from_greys(grey_ref: np.ndarray, grey_j: np.ndarray, keep: list | None = None) -> tuple[np.ndarray | None, dict]:
    """Dense residual displacement of frame ``j`` against the reference after a global
    registration: (H, W, 2) float32 ``flow`` such that ``ref(x) ~ j(x + flow(x))``, or None when
    it moves fewer than 1 % of the pixels by more than :data:`FLOW_MIN_PX` (the frame keeps its
    registration). For handheld brackets with parallax: a translation or a homography registers
    one depth; a window's skyline and the room in front of it move apart when the hand moves.

    Frame ``j``'s uint8 grey codes are brought to the reference's tone scale
    (:func:`exposure_lut`) and both are reduced to at most :data:`FLOW_SIDE` pixels on the long
    side. The residual is first measured on 32-pixel tiles (:func:`block_displacements`); unless
    one of them is off (:data:`FLOW_GATE_PX`) the frame keeps its registration. Then OpenCV's DIS optical flow (Kroeger et al. 2016, preset ``MEDIUM``) is computed both
    ways. The flow is trusted where both frames' codes are within :data:`FLOW_CODES`, the
    reference has structure (:data:`FLOW_MIN_GRADIENT`), the two flows agree
    (:data:`FLOW_CONSISTENCY`) and the flow is small (:data:`FLOW_MAX_PX`); elsewhere (sky, clipped or dark regions, occlusions) it is
    filled from the trusted flow around and pulled to zero where none is near
    (:data:`FLOW_SIGMA`, :data:`FLOW_PRIOR`). Deterministic (DIS on fixed inputs).

    Returns ``(flow, details)``: the tiles measured and off, the trusted fraction, the flow's
    p50 / p99 magnitude (full resolution pixels). ``keep`` (a list): the working-resolution flow
    (or None), its reduction, the full shape and the details are appended to it
    (:func:`residual_flow` keeps them; :func:`full_resolution_flow` gives the flow back)."""
    import cv2

    gr, gj = np.asarray(grey_ref), np.asarray(grey_j)
    h, w = gr.shape
    s = 1
    while max(h, w) / s > FLOW_SIDE:
        s *= 2
    size = (max(1, w // s), max(1, h // s))
    lut = exposure_lut(gj, gr)
    a = cv2.resize(gr, size, interpolation=cv2.INTER_AREA) if s > 1 else gr.copy()
    b = cv2.resize(np.clip(np.rint(lut[gj]), 0, 255).astype(np.uint8), size, interpolation=cv2.INTER_AREA)
    jo = cv2.resize(gj, size, interpolation=cv2.INTER_AREA) if s > 1 else gj
    lo, hi = FLOW_CODES
    both = (a >= lo) & (a <= hi) & (jo >= lo) & (jo <= hi)
    tiles = block_displacements(a.astype(np.float32), b.astype(np.float32), both, 32)
    tiles = tiles[tiles[:, 4] >= FLOW_MIN_PEAK]
    off = int(np.count_nonzero(np.hypot(tiles[:, 2], tiles[:, 3]) * s > FLOW_GATE_PX))
    details: dict = {"tiles": int(len(tiles)), "tiles_off": off}
    if off == 0:
        if keep is not None:
            keep.append((None, s, (h, w), details))
        return None, details
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fwd = dis.calc(a, b, None)
    bwd = dis.calc(b, a, None)
    hs, ws = a.shape
    xs, ys = np.meshgrid(np.arange(ws, dtype=np.float32), np.arange(hs, dtype=np.float32))
    back = cv2.remap(bwd, xs + fwd[..., 0], ys + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    trust = (both
             & (_gradient(a.astype(np.float32)) >= FLOW_MIN_GRADIENT)
             & (np.hypot(*np.moveaxis(fwd + back, -1, 0)) <= FLOW_CONSISTENCY)
             & (np.hypot(fwd[..., 0], fwd[..., 1]) * s <= FLOW_MAX_PX))
    wgt = trust.astype(np.float32)
    num = cv2.GaussianBlur(fwd * wgt[..., None], (0, 0), FLOW_SIGMA)
    den = cv2.GaussianBlur(wgt, (0, 0), FLOW_SIGMA)
    flow = np.where(trust[..., None], fwd, num / (den + FLOW_PRIOR)[..., None]).astype(np.float32)
    details["trusted"] = float(trust.mean())
    if keep is not None:
        keep.append((flow, s, (h, w), details))
    return full_resolution_flow(flow, s, (h, w), details)


def full_resolution_flow(flow: np.ndarray, s: int, shape: tuple, details: dict) -> tuple[np.ndarray | None, dict]:
    """The working-resolution ``flow`` (reduced ``s`` times) of :func:`flow_from_greys` at full
    resolution ``shape`` (H, W), with its p50 / p99 magnitude in ``details``; None when it moves
    fewer than 1 % of the pixels by more than :data:`FLOW_MIN_PX`."""
    import cv2

    h, w = shape
    if s > 1:
        flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR) * np.float32(s)
    mag = np.hypot(flow[..., 0], flow[..., 1])
    details = {**details, "p50_px": float(np.median(mag)), "p99_px": float(np.quantile(mag[::4, ::4], 0.99))}
    if float(np.mean(mag > FLOW_MIN_PX)) < 0.01:
        return None, details
    return flow, details


def flow_warp(image: np.ndarray, flow: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``out[y, x] = image[(y, x) + flow]`` (bilinear, border replication) and the (H, W) bool mask
    of the pixels whose source lies inside ``image``."""
    import cv2

    h, w = image.shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    mx, my = xs + flow[..., 0], ys + flow[..., 1]
    warped = cv2.remap(np.ascontiguousarray(image), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if out is not None:
        out[...] = warped
        warped = out
    inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    return warped, inside


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
def align_images(images: np.ndarray, method: str = "translation", reference: int | None = None, seed: int = 0,
                 max_bits: int = 6, exclusion: int = 4) -> Alignment:
    """Register every image of a bracket to ``reference`` (default: the middle image).

    Neighbouring exposures are registered pairwise and the transforms chained towards
    the reference. Returns an :class:`Alignment` (aligned images, validity masks,
    transforms; integer ``shifts`` for ``"translation"``/``"none"``).
    """
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"images must have shape (N, H, W, 3), got {arr.shape}")
    n, h, w, _ = arr.shape
    if method not in ALIGNMENTS:
        raise InputError(f"unknown alignment {method!r}; use one of {', '.join(ALIGNMENTS)}")
    ref = n // 2 if reference is None else int(reference)
    if not 0 <= ref < n:
        raise InputError(f"reference image {reference} is out of range 0..{n - 1}")
    eye = np.eye(3)
    if method == "none":
        return Alignment(images=np.ascontiguousarray(arr, dtype=np.float32), valid=np.ones((n, h, w), bool),
                         transforms=np.repeat(eye[None], n, axis=0), method=method, reference=ref,
                         shifts=np.zeros((n, 2), dtype=int))
    grey = [to_grey8(arr[j]) for j in range(n)]
    pairwise = "translation" if method == "flow" else method
    transforms, info = chain_transforms(grey, pairwise, ref, seed=seed, max_bits=max_bits, exclusion=exclusion)
    out = np.empty((n, h, w, 3), dtype=np.float32)
    valid = np.empty((n, h, w), dtype=bool)
    shifts = None
    if pairwise == "translation":
        shifts = transforms_to_shifts(transforms)
        for j in range(n):              # written in place: no per-frame temporaries
            src = arr[j] if arr.dtype == np.float32 else arr[j].astype(np.float32)
            shift_into(out[j], src, shifts[j, 0], shifts[j, 1])
            valid[j] = shift_valid(h, w, shifts[j, 0], shifts[j, 1])
        if method == "flow":            # the residual flow of each frame, from the reference outwards
            info["flow"] = {}
            for j in list(range(ref - 1, -1, -1)) + list(range(ref + 1, n)):
                a = j + 1 if j < ref else j - 1
                grey[j] = to_grey8(out[j])
                flow, details = residual_flow(grey[a], grey[j])
                details["warped"] = flow is not None
                info["flow"][j] = details
                if flow is not None:
                    _, inside = flow_warp(out[j], flow, out=out[j])
                    moved, _ = flow_warp(valid[j].astype(np.uint8) * np.uint8(255), flow)
                    valid[j] = (moved == 255) & inside
                    grey[j] = to_grey8(out[j])
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
    the per-pair details. ``method`` is ``"translation"`` or ``"homography"`` (falls back to MTB
    for frames too dark or bright for features). Pairs are registered in ``threads``
    threads (default: the usable cores) when the frames are large."""
    n = len(grey)
    h, w = grey[0].shape
    eye = np.eye(3)
    # grey histograms once per image (every k-th row above MTB_PIXELS) for common_percentiles;
    # MTB_PIXELS is read from its module at call time, so that one setting governs this and the scoring
    hstep = max(1, -(-h * w // ward2003.MTB_PIXELS))
    hists = [np.bincount(g[::hstep].ravel(), minlength=256) for g in grey]
    # pairwise transforms T_(a <- b): coords in image a (nearer the reference) -> coords in b
    transforms = np.repeat(eye[None], n, axis=0)
    info: dict = {"pairs": []}
    order = list(range(ref - 1, -1, -1)) + list(range(ref + 1, n))

    def translation(a: int, j: int) -> tuple[np.ndarray, list, list]:
        qs = common_percentiles_hist(hists[a], hists[j])
        dy, dx = mtb_shift(grey[a], grey[j], max_bits=max_bits, exclusion=exclusion, percentiles=qs)
        return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]), [dy, dx], list(qs)

    def register(j: int) -> tuple[np.ndarray, dict]:
        """Transform T_(a <- j) of frame j against its neighbour a nearer the reference."""
        a = j + 1 if j < ref else j - 1
        if method == "translation":
            t, shift, qs = translation(a, j)
            return t, {"from": a, "to": j, "shift": shift, "percentiles": qs}
        try:
            t, n_inl = estimate_homography(grey[a], grey[j], seed=seed + j)
            return t, {"from": a, "to": j, "inliers": n_inl}
        except StackError as exc:   # too dark/bright for features: translation instead
            t, shift, _ = translation(a, j)
            return t, {"from": a, "to": j, "fallback": "translation", "shift": shift, "reason": str(exc)}

    # the pairs are independent (NumPy releases the GIL on the bitmaps): register them in
    # threads, then chain in order
    from concurrent.futures import ThreadPoolExecutor

    if threads is None:
        threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = min(len(order), max(1, int(threads)))
    if workers > 1 and h * w >= ward2003.MTB_PIXELS:
        with ThreadPoolExecutor(workers, thread_name_prefix="derender-align") as ex:
            found = list(ex.map(register, order))
    else:
        found = [register(j) for j in order]
    for j, (t, pair) in zip(order, found):
        a = pair["from"]
        info["pairs"].append(pair)
        transforms[j] = t @ transforms[a]
    return transforms, info
