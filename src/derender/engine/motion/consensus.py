"""Consensus correction: pixels merged from a subset of the frames carry that subset's rendering bias; remove it.

Beyond both papers. Ghost removal (:mod:`derender.engine.motion.deghost`) and alignment leave
frames out of a pixel: where an object moved only the reference frame (and the frames that
agree with it) is merged. A method with one response curve for the whole bracket
(Debevec & Malik, Robertson) renders each frame through that common curve, but a camera that
changes gain, white balance or tone curve between frames (the ``auto`` pipelines) renders
frame ``j`` a little brighter or darker than the curve says, by an amount that depends on the
code. Where every frame takes part these biases average out; where one frame is left alone
its own bias is the pixel's error (measured on the ``paper`` family: Robertson's object pixels
that the reference sees unclipped were 2.5x the still twin's error with only the reference
left, although ghost removal kept exactly the right frames).

Per frame ``j`` and channel ``c``, with ``mu_j(z)`` the plan's log radiance of code ``z`` and
``w_j(z)`` its merge weight, on the pixels every frame takes part in (set ``A``, on a grid of at
most :data:`CONSENSUS_PIXELS`):

    m(p)      = sum_j w_j(z_jp) mu_j(z_jp) / sum_j w_j(z_jp)                  (the consensus)
    d_j(c, b) = med_{p in A, z_jpc in bin b} [mu_j(z_jpc) - m_c(p)]           (frame j's bias)
    d_j      <- d_j * d_j^2 / (d_j^2 + MAD_j^2)                                (shrunk where the bin scatters)

in bins of :data:`CONSENSUS_BIN` codes (bins with fewer than :data:`CONSENSUS_MIN_COUNT`
pixels get no correction). A pixel merged from the frames ``S`` (``valid``) is then divided by

    exp( sum_{j in S} w_j(z_jp) d_j(c, bin(z_jpc)) / sum_{j in S} w_j(z_jp) )

per channel, and its variance by that factor squared. Pixels every frame takes part in are
not touched (their result is byte-identical), nor are channels no frame observes. The engine
corrects where ghost removal left frames out (``MotionOptions.consensus``, on with
``deghost``); pixels that lack a frame only because alignment did not cover them keep their
value, so that ``--align`` alone changes nothing (measured: on the tuning families correcting
them too changed the static zone by 0.01-0.02 of the still twin's error; on the held-out
``dslr-lut`` handheld brackets it raised Robertson's static ratio 1.03 -> 1.14).

Only table plans (one curve per channel for the bracket) are corrected: paper 1's stabilised
merges fit a gamma and a 3x3 matrix per frame, and paper 2's model a distribution per colour,
and neither gained on the tuning families (``derender experiment ghosts``, docs/results-ghosts.md).
Shrinkage: the held-out ``dslr-lut`` family's 3D LUT makes the bias hue-dependent, which no
per-code table can hold; the shrinkage keeps such bins near zero.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit, prange

__all__ = ["CONSENSUS_BIN", "CONSENSUS_MIN_COUNT", "CONSENSUS_PIXELS", "frame_biases", "consensus_correct"]

#: Codes per bin of the per-frame bias tables.
CONSENSUS_BIN = 16

#: A bin needs this many consensus pixels to be corrected.
CONSENSUS_MIN_COUNT = 20

#: The bias tables are measured on every s-th row and column so that at most about this many
#: pixels remain.
CONSENSUS_PIXELS = 1 << 16

def _log_tables(plan) -> tuple[np.ndarray, np.ndarray]:
    """(N, 256, 3) float64 log radiance of every frame's codes (NaN where not finite) and their
    merge weights (N, 256, 3) float64 (0 where clipped), from a table plan."""
    vals = np.asarray(plan.values, dtype=np.float64)
    if plan.domain == "linear":
        with np.errstate(divide="ignore", invalid="ignore"):
            vals = np.where(vals > 0, np.log(vals), np.nan)
    vals = np.where(np.isfinite(vals), vals, np.nan)
    n = vals.shape[0]
    w = np.stack([np.asarray(plan.weight_of(j), dtype=np.float64) for j in range(n)])
    if plan.image_weights is not None:
        w = w * np.asarray(plan.image_weights, dtype=np.float64)[:, None, None]
    w = np.where(np.isfinite(vals) & (w > 0), w, 0.0)
    return np.nan_to_num(vals, nan=0.0), w


def _gather(codes: np.ndarray, vals: np.ndarray, w: np.ndarray, mean_weights: bool) -> tuple[np.ndarray, np.ndarray]:
    """Log radiance and weights (N, K, 3) of codes (N, K, 3) uint8 under per-frame tables."""
    n = codes.shape[0]
    ch = np.arange(3)
    mu = np.empty(codes.shape, np.float64)
    wt = np.empty(codes.shape, np.float64)
    for j in range(n):
        z = codes[j].astype(np.intp)
        mu[j] = vals[j][z, ch]
        wt[j] = w[j][z, ch]
    if mean_weights:                    # the kernel's "mean" mode: one weight, every channel
        wt[:] = wt.mean(axis=-1, keepdims=True)
    return mu, wt


def frame_biases(plan, codes: np.ndarray, *, tables: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Per-frame bias tables ``d`` (N, 3, 256 // CONSENSUS_BIN) float64 (module docstring) from
    ``codes`` (N, K, 3) uint8: pixels every frame takes part in. ``tables``: the plan's log
    radiance and weight tables when the caller has them already."""
    vals, w = _log_tables(plan) if tables is None else tables
    n, k = codes.shape[:2]
    nb = 256 // CONSENSUS_BIN
    out = np.zeros((n, 3, nb))
    if k == 0:
        return out
    mu, wt = _gather(codes, vals, w, plan.channel_weights == "mean")
    sw = wt.sum(axis=0)
    cons = (wt * mu).sum(axis=0) / np.where(sw > 0, sw, 1.0)
    bins = codes.astype(np.intp) // CONSENSUS_BIN
    for j in range(n):
        d = mu[j] - cons
        for c in range(3):
            use = (wt[j][:, c] > 0) & (sw[:, c] > wt[j][:, c])     # observed, and some other frame too
            if not use.any():
                continue
            dc, bc = d[use, c], bins[j][use, c]
            order = np.argsort(bc, kind="stable")
            dc, bc = dc[order], bc[order]
            starts = np.searchsorted(bc, np.arange(nb + 1))
            for b in range(nb):
                seg = dc[starts[b]:starts[b + 1]]
                if seg.size < CONSENSUS_MIN_COUNT:
                    continue
                med = float(np.median(seg))
                mad = 1.4826 * float(np.median(np.abs(seg - med)))
                out[j, c, b] = med * med * med / (med * med + mad * mad + 1e-12)
    return out


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _correct_kernel(frames, valid, where, w_lut, d_lut, mean_w, radiance, variance, has_variance):  # pragma: no cover - compiled
    """Per pixel (rows in parallel) where ``where`` and some frame is left out: divide by
    ``exp(sum_S w d / sum_S w)`` per channel. Returns per row (touched pixels, sum |delta|)."""
    n, h, w = valid.shape
    counts = np.zeros(h, np.int64)
    sums = np.zeros(h, np.float64)
    for y in prange(h):
        for x in range(w):
            if not where[y, x]:
                continue
            full = True
            for j in range(n):
                if valid[j, y, x] == 0:
                    full = False
                    break
            if full:
                continue
            counts[y] += 1
            num0 = 0.0
            num1 = 0.0
            num2 = 0.0
            den0 = 0.0
            den1 = 0.0
            den2 = 0.0
            for j in range(n):
                if valid[j, y, x] == 0:
                    continue
                z0 = frames[j, y, x, 0]
                z1 = frames[j, y, x, 1]
                z2 = frames[j, y, x, 2]
                a0 = w_lut[j, z0, 0]
                a1 = w_lut[j, z1, 1]
                a2 = w_lut[j, z2, 2]
                if mean_w:
                    m = (a0 + a1 + a2) / 3.0
                    a0 = m
                    a1 = m
                    a2 = m
                num0 += a0 * d_lut[j, z0, 0]
                num1 += a1 * d_lut[j, z1, 1]
                num2 += a2 * d_lut[j, z2, 2]
                den0 += a0
                den1 += a1
                den2 += a2
            d0 = num0 / den0 if den0 > 0 else 0.0
            d1 = num1 / den1 if den1 > 0 else 0.0
            d2 = num2 / den2 if den2 > 0 else 0.0
            f0 = np.exp(-d0)
            f1 = np.exp(-d1)
            f2 = np.exp(-d2)
            radiance[y, x, 0] *= f0
            radiance[y, x, 1] *= f1
            radiance[y, x, 2] *= f2
            if has_variance:
                variance[y, x, 0] *= f0 * f0
                variance[y, x, 1] *= f1 * f1
                variance[y, x, 2] *= f2 * f2
            sums[y] += abs(d0) + abs(d1) + abs(d2)
    return counts, sums


