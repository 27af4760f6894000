"""The fused variance kernels against a NumPy oracle of the formula in derender.engine.variance.

The kernels accumulate the variance in the radiance's own pass (:mod:`derender.engine.variance_kernels`,
one read of each frame's codes, float32 sums of positive terms); the oracle evaluates the
docstring's formula directly, per pixel-channel, in float64 over every frame, from the plan's
tables. The edge term is off (``edge=0``), so the comparison is of the kernels' sums alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.memory import N_CODES
from derender.engine.plans import MatrixPlan, TablePlan
from derender.engine.variance import matrix_variance_tables, variance_tables

RTOL = 1e-4


def _bracket(n=5, h=37, w=301, seed=3):
    """Codes of a noisy linear scene seen at ``n`` exposures (gamma 2.2, clipped)."""
    rng = np.random.default_rng(seed)
    scene = np.exp(rng.normal(-1.5, 1.3, size=(h, w, 3)))
    times = 2.0 ** np.arange(n, dtype=np.float64) / 8.0
    frames = np.empty((n, h, w, 3), dtype=np.uint8)
    for j, t in enumerate(times):
        x = scene * t * np.exp(rng.normal(0, 0.05, size=scene.shape))
        frames[j] = np.clip(np.round(255 * np.clip(x, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.uint8)
    return frames, times


def _tables(times, domain):
    z = np.arange(N_CODES, dtype=np.float64)
    lin = np.maximum(z / 255.0, 0.5 / 255.0) ** 2.2
    lin = lin[None, :, None] * np.array([1.0, 0.9, 1.1])[None, None, :] / times[:, None, None]
    values = np.log(lin) if domain == "log" else lin
    hat = np.minimum(z, 255 - z)[:, None] * np.ones(3) / 127.0
    hat[0] = hat[255] = 0.0
    return values.astype(np.float32), hat.astype(np.float32)


def _oracle_table(frames, plan, weights_k):
    """Var r per pixel-channel (H, W, 3), float64, from the docstring's formula."""
    vm = plan.variance
    n = frames.shape[0]
    j_idx = np.arange(n)[:, None, None, None]
    c_idx = np.arange(3)[None, None, None, :]
    u = plan.values.astype(np.float64)[j_idx, frames, c_idx]
    wc = weights_k[j_idx, frames, c_idx]                      # float32, as the kernel scales them
    if plan.channel_weights == "mean":
        wc = np.repeat(((wc[..., 0] + wc[..., 1]) + wc[..., 2])[..., None], 3, axis=-1)
    wc = wc.astype(np.float64)
    tn = vm.noise.astype(np.float64)[j_idx, frames, c_idx]
    tq = vm.quant.astype(np.float64)[j_idx, frames, c_idx]
    s0 = wc.sum(0)
    s1 = (wc * u).sum(0)
    s2 = (wc * u * u).sum(0)
    w2 = (wc * wc).sum(0)
    q = (wc * wc * (tn + tq)).sum(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = s1 / s0
        d = np.maximum(s2 / s0 - mean * mean, 0.0)
        r = w2 / s0 ** 2
        rob = (wc * wc * (u - mean) ** 2).sum(0) / s0 ** 2       # the robust (sandwich) term
        var_u = (vm.inflate * q / s0 ** 2 + vm.inflate_dis * d * r / np.maximum(1 - r, vm.r_floor)
                 + vm.inflate_sys * d + vm.inflate_robust * rob)
    return var_u, s0 > 0


@pytest.mark.parametrize("domain,channel_weights,method", [
    ("log", "mean", "debevec"), ("log", "independent", "debevec"),
    ("linear", "mean", "robertson"), ("linear", "independent", "robertson")])
def test_table_kernel_variance_equals_formula(domain, channel_weights, method):
    from derender.engine.table_kernel import _table_kernel_tables, table_kernel_merge

    frames, times = _bracket()
    values, hat = _tables(times, domain)
    vm = variance_tables(values, domain, method)
    vm.edge = 0.0
    vm.inflate_dis = 0.5        # the methods' constants leave it 0: exercise the term too
    vm.inflate_robust = 0.7     # likewise
    plan = TablePlan(values=values, weights=hat, channel_weights=channel_weights, domain=domain, variance=vm)
    n = frames.shape[0]
    res = table_kernel_merge(frames, plan, list(range(n - 1, -1, -1)), threads=2)
    _, weights_k = _table_kernel_tables(plan, n)
    var_u, measured = _oracle_table(frames, plan, weights_k.astype(np.float32))
    rad = np.asarray(res.radiance, dtype=np.float64)
    shared2 = vm.shared ** 2
    expect = (var_u + shared2) * rad ** 2 if domain == "log" else var_u + shared2 * rad ** 2
    got = np.asarray(res.variance, dtype=np.float64)
    assert measured.mean() > 0.9
    np.testing.assert_allclose(got[measured], expect[measured], rtol=RTOL, atol=0)
    # the radiance equals the kernel without a variance, byte for byte
    plain = table_kernel_merge(frames, TablePlan(values=values, weights=hat, channel_weights=channel_weights,
                                                 domain=domain), list(range(n - 1, -1, -1)), threads=2)
    np.testing.assert_array_equal(np.asarray(res.radiance), np.asarray(plain.radiance))
    np.testing.assert_array_equal(res.mask, plain.mask)


def test_matrix_kernel_variance_equals_formula():
    from derender.engine.matrix import merge_matrix_frames

    frames, times = _bracket(seed=5)
    n = frames.shape[0]
    lin, hat = _tables(times, "linear")
    rng = np.random.default_rng(7)
    mats = (np.eye(3)[None] + rng.normal(0, 0.08, size=(n, 3, 3))).astype(np.float64)
    shifts = np.zeros((n, 2), dtype=np.int64)
    shifts[1] = (1, -2)                # frames read through a shift: outside the frame they take no part
    vm = matrix_variance_tables(lin, "stabilized")
    vm.edge = 0.0
    vm.inflate_sys = 0.3
    vm.inflate_robust = 0.6
    plan = MatrixPlan(values=lin, matrices=mats, weights=hat, shifts=shifts, variance=vm)
    res = merge_matrix_frames(frames, plan, times, threads=2)
    plain = merge_matrix_frames(frames, MatrixPlan(values=lin, matrices=mats, weights=hat, shifts=shifts), times,
                                threads=2)
    np.testing.assert_array_equal(np.asarray(res.radiance), np.asarray(plain.radiance))
    np.testing.assert_array_equal(res.mask, plain.mask)
    # oracle: frame j's estimate v = max(M_j L_j(z), 0) at (y + dy, x + dx), weight = min over channels
    h, w = frames.shape[1:3]
    s0 = np.zeros((h, w))
    w2 = np.zeros((h, w))
    s1 = np.zeros((h, w, 3))
    s2 = np.zeros((h, w, 3))
    p1 = np.zeros((h, w, 3))
    p2 = np.zeros((h, w, 3))
    q = np.zeros((h, w, 3))
    usable = np.zeros((h, w), bool)
    m32 = mats.astype(np.float32)
    for j in range(n):
        dy, dx = shifts[j]
        ys, xs = np.arange(h) + dy, np.arange(w) + dx
        oky, okx = (ys >= 0) & (ys < h), (xs >= 0) & (xs < w)
        z = np.zeros((h, w, 3), dtype=np.int64)
        z[np.ix_(oky, okx)] = frames[j][np.ix_(ys[oky], xs[okx])]
        inside = oky[:, None] & okx[None, :]
        wmin = np.min(hat[z, np.arange(3)], axis=-1).astype(np.float64) * inside
        usable |= wmin > 0
        l = lin[j][z, np.arange(3)]
        v = np.maximum(np.einsum("ck,hwk->hwc", m32[j], l, dtype=np.float32), 0).astype(np.float64)
        s_nq = np.einsum("ck,hwk->hwc", mats[j] ** 2,
                         (vm.noise[j] + vm.quant[j]).astype(np.float64)[z, np.arange(3)])
        s0 += wmin
        w2 += wmin ** 2
        s1 += wmin[..., None] * v
        s2 += wmin[..., None] * v * v
        p1 += (wmin ** 2)[..., None] * v
        p2 += (wmin ** 2)[..., None] * v * v
        q += (wmin ** 2)[..., None] * s_nq
    ok = usable & (s0 > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = s1 / s0[..., None]
        d = np.maximum(s2 / s0[..., None] - mean ** 2, 0)
        r = (w2 / s0 ** 2)[..., None]
        var = (vm.inflate * q / s0[..., None] ** 2 + vm.inflate_dis * d * r / np.maximum(1 - r, vm.r_floor)
               + vm.inflate_sys * d + vm.shared ** 2 * np.asarray(res.radiance, dtype=np.float64) ** 2
               + vm.inflate_robust * np.maximum(p2 - 2 * mean * p1 + mean ** 2 * w2[..., None], 0) / s0[..., None] ** 2)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.asarray(res.variance, dtype=np.float64)[ok], var[ok], rtol=RTOL, atol=0)


@pytest.mark.parametrize("relative", [False, True])
def test_variance_finish_rows_equals_float64_oracle(relative):
    """The edge term ``e2 Var_3x3(r)`` (band rows and image columns repeated at the ends) and the
    log domain's ``r^2`` scaling, against float64 NumPy; a 2e6 highlight above dark texture
    (where float32 running box sums over the image lose the dark pixels' local variance)."""
    from derender.engine.variance import SOURCE_STRIDE, VAR_CAP, new_parts
    from derender.engine.variance_kernels import variance_finish_rows

    rng = np.random.default_rng(11)
    h, w, y0, y1 = 96, 70, 8, 90
    rad = np.exp(rng.normal(-2.5, 1.0, size=(3, h, w))).astype(np.float32)
    rad[:, y0:y0 + 20, 10:30] = 2e6
    var = (rng.random((3, h, w)) * 1e-3).astype(np.float32)
    parts = new_parts(h, w)
    parts[:4] = rng.random(parts[:4].shape).astype(np.float32)
    e2 = float(np.float32(0.3 ** 2))
    got, got_parts = var.copy(), parts.copy()
    variance_finish_rows(rad, got, got_parts, e2, relative, y0, y1, 0, SOURCE_STRIDE, VAR_CAP)
    r = rad[:, y0:y1].astype(np.float64)
    pad = np.pad(r, ((0, 0), (1, 1), (1, 1)), mode="edge")
    win = np.stack([pad[:, a:a + y1 - y0, b:b + w] for a in range(3) for b in range(3)])
    local = np.maximum((win ** 2).mean(0) - win.mean(0) ** 2, 0.0)
    base = var[:, y0:y1].astype(np.float64)
    if relative:
        base = base * (rad[:, y0:y1] * rad[:, y0:y1]).astype(np.float64)
    expect = np.minimum(base + e2 * local, VAR_CAP)
    np.testing.assert_allclose(got[:, y0:y1], expect, rtol=1e-5, atol=0)
    np.testing.assert_array_equal(got[:, :y0], var[:, :y0])       # rows outside the band untouched
    ys = [y for y in range(y0, y1) if y % SOURCE_STRIDE == 0]
    for y in ys:
        np.testing.assert_allclose(got_parts[4, y // SOURCE_STRIDE].T, e2 * local[:, y - y0], rtol=1e-5, atol=1e-30)
