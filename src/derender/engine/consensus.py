"""Consensus correction: pixels merged from a subset of the frames carry that subset's rendering bias; remove it.

Beyond both papers. Ghost removal (:mod:`derender.engine.deghost`) and alignment leave
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
and neither gained on the tuning families (``derender experiment ghosts``, docs/ghosts.md).
Shrinkage: the held-out ``dslr-lut`` family's 3D LUT makes the bias hue-dependent, which no
per-code table can hold; the shrinkage keeps such bins near zero.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["CONSENSUS_BIN", "CONSENSUS_MIN_COUNT", "CONSENSUS_PIXELS", "frame_biases", "consensus_correct"]

#: Codes per bin of the per-frame bias tables.
CONSENSUS_BIN = 16

#: A bin needs this many consensus pixels to be corrected.
CONSENSUS_MIN_COUNT = 20

#: The bias tables are measured on every s-th row and column so that at most about this many
#: pixels remain.
CONSENSUS_PIXELS = 1 << 19

#: Pixels corrected per chunk (bounds the memory of the gathered codes and tables).
_CHUNK = 1 << 20


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


def frame_biases(plan, codes: np.ndarray) -> np.ndarray:
    """Per-frame bias tables ``d`` (N, 3, 256 // CONSENSUS_BIN) float64 (module docstring) from
    ``codes`` (N, K, 3) uint8: pixels every frame takes part in."""
    vals, w = _log_tables(plan)
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


def consensus_correct(radiance: np.ndarray, variance: np.ndarray | None, plan, frames: np.ndarray,
                      valid: np.ndarray | None, *, where: np.ndarray | None = None) -> dict[str, Any] | None:
    """Correct, in place, the pixels of ``radiance`` (H, W, 3) (and ``variance``) that were merged
    from a subset of ``frames`` (N, H, W, 3) uint8 (``valid`` (N, H, W) uint8, 0 = left out) under
    a table ``plan`` (module docstring); ``where`` (H, W) bool limits the correction to those
    pixels (the engine: where ghost removal left a frame out). Returns a summary for the
    result's info, or None when nothing was corrected (no table plan, or every frame takes
    part everywhere)."""
    from derender.engine.deghost import _lut3
    from derender.engine.plans import TablePlan

    if not isinstance(plan, TablePlan) or valid is None:
        return None
    n, h, w = frames.shape[:3]
    full = np.all(valid != 0, axis=0)
    todo = ~full if where is None else (~full & where)
    ys, xs = np.nonzero(todo)
    if ys.size == 0:
        return None
    step = max(1, int(np.ceil(np.sqrt(h * w / CONSENSUS_PIXELS))))
    grid_full = full[::step, ::step]
    gy, gx = np.nonzero(grid_full)
    codes = frames[:, ::step, ::step][:, gy, gx]               # (N, K, 3)
    d = frame_biases(plan, codes)
    _, wtab = _log_tables(plan)
    mean_w = plan.channel_weights == "mean"
    # per frame, per code: the merge weight and the bias (what the correction sums), as LUTs
    codes256 = np.arange(256) // CONSENSUS_BIN
    w_lut = wtab.astype(np.float32)                                              # (N, 256, 3)
    d_lut = np.stack([d[j][:, codes256].T for j in range(n)]).astype(np.float32)  # (N, 256, 3)
    sum_abs, count = 0.0, 0
    for s in range(0, ys.size, _CHUNK):
        yy, xx = ys[s:s + _CHUNK], xs[s:s + _CHUNK]
        num = np.zeros((yy.size, 1, 3), np.float32)
        den = np.zeros((yy.size, 1, 3), np.float32)
        for j in range(n):
            cz = np.ascontiguousarray(frames[j, yy, xx]).reshape(-1, 1, 3)
            wt = _lut3(cz, w_lut[j])
            if mean_w:
                wt[:] = wt.mean(axis=-1, keepdims=True)
            wt *= (valid[j, yy, xx] != 0).reshape(-1, 1, 1)
            num += wt * _lut3(cz, d_lut[j])
            den += wt
        delta = np.divide(num, den, out=np.zeros_like(num), where=den > 0).reshape(-1, 3)
        f = np.exp(-delta)
        radiance[yy, xx] *= f
        if variance is not None:
            variance[yy, xx] *= f * f
        sum_abs += float(np.abs(delta).sum(dtype=np.float64))
        count += delta.size
    return {"pixels": float(ys.size / (h * w)), "grid_step": step, "consensus_pixels": int(gy.size),
            "mean_abs_log_correction": sum_abs / max(count, 1),
            "bias": np.round(d, 4).tolist()}
