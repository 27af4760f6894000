"""Reference choice (paper 1, Sec. 3.1, Algorithm 1 step 1): the best-exposed image.

The stabiliser maps every image onto one reference image ``N'`` (eq. 9-10:
``I'_j = H_j L_j`` with ``H_j = A_N' A_j^-1``), so the result carries the reference's exposure
and colour rendering. The paper takes "the best exposed image ... the one with less over
and under-exposed pixels": :func:`select_reference` counts, per image, the pixels with a
channel at or above :data:`REF_HIGH` (over-exposed) or at or below :data:`REF_LOW`
(under-exposed) and keeps the image with the fewest, ties going to the middle of the
bracket. The result depends on that choice (paper 1, Fig. 5): :func:`reasonable_references`
lists the images usable as one, for
:func:`derender.evaluation.table1.reference_spread` and the reference-free joint variant
(:func:`derender.hdr.stabilize.colour_matrices.joint_colour_matrices`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.core.errors import InputError, StackError
from derender.core.types import Stack

__all__ = ["REF_LOW", "REF_HIGH", "REF_PIXELS", "check_images", "exposure_fractions", "select_reference",
           "reasonable_references"]


#: Reference selection: a pixel is over-exposed when any channel is >= REF_HIGH and
#: under-exposed when any channel is <= REF_LOW (normalised codes; 0.02/0.98 = 5/250 of
#: 255, the zero points of the default trapezoid weight).
REF_LOW = 0.02
#: Over-exposure threshold of the reference selection (see REF_LOW).
REF_HIGH = 0.98


#: Reference selection counts at most about this many pixels per frame (row subsample).
REF_PIXELS = 1 << 20


def check_images(images: Any) -> np.ndarray:
    """The (N, H, W, 3) image array of a :class:`~derender.core.types.Stack` or array-like, N >= 2
    (:class:`InputError` for another shape, :class:`StackError` for a single image)."""
    arr = images.images if isinstance(images, Stack) else np.asarray(images)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"images must have shape (N, H, W, 3), got {arr.shape}")
    if arr.shape[0] < 2:
        raise StackError("an exposure stack needs at least two images")
    return arr


def exposure_fractions(images: Any, low: float = REF_LOW, high: float = REF_HIGH,
                       valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fractions of over-exposed (any channel ``>= high``) and under-exposed (any channel
    ``<= low``, and not over-exposed) pixels per image, each (N,), of float images in
    [0, 1] or of uint8 codes (read as ``k / 255``). ``valid`` (N, H, W)
    restricts the count (registration borders). Frames above :data:`REF_PIXELS` pixels are
    counted on every k-th row (fractions, not counts, are compared)."""
    arr = check_images(images)
    n, h, w = arr.shape[:3]
    step = -(-h * w // REF_PIXELS)
    if step > 1:
        arr = arr[:, ::step]
        valid = None if valid is None else np.asarray(valid)[:, ::step]
    if arr.dtype == np.uint8:      # 8-bit codes k, read as k * float32(1/255): the same comparisons on k
        cv = np.arange(256, dtype=np.float32) * np.float32(1.0 / 255.0)
        high, low = int(np.argmax(cv >= high)) if (cv >= high).any() else 256, int(np.sum(cv <= low)) - 1
    over = np.empty(n)
    under = np.empty(n)
    for j in range(n):
        z = arr[j]
        # any channel >= high <=> brightest channel >= high (channel max/min without reduce over a size-3 axis)
        o = np.maximum(np.maximum(z[..., 0], z[..., 1]), z[..., 2]) >= high
        u = (np.minimum(np.minimum(z[..., 0], z[..., 1]), z[..., 2]) <= low) & ~o
        if valid is not None:
            v = np.asarray(valid[j], dtype=bool)
            cnt = max(int(v.sum()), 1)
            over[j], under[j] = (o & v).sum() / cnt, (u & v).sum() / cnt
        else:
            over[j], under[j] = o.mean(), u.mean()
    return over, under


def select_reference(images: Any, low: float = REF_LOW, high: float = REF_HIGH,
                     valid: np.ndarray | None = None) -> int:
    """Index of the best-exposed image (paper 1, Sec. 3.1): fewest over- plus under-exposed
    pixels (thresholds of :func:`exposure_fractions`); ties go to the image nearest the
    middle of the bracket."""
    over, under = exposure_fractions(images, low, high, valid)
    bad = over + under
    n = bad.size
    mid = (n - 1) / 2.0
    order = sorted(range(n), key=lambda j: (round(float(bad[j]), 12), abs(j - mid), j))
    return int(order[0])


def reasonable_references(images: Any, max_bad: float = 0.5) -> list[int]:
    """Images usable as reference: at most ``max_bad`` of their pixels over- or
    under-exposed (:func:`exposure_fractions`), always including the best-exposed one."""
    over, under = exposure_fractions(images)
    refs = [int(j) for j in np.flatnonzero(over + under <= max_bad)]
    best = select_reference(images)
    return sorted(set(refs) | {best})
