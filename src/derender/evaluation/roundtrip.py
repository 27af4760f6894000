"""Round trip: a merge rendered back through its method's own forward model must give back the frames.

A real bracket has no truth, but every method states how a frame's codes become radiance (its
plan, :mod:`derender.engine.plans`). Rendering the merged map back through that statement must
return each frame's codes wherever the frame was unclipped and took part (not a ghost, not
uncovered): a merge that does not re-render its own frames has a model that does not hold.

Per frame ``j`` and channel ``c`` (:func:`round_trip`):

* **table plans** (Debevec & Malik, Robertson): the frame's value table ``v_j(z)`` (log radiance
  ``g(z) - ln t_j``, or its linear form) is inverted on the codes the method gives weight,
  ``z_hat = v_j^-1(ln R_c - k)`` (linear interpolation between codes);
* **matrix plans** (paper 1's stabilised merges): the frame's linear colour is
  ``x = M_j^-1 R e^-k``, and each channel is inverted through its linearisation table,
  ``z_hat_c = L_jc^-1(x_c)``;

``k`` is one log scale per map: the median of ``ln R - v_j(z)`` over every frame's usable
pixel-channels, each counted by its merge weight (the scale the merge itself implies): a map
written in other units (a photometric factor) still round-trips. (The reference frame's own
pixels alone do not fix it: on Memorial its usable codes are mostly the film base, codes
1-15, where one code spans a factor of 2 in radiance; the scale read there was 0.89 off
in ``ln``, and every long frame then missed by 27-39 codes.)
The residual ``|z_hat - z|`` (codes, per pixel and channel) is summarised per frame (median,
p95, pixels) and per
region (a grid of :data:`REGIONS` x :data:`REGIONS` cells), and a map of the pixels where
some frame misses by more than :data:`FAIL_CODES` codes shows where the model fails.

Frames do not count alike in a merge: a frame that is clipped or nearly black almost everywhere
carries little of its weight, and its residual says little about the map. Each frame's
``share`` is the fraction of the merge's weight it carries (the plan's weight table at its
codes, times its image weight, summed over the pixel-channels it takes part in), and the
residuals of all frames pooled with those weights give one ``weighted_median`` and
``weighted_p95`` per merge: the round trip where the map's values come from.

**Registration tolerance** (``tolerance = r`` pixels, :func:`tolerant_residual`). On a handheld
bracket the engine registers frames by one integer shift (or a global homography) while the
scene's parts move differently (parallax between a window frame and the street behind it, lens
distortion, rounding to the pixel): at an edge a frame's code then differs from the map's by the
edge's contrast, whatever the forward model. With ``r > 0`` every :data:`SHIFT_BLOCK`-pixel block
of frame ``j`` first takes the shift ``s`` (steps of :data:`SHIFT_STEP` px, ``|s_y|, |s_x| <= r``,
bilinear) that minimises its mean residual, ``min_s mean_block |z_hat(x) - z_j(x + s)|``, and the
residual is read after it: a local misregistration of up to ``r`` pixels is not counted, while
one shift per block cannot absorb pixel noise, a wrong curve or a wrong gain. Measured on the
ping-pong bracket (``stabilized --deghost``, integer registration): after a global homography
(OpenCV's ECC) the middle frame's textured 128 px blocks still move by up to 2.3 px against the
reference's (phase correlation; most 0.3-2 px, varying across the image).

**Box means** (``scale = S``, :func:`box_means`): the frame's codes and the re-rendered codes
are both averaged over ``S x S`` boxes (pixels whose whole box is usable) before they are
compared. A per-pixel forward model does not render in-camera sharpening, demosaicing or JPEG
blocks: on the sculpture garden (a tripod, where no tolerance helps) 5x5 means take the frames'
medians from 0.94-2.84 to 0.49-1.50 codes (``docs/results.md``, the round trip).

**The black floor is a clip** (``black``, :func:`bracket_black`). A film scan's base and fog
(Memorial: codes 15/20/19, found by the rule the classic merges use to give those codes no
weight, :func:`derender.engine.weights.black_codes`) is a black clip: the frame says only that
the scene is at most that dark, and the forward model, which has no such floor, renders a darker
map below it. Codes at or below the floor are therefore neither scored nor read for the scale,
as clipped whites are not. On Memorial (``stabilized``, 2 px tolerance, 5x5 means) the floor
took the pooled round trip from 1.03 / 5.3 to 0.57 / 2.3 codes: 95 % and more of the short
frames' pixels were film base. A digital bracket has no floor (``[0, 0, 0]``) and is scored as before.

**The reference is scored everywhere.** Ghost removal never leaves the reference frame out
and alignment never moves it: where other frames were left out (or replaced by their
motion-compensated views) the map must still give back the reference's codes. Those pixels
are excluded from the other frames only; a ghost in the output (a second outline, a blend of
instants) then shows in the reference's row. Measured before this rule (2 px, 5x5 means,
``stabilized --deghost``): at the ghost mask's pixels the reference's residual was p95 14 codes
on pingpong (25 % of them over 4) and 25 codes on the sculpture garden (59 %), unscored.

**Registration replayed** (:func:`replay_alignment`). A merge registered with ``--align flow``
or ``homography`` keeps its warped frames to itself; the round trip runs the engine's public
:func:`derender.engine.motion.run.align_frames` again on the same codes with the merge's
reference and seed and refuses the frames unless it finds the registration the merge recorded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FAIL_CODES", "REGIONS", "SHIFT_BLOCK", "SHIFT_STEP", "RoundTrip", "round_trip", "tolerant_residual",
           "box_means", "inverse_tables", "bracket_black", "bracket_round_trip", "FLOOR_PIXELS",
           "replay_alignment"]

#: A frame misses a pixel when its re-rendered code is further than this from its own.
FAIL_CODES = 4.0

#: The residuals are also summarised on a grid of REGIONS x REGIONS cells of the image.
REGIONS = 4


@dataclass
class RoundTrip:
    """Per frame (in the plan's order, by exposure time): ``median`` and ``p95`` of ``|z_hat - z|``
    (codes) over the channels of its usable pixels and their number ``pixels``; ``regions``
    (N, REGIONS, REGIONS) medians per cell (NaN where a cell has none); ``fail`` (H, W) uint8,
    how many frames miss the pixel by more than :data:`FAIL_CODES`; ``share`` (N,) the fraction of
    the merge's weight each frame carries, ``weighted_median`` and ``weighted_p95`` the residual
    pooled over all frames with those weights; ``tolerance`` the registration tolerance (pixels) the
    residuals were taken with and ``scale`` the side of the box means compared (module docstring);
    ``black`` the black floor per channel counted as a black clip (None: none)."""

    median: np.ndarray
    p95: np.ndarray
    pixels: np.ndarray
    regions: np.ndarray
    fail: np.ndarray
    share: np.ndarray
    weighted_median: float
    weighted_p95: float
    tolerance: float = 0.0
    scale: int = 1
    black: list | None = None

    def rows(self, names: list[str] | None = None) -> list[dict]:
        """One JSON-friendly row per frame."""
        out = []
        for j in range(self.median.size):
            out.append({"frame": names[j] if names else j, "median": float(self.median[j]),
                        "p95": float(self.p95[j]), "pixels": int(self.pixels[j]), "share": float(self.share[j])})
        return out


#: Residual histogram bin (codes) of the weighted quantiles.
_BIN = 0.02


def _weighted_quantiles(hist: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """Quantiles of the residuals binned in ``hist`` (weights per :data:`_BIN`-wide bin)."""
    total = float(hist.sum())
    if total <= 0:
        return [float("nan")] * len(qs)
    cum = np.cumsum(hist) / total
    return [float((np.searchsorted(cum, q) + 0.5) * _BIN) for q in qs]


def _weight_table(plan, j: int) -> np.ndarray:
    """Frame j's (256, 3) merge weight per code and channel: the plan's table times its image weight."""
    if _plan_kind(plan) == "table":
        w = np.asarray(plan.weight_of(j), dtype=np.float64)
        if plan.image_weights is not None:
            w = w * float(np.asarray(plan.image_weights)[j])
        return w
    return np.asarray(plan.weights, dtype=np.float64)


def inverse_tables(values: np.ndarray, usable: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per channel, the (value, code) pairs of the usable codes of a frame's (256, 3) table, in
    increasing value (ties and reversals dropped: the inverse of a monotone response)."""
    out = []
    codes = np.arange(values.shape[0], dtype=np.float64)
    for c in range(values.shape[1]):
        ok = usable[:, c] & np.isfinite(values[:, c])
        v, z = values[ok, c].astype(np.float64), codes[ok]
        keep = np.concatenate([[True], np.diff(np.maximum.accumulate(v)) > 0]) if v.size else np.zeros(0, bool)
        out.append((v[keep], z[keep]))
    return out


def _plan_kind(plan) -> str:
    from derender.engine.plans import MatrixPlan, TablePlan

    if isinstance(plan, TablePlan):
        return "table"
    if isinstance(plan, MatrixPlan):
        return "matrix"
    raise TypeError(f"no forward model to render a {type(plan).__name__} back (table and matrix plans only)")


def _frame_log_values(plan, j: int) -> np.ndarray:
    """Frame j's (256, 3) per-channel table in the log domain (table plans: as the plan says)."""
    vals = np.asarray(plan.values[j], dtype=np.float64)
    if _plan_kind(plan) == "table" and plan.domain == "log":
        return vals
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(vals > 0, np.log(vals), -np.inf)


def _usable(plan, j: int, black=None) -> np.ndarray:
    """Frame j's (256, 3) codes the round trip reads: the merge gives them weight and they lie
    above the bracket's black floor ``black`` (per channel; none when None)."""
    w = np.asarray(plan.weight_of(j) if _plan_kind(plan) == "table" else plan.weights)
    ok = w > 0
    if black is not None:
        for c, b in enumerate(black):
            ok[: max(int(b), -1) + 1, c] = False
    return ok


def _frame_view(plan, frames: np.ndarray, j: int) -> np.ndarray:
    """Frame j's codes on the result's grid (a matrix plan's integer shift applied)."""
    shifts = getattr(plan, "shifts", None)
    if shifts is None or _plan_kind(plan) != "matrix":
        return frames[j]
    dy, dx = (int(s) for s in np.asarray(shifts)[j])
    if dy == 0 and dx == 0:
        return frames[j]
    from derender.engine.motion.align import shift_into

    out = np.empty_like(frames[j])
    shift_into(out, frames[j], dy, dx)
    return out


def _log_prediction(plan, table: np.ndarray, j: int, z: np.ndarray) -> np.ndarray:
    """``ln`` of what frame j's codes ``z`` say the map is (up to the map's scale): the table
    (table plans) or ``ln(M_j L_j(z))`` (matrix plans)."""
    if _plan_kind(plan) == "table":
        return table[z, np.arange(3)]
    lin = np.exp(table[z, np.arange(3)])
    mixed = np.einsum("ck,...k->...c", np.asarray(plan.matrices[j], np.float64), lin)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(mixed > 0, np.log(np.maximum(mixed, 1e-300)), np.nan)


def _log_scale(plan, frames: np.ndarray, log_r: np.ndarray, tables: list, usable: list,
               exclude: np.ndarray | None) -> float:
    """The map's log scale ``k``: the weighted median of ``ln R - prediction`` over every frame's
    usable pixel-channels (every ``step``-th row), weights the merge's (module docstring)."""
    step = max(1, frames.shape[1] // 256)
    diffs, weights = [], []
    for j in range(frames.shape[0]):
        z = _frame_view(plan, frames, j)[::step].astype(np.intp)
        pred = _log_prediction(plan, tables[j], j, z)
        wz = _weight_table(plan, j)[z, np.arange(3)]
        ok = usable[j][z, np.arange(3)] & np.isfinite(pred) & (wz > 0)
        if exclude is not None:
            ok &= (np.asarray(exclude[j])[::step] == 0)[..., None]
        diffs.append((log_r[::step] - pred)[ok])
        weights.append(wz[ok])
    d, w = np.concatenate(diffs), np.concatenate(weights)
    if d.size == 0:
        return 0.0
    order = np.argsort(d, kind="stable")
    cum = np.cumsum(w[order])
    return float(d[order][np.searchsorted(cum, 0.5 * cum[-1])])


#: Side (pixels) of the blocks that each take one registration shift (:func:`tolerant_residual`).
SHIFT_BLOCK = 32

#: Step (pixels) of the shifts a block may take (:func:`tolerant_residual`).
SHIFT_STEP = 0.5


def box_means(z: np.ndarray, zhat: np.ndarray, ok: np.ndarray, scale: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``scale x scale`` box means of a frame's codes ``z`` and of its re-rendered codes ``zhat``
    (H, W, 3), and the pixels whose whole box is in ``ok`` (H, W) (the only ones scored):
    ``(z_mean, zhat_mean, ok_box)``, float32, float32, bool (module docstring).

    Examples
    --------
    >>> import numpy as np
    >>> z = np.tile(np.array([[100, 110]], np.uint8), (4, 2))[..., None].repeat(3, axis=-1)
    >>> zhat = np.full((4, 4, 3), 105.0)                   # right on average, not pixel by pixel
    >>> zm, zhm, ok = box_means(z, zhat, np.ones((4, 4), bool), 2)
    >>> float(np.abs(zm - zhm)[ok].max()) <= 0.0 + 1e-6
    True
    """
    import cv2

    k = int(scale)
    if k < 1:
        raise ValueError(f"scale must be >= 1 pixel, got {scale}")
    okb = np.asarray(ok, dtype=bool)
    if k == 1:
        return np.asarray(z, np.float32), np.asarray(zhat, np.float32), okb
    zm = cv2.blur(np.asarray(z, np.float32), (k, k), borderType=cv2.BORDER_REPLICATE)
    zhm = cv2.blur(np.asarray(zhat, np.float32), (k, k), borderType=cv2.BORDER_REPLICATE)
    inside = cv2.erode(okb.astype(np.uint8), np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT,
                       borderValue=0) > 0
    return zm.reshape(np.shape(z)), zhm.reshape(np.shape(z)), inside


def tolerant_residual(z: np.ndarray, zhat: np.ndarray, tolerance: float = 0, ok: np.ndarray | None = None) -> np.ndarray:
    """``|z_hat - z|`` (``tolerance`` 0), or the residual after each :data:`SHIFT_BLOCK`-pixel block
    of the frame ``z`` (H, W, 3) takes the shift (steps of :data:`SHIFT_STEP`, at most
    ``tolerance`` pixels in y and x; bilinear) that fits ``z_hat`` best over the block's pixels
    ``ok`` (module docstring): (H, W, 3) float64. One shift per block cannot follow pixel noise,
    a wrong curve or gain; it follows a misregistration of up to ``tolerance`` pixels.

    Examples
    --------
    >>> import numpy as np
    >>> z = np.zeros((32, 32, 3), np.uint8); z[:, 17:] = 100      # an edge
    >>> zhat = np.zeros((32, 32, 3)); zhat[:, 16:] = 100.0        # the map's edge one pixel off
    >>> float(tolerant_residual(z, zhat).max()), float(tolerant_residual(z, zhat, 1).max())
    (100.0, 0.0)
    """
    zf = np.asarray(z, dtype=np.float64)
    zhat = np.asarray(zhat, dtype=np.float64)
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0 pixels, got {tolerance}")
    best = np.abs(zhat - zf)
    if tolerance == 0:
        return best
    import cv2

    h, w = zf.shape[:2]
    b = SHIFT_BLOCK
    by, bx = np.minimum(np.arange(h) // b, (h - 1) // b), np.minimum(np.arange(w) // b, (w - 1) // b)
    nby, nbx = int(by[-1]) + 1, int(bx[-1]) + 1
    cells = (by[:, None] * nbx + bx[None, :]).ravel()
    okf = np.ones((h, w)) if ok is None else np.asarray(ok, dtype=np.float64)
    count = np.maximum(np.bincount(cells, weights=okf.ravel(), minlength=nby * nbx), 1.0)

    def score(d: np.ndarray) -> np.ndarray:
        return np.bincount(cells, weights=(d.mean(axis=-1) * okf).ravel(), minlength=nby * nbx) / count

    best_score = score(best)
    src = zf.astype(np.float32)
    steps = np.arange(-float(tolerance), float(tolerance) + 1e-9, SHIFT_STEP)
    for dy in steps:
        for dx in steps:
            if dy == 0 and dx == 0:
                continue
            m = np.float32([[1, 0, -dx], [0, 1, -dy]])      # the frame's code at (y + dy, x + dx)
            moved = cv2.warpAffine(src, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            d = np.abs(zhat - moved.reshape(zf.shape))
            sc = score(d)
            better = sc < best_score
            if np.any(better):
                take = better[cells].reshape(h, w)
                best[take] = d[take]
                best_score = np.where(better, sc, best_score)
    return best


def round_trip(plan, frames: np.ndarray, radiance: np.ndarray, *,
               exclude: np.ndarray | None = None, tolerance: float = 0, scale: int = 1,
               black=None) -> RoundTrip:
    """:class:`RoundTrip` of ``radiance`` (H, W, 3) against ``frames`` (N, H, W, 3) uint8, by time, on
    the grid the plan merged them), rendered back through ``plan`` (module docstring).
    The map's log scale ``k`` is the one the merge implies (module docstring); ``exclude`` (N, H, W)
    nonzero where a frame did not take part (ghost removal, not covered after alignment);
    ``tolerance`` the registration tolerance in pixels (:func:`tolerant_residual`); ``scale`` > 1
    compares ``scale x scale`` box means of the codes and of the re-rendered codes (:func:`box_means`);
    ``black`` the bracket's black floor per channel (:func:`derender.engine.weights.black_codes`):
    codes at or below it are a black clip, neither scored nor read for the scale."""
    kind = _plan_kind(plan)
    n, h, w = frames.shape[:3]
    rad = np.maximum(np.asarray(radiance, dtype=np.float64), 1e-300)
    log_r = np.log(rad)
    tables = [_frame_log_values(plan, j) for j in range(n)]
    usable = [_usable(plan, j, black) for j in range(n)]
    k = _log_scale(plan, frames, log_r, tables, usable, exclude)
    med, p95, cnt = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, np.int64)
    regions = np.full((n, REGIONS, REGIONS), np.nan)
    fail = np.zeros((h, w), np.uint8)
    carried = np.zeros(n)
    hist = np.zeros(int(256 / _BIN) + 1)
    ry = np.minimum(np.arange(h) * REGIONS // h, REGIONS - 1)
    rx = np.minimum(np.arange(w) * REGIONS // w, REGIONS - 1)
    cell = (ry[:, None] * REGIONS + rx[None, :])
    for j in range(n):
        z = _frame_view(plan, frames, j).astype(np.intp)
        ok = usable[j][z, np.arange(3)].all(axis=-1)
        if exclude is not None:
            ok &= np.asarray(exclude[j]) == 0
        if kind == "table":
            target = log_r - k
        else:
            minv = np.linalg.inv(np.asarray(plan.matrices[j], np.float64))
            x = np.einsum("ck,hwk->hwc", minv, rad * np.exp(-k))
            ok &= np.all(x > 0, axis=-1)
            target = np.log(np.maximum(x, 1e-300))
        zhat = np.empty((h, w, 3))
        for c, (v, zz) in enumerate(inverse_tables(tables[j], usable[j])):
            if v.size < 2:
                ok &= False
                zhat[..., c] = 0.0
                continue
            zhat[..., c] = np.interp(target[..., c], v, zz)
        if scale > 1:                              # compare box means (module docstring)
            zc, zhc, ok = box_means(z, zhat, ok, scale)
        else:
            zc, zhc = z, zhat
        d = tolerant_residual(zc, zhc, tolerance, ok)   # per pixel and channel
        sel = d[ok].ravel()
        cnt[j] = int(np.count_nonzero(ok))
        if sel.size:
            med[j], p95[j] = float(np.median(sel)), float(np.quantile(sel, 0.95))
            sums = np.bincount(cell[ok], minlength=REGIONS * REGIONS)
            for r in np.flatnonzero(sums):
                regions[j].flat[r] = float(np.median(d[ok & (cell == r)]))
        fail += (ok & (d.max(axis=-1) > FAIL_CODES)).astype(np.uint8)
        wz = _weight_table(plan, j)[z, np.arange(3)][ok]            # the weight each residual carries
        carried[j] = float(wz.sum())
        hist += np.bincount(np.minimum(d[ok] / _BIN, hist.size - 1).astype(np.intp).ravel(), weights=wz.ravel(),
                            minlength=hist.size)
    share = carried / carried.sum() if carried.sum() > 0 else carried
    wmed, wp95 = _weighted_quantiles(hist, (0.5, 0.95))
    return RoundTrip(median=med, p95=p95, pixels=cnt, regions=regions, fail=fail, share=share,
                     weighted_median=wmed, weighted_p95=wp95, tolerance=float(tolerance),
                     scale=int(scale), black=None if black is None else [int(b) for b in black])


def replay_alignment(frames: np.ndarray, res, motion=None) -> None:
    """Warp ``frames`` (N, H, W, 3) uint8, by time, **in place** as the merge ``res`` did with
    ``--align flow`` or ``homography``: the engine's public
    :func:`derender.engine.motion.run.align_frames` run again on the same codes with the merge's
    reference and seed (the merge keeps its warped frames and flows to itself). The
    registration found must be the one the merge recorded (``res.info["alignment"]``: integer
    shifts and each frame's flow summary, or the homographies), else :class:`InputError`: a
    round trip against other warps would score the registration, not the model."""
    from derender.core.errors import InputError
    from derender.engine.motion.run import align_frames

    al = res.info.get("alignment") or {}
    mode = al.get("align")
    seed = int(getattr(motion, "seed", 0) or 0)
    _, info = align_frames(frames, None, int(res.info["reference"]), mode, seed=seed)
    if mode == "flow":
        same = info.get("shifts") == al.get("shifts") and _plain(info.get("flow")) == _plain(al.get("flow"))
    else:
        same = np.allclose(np.asarray(info.get("homographies")), np.asarray(al.get("homographies")), atol=1e-9)
    if not same:
        raise InputError(f"the round trip could not reproduce the merge's --align {mode} registration")


def _plain(x):
    """``x`` with dict keys as strings and arrays as lists (two registration records compared)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


#: :func:`bracket_black` reads the black floor on about this many pixels of every frame.
FLOOR_PIXELS = 65536


def bracket_black(frames: np.ndarray, times) -> list[int]:
    """The bracket's black floor per channel, by the rule the merges use
    (:func:`derender.engine.weights.black_codes`), read on a grid of about :data:`FLOOR_PIXELS`
    pixels of ``frames`` (N, H, W, 3), registered, with exposure ``times`` (N,): ``[0, 0, 0]`` on
    a digital bracket, the film base and fog on a film scan (Memorial: codes 13-20).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> scene = rng.uniform(0.2, 1.0, (64, 64, 3))
    >>> scene[:32] = 0.0                          # the top half unexposed
    >>> times = np.array([1.0, 2.0, 4.0, 8.0])
    >>> base = 16                                 # a film base: no frame goes below code 16
    >>> frames = np.stack([base + 200 * scene * t / 8 for t in times]).astype(np.uint8)
    >>> bracket_black(frames, times)
    [16, 16, 16]
    """
    from derender.engine.weights import black_codes

    z = np.asarray(frames)
    n, h, w = z.shape[:3]
    step = max(1, int(np.sqrt(h * w / FLOOR_PIXELS)))
    return [int(b) for b in black_codes(z[:, ::step, ::step].reshape(n, -1, z.shape[-1]), times)]


def bracket_round_trip(paths, method: str = "debevec", *, times=None, times_file=None, times_file_inverse: bool = False,
                       motion=None, tolerance: float = 0, scale: int = 1,
                       floor: bool = True) -> tuple[RoundTrip, "object", list[str]]:
    """Merge the image files ``paths`` with ``method`` (:func:`derender.hdr.files.merge_files`,
    its ``motion``: reference, align, deghost, a
    :class:`~derender.engine.motion.run.MotionOptions`), then render the map back through the
    method's plan against the files' own codes (:func:`round_trip`): the frames in exposure
    order, moved by the engine's registration (integer shifts; flow and homography warps replayed,
    :func:`replay_alignment`), pixels where ghost removal or alignment
    left any frame out excluded from every frame but the reference (module docstring), ``tolerance`` the registration tolerance (pixels,
    :func:`tolerant_residual`) and ``scale`` the box means compared (:func:`box_means`); with
    ``floor`` the bracket's black floor (:func:`bracket_black`) is a black clip. Returns the
    :class:`RoundTrip`, the merge result and the frames' names in exposure order."""
    from pathlib import Path

    from derender.core.errors import InputError
    from derender.hdr.files import merge_files
    from derender.io.exif import file_times
    from derender.io.files import expand_image_paths
    from derender.io.images import read_codes

    paths = expand_image_paths(paths)
    res = merge_files(paths, times, method=method, times_file=times_file, times_file_inverse=times_file_inverse,
                      motion=motion)
    if res.plan is None:
        raise InputError(f"merge method {method!r} has no engine plan to render back")
    try:
        _plan_kind(res.plan)
    except TypeError as exc:
        raise InputError(f"merge method {method!r}: {exc}") from None
    t = np.asarray(file_times(paths, times, times_file, times_file_inverse), dtype=np.float64)
    order = np.argsort(t, kind="stable")
    frames = []
    for i in order:
        codes = read_codes(paths[i])
        if codes is None:
            raise InputError(f"{Path(paths[i]).name} is not an 8-bit image: the round trip reads 8-bit codes")
        frames.append(codes)
    frames = np.stack(frames)
    al = res.info.get("alignment") or {}
    shifts = al.get("shifts")
    if al.get("align") in ("flow", "homography"):
        replay_alignment(frames, res, motion)
    elif shifts is not None:
        from derender.engine.motion.align import shift_into

        tmp = np.empty_like(frames[0])
        for j, (dy, dx) in enumerate(shifts):
            if dy or dx:
                tmp[...] = frames[j]
                shift_into(frames[j], tmp, int(dy), int(dx))
    exclude = None
    if res.ghosts is not None and np.any(res.ghosts):
        exclude = np.repeat((res.ghosts != 0)[None], frames.shape[0], axis=0)
        ref = res.info.get("reference")
        if ref is not None:
            exclude[int(ref)] = False     # never left out nor warped: the map must give back its instant
    black = bracket_black(frames, t[order]) if floor else None
    rt = round_trip(res.plan, frames, res.radiance, exclude=exclude, tolerance=tolerance, scale=scale, black=black)
    return rt, res, [Path(paths[i]).name for i in order]
