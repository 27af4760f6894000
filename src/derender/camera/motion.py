"""Motion between exposures: moving objects and camera shake, with exact truth and zone maps.

Real brackets are taken by hand and of scenes that move. This module makes the simulator's
brackets do both, so that ghost removal and alignment can be scored against exact truth:
the scene is rendered on a canvas ``margin`` pixels larger on every side; frame
``j`` sees

* **camera shake**: the crop of the canvas at integer offset ``shift_j = (dy_j, dx_j)``
  (``|shift| <= shake`` pixels, drawn uniformly; the reference frame at offset 0), so a
  scene point at canvas position ``p`` appears at ``p - margin - shift_j`` in frame ``j``;
* **moving objects**: discs of the scene's own texture (copied from elsewhere in the canvas,
  so their camera RGB is physically rendered), each moving on a straight line across the
  bracket (``travel`` x the image width from the first to the last frame) and pasted over
  the canvas before the crop.

The truth is frame ``reference``'s scene: what the merge should show is that instant, on that
frame's pixel grid. :func:`motion_zones` labels the reference's pixels ``STATIC`` (no object
covers them in any frame, in the reference's coordinates), ``SWEPT`` (an object covers them in
some frame but not in the reference: the background must win) and ``OBJECT`` (an object covers
them in the reference). :meth:`MotionSpec.still` gives, with the same seed, the *still twin*:
the same canvas, noise, pipeline and objects, frozen where they are at the reference instant,
no shake: the same truth with nothing moving, so the best result a merge can reach on each
zone (the objects included) is known.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.core.errors import InputError

__all__ = ["MotionSpec", "MotionPlan", "plan_motion", "compose_frames", "motion_zones",
           "ZONE_STATIC", "ZONE_SWEPT", "ZONE_OBJECT", "ZONE_NAMES"]

#: Zone code of :func:`motion_zones`: no object covers the pixel in any frame.
ZONE_STATIC = 0
#: Zone code: an object covers the pixel in some frame, not in the reference.
ZONE_SWEPT = 1
#: Zone code: an object covers the pixel in the reference frame.
ZONE_OBJECT = 2

#: Names of the zones, by code.
ZONE_NAMES = ("static", "swept", "object")


@dataclass(frozen=True)
class MotionSpec:
    """What moves: ``objects`` discs of radius ``radius`` (fraction of the image height)
    travelling ``travel`` x the image width over the bracket (``frozen``: they stay where they
    are at the reference instant); camera shake up to ``shake`` pixels per frame; ``reference``
    the frame whose instant is the truth (None: the middle frame, as hdrgen and paper 1 take it)."""

    objects: int = 3
    radius: float = 0.09
    travel: float = 0.25
    shake: int = 0
    reference: int | None = None
    margin: int | None = None        # canvas margin (px); None: ``shake``
    frozen: bool = False             # objects stay where they are at the reference instant

    def still(self) -> "MotionSpec":
        """The still twin: nothing moves (the same objects frozen where they are at the
        reference instant, no shake), the same canvas, truth and reference."""
        return MotionSpec(objects=self.objects, radius=self.radius, travel=self.travel, shake=0,
                          reference=self.reference, margin=self.canvas_margin, frozen=True)

    def tripod(self) -> "MotionSpec":
        """The same objects on the same paths, without camera shake (the same canvas)."""
        return MotionSpec(objects=self.objects, radius=self.radius, travel=self.travel, shake=0,
                          reference=self.reference, margin=self.canvas_margin, frozen=self.frozen)

    @property
    def canvas_margin(self) -> int:
        return int(self.shake if self.margin is None else self.margin)


@dataclass(frozen=True)
class MotionPlan:
    """A drawn motion: canvas ``margin``, per-frame camera offsets ``shifts`` (N, 2) int
    (dy, dx), per object its source centre (canvas), its path of centres (N, 2) (canvas)
    and radius (px), and the reference frame."""

    margin: int
    shifts: np.ndarray
    sources: np.ndarray
    paths: np.ndarray
    radius: float
    reference: int
    size: tuple[int, int]            # (W, H) of the frames


def plan_motion(spec: MotionSpec, n_frames: int, size: tuple[int, int], seed: int) -> MotionPlan:
    """Draw the shake offsets and the objects' paths for ``n_frames`` frames of ``size = (W, H)``
    (two independent streams of ``seed``: the objects of a handheld bracket and of its
    :meth:`MotionSpec.tripod` twin are the same)."""
    w, h = int(size[0]), int(size[1])
    if spec.objects < 0 or spec.shake < 0 or not (0 < spec.radius < 0.5) or not (0 <= spec.travel <= 1):
        raise InputError(f"invalid motion {spec}")
    ref = n_frames // 2 if spec.reference is None else int(spec.reference)
    if not 0 <= ref < n_frames:
        raise InputError(f"reference frame {ref} out of range 0..{n_frames - 1}")
    if spec.shake > min(w, h) // 4:
        raise InputError(f"camera shake {spec.shake} px is too large for a {w}x{h} image")
    margin = spec.canvas_margin
    if margin < spec.shake:
        raise InputError(f"canvas margin {margin} px is smaller than the shake {spec.shake} px")
    rng_shake, rng = (np.random.default_rng(s) for s in np.random.SeedSequence([int(seed), 23]).spawn(2))
    shifts = np.zeros((n_frames, 2), dtype=np.int64)
    if spec.shake > 0:
        shifts = rng_shake.integers(-spec.shake, spec.shake + 1, size=(n_frames, 2))
        shifts[ref] = 0
    r = spec.radius * h
    k = int(spec.objects)
    sources = np.stack([rng.uniform(margin + r, margin + h - r, k), rng.uniform(margin + r, margin + w - r, k)], 1) \
        if k else np.zeros((0, 2))
    # straight paths through the frame, centred at a random place at the reference instant
    paths = np.zeros((k, n_frames, 2))
    steps = (np.arange(n_frames) - ref) / max(n_frames - 1, 1)
    if spec.frozen:
        steps = np.zeros(n_frames)
    for i in range(k):
        centre = np.array([rng.uniform(margin + r, margin + h - r), rng.uniform(margin + r, margin + w - r)])
        angle = rng.uniform(0, 2 * np.pi)
        direction = np.array([np.sin(angle), np.cos(angle)]) * spec.travel * w
        paths[i] = centre[None, :] + steps[:, None] * direction[None, :]
    return MotionPlan(margin=margin, shifts=shifts, sources=sources, paths=paths, radius=float(r), reference=ref,
                      size=(w, h))


def _disc(shape: tuple[int, int], centre: np.ndarray, radius: float) -> np.ndarray:
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return (yy + 0.5 - centre[0]) ** 2 + (xx + 0.5 - centre[1]) ** 2 <= radius * radius


def compose_frames(canvas: np.ndarray, plan: MotionPlan) -> np.ndarray:
    """Each frame's (N, H, W, C) view of ``canvas`` (the scene on the margin-enlarged canvas,
    any per-pixel quantity, e.g. camera RGB per unit exposure), objects pasted, then cropped."""
    w, h = plan.size
    m = plan.margin
    ch, cw = canvas.shape[:2]
    if (ch, cw) != (h + 2 * m, w + 2 * m):
        raise InputError(f"canvas {cw}x{ch} does not match {w}x{h} with margin {m}")
    r = plan.radius
    ri = int(np.ceil(r)) + 1
    n = plan.shifts.shape[0]
    out = np.empty((n, h, w) + canvas.shape[2:], dtype=canvas.dtype)
    for j in range(n):
        frame = canvas.copy()
        for i in range(plan.sources.shape[0]):
            sy, sx = plan.sources[i]
            sy0, sx0 = int(round(sy)) - ri, int(round(sx)) - ri
            src_slice = _clip_box(sy0, sx0, 2 * ri, 2 * ri, ch, cw)
            if src_slice is None:
                continue
            patch = canvas[src_slice].copy()
            src_mask = _disc(patch.shape[:2], np.array([sy - src_slice[0].start, sx - src_slice[1].start]), r)
            ty, tx = plan.paths[i, j]
            dy, dx = int(round(ty - sy)), int(round(tx - sx))
            dst = _clip_box(src_slice[0].start + dy, src_slice[1].start + dx, patch.shape[0], patch.shape[1], ch, cw)
            if dst is None:
                continue
            oy, ox = dst[0].start - (src_slice[0].start + dy), dst[1].start - (src_slice[1].start + dx)
            sub = patch[oy:oy + (dst[0].stop - dst[0].start), ox:ox + (dst[1].stop - dst[1].start)]
            msk = src_mask[oy:oy + sub.shape[0], ox:ox + sub.shape[1]]
            frame[dst][msk] = sub[msk]
        dy, dx = plan.shifts[j]
        out[j] = frame[m + dy:m + dy + h, m + dx:m + dx + w]
    return out


def _clip_box(y0: int, x0: int, hh: int, ww: int, h: int, w: int):
    y1, x1 = min(y0 + hh, h), min(x0 + ww, w)
    y0, x0 = max(y0, 0), max(x0, 0)
    if y1 <= y0 or x1 <= x0:
        return None
    return (slice(y0, y1), slice(x0, x1))


def motion_zones(plan: MotionPlan) -> np.ndarray:
    """(H, W) uint8 zones of the reference frame's pixels (module docstring)."""
    w, h = plan.size
    m = plan.margin
    ref = plan.reference
    zones = np.full((h, w), ZONE_STATIC, dtype=np.uint8)
    if plan.sources.shape[0] == 0:
        return zones
    shape = (h + 2 * m, w + 2 * m)
    crop = (slice(m, m + h), slice(m, m + w))            # the reference's offset is 0
    ever = np.zeros((h, w), bool)
    now = np.zeros((h, w), bool)
    for i in range(plan.sources.shape[0]):
        for j in range(plan.shifts.shape[0]):
            # frame j's pixel q shows canvas point q + m + shift_j; registered onto the reference
            # (q' = q + shift_j), its object covers the reference pixels q' with q' + m in the
            # object's disc: zones are in scene coordinates, as a perfect alignment sees them
            ever |= _disc(shape, plan.paths[i, j], plan.radius + 1.0)[crop]
        now |= _disc(shape, plan.paths[i, ref], plan.radius + 1.0)[crop]
    zones[ever] = ZONE_SWEPT
    zones[now] = ZONE_OBJECT
    return zones
