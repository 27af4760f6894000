"""Motion-compensated fill: where ghost removal left a frame out, that frame's own view of the
moved thing, found by dense optical flow and kept only if it passes the consistency test.

Ghost removal (:mod:`derender.engine.motion.deghost`) keeps the scene of the reference instant but,
where something moved, leaves only the reference frame: an object clipped or too dark in
the reference has no other measurement, and its radiance is the reference's bound or noise.
The object is still in the other frames, elsewhere. Per frame ``j`` with rejected pixels:

1. both frames as log radiance under the method's plan (:func:`derender.engine.motion.deghost.frame_estimates`,
   mean of the channels, frame j's global offset removed), clipped to the range *both* frames
   observe and scaled to 8 bits: a short exposure's unclipped object and the reference's clipped
   one then look alike (the exposure normalisation of Kalantari & Ramamoorthi 2017);
2. dense optical flow from the reference to frame j (OpenCV's DIS, Kroeger et al. 2016) on the
   detection grid, brought to full resolution;
3. the rejected regions **grow over the moving thing's smooth inside**
   (:func:`grow_by_motion`): the test compares codes in a small window, so a smooth surface
   that moved (a face's skin, a shirt) agrees with itself shifted and passes, while its edges
   and features are rejected; the merge then switched, blob by blob, between the frames'
   differently placed and differently exposed views of it: hard-edged patches and a second
   outline inside the moving head (measured on the ping-pong bracket, issue 36). Cells near
   the large rejected regions whose reliable flow departs from the background's own motion by
   more than :data:`MOTION_PX`, in regions that touch them, are rejected too; where the warped
   view passes (next step) it fills them, else the reference alone gives them;
4. frame j's codes sampled through the flow (nearest code: the colours stay ones the frame
   has, as paper 2's per-colour tables need), tested against the reference with the same
   test and the same offset and spread as frame j itself (:class:`~derender.engine.motion.deghost.ConsistencyTest`);
5. where the warped frame agrees and the frame had been rejected, its warped codes replace its
   own and it takes part again. "Agrees" is the detection's own rule: outside the warped
   frame's rejected regions *dilated* as the detection dilates them (without the dilation a
   flow of about a pixel gave back the margins the detection had added around a moving
   person, and those margins showed the person's other instants: measured on the sculpture
   garden, issue 36).

A clipped reference bounds the radiance from one side only, so a wrong flow that brings a
brighter patch there would pass the test: the flow is trusted only where its forward-backward
error is below :data:`FLOW_CHECK` pixels (of the detection grid).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["FLOW_CHECK", "FLOW_PIXELS", "MOTION_PX", "MOTION_REACH", "MOTION_MIN_REGION", "MOTION_BACKGROUND_PX", "MOTION_MIN_SHARE", "compensate_frames", "grow_by_motion"]

#: Largest forward-backward disagreement of the flow (pixels of the grid it is computed on)
#: where a compensated pixel is used.
FLOW_CHECK = 1.0


#: A detection-grid cell near a moving thing whose flow departs from the background's by more
#: than this (full-resolution pixels) is taken as part of it (:func:`grow_by_motion`).
MOTION_PX = 2.0

#: The flow is used to grow the rejected regions only when it moves the background (the
#: accepted cells away from them) by at most this (median, full-resolution pixels): the frames
#: are registered already, so a flow that moves their background further is failing, not
#: measuring motion (measured: the iPhone's still bracket, flow-aligned, its frames 4, 7 and 8
#: 14-52 px; the ping-pong bracket 4.3 / 6.1 px with ``--align translation``, its parallax,
#: 0.6 / 1.0 px with ``--align flow``).
MOTION_BACKGROUND_PX = 8.0

#: ... and only those of whose usable cells at least this fraction move against the
#: background (measured: the ping-pong player's regions 0.83-1.0, the still iPhone's skyline
#: regions 0.18 and 0.27).
MOTION_MIN_SHARE = 0.5

#: Only rejected regions (8-connected) of at least this fraction of the grid grow: a moving
#: thing, not the specks a misregistered edge leaves.
MOTION_MIN_REGION = 0.002

#: The moving things' motion (grid pixels) is taken as at most this (:func:`grow_by_motion`).
MOTION_REACH = 64

#: The flow is computed on at most about this many pixels (every k-th row and column of the
#: detection grid), then brought to full resolution: measured 0.68 -> 0.2 s per 5 frames of
#: 0.77 MP, no change in the filled pixels' test.
FLOW_PIXELS = 1 << 18


def _grey8(mu: np.ndarray, cens: np.ndarray, lo: float, hi: float) -> np.ndarray:
    g = mu.mean(axis=-1)
    g = np.clip((g - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255)
    return np.ascontiguousarray(np.rint(g).astype(np.uint8))


def _observed_range(mu: np.ndarray, cens: np.ndarray) -> tuple[float, float] | None:
    obs = np.all(cens == 0, axis=-1)
    if np.count_nonzero(obs) < 64:
        return None
    g = mu.mean(axis=-1)[obs]
    return float(np.percentile(g, 0.5)), float(np.percentile(g, 99.5))


def compensate_frames(frames: np.ndarray, test, rejected: np.ndarray, valid: np.ndarray | None,
                      offsets: dict, threads: int | None = None, grown: dict | None = None) -> dict[str, Any]:
    """Fill the ``rejected`` pixels of every frame from its flow-compensated view (module
    docstring), **in place**: ``frames[j]`` takes the warped codes and ``rejected[j]`` turns
    False where they pass ``test`` (a :class:`~derender.engine.motion.deghost.ConsistencyTest` of the
    reference). ``offsets[j]``: frame j's :class:`~derender.engine.motion.deghost.FrameAgreement` of the
    detection. Before the fill, each frame's rejected regions grow over the moving thing's
    smooth inside (:func:`grow_by_motion`; ``grown``, a dict: frame -> its grown grid cells).
    Returns the filled and grown fractions per frame."""
    from derender.engine.motion.deghost import frame_estimates, map_frames

    n, h, w = frames.shape[:3]
    ref = test.ref
    step = test.step
    hs, ws = test.hs, test.ws
    rng_r = _observed_range(test.mu_r, test.cens_r)
    out: dict[str, Any] = {"frames": []}
    if rng_r is None:
        return out

    def one(j: int) -> dict | None:
        """Frame j's fill (frames[j] and rejected[j] only: the frames run in threads)."""
        if not rejected[j].any():
            return None
        agreement = offsets[j]
        grid_j = test.grid(frames[j])
        mu_j, _, cens_j = frame_estimates(test.plan, grid_j, j)
        mu_j = mu_j - agreement.maps(grid_j)[0]
        rng_j = _observed_range(mu_j, cens_j)
        if rng_j is None:
            return None
        lo, hi = max(rng_r[0], rng_j[0]), min(rng_r[1], rng_j[1])
        if hi - lo < 0.5:          # the two exposures share almost no range: nothing to match
            return None
        a8 = _grey8(test.mu_r, test.cens_r, lo, hi)
        b8 = _grey8(mu_j, cens_j, lo, hi)
        fwd, reliable = _checked_flow(a8, b8, (hs, ws))
        iy, ix, ok = _flow_samples(fwd, reliable, step, (h, w), None if valid is None else valid[j])
        grow = grow_by_motion(rejected[j], fwd, reliable, test)
        if grow is not None and grown is not None:
            grown[j] = grow
        q, _, _ = test.statistic(frames[j][iy, ix], j, ok, agreement, on_grid=True)
        use_g = test.sub(rejected[j]) & ~test.regions_grid(q, dilate=True) & (ok != 0)
        if not use_g.any():
            return {"frame": j, "filled": 0.0, "grown": 0.0 if grow is None else float(grow.mean())}
        filled = _fill_from_flow(frames[j], rejected[j], use_g, fwd, step)
        return {"frame": j, "filled": float(filled) / (h * w),
                "grown": 0.0 if grow is None else float(grow.mean())}

    others = [j for j in range(n) if j != ref]
    out["frames"] = [r for r in map_frames(one, others, threads) if r is not None]
    return out


