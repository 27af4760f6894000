"""Fitting data of the stabiliser: block means of well-exposed pixels (paper 1, Sec. 3.1).

The paper fits every pair ``(I_j, I_N')`` on corresponding pixels, "discarding over and
under-exposed pixels" (eq. 9). Here the correspondences are ``block x block``-pixel blocks
(2x2 by default) of the registered images: the fits (:mod:`.exponents`,
:mod:`.colour_matrices`) average each block's *linearised* values, since noise in both
images biases pixel-wise fits while block means keep the linear relation
``L_ref = H_j L_j`` exact. A block takes part in the fit of a pair only where all its
pixels' channels lie in (:data:`FIT_LOW`, :data:`FIT_HIGH`) in the brighter image and in
(:data:`FIT_FLOOR`, :data:`FIT_HIGH`) in the darker one, inside both registration masks
(:meth:`Blocks.pair`). :func:`make_blocks` gathers a seeded random subset of at most
``max_blocks`` blocks (a 2-pixel frame left out), reading only those pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from derender.core.errors import InputError

__all__ = ["FIT_LOW", "FIT_HIGH", "FIT_FLOOR", "Blocks", "make_blocks"]


#: Fitting range for gammas and H_j: a pixel takes part only if all its channels lie in
#: (FIT_LOW, FIT_HIGH) in the brighter image of a pair and in (FIT_FLOOR, FIT_HIGH) in
#: the darker one. FIT_HIGH is well below 1 because sensors clip
#: *before* the colour matrix: a pixel with one saturated raw channel can render below
#: 255 in every channel, and such pixels break the 3x3 relation (eq. 9).
FIT_LOW = 0.12
#: Upper limit of the fit range (see FIT_LOW).
FIT_HIGH = 0.85


#: The darker image of a pair is only required to exceed FIT_FLOOR (see :meth:`Blocks.pair`).
FIT_FLOOR = 0.03


def _block_view(img: np.ndarray, bs: int) -> np.ndarray:
    """(H, W, 3) -> (H//bs * W//bs, bs*bs, 3) blocks (crop to a multiple of bs)."""
    h, w = img.shape[0] // bs * bs, img.shape[1] // bs * bs
    b = img[:h, :w].reshape(h // bs, bs, w // bs, bs, 3).transpose(0, 2, 1, 3, 4)
    return b.reshape(-1, bs * bs, 3)


@dataclass
class Blocks:
    """Pixel blocks used for fitting: codes (N, nb, bs*bs, 3), per-block min/max code (N, nb)
    and registration validity (N, nb)."""

    codes: np.ndarray
    bmin: np.ndarray
    bmax: np.ndarray
    valid: np.ndarray
    brightness: np.ndarray   # (N,) median code of each image (orders a pair by exposure)

    def pair(self, j: int, k: int, low: float, high: float, floor: float) -> np.ndarray:
        """Blocks usable for the pair (j, k): inside both registration masks, below ``high``
        in both images, above ``low`` in the brighter image and above ``floor`` in the
        darker one. Thresholding the darker image only at a low ``floor`` avoids a
        truncation bias: its noisy dark values are selected through the brighter image,
        whose noise is independent of them."""
        dark, bright = (j, k) if self.brightness[j] <= self.brightness[k] else (k, j)
        return (self.valid[j] & self.valid[k] & (self.bmax[j] < high) & (self.bmax[k] < high)
                & (self.bmin[bright] > low) & (self.bmin[dark] > floor))


def _pixels(images: Any, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """``images[j][ys, xs]`` of an array, or ``images.pixels(j, ys, xs)`` of a lazy stack
    (the streaming merge of :mod:`derender.hdr.files` keeps 8-bit frames and their shifts)."""
    if hasattr(images, "pixels"):
        return images.pixels(j, ys, xs)
    return np.asarray(images[j])[ys, xs]


def make_blocks(images: np.ndarray, valid: np.ndarray | None, block: int, max_blocks: int,
                seed: int, times: np.ndarray | None = None) -> Blocks:
    """:class:`Blocks` of ``block x block`` pixels of the (N, H, W, 3) ``images`` (an array or
    a lazy stack with ``pixels(j, ys, xs)``): at most ``max_blocks`` of them, drawn with
    ``seed`` from the blocks clear of a 2-pixel frame, in row-major order; ``valid``
    (N, H, W) registration masks or None. Pairs are ordered by ``log times`` when given,
    else by each image's median code."""
    n, h, w, _ = images.shape
    bs = max(1, int(block))
    if h < bs or w < bs:
        raise InputError(f"images of {w}x{h} are smaller than the fitting block of {bs} px")
    nby, nbx = h // bs, w // bs
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 5]))
    # leave out a 2-pixel frame (demosaicing borders of in-camera rendering): the kept blocks
    # are a rectangle of block rows / columns, numbered row-major (no per-block arrays: a
    # 24 MP frame has 6 M blocks)
    by0, by1 = -(-2 // bs), (h - 2) // bs - 1          # block rows with by*bs >= 2 and (by+1)*bs <= h-2
    bx0, bx1 = -(-2 // bs), (w - 2) // bs - 1
    if by1 < by0 or bx1 < bx0:
        by0, by1, bx0, bx1 = 0, nby - 1, 0, nbx - 1
    kx_n = bx1 - bx0 + 1
    n_inner = (by1 - by0 + 1) * kx_n
    if n_inner > max_blocks:        # rng.choice(keep, k) == keep[rng.choice(keep.size, k)]
        pick = rng.choice(n_inner, size=max_blocks, replace=False)
    else:
        pick = np.arange(n_inner)
    keep = np.sort((by0 + pick // kx_n) * nbx + bx0 + pick % kx_n)
    codes = np.empty((n, keep.size, bs * bs, 3), dtype=np.float64)
    vmask = np.ones((n, keep.size), dtype=bool)
    # pixel coordinates of the kept blocks only (no full-size copies): (nkeep, bs*bs), row-major in a block
    ky, kx = np.divmod(keep, nbx)
    oy, ox = np.divmod(np.arange(bs * bs), bs)
    ys = ky[:, None] * bs + oy[None, :]
    xs = kx[:, None] * bs + ox[None, :]
    for j in range(n):
        codes[j] = _pixels(images, j, ys, xs)
        if valid is not None:
            vmask[j] = _pixels(valid, j, ys, xs).all(axis=1)
    if times is not None:
        brightness = np.log(np.asarray(times, dtype=np.float64))
    else:
        brightness = np.array([float(np.median(codes[j][vmask[j]])) if vmask[j].any() else 0.0 for j in range(n)])
    return Blocks(codes=codes, bmin=codes.min(axis=(2, 3)), bmax=codes.max(axis=(2, 3)), valid=vmask,
                  brightness=brightness)
