"""The samples of the stabilised merges' curve fit
(:func:`~derender.hdr.stabilize.filmic.unclipped_debevec`): where the grid samples lie, which of
them a clipped neighbour or a frame that does not take part leaves out, and the optional
code-stratified samples that fill the code bins the grid sees rarely.

Debevec & Malik (1997, Sec. 2.1) fit ``g(Z_pj) = ln E_p + ln t_j`` on a few hundred pixels; here
:data:`CURVE_SAMPLES` positions of a seeded grid
(:func:`derender.response.curves.grid_positions`), a sample ``(p, j)`` counting in no channel
(code 0, hat weight 0) when some channel of image ``j`` reaches :data:`CURVE_CLIP` within
:data:`CURVE_CLIP_RADIUS` pixels of ``p`` (the reason is in
:func:`~derender.hdr.stabilize.filmic.unclipped_debevec`). With :data:`CURVE_BIN_MIN` > 0
(off by default; issue 36 item 6, docs/uncertainty.md) samples from a denser grid are added to
every code bin of every channel that holds fewer than that many observations
(:func:`sparse_bin_samples`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.engine.motion.reference_frame import REF_HIGH

__all__ = ["CURVE_CLIP", "CURVE_CLIP_RADIUS", "CURVE_BIN_MIN", "CURVE_BIN_WIDTH", "CURVE_BIN_CODES",
           "CURVE_BIN_CANDIDATES", "CURVE_SAMPLES", "unclipped_samples", "codes_at_positions", "sparse_bin_samples"]


#: Response fit of the curve model (:func:`~derender.hdr.stabilize.filmic.unclipped_debevec`): a sample (pixel, image) is left
#: out when any channel of it or of a pixel within CURVE_CLIP_RADIUS reaches CURVE_CLIP.
CURVE_CLIP = REF_HIGH

#: Radius (px) of the neighbourhood that excludes a sample next to a clipped pixel (see CURVE_CLIP).
CURVE_CLIP_RADIUS = 1


#: Code-stratified samples of that fit (:func:`~derender.hdr.stabilize.filmic.unclipped_debevec`): every code bin of
#: :data:`CURVE_BIN_WIDTH` codes within :data:`CURVE_BIN_CODES` of every channel that the
#: :data:`CURVE_SAMPLES` grid samples see fewer than this many times (kept frame observations) gets
#: samples added from a denser grid (:data:`CURVE_BIN_CANDIDATES` times as many positions) whose codes
#: fall in it, so that a part of a curve that only a small region of the scene shows (the iPhone's blue
#: codes 170-200: a few dozen grid samples) is fitted on a number of samples that does not hang on
#: where the grid lands (issue 36 item 6). 0 (the default): the grid alone. Measured on the iPhone 6
#: bracket (docs/uncertainty.md, "Why the stabilised sky's blue moves"): 256 narrows the spread of the
#: sky's B/G over grid seeds (half size 2.07-4.39 -> 3.00-3.40) but moves it bluer and leaves it
#: 2.68-3.56 across sizes and alignments (1.69-2.94 without), so it stays off.
CURVE_BIN_MIN = 0

#: Width (codes) of the bins of :data:`CURVE_BIN_MIN`.
CURVE_BIN_WIDTH = 8

#: Codes ``(lo, hi)`` whose bins :data:`CURVE_BIN_MIN` fills.
CURVE_BIN_CODES = (16, 239)

#: Candidate positions for :data:`CURVE_BIN_MIN`: this many times :data:`CURVE_SAMPLES`.
CURVE_BIN_CANDIDATES = 16


#: Grid samples of that fit (the Schur-complement solver costs little per sample; lambda
#: grows with sqrt(samples / 256)). With Debevec's 256 the camera-style gain over debevec
#: swung by up to 2.6 dB per scene with the sampling seed; measured with ``derender
#: experiment fusion-gain --styles camera`` (9 scenes, seeds 0-2 / 3-5): 256 samples
#: +1.76 / +1.97 dB L, 1024 +2.19 / +2.36.
CURVE_SAMPLES = 1024


def unclipped_samples(codes_at: Any, n: int, shape: tuple[int, int], *, seed: int, high: float, radius: int,
                       valid_at: Any) -> tuple[np.ndarray, np.ndarray]:
    """The :data:`CURVE_SAMPLES` grid samples' codes (N, P, 3) int32, 0 (hat weight 0) where the sample
    has a clipped neighbour or its image does not take part, and that mask ``clipped`` (N, P); with
    :data:`CURVE_BIN_MIN` > 0, followed by the samples added to the code bins the grid leaves sparse
    (:func:`sparse_bin_samples`)."""
    from derender.response.curves import grid_positions

    h, w = int(shape[0]), int(shape[1])
    ys, xs = grid_positions(h, w, CURVE_SAMPLES, seed)
    codes, clipped = codes_at_positions(codes_at, n, (h, w), ys, xs, high=high, radius=radius, valid_at=valid_at)
    if CURVE_BIN_MIN > 0:
        cy, cx = grid_positions(h, w, CURVE_SAMPLES * CURVE_BIN_CANDIDATES, seed + 1)
        cc, ck = codes_at_positions(codes_at, n, (h, w), cy, cx, high=high, radius=radius, valid_at=valid_at)
        extra = sparse_bin_samples(codes, cc)
        codes = np.concatenate([codes, cc[:, extra]], axis=1)
        clipped = np.concatenate([clipped, ck[:, extra]], axis=1)
    return codes, clipped


def codes_at_positions(codes_at: Any, n: int, shape: tuple[int, int], ys: np.ndarray, xs: np.ndarray, *,
                        high: float, radius: int, valid_at: Any) -> tuple[np.ndarray, np.ndarray]:
    """Codes (N, P, 3) int32 at the positions, 0 where clipped within ``radius`` or not valid, and that mask."""
    h, w = int(shape[0]), int(shape[1])
    top = int(np.ceil(high * 255 - 1e-9))
    codes = np.stack([np.asarray(codes_at(j, ys, xs)) for j in range(n)]).astype(np.int32)   # (N, P, 3)
    clipped = np.zeros(codes.shape[:2], dtype=bool)
    r = int(radius)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            yy, xx = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
            for j in range(n):
                clipped[j] |= np.asarray(codes_at(j, yy, xx)).max(axis=-1) >= top
    if valid_at is not None:
        for j in range(n):
            clipped[j] |= ~np.asarray(valid_at(j, ys, xs), dtype=bool)
    codes[clipped] = 0                       # hat weight 0: the sample drops out of every channel
    return codes, clipped


def sparse_bin_samples(codes: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """Indices of candidate samples ``cand`` (N, C, 3) to add to ``codes`` (N, P, 3) (0: left out) so
    that every code bin of :data:`CURVE_BIN_WIDTH` codes (within :data:`CURVE_BIN_CODES`) of every
    channel holds at least :data:`CURVE_BIN_MIN` kept observations (frame, sample) where the
    candidates allow; candidates taken in grid order, evenly spread over those that qualify."""
    lo, hi = CURVE_BIN_CODES
    width = CURVE_BIN_WIDTH
    nb = 256 // width
    chosen = np.zeros(cand.shape[1], dtype=bool)

    def counts(z: np.ndarray) -> np.ndarray:          # (nb, 3) kept observations per bin
        out = np.zeros((nb, 3), dtype=np.int64)
        for c in range(3):
            zc = z[..., c]
            out[:, c] = np.bincount((zc[zc > 0] // width).ravel(), minlength=nb)[:nb]
        return out

    have = counts(codes)
    cb = cand // width                                   # (N, C, 3)
    for c in range(3):
        for b in range(lo // width, (hi + 1) // width):
            need = CURVE_BIN_MIN - int(have[b, c])
            if need <= 0:
                continue
            hit = ((cb[..., c] == b) & (cand[..., c] > 0)).any(axis=0) & ~chosen
            idx = np.flatnonzero(hit)
            if idx.size == 0:
                continue
            take = idx[np.unique(np.linspace(0, idx.size - 1, min(need, idx.size)).round().astype(int))]
            chosen[take] = True
            have += counts(cand[:, take])
    return np.flatnonzero(chosen)