def grow_by_motion(rejected_j: np.ndarray, fwd: np.ndarray, reliable: np.ndarray, test) -> np.ndarray | None:
    """Frame j's rejected pixels ``rejected_j`` (H, W) bool grown, **in place**, over the moving
    thing's smooth inside (module docstring, step 3); returns the grown detection-grid cells
    ((hs, ws) bool), or None.

    On the detection grid, with ``fwd`` (hs, ws, 2) the flow from the reference to frame j (grid
    pixels) and a cell *usable* where the flow is ``reliable`` and the reference observes every
    channel:

    * the moving things are the rejected regions (8-connected) of at least
      :data:`MOTION_MIN_REGION` of the grid (not the specks a misregistered edge leaves); their
      motion ``m`` is the p90 of ``|fwd|`` over their usable cells that move by more than
      :data:`MOTION_PX` (none: nothing grows);
    * the background's own residual motion ``b`` (a handheld bracket's parallax after a
      translation) is the flow of the usable, accepted cells farther than ``3 m`` from them
      (at most ``3`` :data:`MOTION_REACH`), smoothed (Gaussian, sigma ``max(8, 3 m)``) and so
      brought under them;
    * the cells within ``3 m`` of them whose usable flow departs from ``b`` by more than
      :data:`MOTION_PX`, in connected regions that touch the regions of which at least
      :data:`MOTION_MIN_SHARE` of the usable cells so depart, are rejected too.

    A rejected region that does not move (flicker, a monitor's bands) grows nowhere; the
    background's parallax moves with ``b`` and is left as it is; a flow that moves the
    background by more than :data:`MOTION_BACKGROUND_PX` (median) is not used."""
    import cv2

    from derender.engine.motion.ghost_kernels import upsample_into

    step = test.step
    sub = test.sub(rejected_j)
    _, blab, stats, _ = cv2.connectedComponentsWithStats(sub.astype(np.uint8), connectivity=8)
    px = np.float32(step)
    fx, fy = fwd[..., 0] * px, fwd[..., 1] * px                  # full-resolution pixels
    usable = (reliable != 0) & np.all(test.cens_r == 0, axis=-1)
    moving = usable & (np.hypot(fx, fy) > MOTION_PX)
    big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= MOTION_MIN_REGION * sub.size)
    bad = np.isin(blab, big[big > 0])
    if not (moving & bad).any():
        return None
    m = int(np.clip(np.ceil(float(np.quantile(np.hypot(fx, fy)[moving & bad], 0.9)) / step), 1, MOTION_REACH))
    wide = 3 * m
    zone = cv2.dilate(bad.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * wide + 1, 2 * wide + 1))) != 0
    bgw = (usable & ~zone & ~sub).astype(np.float32)
    if bgw.sum() < 64 or float(np.median(np.hypot(fx, fy)[bgw > 0])) > MOTION_BACKGROUND_PX:
        return None              # no background, or a flow that does not register it: no evidence
    sigma = float(max(8, wide))
    den = cv2.GaussianBlur(bgw, (0, 0), sigma)
    far = den < 1e-3                   # no background near: the median background motion
    bx = np.where(far, float(np.median(fx[bgw > 0])), cv2.GaussianBlur(fx * bgw, (0, 0), sigma) / np.maximum(den, 1e-3))
    by = np.where(far, float(np.median(fy[bgw > 0])), cv2.GaussianBlur(fy * bgw, (0, 0), sigma) / np.maximum(den, 1e-3))
    rel = usable & zone & (np.hypot(fx - bx, fy - by) > MOTION_PX)
    ucount = np.bincount(blab[usable], minlength=len(stats))
    rcount = np.bincount(blab[rel], minlength=len(stats))
    moves = [c for c in big[big > 0] if ucount[c] and rcount[c] >= MOTION_MIN_SHARE * ucount[c]]
    bad = np.isin(blab, moves)          # the rejected regions that move against the background
    if not bad.any():
        return None
    _, lab = cv2.connectedComponents((rel | bad).astype(np.uint8), connectivity=8)
    touch = np.unique(lab[bad])
    grow = np.isin(lab, touch[touch > 0]) & rel & ~sub
    if not grow.any():
        return None
    full = np.empty(rejected_j.shape, np.uint8)
    upsample_into(grow.view(np.uint8), step, full)
    np.logical_or(rejected_j, full.view(bool), out=rejected_j)
    return grow


