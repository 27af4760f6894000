"""Intensity mapping functions between two frames of a bracket, learnt from the frames themselves.

Two frames of a still scene are tied pixel by pixel: whatever the camera did between them (a
longer exposure, another white balance, gain or tone curve, a 3D look-up table, a film and a
scanner), a code ``p`` of frame ``j`` is always seen as about the same code of the reference
frame ``r``. This map, the *intensity mapping function* (IMF; Grossberg & Nayar 2003,
"Determining the camera response from images: what is knowable?"), needs no response curve
and no noise model: it is read off the joint histogram of the two frames' codes, per channel.
Its spread at each code is the noise, quantisation and rendering variation the two frames
really show there, estimated from the bracket itself in the spirit of Granados et al. 2013
("Automatic noise modeling for ghost-free HDR reconstruction").

Per channel and predictor code ``p`` (:func:`mapping_tables`): the pixels whose predictor code
lies in the narrowest window of codes around ``p`` holding at least :data:`MIN_PIXELS` of them;
``m(p)`` the median of their target codes (codes as unit bins: a continuous median) and
``s(p) = max(1.4826 MAD, SIGMA_FLOOR)`` their robust spread. A moving object is a minority
of the pixels of a code, so the median and the MAD do not follow it.

A pixel then disagrees (:func:`mapping_z2`) when, in **both directions**, its code in one frame
is far from what its code in the other predicts:

``z_{j->r} = (c_r - m_{jr}(c_j)) / sqrt(s_{jr}(c_j)^2 + (e |grad c_r|)^2)``, likewise ``z_{r->j}``,
and ``z_c^2 = min(z_{j->r}^2, z_{r->j}^2)``, with ``e`` the misregistration an edge may show
(:data:`derender.engine.motion.deghost.EDGE_SHIFT` pixels). The minimum makes clipping harmless: a
code clipped in one frame predicts the other frame's code badly (its spread is wide, or its
median far), but the other frame's unclipped code predicts the clipped one exactly; a real ghost
is inconsistent both ways.

Limit: a moving thing whose codes are rare in one frame (a uniform object of a colour the still
scene does not show) takes over the median of those codes there, so one direction follows it
and the minimum lets it pass. Reading the larger direction where both frames observe a channel,
or only a direction whose codes pass a round trip through the other, catches such a thing but
rejected 7-11 % of the still Memorial and Frobisher brackets (against 0.1-1.3 % with the
minimum; measured with ``derender experiment consistency``), and a still scene that changes
with ``--deghost`` is the worse error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MIN_PIXELS", "SIGMA_FLOOR", "MappingTables", "mapping_tables", "mapping_z2", "gradient2"]

#: A code's median and spread are read from at least this many pixels (of the nearest codes
#: when that code alone has fewer).
MIN_PIXELS = 64

#: The smallest spread (codes) of a mapping: 8-bit quantisation of both frames and a code of
#: sensor and JPEG noise (what :data:`derender.engine.motion.deghost.CODE_SIGMA` says).
SIGMA_FLOOR = 1.0

_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class MappingTables:
    """One direction's intensity mapping: per predictor code and channel, the median target code
    ``median`` (256, 3) float32 and its robust spread ``sigma`` (256, 3) float32 (module docstring);
    ``count`` (256, 3) the pixels seen at each predictor code."""

    median: np.ndarray
    sigma: np.ndarray
    count: np.ndarray

    def predict(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The predicted target codes and their spread for (h, w, 3) uint8 predictor ``codes``
        (float32 each)."""
        return _lut3(codes, self.median), _lut3(codes, self.sigma)


