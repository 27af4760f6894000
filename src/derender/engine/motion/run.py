"""Reference frame, alignment and ghost removal, one step of the engine for every method.

Real brackets are shot by hand and things move in them. :func:`run_motion` is the engine's
path for such brackets, whatever the method (its plan says how codes become radiance and
with what uncertainty; this module only decides *which pixels of which frame* take part):

1. **Reference frame** (:func:`resolve_reference`): the result shows the scene at that
   frame's instant, on its pixel grid. ``"auto"`` is paper 1's rule (Sec. 3.1,
   :func:`derender.engine.motion.reference_frame.select_reference`: fewest over- and
   under-exposed pixels, ties to the middle of the bracket).
2. **Alignment** (:func:`align_frames`): every frame is registered to the reference and
   warped in place (8-bit codes): ``"translation"`` by Ward's median threshold bitmaps
   (:mod:`derender.engine.motion.ward2003`, integer shifts, exact codes), ``"homography"`` by ORB
   features and a seeded RANSAC (:func:`derender.engine.motion.align.estimate_homography`,
   bilinear on the codes), ``"flow"`` by Ward's shifts and then each frame's dense residual
   flow (:func:`derender.engine.motion.align.residual_flow`, bilinear on the codes where a
   residual is measured; handheld brackets with parallax). Pixels a frame does not cover after
   warping are left out of that frame (``valid``).
3. **Ghost removal** (:mod:`derender.engine.motion.deghost`): per pixel and frame, the frame's
   radiance against the reference's under the method's own noise model, pooled over a window,
   cleaned into regions; inconsistent frames get no weight there. The method is then
   *calibrated again without them* (fit, detect, refit: its response samples, the
   stabiliser's gamma/3x3 fits read only consistent pixels) and the decision is made once
   more with the refitted model. After the last decision (refitted or not) the rejected
   pixels are filled from each frame's motion-compensated view where it passes
   (:mod:`derender.engine.motion.compensation`).
4. **Merge**: the method's plan on the engine's kernels with the ``valid`` planes
   (:func:`derender.engine.frames.merge_held`, the plain run's dispatch:
   :func:`derender.engine.kernels.table_merge_rows`, ``stabilized_merge_rows``,
   ``gaussian_moments_band``); where no frame that takes part has weight, the shortest
   (bright) or longest (dark) frame that takes part gives the value, as before.
5. **Consensus correction** (:mod:`derender.engine.motion.consensus`) and **censored fill**
   (:mod:`derender.engine.motion.censored_fill`): where ghost removal left only clipped frames
   at a pixel that a rejected frame saw unclipped, the bound is raised to a fill from the
   measured clipped scene around it, with a variance covering the difference.

The frames are held in memory (N x H x W x 3 bytes, plus one byte per pixel and frame for
``valid``); the memory is checked before any pixel is decoded.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from derender.core.errors import InputError, StackError
from derender.core.memory import check_memory
from derender.core.types import HDRResult, check_brightness_order
from derender.engine.frames import ArrayFrames, FileFrames, clipped_pixels, frame_brightness, merge_held
from derender.engine.motion.align import ALIGNMENTS
from derender.engine.options import EngineOptions, OutputOptions
from derender.engine.outputs import write_outputs

__all__ = ["MotionOptions", "resolve_reference", "align_frames", "refine_shifts", "bitmap_agreement",
           "check_one_scene", "run_motion", "REFINE_PIXELS", "REFINE_REACH", "MIN_BITMAP_AGREEMENT",
           "SCENE_CHECK_PIXELS"]


@dataclass(frozen=True, kw_only=True)
class MotionOptions:
    """What the engine does about camera shake and moving things (see the module docstring),
    for every method. Built once where the user's input is parsed and checked when made.

    Attributes
    ----------
    reference : int, "auto" or None
        The reference frame: an index among the images *as given* (0-based; the CLI counts
        from 1), or ``"auto"`` / None for paper 1's rule.
    align : str or None
        ``"none"``, ``"translation"`` (Ward's MTB), ``"homography"`` (features) or ``"flow"``
        (Ward's MTB, then a dense residual flow per frame); None: the
        method's own default (:attr:`derender.engine.plans.MethodDefaults.own_align`:
        ``"translation"`` for paper 1's methods, which register their frames themselves,
        ``"none"`` for the others).
    deghost : bool
        Exclude, per pixel, the frames inconsistent with the reference.
    ghost_threshold : float or None
        The pooled statistic's threshold: a frame is rejected where the window mean of
        ``z^2`` per channel exceeds it (None: :data:`derender.engine.motion.deghost.GHOST_THRESHOLD`).
    compensate : bool
        With ``deghost``: fill the rejected pixels of each frame from its own view of the moved
        thing, found by optical flow and tested again (:mod:`derender.engine.motion.compensation`).
    consensus : bool
        With ``deghost``: pixels where ghost removal left frames out lose the rendering bias of
        the frames that remain (:mod:`derender.engine.motion.consensus`; methods with one curve for
        the bracket).
    censored_fill : bool
        With ``deghost``: pixels that only clipped frames measure, because every frame that saw
        them unclipped was rejected as a ghost, are filled from the measured clipped scene
        around them, above their bound, with a variance that says so
        (:mod:`derender.engine.motion.censored_fill`).
    seed : int
        Seeds the homography's RANSAC.

    Examples
    --------
    >>> from derender.engine.motion.run import MotionOptions
    >>> motion = MotionOptions(reference=2, align="translation", deghost=True)
    >>> motion.needs_motion_run(), MotionOptions().needs_motion_run()
    (True, False)
    >>> MotionOptions(align="translation").needs_motion_run(own_align="translation")
    False
    """

    reference: int | str | None = None
    align: str | None = None
    deghost: bool = False
    ghost_threshold: float | None = None
    compensate: bool = True
    consensus: bool = True
    censored_fill: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        # every message starts with the field's name (the CLI names its flag)
        if self.align is not None and self.align not in ALIGNMENTS:
            raise InputError(f"align takes {', '.join(ALIGNMENTS)}, got {self.align!r}")
        ref = self.reference
        if isinstance(ref, str):
            if ref.strip().lower() != "auto":
                raise InputError(f"reference must be a frame index or 'auto', got {ref!r}")
            object.__setattr__(self, "reference", None)
        elif ref is not None:
            if isinstance(ref, bool) or not float(ref).is_integer() or int(ref) < 0:
                raise InputError(f"reference must be a frame index (from 0) or 'auto', got {ref!r}")
            object.__setattr__(self, "reference", int(ref))
        for name in ("deghost", "compensate", "consensus", "censored_fill"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.ghost_threshold is not None and not (np.isfinite(self.ghost_threshold) and self.ghost_threshold > 0):
            raise InputError(f"ghost_threshold must be a positive number, got {self.ghost_threshold!r}")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise InputError(f"seed must be a whole number (0 or more), got {self.seed!r}")

    def align_for(self, own_align: str = "none") -> str:
        """The alignment to run for a method that registers its frames by ``own_align`` itself."""
        return own_align if self.align is None else self.align

    def needs_motion_run(self, own_align: str = "none") -> bool:
        """Whether a method that registers its frames by ``own_align`` itself (in the plain run)
        needs the engine's motion run for these options: a reference frame, ghost removal, or
        another alignment than its own."""
        return self.deghost or self.reference is not None or self.align_for(own_align) != own_align


def resolve_reference(option: int | None, frames: np.ndarray, order: np.ndarray | None = None) -> int:
    """The reference frame's index among ``frames`` (sorted by time): ``option`` is an index
    among the frames as given (``order[k]`` is frame k's given index), None for paper 1's rule."""
    from derender.engine.motion.reference_frame import select_reference

    n = frames.shape[0]
    if option is None:
        return int(select_reference(frames))
    if not 0 <= option < n:
        raise InputError(f"reference frame {option} is out of range: the bracket has {n} images (0..{n - 1})")
    if order is None:
        return int(option)
    return int(np.flatnonzero(np.asarray(order) == option)[0])


def align_frames(frames: np.ndarray, grey: np.ndarray | None, ref: int, align: str, seed: int = 0,
                 threads: int | None = None) -> tuple[np.ndarray | None, dict[str, Any]]:
    """Register ``frames`` (N, H, W, 3) uint8 to frame ``ref`` and warp them **in place**.

    ``grey``: (N, H, W) uint8 grey images (:func:`derender.engine.motion.ward2003.grey8_codes`),
    made here when None. Returns ``valid`` ((N, H, W) uint8, 1 where the warped pixel comes
    from inside frame j; None when no frame moved) and the details (per-frame shifts or
    homographies, per-pair registration). ``"homography"`` refuses a bracket in which no pair
    of neighbouring frames has features to match (:class:`InputError`); a single dark or
    bright frame falls back to a translation (recorded per pair)."""
    from derender.engine.motion.align import chain_transforms, shift_into, shift_valid, transforms_to_shifts
    from derender.engine.motion.ward2003 import grey8_codes

    n, h, w = frames.shape[:3]
    info: dict[str, Any] = {"align": align}
    if align == "none":
        return None, info
    if grey is None:
        grey = np.empty((n, h, w), dtype=np.uint8)
        for j in range(n):
            grey8_codes(frames[j], out=grey[j])
    method = "translation" if align == "flow" else align
    transforms, pinfo = chain_transforms(list(grey), method, ref, seed=seed, threads=threads)
    pairs = pinfo.get("pairs", [])
    if align == "homography" and pairs and all("fallback" in p for p in pairs):
        reasons = sorted({p.get("reason", "") for p in pairs})
        raise InputError("--align homography found no features to match between any two frames "
                         f"({reasons[0]}); use --align translation or none")
    info["pairs"] = pairs
    valid = None
    if align in ("translation", "flow"):
        shifts = transforms_to_shifts(transforms)
        info["shifts"] = shifts.tolist()
        moved = [j for j in range(n) if shifts[j, 0] or shifts[j, 1]]
        if moved:
            valid = np.ones((n, h, w), dtype=np.uint8)
            tmp = np.empty_like(frames[0])
            for j in moved:
                tmp[...] = frames[j]
                shift_into(frames[j], tmp, int(shifts[j, 0]), int(shifts[j, 1]))
                valid[j] = shift_valid(h, w, int(shifts[j, 0]), int(shifts[j, 1]))
                if align == "flow":
                    gtmp = grey[j].copy()
                    shift_into(grey[j], gtmp, int(shifts[j, 0]), int(shifts[j, 1]))
        if align == "flow":
            valid = _flow_residuals(frames, grey, ref, valid, info)
        return valid, info
    import cv2

    info["homographies"] = transforms.tolist()
    valid = np.ones((n, h, w), dtype=np.uint8)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    ones = np.ones((h, w), dtype=np.uint8)
    for j in range(n):
        if j == ref or np.allclose(transforms[j], np.eye(3)):
            continue
        m = np.asarray(transforms[j], dtype=np.float64)
        warped = cv2.warpPerspective(frames[j], m, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        frames[j] = warped
        cover = cv2.warpPerspective(ones, m, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        valid[j] = cover
    return valid, info


def _flow_residuals(frames: np.ndarray, grey: np.ndarray, ref: int, valid: np.ndarray | None,
                    info: dict[str, Any]) -> np.ndarray | None:
    """``--align flow`` after the translations: each frame, from the reference outwards, is
    warped **in place** by its residual flow against its neighbour nearer the reference (already
    registered; :func:`derender.engine.motion.align.residual_flow`), its grey plane and ``valid``
    with it. Returns ``valid``; ``info["flow"]`` holds each frame's flow summary."""
    from derender.engine.motion.align import flow_warp, residual_flow

    n, h, w = frames.shape[:3]
    info["flow"] = {}
    order = list(range(ref - 1, -1, -1)) + list(range(ref + 1, n))
    for j in order:
        a = j + 1 if j < ref else j - 1
        flow, details = residual_flow(grey[a], grey[j])
        details["warped"] = flow is not None
        info["flow"][j] = details
        if flow is None:
            continue
        _, inside = flow_warp(frames[j], flow, out=frames[j])
        flow_warp(grey[j], flow, out=grey[j])
        if valid is None:
            valid = np.ones((n, h, w), dtype=np.uint8)
        # the frame's own validity (after the translation) follows its pixels, nearest
        vj, _ = flow_warp(valid[j] * np.uint8(255), flow)
        valid[j] = (vj == 255) & inside
    return valid


#: The consistency check of the alignment scores each candidate shift on at most about
#: this many pixels.
REFINE_PIXELS = 1 << 16

#: Candidate corrections (pixels) of each frame's registration shift in that check.
REFINE_REACH = 1


def refine_shifts(frames: np.ndarray, valid: np.ndarray | None, plan, ref: int, rejected: np.ndarray | None,
                  shifts: list | None, threads: int | None = None) -> tuple[np.ndarray | None, dict[str, Any]]:
    """Check each frame's registration against the reference with the method's own noise model,
    leaving out what ghost removal rejected, and move it where it agrees best.

    Ward's bitmaps count every edge alike, so a bright object moving across a dark frame can pull
    its shift by a pixel or two (measured on the simulator: a tripod bracket's darkest frame moved
    by (2, -2) while the static scene had not). Here every correction within
    :data:`REFINE_REACH` pixels of the current registration is scored by the mean capped ``z^2``
    of :func:`derender.engine.motion.intensity_mapping.mapping_z2` over the pixels no frame has rejected (on
    at most :data:`REFINE_PIXELS` of them), ties keeping the registration as it is; the frames
    move **in place** and ``valid`` with them. Returns ``valid`` and the corrections."""
    from derender.engine.motion.align import shift_into, shift_valid
    from derender.engine.motion.deghost import ConsistencyTest, map_frames

    n, h, w = frames.shape[:3]
    test = ConsistencyTest(plan, frames[ref], ref, pixels=REFINE_PIXELS)
    st = test.step
    keep = np.ones((test.hs, test.ws), dtype=bool)
    if rejected is not None:          # on the grid first: the full-resolution planes are N bytes a pixel
        keep &= ~rejected[:, ::st, ::st].any(axis=0)
    if valid is not None:
        keep &= (valid[:, ::st, ::st] != 0).all(axis=0)
    m = max(REFINE_REACH + 1, 2)
    border = np.zeros_like(keep)
    border[-(-m // st):test.hs - (-(-m // st)), -(-m // st):test.ws - (-(-m // st))] = True
    keep &= border
    info: dict[str, Any] = {"corrections": {}}
    if keep.sum() < 256:
        return valid, info
    ok = keep.astype(np.uint8)
    tmp = np.empty_like(frames[0])
    r = int(REFINE_REACH)
    rows0, cols0 = np.arange(0, h, st), np.arange(0, w, st)
    cands = sorted(((dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)), key=lambda d: abs(d[0]) + abs(d[1]))

    def score(j: int) -> list[float]:
        """Frame j's mean capped ``z^2`` at every candidate (reads frame j only: frames in threads)."""
        scores = []
        agreement = None
        for dy, dx in cands:
            # the grid of the frame read at (y + dy, x + dx): gathered, never shifted whole
            grid = frames[j][np.ix_(np.clip(rows0 + dy, 0, h - 1), np.clip(cols0 + dx, 0, w - 1))]
            q, _, agreement = test.statistic(grid, j, ok, agreement, on_grid=True)   # one per frame: comparable
            scores.append(float(q[keep].mean()))
        return scores

    others = [j for j in range(n) if j != ref]
    for j, scores in zip(others, map_frames(score, others, threads)):      # scored in threads, moved in order
        best = int(np.argmin(scores))
        if best != 0 and scores[best] < scores[0] * 0.9:
            dy, dx = cands[best]
            tmp[...] = frames[j]
            shift_into(frames[j], tmp, dy, dx)
            moved = shift_valid(h, w, dy, dx).astype(np.uint8)
            if valid is None:
                valid = np.ones((n, h, w), dtype=np.uint8)
            vj = valid[j].copy()
            shift_into(valid[j], vj, dy, dx)
            valid[j] &= moved
            info["corrections"][j] = [int(dy), int(dx)]
            if shifts is not None:
                shifts[j] = [int(shifts[j][0] + dy), int(shifts[j][1] + dx)]
    return valid, info


#: Neighbouring frames whose threshold bitmaps agree on less than this fraction of the pixels
#: both expose well are not of one scene (measured: 0.85-0.99 for the simulator's moving
#: brackets and the real ones in ``../shared/data``; two different scenes about 0.5).
MIN_BITMAP_AGREEMENT = 0.65

#: The scene check reads at most about this many pixels per frame.
SCENE_CHECK_PIXELS = 1 << 18


def bitmap_agreement(grey_a: np.ndarray, grey_b: np.ndarray) -> float | None:
    """How alike two exposures of one scene look: the fraction of pixels, among those neither
    frame has near its threshold, on the same side of it, over Ward's thresholds at
    :func:`~derender.engine.motion.ward2003.common_percentiles` (exposure-invariant; 1 for one scene,
    about 0.5 for unrelated images). None when they share fewer than 256 such pixels."""
    from derender.engine.motion.ward2003 import common_percentiles, median_threshold_bitmaps

    agree = total = 0
    for q in common_percentiles(grey_a, grey_b):
        ba, ea = median_threshold_bitmaps(grey_a, 4, q)
        bb, eb = median_threshold_bitmaps(grey_b, 4, q)
        both = ea & eb
        agree += int(np.count_nonzero((ba == bb) & both))
        total += int(np.count_nonzero(both))
    return agree / total if total >= 256 else None


def check_one_scene(frames: np.ndarray, names: list[str]) -> list[float | None]:
    """Refuse (:class:`StackError`) a bracket whose neighbouring frames (by time, after
    alignment) disagree in structure: :func:`bitmap_agreement` below
    :data:`MIN_BITMAP_AGREEMENT`. Returns the agreements of the neighbouring pairs."""
    from derender.engine.motion.ward2003 import grey8_codes

    n, h, w = frames.shape[:3]
    s = max(1, int(np.ceil(np.sqrt(h * w / SCENE_CHECK_PIXELS))))
    grey = [grey8_codes(np.ascontiguousarray(frames[j, ::s, ::s])) for j in range(n)]
    out: list[float | None] = []
    for j in range(n - 1):
        a = bitmap_agreement(grey[j], grey[j + 1])
        out.append(None if a is None else round(a, 4))
        if a is not None and a < MIN_BITMAP_AGREEMENT:
            raise StackError(f"{names[j]} and {names[j + 1]} do not show one scene (their structure agrees on "
                             f"{100 * a:.0f} % of the pixels, one scene gives over {100 * MIN_BITMAP_AGREEMENT:.0f} %): "
                             "these images are not one bracket")
    return out


def _access(method, source, frames: np.ndarray, valid: np.ndarray | None, ref: int, threads: int | None):
    """The :class:`~derender.engine.plans.FrameAccess` a method plans from on the motion path:
    held (aligned) frames, the reference, ``valid``; streamed methods' samples only at
    positions every frame takes part in."""
    from derender.engine.plans import FrameAccess
    from derender.engine.tables import code_histograms

    h, w = frames.shape[1:3]
    samples = None
    if not method.holds_frames:
        pos = method.sample_positions(h, w)
        if pos is not None:
            ys, xs = pos
            if valid is not None:
                keep = np.all(valid[:, ys, xs] != 0, axis=0)
                group = int(method.sample_cluster)       # positions come in clusters: keep whole ones
                if group > 1:
                    keep = np.repeat(keep.reshape(-1, group).all(axis=1), group)
                ys, xs = ys[keep], xs[keep]
            samples = frames[:, ys, xs]
            if method.sample_cluster == 1:
                samples = samples.astype(np.int32)
    return FrameAccess(times=source.times, shape=(h, w), samples=samples, frames=frames, threads=threads,
                       histogram_fn=lambda: np.stack([code_histograms(f) for f in frames]),
                       reference=ref, valid=valid, aligned=True)


def run_motion(method, source, motion: MotionOptions, output: OutputOptions | None = None,
               engine: EngineOptions | None = None, *, inputs: Iterable[str | os.PathLike] = (),
               order_hint: str | None = None) -> HDRResult:
    """Merge ``source`` (:class:`~derender.engine.frames.FileFrames` or
    :class:`~derender.engine.frames.ArrayFrames`) with ``method`` on the motion path, and
    optionally write the radiance and the variance to the OpenEXR files of ``output``
    (:func:`derender.engine.outputs.write_outputs`, with the attributes of
    :func:`~derender.engine.outputs.motion_attributes`).

    The motion run of the engine, beside the plain run (:func:`derender.engine.run.run`): the
    registry chooses between them (:func:`derender.hdr.registry.merge`,
    :func:`derender.hdr.files.merge_files`), when ``motion`` asks for a reference frame,
    alignment or ghost removal (:meth:`MotionOptions.needs_motion_run`). ``engine``: its
    ``threads``. ``info["engine_path"]`` is ``"motion"``; the outputs are held
    (``info["outputs_held"]``)."""
    t0 = time.perf_counter()
    if source.n < 2:
        raise StackError("an exposure stack needs at least two images")
    out = output or OutputOptions()
    threads = (engine or EngineOptions()).threads
    res = _merge_motion(method, source, motion, threads, order_hint)
    res.info["engine_path"] = "motion"
    res.info["reference_name"] = source.name(res.info["reference"])
    res.info["outputs_held"] = True
    write_outputs(res, out.output, out.variance_output, half=out.half, compression=out.compression,
                  inputs=list(inputs), threads=threads, name=method.name)
    res.info["total_seconds"] = time.perf_counter() - t0
    return res


def _read_held(source, align: str, threads: int | None, order_hint: str | None):
    """Every frame of ``source`` held (a copy of an in-memory stack's codes: aligned and filled
    in place), Ward's grey planes made in the decoding threads when ``align`` asks, the
    brightness order checked: ``(frames, grey, n_clipped)``."""
    n = source.n
    if isinstance(source, FileFrames):
        h, w = source.infos[0].height, source.infos[0].width
    elif isinstance(source, ArrayFrames):
        h, w = source.codes.shape[1:3]
    else:
        raise TypeError(f"unknown frame source {type(source).__name__}")
    check_memory(n * h * w * 5 + h * w * 16, f"aligning and checking {n} frames of {w}x{h} for motion")
    derive = None
    if align != "none":
        from derender.engine.motion.ward2003 import grey8_codes

        derive = lambda frame, out: grey8_codes(frame, out=out)  # noqa: E731 - made in the decoding threads
    frames, grey = source.read_all(threads, derive=derive)
    if isinstance(source, ArrayFrames) and np.shares_memory(frames, source.codes):
        frames = frames.copy()       # aligned and filled in place: the caller's array stays as it was
    n_clipped = clipped_pixels(frames[0])
    if order_hint is not None:
        check_brightness_order(source.times, [frame_brightness(f) for f in frames],
                               [source.name(j) for j in range(n)], order_hint)
    return frames, grey, n_clipped


class _GhostRemoval:
    """Step 3 of the module docstring on held, aligned frames: detect, check the registration
    (translation), fill from the flow-compensated views, refit the method without the rejected
    pixels and detect again (:mod:`derender.engine.motion.deghost`)."""

    def __init__(self, method, source, frames: np.ndarray, ref: int, motion: MotionOptions, threads: int | None):
        from derender.engine.motion.deghost import GHOST_THRESHOLD

        self.method, self.source, self.frames, self.ref = method, source, frames, ref
        self.motion, self.threads = motion, threads
        self.threshold = GHOST_THRESHOLD if motion.ghost_threshold is None else float(motion.ghost_threshold)
        self.spare: list = []          # a round's rejection plane, reused by the next round
        self.before_fill: np.ndarray | None = None     # frames rejected per pixel before the last fill
        self.hidden: np.ndarray | None = None          # (H, W, 3): a rejected frame has a code below the clip

    def detect(self, plan, valid):
        from derender.engine.motion.deghost import detect_ghosts

        return detect_ghosts(self.frames, plan, self.ref, valid, threshold=self.threshold, threads=self.threads,
                             out=self.spare.pop() if self.spare else None)

    def fill(self, plan, rejected, info, valid) -> None:
        from derender.engine.motion.compensation import compensate_frames
        from derender.engine.motion.deghost import ConsistencyTest

        test = ConsistencyTest(plan, self.frames[self.ref], self.ref, self.threshold)
        # the frames whose own codes will not be merged at each pixel: the fill takes the rejections
        # back where a frame's warped view passes, but those pixels are not that frame's codes either
        self.before_fill = rejected.sum(axis=0, dtype=np.uint8)
        grown: dict = {}
        info["compensation"] = compensate_frames(self.frames, test, rejected, valid, info["agreements"],
                                                 threads=self.threads, grown=grown)
        if grown:                          # the moving thing's inside, grown before the fill: left out too
            from derender.engine.motion.ghost_kernels import upsample_into

            plane = np.empty(rejected.shape[1:], np.uint8)
            for g in grown.values():
                upsample_into(g.view(np.uint8), test.step, plane)
                self.before_fill += plane

    def run(self, plan, access, valid, ainfo: dict):
        """``(plan, access, valid, ghosts, rejected_anywhere, info)`` after ghost removal: the
        (refitted) plan and its access, ``valid`` without the rejected pixels, the count of
        frames rejected per pixel before the fill (None: none; a filled frame takes part with
        its warped codes, not its own) and where any frame is still left out."""
        from derender.engine.motion.deghost import REFIT_MIN_REJECTED, merge_valid

        frames, ref, compensate = self.frames, self.ref, self.motion.compensate
        refits = self.method.refits_on_frames
        rejected, ginfo = self.detect(plan, valid)
        if self.motion.align_for(self.method.own_align) == "translation":
            # the registration checked with the method's noise model, the ghosts left out
            valid, rinfo = refine_shifts(frames, valid, plan, ref, rejected, ainfo.get("shifts"), threads=self.threads)
            ainfo["refined"] = rinfo["corrections"]
            if rinfo["corrections"]:
                if rejected is not None:
                    self.spare.append(rejected)
                rejected, ginfo = self.detect(plan, valid)
        refit = rejected is not None and refits and ginfo["rejected"] >= REFIT_MIN_REJECTED
        if rejected is not None and compensate and not refit:
            self.fill(plan, rejected, ginfo, valid)      # else after the refit (filled pixels posterised the fits)
        rounds = 1
        if refit:
            # fit, detect, refit: the method's calibration on the consistent (and filled) pixels only
            access = _access(self.method, self.source, frames, merge_valid(valid, rejected, in_place=True), ref,
                             self.threads)
            plan = self.method.plan(access)         # (access.valid, the first round's plane, stays: finish may read it)
            rejected, ginfo = self.detect(plan, valid)
            if rejected is not None and compensate:
                self.fill(plan, rejected, ginfo, valid)
            rounds = 2
        ginfo["rounds"] = rounds
        ginfo.pop("agreements", None)      # the per-frame summaries stay in ginfo["frames"]
        ghosts = anywhere = None
        if rejected is not None:
            ghosts = rejected.sum(axis=0, dtype=np.uint8)
            anywhere = ghosts > 0              # where frames are left out of the merge (the consensus corrects there)
            if self.before_fill is not None:   # the ghost map: left out or replaced by the warped view
                ghosts = self.before_fill
        covered = valid is None              # then the merged validity is the rejections' alone: counted
        if rejected is not None and self.motion.censored_fill:     # a frame left out would have measured it
            from derender.engine.motion.censored_fill import hidden_views

            self.hidden = hidden_views(self.frames, rejected)
        valid = merge_valid(valid, rejected, in_place=True)
        self.spare.clear()
        if valid is not None and not (covered and ghosts is not None):
            uncovered = (valid == 0).sum(axis=0, dtype=np.uint8)
            ghosts = uncovered if ghosts is None else np.maximum(ghosts, uncovered)
        return plan, access, valid, ghosts, anywhere, ginfo


def _merge_motion(method, source, motion: MotionOptions, threads: int | None, order_hint: str | None) -> HDRResult:
    """Merge ``source`` with ``method`` on the motion path (module docstring): every frame held,
    the reference chosen, the frames aligned, inconsistent pixels excluded, the method
    calibrated on what is left. ``info`` records ``reference`` (index by time),
    ``reference_input`` (index among the images as given, 0-based), ``align`` (shifts or
    homographies) and ``deghost`` (threshold, rejected fraction per frame, rounds);
    ``result.ghosts`` is the (H, W) uint8 count of frames whose own codes are not merged at
    each pixel (rejected as inconsistent, also where the motion-compensated fill replaced them,
    or not covered after warping)."""
    t0 = time.perf_counter()
    n = source.n
    align = motion.align_for(method.own_align)
    frames, grey, n_clipped = _read_held(source, align, threads, order_hint)
    h, w = frames.shape[1:3]
    t1 = time.perf_counter()
    order = getattr(source, "order", None)
    ref = resolve_reference(motion.reference, frames, order)
    valid, ainfo = align_frames(frames, grey, ref, align, seed=motion.seed, threads=threads)
    del grey
    ainfo["agreement"] = check_one_scene(frames, [source.name(j) for j in range(n)])
    t2 = time.perf_counter()
    access = _access(method, source, frames, valid, ref, threads)
    plan = method.plan(access)
    t3 = time.perf_counter()
    ghosts = anywhere = hidden = None
    ginfo: dict[str, Any] = {}
    if motion.deghost:
        removal = _GhostRemoval(method, source, frames, ref, motion, threads)
        plan, access, valid, ghosts, anywhere, ginfo = removal.run(plan, access, valid, ainfo)
        hidden = removal.hidden
    elif valid is not None:
        ghosts = (valid == 0).sum(axis=0, dtype=np.uint8)
    t4 = time.perf_counter()
    res = merge_held(plan, frames, source.times, threads=threads, valid=valid, ref=ref, name=method.name)
    t45 = time.perf_counter()
    if motion.consensus and anywhere is not None:
        from derender.engine.motion.consensus import consensus_correct

        cinfo = consensus_correct(res.radiance, res.variance, plan, frames, valid, where=anywhere, threads=threads)
        if cinfo is not None:
            res.info["consensus"] = cinfo
    if hidden is not None:
        from derender.engine.motion.censored_fill import censored_fill

        finfo = censored_fill(res.radiance, res.variance, frames, valid, hidden, ref)
        del hidden
        if finfo is not None:
            res.info["censored_fill"] = finfo
    t5 = time.perf_counter()
    res.ghosts = ghosts if ghosts is not None else np.zeros((h, w), dtype=np.uint8)
    res.info.update({"n_clipped": n_clipped, "reference": ref,
                     "reference_input": int(order[ref]) if order is not None else ref, "alignment": ainfo})
    if motion.deghost:
        res.info["deghost"] = ginfo
    res.info["motion"] = {"reference": motion.reference, "align": align, "deghost": motion.deghost,
                          "compensate": motion.compensate, "consensus": motion.consensus,
                          "censored_fill": motion.censored_fill}
    res.info.setdefault("timings", {}).update({"decode_s": t1 - t0, "align_s": t2 - t1, "plan_s": t3 - t2,
                                               "deghost_s": t4 - t3, "merge_s": t45 - t4,
                                               "consensus_s": t5 - t45})
    res.info["streaming"] = {"frames_kept": n, "decodes": n if isinstance(source, FileFrames) else 0}
    res.plan = plan            # the forward model the map was merged with (evaluation.roundtrip)
    method.finish(res, access)
    return res