def _checked_flow(a8: np.ndarray, b8: np.ndarray, grid_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """DIS optical flow from grey image ``a8`` to ``b8`` (both on the detection grid), on a coarser
    grid when the grid has more than :data:`FLOW_PIXELS` pixels, and where it passes the
    forward-backward check (:data:`FLOW_CHECK`): ``(flow (hs, ws, 2) in grid pixels, reliable uint8)``."""
    import cv2

    hs, ws = grid_shape
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)     # one per thread
    fs = max(1, int(np.ceil(np.sqrt(hs * ws / FLOW_PIXELS))))
    if fs > 1:                 # the flow on a coarser grid, brought back to the detection grid
        size = (max(8, ws // fs), max(8, hs // fs))
        a8c, b8c = (cv2.resize(x, size, interpolation=cv2.INTER_AREA) for x in (a8, b8))
    else:
        a8c, b8c = a8, b8
    fwd = dis.calc(a8c, b8c, None)
    bwd = dis.calc(b8c, a8c, None)
    hc, wc = a8c.shape
    cy, cx = np.mgrid[0:hc, 0:wc].astype(np.float32)
    # forward-backward check: x -> x + f(x) -> back by b at that point
    bx = cv2.remap(bwd[..., 0], cx + fwd[..., 0], cy + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    by = cv2.remap(bwd[..., 1], cx + fwd[..., 0], cy + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    reliable = ((fwd[..., 0] + bx) ** 2 + (fwd[..., 1] + by) ** 2 <= FLOW_CHECK ** 2).astype(np.uint8)
    if (hc, wc) != (hs, ws):
        fwd = cv2.resize(fwd, (ws, hs), interpolation=cv2.INTER_LINEAR) * np.float32(ws / wc)
        reliable = cv2.resize(reliable, (ws, hs), interpolation=cv2.INTER_NEAREST)
    return fwd, reliable


def _flow_samples(fwd: np.ndarray, reliable: np.ndarray, step: int, shape: tuple[int, int],
                  valid_j: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the detection grid's pixels land in the frame through the flow: ``(iy, ix)`` (nearest
    full-resolution pixel) and ``ok`` (uint8: inside the frame, in ``valid_j`` and a reliable flow)."""
    h, w = shape
    hs, ws = fwd.shape[:2]
    gy, gx = np.mgrid[0:hs, 0:ws].astype(np.float32)
    sx = (gx + fwd[..., 0]) * step
    sy = (gy + fwd[..., 1]) * step
    inside = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)
    ix = np.clip(np.rint(sx), 0, w - 1).astype(np.intp)
    iy = np.clip(np.rint(sy), 0, h - 1).astype(np.intp)
    if valid_j is not None:
        inside &= valid_j[iy, ix] != 0
    ok = (inside & (reliable != 0)).astype(np.uint8)
    return iy, ix, ok


def _fill_from_flow(frame: np.ndarray, rejected: np.ndarray, use_g: np.ndarray, fwd: np.ndarray,
                    step: int) -> int:
    """Fill, in place, the ``rejected`` pixels of ``frame`` in the grid cells ``use_g`` with the codes
    the cell's flow points at (nearest code), and clear them in ``rejected``; the number filled."""
    h, w = rejected.shape
    # full resolution only at the grid cells that passed: each cell's step x step pixels, moved
    # by the cell's flow (nearest code), where frame j was rejected
    cy_, cx_ = np.nonzero(use_g)
    dy, dx = np.mgrid[0:step, 0:step]
    ys = (cy_[:, None] * step + dy.reshape(1, -1)).reshape(-1)
    xs = (cx_[:, None] * step + dx.reshape(1, -1)).reshape(-1)
    keep = (ys < h) & (xs < w)
    ys, xs = ys[keep], xs[keep]
    cell = (ys // step, xs // step)
    keep = rejected[ys, xs]
    ys, xs = ys[keep], xs[keep]
    cell = (cell[0][keep], cell[1][keep])
    sx = np.rint(xs + fwd[cell[0], cell[1], 0] * step).astype(np.intp)
    sy = np.rint(ys + fwd[cell[0], cell[1], 1] * step).astype(np.intp)
    keep = (sx >= 0) & (sx < w) & (sy >= 0) & (sy < h)
    ys, xs, sy, sx = ys[keep], xs[keep], sy[keep], sx[keep]
    frame[ys, xs] = frame[sy, sx]      # gathered first, then written
    rejected[ys, xs] = False
    return int(ys.size)