def _lut3(codes: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Per-channel look-up of a (256, 3) table on (h, w, 3) uint8 codes, float32 (OpenCV's LUT)."""
    import cv2

    lut = np.ascontiguousarray(np.asarray(table, dtype=np.float32).reshape(1, 256, 3))
    return cv2.LUT(np.ascontiguousarray(codes), lut)


def _channel_tables(pred: np.ndarray, target: np.ndarray, min_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(256,) median, spread and count of one channel (module docstring); codes of a channel
    seen nowhere take the nearest window's values (the window grows until it holds data)."""
    hist = np.bincount(pred.astype(np.intp) * 256 + target.astype(np.intp), minlength=65536)
    hist = hist.reshape(256, 256).astype(np.int64)
    counts = hist.sum(axis=1)
    total = int(counts.sum())
    if total == 0:
        return np.arange(256, dtype=np.float64), np.full(256, np.inf), counts
    need = min(min_pixels, total)
    ccount = np.concatenate([[0], np.cumsum(counts)])
    p = np.arange(256)[:, None]
    r = np.arange(256)[None, :]
    lo = np.clip(p - r, 0, 255)
    hi = np.clip(p + r, 0, 255)
    n_win = ccount[hi + 1] - ccount[lo]                   # (256 predictor codes, 256 radii)
    radius = np.argmax(n_win >= need, axis=1)             # the narrowest window holding enough
    lo, hi = np.clip(np.arange(256) - radius, 0, 255), np.clip(np.arange(256) + radius, 0, 255)
    rows = np.vstack([np.zeros((1, 256), np.int64), np.cumsum(hist, axis=0)])
    pooled = rows[hi + 1] - rows[lo]                      # (256, 256): target histogram per window
    cdf = np.cumsum(pooled, axis=1)
    n = cdf[:, -1].astype(np.float64)
    half = n / 2.0
    t = np.argmax(cdf >= half[:, None], axis=1)           # the code holding the median
    below = np.where(t > 0, cdf[np.arange(256), np.maximum(t - 1, 0)], 0)
    inbin = np.maximum(pooled[np.arange(256), t], 1)
    median = t - 0.5 + (half - below) / inbin             # codes as unit bins: a continuous median
    # MAD: the smallest d with half the pixels within [median - d, median + d] (codes as points)
    d = np.arange(256)[None, :]
    upper = np.clip(np.floor(median[:, None] + d), 0, 255).astype(np.intp)
    lower = np.ceil(median[:, None] - d).astype(np.intp)
    within = cdf[np.arange(256)[:, None], upper] - np.where(lower > 0, cdf[np.arange(256)[:, None],
                                                                           np.clip(lower - 1, 0, 255)], 0)
    mad = np.argmax(within >= half[:, None], axis=1).astype(np.float64)
    sigma = np.maximum(_MAD_TO_SIGMA * mad, SIGMA_FLOOR)
    return median, sigma, counts


def mapping_tables(pred: np.ndarray, target: np.ndarray, min_pixels: int = MIN_PIXELS) -> MappingTables:
    """:class:`MappingTables` predicting ``target``'s codes from ``pred``'s: both (m, 3) uint8 codes
    of the same m pixels (those where the two frames may be compared)."""
    pred = np.asarray(pred).reshape(-1, 3)
    target = np.asarray(target).reshape(-1, 3)
    med = np.empty((256, 3), np.float32)
    sig = np.empty((256, 3), np.float32)
    cnt = np.empty((256, 3), np.int64)
    for c in range(3):
        m, s, n = _channel_tables(pred[:, c], target[:, c], min_pixels)
        med[:, c], sig[:, c], cnt[:, c] = m, s, n
    return MappingTables(median=med, sigma=sig, count=cnt)


def gradient2(codes: np.ndarray) -> np.ndarray:
    """Squared gradient magnitude (central differences, codes per grid pixel) of (h, w, 3) codes, float32."""
    import cv2

    f = codes.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    return gx * gx + gy * gy


def mapping_z2(codes_j: np.ndarray, codes_r: np.ndarray, forward: MappingTables, backward: MappingTables,
               edge_shift: float, cap: float, ok: np.ndarray | None = None) -> np.ndarray:
    """Per pixel, ``min(mean_c z_c^2, cap)`` (module docstring) of frame j's (h, w, 3) uint8
    ``codes_j`` against the reference's ``codes_r``: (h, w) float32, 0 where ``ok`` ((h, w),
    nonzero where the two may be compared) is 0. ``forward`` predicts the reference's codes
    from frame j's, ``backward`` frame j's from the reference's."""
    e2 = np.float32(edge_shift * edge_shift)
    m_f, s_f = forward.predict(codes_j)
    m_b, s_b = backward.predict(codes_r)
    z_f = (codes_r.astype(np.float32) - m_f) ** 2 / (s_f * s_f + e2 * gradient2(codes_r))
    z_b = (codes_j.astype(np.float32) - m_b) ** 2 / (s_b * s_b + e2 * gradient2(codes_j))
    z2 = np.minimum(z_f, z_b).mean(axis=-1)
    np.minimum(z2, np.float32(cap), out=z2)
    if ok is not None:
        z2[np.asarray(ok) == 0] = 0.0
    return z2.astype(np.float32, copy=False)
