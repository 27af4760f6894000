"""The compiled step of ghost removal (:mod:`derender.engine.motion.deghost`).

:func:`upsample_into` writes a detection-grid mask into a full-resolution plane in place. It
is compiled once and cached on disk (``cache=True``). The consistency statistic itself is
vectorised NumPy and OpenCV (:mod:`derender.engine.motion.intensity_mapping`); the merge
kernels live in :mod:`derender.engine.kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["upsample_into"]


@njit(nogil=True, cache=True)
def upsample_into(mask, step, out):  # pragma: no cover - compiled
    """``out[y, x] = mask[y // step, x // step] != 0`` for every pixel of ``out`` ((H, W) bool or
    uint8; ``mask`` the (hs, ws) detection grid, every ``step``-th row and column): a grid
    mask at full resolution written in place, no temporary plane (fresh memory costs a page
    fault per 4 kB on first touch). The index is OpenCV's nearest-neighbour rule
    ``floor(y * (1 / step))``, clamped to the grid, so that the planes equal
    ``cv2.resize(..., INTER_NEAREST)``'s."""
    h, w = out.shape[0], out.shape[1]
    hs, ws = mask.shape[0], mask.shape[1]
    inv = 1.0 / step
    cols = np.empty(w, np.int64)
    for x in range(w):
        cols[x] = min(int(np.floor(x * inv)), ws - 1)
    prev = -1
    for y in range(h):
        sy = min(int(np.floor(y * inv)), hs - 1)
        if sy == prev:          # the row above read the same grid row: copy it
            for x in range(w):
                out[y, x] = out[y - 1, x]
            continue
        prev = sy
        for x in range(w):
            out[y, x] = mask[sy, cols[x]] != 0
