"""Views of a bracket's aligned 8-bit frames for the stabilised merges, without making them whole.

:class:`ShiftedFrames` reads frames through integer registration shifts (what
:func:`derender.engine.motion.align.align_images` would produce, pixel by pixel), :class:`ShiftedValid`
and :class:`HeldValid` the matching registration / ghost-removal masks, :class:`CodeFrameRows`
every k-th row of the shifted frames, and :class:`LazyAlignment` bundles them as the
:class:`~derender.engine.motion.align.Alignment` that :func:`.method.stabilize_aligned` reads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.engine.tables import code_values

__all__ = ["ShiftedFrames", "ShiftedValid", "HeldValid", "CodeFrameRows", "LazyAlignment"]


class ShiftedFrames:
    """8-bit frames seen through integer registration shifts, as the float images
    :func:`derender.engine.motion.align.align_images` would produce (``out[y, x] = frame[clip(y + dy),
    clip(x + dx)]``, codes as ``k * float32(1/255)``), without making them: ``shape`` and
    ``pixels(j, ys, xs)`` for :func:`stabilize_aligned`; ``codes(j)`` gives the aligned
    uint8 frame."""

    def __init__(self, frames: np.ndarray, shifts: np.ndarray):
        self.frames = frames
        self.shifts = np.asarray(shifts, dtype=int)
        h, w = frames[0].shape[:2]
        self.shape = (len(frames), h, w, 3)
        self.valid_view = ShiftedValid(self)

    def _where(self, j: int, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.shape[1:3]
        dy, dx = self.shifts[j]
        return np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)

    def pixels(self, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        yy, xx = self._where(j, ys, xs)
        return code_values()[self.frames[j][yy, xx]]

    def code_pixels(self, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        yy, xx = self._where(j, ys, xs)
        return self.frames[j][yy, xx]

    def codes(self, j: int, out: np.ndarray | None = None) -> np.ndarray:
        from derender.engine.motion.align import shift_into

        dy, dx = self.shifts[j]
        if dy == 0 and dx == 0:
            return self.frames[j]
        out = np.empty_like(self.frames[j]) if out is None else out
        shift_into(out, self.frames[j], int(dy), int(dx))
        return out


class ShiftedValid:
    """Registration masks of :class:`ShiftedFrames` (``shape``, ``pixels``), never made whole."""

    def __init__(self, frames: ShiftedFrames):
        self.f = frames
        self.shape = frames.shape[:3]

    def pixels(self, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        h, w = self.shape[1:3]
        dy, dx = self.f.shifts[j]
        return (ys + dy >= 0) & (ys + dy < h) & (xs + dx >= 0) & (xs + dx < w)


class HeldValid:
    """The engine's ``valid`` planes (N, H, W) uint8 (alignment, ghost removal) as the fits read them."""

    def __init__(self, valid: np.ndarray):
        self.valid = valid
        self.shape = valid.shape

    def pixels(self, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        return self.valid[j][ys, xs] != 0


class CodeFrameRows:
    """Every ``rows``-th row of the aligned uint8 frames of a :class:`ShiftedFrames`, one at a time."""

    def __init__(self, view: ShiftedFrames, rows: int = 1):
        self.view, self.rows = view, max(int(rows), 1)

    def __getitem__(self, j: int) -> np.ndarray:
        if self.rows == 1:
            return self.view.codes(j)
        from derender.engine.motion.align import shift_into

        # the rows of the shifted frame, without shifting the whole frame first (at 24 MP that
        # copied 72 MB per frame to keep one row in ``rows``): shift_into's clipped source rows
        frame = self.view.frames[j]
        h = frame.shape[0]
        dy, dx = (int(v) for v in self.view.shifts[j])
        sub = frame[np.clip(np.arange(0, h, self.rows) + dy, 0, h - 1)]
        if dx == 0:
            return sub
        out = np.empty_like(sub)
        shift_into(out, sub, 0, dx)
        return out


@dataclass
class LazyAlignment:
    """What :func:`stabilize_aligned` reads of an :class:`~derender.engine.motion.align.Alignment`."""

    images: ShiftedFrames
    valid: ShiftedValid
    transforms: np.ndarray
    method: str
    reference: int
    shifts: np.ndarray
    info: dict