def consensus_correct(radiance: np.ndarray, variance: np.ndarray | None, plan, frames: np.ndarray,
                      valid: np.ndarray | None, *, where: np.ndarray | None = None,
                      threads: int | None = None) -> dict[str, Any] | None:
    """Correct, in place, the pixels of ``radiance`` (H, W, 3) float32 (and ``variance``) that were
    merged from a subset of ``frames`` (N, H, W, 3) uint8 (``valid`` (N, H, W) uint8, 0 = left out)
    under a table ``plan`` (module docstring); ``where`` (H, W) bool limits the correction to those
    pixels (the engine: where ghost removal left a frame out). Returns a summary for the
    result's info, or None when nothing was corrected (no table plan, or every frame takes
    part everywhere). ``threads``: the compiled kernel's (all CPUs when None)."""
    from derender.engine.matrix import KERNEL_LOCK, set_numba_threads
    from derender.engine.plans import TablePlan

    if not isinstance(plan, TablePlan) or valid is None:
        return None
    n, h, w = frames.shape[:3]
    step = max(1, int(np.ceil(np.sqrt(h * w / CONSENSUS_PIXELS))))
    vg = valid[:, ::step, ::step]
    gy, gx = np.nonzero(np.all(vg != 0, axis=0))
    tables = _log_tables(plan)
    d = frame_biases(plan, frames[:, ::step, ::step][:, gy, gx], tables=tables)
    wtab = tables[1]
    bins = np.arange(256) // CONSENSUS_BIN
    d_lut = np.ascontiguousarray(np.stack([d[j][:, bins].T for j in range(n)]), dtype=np.float64)
    where_ = np.ones((h, w), np.bool_) if where is None else np.ascontiguousarray(where, dtype=np.bool_)
    var = variance if variance is not None else np.zeros((1, 1, 3), np.float32)
    if radiance.dtype != np.float32:
        raise TypeError(f"consensus_correct needs float32 radiance, got {radiance.dtype}")
    with KERNEL_LOCK:
        set_numba_threads(threads)
        counts, sums = _correct_kernel(frames, np.ascontiguousarray(valid), where_,
                                       np.ascontiguousarray(wtab, dtype=np.float64), d_lut,
                                       plan.channel_weights == "mean", radiance, var, variance is not None)
    touched = int(counts.sum())
    if touched == 0:
        return None
    return {"pixels": touched / (h * w), "grid_step": step, "consensus_pixels": int(gy.size),
            "mean_abs_log_correction": float(sums.sum()) / (3 * touched),
            "bias": np.round(d, 4).tolist()}
