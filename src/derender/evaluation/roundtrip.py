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

``k`` is one log scale per map (the median over the reference frame's usable pixel-channels
of ``ln R - v_ref(z)``): a map written in other units (a photometric factor) still round-trips.
The residual ``|z_hat - z|`` (codes, per pixel and channel) is summarised per frame (median,
p95, pixels) and per
region (a grid of :data:`REGIONS` x :data:`REGIONS` cells), and a map of the pixels where
some frame misses by more than :data:`FAIL_CODES` codes shows where the model fails.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FAIL_CODES", "REGIONS", "RoundTrip", "round_trip", "inverse_tables", "bracket_round_trip"]

#: A frame misses a pixel when its re-rendered code is further than this from its own.
FAIL_CODES = 4.0

#: The residuals are also summarised on a grid of REGIONS x REGIONS cells of the image.
REGIONS = 4


@dataclass
class RoundTrip:
    """Per frame (in the plan's order, by exposure time): ``median`` and ``p95`` of ``|z_hat - z|``
    (codes) over the channels of its usable pixels and their number ``pixels``; ``regions``
    (N, REGIONS, REGIONS) medians per cell (NaN where a cell has none); ``fail`` (H, W) uint8,
    how many frames miss the pixel by more than :data:`FAIL_CODES`."""

    median: np.ndarray
    p95: np.ndarray
    pixels: np.ndarray
    regions: np.ndarray
    fail: np.ndarray

    def rows(self, names: list[str] | None = None) -> list[dict]:
        """One JSON-friendly row per frame."""
        out = []
        for j in range(self.median.size):
            out.append({"frame": names[j] if names else j, "median": float(self.median[j]),
                        "p95": float(self.p95[j]), "pixels": int(self.pixels[j])})
        return out


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


def _usable(plan, j: int) -> np.ndarray:
    w = np.asarray(plan.weight_of(j) if _plan_kind(plan) == "table" else plan.weights)
    return w > 0


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


def round_trip(plan, frames: np.ndarray, radiance: np.ndarray, *, reference: int,
               exclude: np.ndarray | None = None) -> RoundTrip:
    """:class:`RoundTrip` of ``radiance`` (H, W, 3) against ``frames`` (N, H, W, 3) uint8, by time, on
    the grid the plan merged them), rendered back through ``plan`` (module docstring).
    ``reference``: the frame whose usable pixels fix the log scale ``k``; ``exclude`` (N, H, W)
    nonzero where a frame did not take part (ghost removal, not covered after alignment)."""
    kind = _plan_kind(plan)
    n, h, w = frames.shape[:3]
    rad = np.maximum(np.asarray(radiance, dtype=np.float64), 1e-300)
    log_r = np.log(rad)
    tables = [_frame_log_values(plan, j) for j in range(n)]
    usable = [_usable(plan, j) for j in range(n)]
    # one log scale: the reference frame's own usable pixel-channels (a sample of rows)
    step = max(1, h // 256)
    zr = _frame_view(plan, frames, reference)[::step].astype(np.intp)
    lr = log_r[::step]
    okr = usable[reference][zr, np.arange(3)]
    if kind == "table":
        pred_r = tables[reference][zr, np.arange(3)]
    else:
        lin = np.exp(tables[reference][zr, np.arange(3)])
        pred_r = np.log(np.maximum(np.einsum("ck,hwk->hwc", np.asarray(plan.matrices[reference], np.float64), lin),
                                   1e-300))
    okr &= np.isfinite(pred_r)
    k = float(np.median((lr - pred_r)[okr])) if okr.any() else 0.0
    med, p95, cnt = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, np.int64)
    regions = np.full((n, REGIONS, REGIONS), np.nan)
    fail = np.zeros((h, w), np.uint8)
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
        d = np.abs(zhat - z)                       # per pixel and channel
        sel = d[ok].ravel()
        cnt[j] = int(np.count_nonzero(ok))
        if sel.size:
            med[j], p95[j] = float(np.median(sel)), float(np.quantile(sel, 0.95))
            sums = np.bincount(cell[ok], minlength=REGIONS * REGIONS)
            for r in np.flatnonzero(sums):
                regions[j].flat[r] = float(np.median(d[ok & (cell == r)]))
        fail += (ok & (d.max(axis=-1) > FAIL_CODES)).astype(np.uint8)
    return RoundTrip(median=med, p95=p95, pixels=cnt, regions=regions, fail=fail)


def bracket_round_trip(paths, method: str = "debevec", *, times=None, times_file=None, times_file_inverse: bool = False,
                       motion=None) -> tuple[RoundTrip, "object", list[str]]:
    """Merge the image files ``paths`` with ``method`` (:func:`derender.hdr.files.merge_files`,
    its ``motion``: reference, align, deghost, a
    :class:`~derender.engine.motion.run.MotionOptions`), then render the map back through the
    method's plan against the files' own codes (:func:`round_trip`): the frames in exposure
    order, moved by the engine's integer registration, pixels where ghost removal or alignment
    left any frame out excluded. Returns the :class:`RoundTrip`, the merge result and the frames'
    names in exposure order."""
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
    if al.get("homographies") is not None and al.get("shifts") is None:
        raise InputError("the round trip follows integer registrations only: merge with --align none or translation")
    shifts = al.get("shifts")
    if shifts is not None:
        from derender.engine.motion.align import shift_into

        tmp = np.empty_like(frames[0])
        for j, (dy, dx) in enumerate(shifts):
            if dy or dx:
                tmp[...] = frames[j]
                shift_into(frames[j], tmp, int(dy), int(dx))
    exclude = None
    if res.ghosts is not None and np.any(res.ghosts):
        exclude = np.broadcast_to(res.ghosts != 0, frames.shape[:3])
    ref = res.info.get("reference")
    ref = int(ref) if ref is not None else frames.shape[0] // 2
    rt = round_trip(res.plan, frames, res.radiance, reference=ref, exclude=exclude)
    return rt, res, [Path(paths[i]).name for i in order]
