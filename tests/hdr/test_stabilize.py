"""Pipeline-aware exposure fusion (derender.stabilize; paper 1, Algorithm 1) on simulator
stacks with exact truth, and on Debevec's Memorial stack.

PSNR follows DESIGN.md (derender.evaluate.psnr_rgbl: least-squares scale, peak = max of
the truth). Scores on these small (192x128) brackets are dominated by the few hundred
pixels that only the shortest exposure sees (the lamp), so acceptance is judged on the
mean over three scene kinds, as paper 1's Table 1 reports means over scenes.
"""

from __future__ import annotations

import numpy as np
import pytest

import derender.engine.motion.reference_frame as RF
import derender.hdr.stabilize as S
import derender.hdr.stabilize.blocks as SB
import derender.hdr.stabilize.exponents as SX
import derender.hdr.stabilize.pair_fit as SP
import derender.hdr.stabilize.solvers as SV
from derender.camera import simulate_bracket
from derender.core.errors import InputError
from derender.core.types import HDRResult, Stack
from derender.engine.motion.run import MotionOptions
from derender.evaluation.metrics import psnr_rgbl
from derender.evaluation.table1 import reference_spread
from derender.hdr.registry import merge

SIZE = (192, 128)
PLANES = ("R", "G", "B", "L")


def _stack(b) -> Stack:
    return Stack(images=b.jpeg_codes.astype(np.float32) / 255.0, times=b.times)


def _auto_trio(style: str, seed: int) -> dict:
    """Auto pipeline (WB, gain, gamma, saturation change per exposure), one bracket per scene
    kind, with the debevec and stabilized merges."""
    out = {}
    for kind in ("outdoor", "indoor", "night"):
        b = simulate_bracket(kind=kind, size=SIZE, pipeline="auto", style=style, seed=seed)
        st = _stack(b)
        out[kind] = {"bracket": b, "stack": st,
                     "debevec": merge(st, method="debevec"), "stabilized": merge(st, method="stabilized")}
    return out


@pytest.fixture(scope="module")
def auto_simple():
    """Simple style, seed 1."""
    return _auto_trio("simple", 1)


def _scores(res, b):
    return psnr_rgbl(res.radiance, b.truth_linear_srgb)


# --------------------------------------------------------------------------- acceptance
def test_stabilized_beats_debevec_on_auto_pipeline_simple(auto_simple):
    diffs = []
    for kind, d in auto_simple.items():
        s, g = _scores(d["stabilized"], d["bracket"]), _scores(d["debevec"], d["bracket"])
        diff = np.array([s[c] - g[c] for c in PLANES])
        assert (diff > 0).sum() >= 3, f"{kind}: stabilized wins on fewer than 3 planes: {diff}"
        diffs.append(diff)
    mean = np.mean(diffs, axis=0)
    assert mean[3] >= 2.0, f"mean PSNR-L gain {mean[3]:.2f} dB"
    assert np.all(mean[:3] >= 1.0), f"mean R/G/B gains {mean[:3]}"


def test_gammas_within_0_05_of_truth_on_auto_pipeline(auto_simple):
    """Display gammas (the simulator's RenderSettings.gamma; encoding exponent 1/gamma)."""
    for kind, d in auto_simple.items():
        info = d["stabilized"].info
        assert info["response"] == "power" and info["gamma_method"] == "times"
        est = np.asarray(info["gammas"])
        true = np.array([s.gamma for s in d["bracket"].settings])
        err = np.abs(est - true)
        # the extreme exposures overlap their single neighbour in a few dark/bright
        # pixels only; they are held to the same bound except in the night scene
        checked = err if kind != "night" else err[1:-1]
        assert checked.max() <= 0.05, f"{kind}: gamma errors {np.round(est - true, 3)}"


def test_blind_gammas_recover_relative_gammas(auto_simple):
    b = auto_simple["outdoor"]["bracket"]
    est = S.estimate_gammas(b.jpeg_codes / 255.0, times=None)
    assert est.method == "blind"
    true = np.array([s.gamma for s in b.settings])
    rel = lambda g: g / np.exp(np.mean(np.log(g)))  # noqa: E731
    np.testing.assert_allclose(rel(est.gammas), rel(true), atol=0.03)


def test_result_conventions(auto_simple):
    d = auto_simple["night"]
    res = d["stabilized"]
    assert isinstance(res, HDRResult)
    assert res.radiance.dtype == np.float32 and res.radiance.shape == (SIZE[1], SIZE[0], 3)
    assert np.isfinite(res.radiance).all()
    assert res.mask.dtype == np.uint8 and set(np.unique(res.mask)) <= {0, 1, 2}
    assert res.info["method"] == "stabilized" and len(res.info["matrices"]) == d["stack"].n
    assert 0 <= res.info["reference"] < d["stack"].n


def test_reference_spread_is_small(auto_simple):
    d = auto_simple["outdoor"]
    rep = reference_spread(d["stack"], d["bracket"].truth_linear_srgb, method="stabilized")
    assert len(rep["references"]) >= 3
    assert rep["spread"]["L"] <= 0.5, rep["psnr"]
    # the reference-free variant: the colour fit never sees the reference (only the
    # registration target does) and its common space is the mean rendering, mean K_j = I, then
    # grey-balanced (one gain per channel, derender.hdr.stabilize.grey_balance): mean K_j = D
    stab = S.stabilize(d["stack"], mode="joint", align="none")
    np.testing.assert_allclose(stab.matrices.mean(axis=0), np.diag(stab.info["grey_balance"]["gains"]), atol=1e-6)
    joint = _scores(S.stabilized_merge(stab), d["bracket"])
    assert joint["L"] >= _scores(d["debevec"], d["bracket"])["L"] + 1.0


def test_fixed_pipeline_no_worse_than_debevec():
    b = simulate_bracket(kind="outdoor", size=SIZE, pipeline="fixed", style="simple", seed=1)
    st = _stack(b)
    s, g = _scores(merge(st, method="stabilized"), b), _scores(merge(st, method="debevec"), b)
    assert all(s[c] >= g[c] - 0.3 for c in PLANES), (s, g)


@pytest.fixture(scope="module")
def auto_camera():
    """The filmic "camera" picture style, seed 0."""
    return _auto_trio("camera", 0)


def test_camera_style_switches_to_a_common_curve(auto_camera):
    """Filmic picture style: per-image power laws do not fit (their gammas drift with the
    exposure), the auto response falls back to a common curve with per-image H_j, which is
    far better than the paper's power model."""
    d = auto_camera["outdoor"]
    auto = d["stabilized"]
    assert auto.info["response"] == "curve"
    assert abs(auto.info["gamma_trend"]) > 0.3
    power = merge(d["stack"], options={"response": "power"}, method="stabilized")
    s, p = _scores(auto, d["bracket"]), _scores(power, d["bracket"])
    assert s["L"] >= p["L"] + 5.0


def test_stabilized_beats_debevec_on_auto_pipeline_camera(auto_camera):
    """Issue 5: PSNR-L over debevec on the auto pipeline, camera style (mean over the scene
    kinds; measured +2.04 on these seed-0 brackets, +2.19 over seeds 0-2 with ``derender
    experiment fusion-gain`` before issue 27; since Debevec's channel tie, which moved debevec up,
    +1.87: -0.94 / +1.52 / +5.04). Single scenes vary: on the outdoor one debevec
    wins by ~1.3 dB, as it does (by ~1.4 dB) against a merge with the simulator's exact
    per-image curves; the lamp edges that only the shortest exposure sees carry most of
    the error there."""
    diffs = [_scores(d["stabilized"], d["bracket"])["L"] - _scores(d["debevec"], d["bracket"])["L"]
             for d in auto_camera.values()]
    assert np.mean(diffs) >= 1.0, diffs


def test_unclipped_debevec_keeps_the_filmic_shoulder():
    """Samples next to a clipped pixel left out: the curve's shoulder (codes 200-250) follows
    the true filmic-plus-gamma inverse of a noise-free, fixed-rendering camera-style bracket
    (plain Debevec: > 1 in ln where raw-clipped pixels render below white)."""
    from derender.camera import encode_gamma_with_toe, filmic_curve
    from derender.response.debevec1997 import calibrate_debevec

    b = simulate_bracket(kind="indoor", size=SIZE, pipeline="fixed", style="camera", seed=0, noise=False)
    codes = b.jpeg_codes
    xs = np.linspace(0.0, 1.0, 400001)
    truth = np.log(np.maximum(np.interp(np.arange(256) / 255, encode_gamma_with_toe(filmic_curve(xs), 2.2), xs),
                              1e-6))

    def shoulder_error(g):
        d = g - truth[:, None]
        return np.abs(d - d[128])[200:251].max(axis=0)

    un = S.unclipped_debevec(lambda j, ys, xs_: codes[j][ys, xs_], codes.shape[0], codes.shape[1:3], b.times)
    plain = calibrate_debevec(_stack(b)).log_inverse
    assert np.all(shoulder_error(un.log_inverse) < 0.15), shoulder_error(un.log_inverse)
    assert shoulder_error(plain).max() > 1.0


def test_unclipped_debevec_recovers_curve_and_exposure_offsets():
    """Oracle: a known S-shaped curve (not a power law) renders 7 frames whose channels are
    exposed by ``t_j exp(o_jc)``, ``o_jc`` ~ U(-0.25, 0.25) per frame and channel (gain and
    white balance changing, without a mean, trend or bend in ``ln t``: the gauge of
    ``CURVE_OFFSET_DEGREE`` 2), noise-free. With the exposures re-estimated (``exposure_rounds=3``,
    the default) the fitted curve follows the true ``ln`` inverse within 0.05 on codes 20-235 and
    the offsets come out within 0.03; plain Debevec & Malik (``exposure_rounds=0``) bends by 0.49.
    Offsets beyond ``CURVE_MAX_OFFSET`` are not a camera's gain steps: the guard falls back to
    the times as given."""
    def s_curve(u):
        y = u ** (1 / 2.2)
        return 0.7 * y + 0.3 * (3 * y ** 2 - 2 * y ** 3)

    rng = np.random.default_rng(0)
    n, h, w = 7, 96, 128
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w], dtype=np.float64)[:, None, None]
    log_x = -7.0 + 7.0 * xx + 0.8 * np.sin(9 * yy + 3 * xx) + 0.5 * np.cos(17 * xx * yy)
    x = np.exp(log_x)[..., None] * np.array([1.0, 0.8, 0.6])
    times = 2.0 ** np.arange(n)
    tc = np.log(times) - np.log(times).mean()
    o = rng.uniform(-0.25, 0.25, size=(n, 3))
    span = np.stack([tc ** k for k in range(S.CURVE_OFFSET_DEGREE + 1)], axis=1)
    o = o - span @ np.linalg.lstsq(span, o, rcond=None)[0]       # no component in the gauge

    def render(offsets):
        return np.stack([np.rint(255 * s_curve(np.clip(x * times[j] * np.exp(offsets[j]), 0, 1)))
                         for j in range(n)]).astype(np.uint8)

    codes = render(o)
    u = np.linspace(0.0, 1.0, 200001)
    truth = np.log(np.maximum(np.interp(np.arange(256) / 255, s_curve(u), u), 1e-12))

    def curve_error(g):
        d = g[20:236] - truth[20:236, None]
        return np.abs(d - d.mean(axis=0)).max()

    fit = S.unclipped_debevec(lambda j, ys, xs: codes[j][ys, xs], n, (h, w), times)
    assert fit.params["exposure_rounds"] == 3 and not fit.params["exposure_offsets_rejected"]
    assert curve_error(fit.log_inverse) < 0.05, curve_error(fit.log_inverse)
    np.testing.assert_allclose(fit.params["exposure_offsets"], o, atol=0.03)
    # plain Debevec & Malik: the times as given, the channels independent (tie=0; with the default
    # channel tie of issue 27 the plain curve bends by 0.13 only)
    plain = S.unclipped_debevec(lambda j, ys, xs: codes[j][ys, xs], n, (h, w), times, exposure_rounds=0, tie=0)
    assert curve_error(plain.log_inverse) > 0.3
    assert np.all(np.asarray(plain.params["exposure_offsets"]) == 0)
    # offsets of 3x the bound: rejected, the curve is plain Debevec & Malik's of those codes
    big = render(o * 3 * S.CURVE_MAX_OFFSET / np.abs(o).max())
    guarded = S.unclipped_debevec(lambda j, ys, xs: big[j][ys, xs], n, (h, w), times)
    assert guarded.params["exposure_offsets_rejected"]
    assert np.all(np.asarray(guarded.params["exposure_offsets"]) == 0)
    np.testing.assert_array_equal(guarded.log_inverse, S.unclipped_debevec(
        lambda j, ys, xs: big[j][ys, xs], n, (h, w), times, exposure_rounds=0).log_inverse)


def test_merge_of_shifted_stack_close_to_unshifted():
    b = simulate_bracket(kind="outdoor", size=(224, 160), pipeline="auto", style="simple", seed=1)
    imgs = b.jpeg_codes.astype(np.float32) / 255.0
    offsets = np.array([[0, 0], [2, -1], [-3, 2], [1, 3], [0, 0], [-2, -2], [3, -3], [-1, 1], [2, 2]])
    h, w, y0, x0 = 128, 192, 16, 16
    cut = lambda o: np.stack([imgs[j, y0 + dy:y0 + dy + h, x0 + dx:x0 + dx + w]  # noqa: E731
                              for j, (dy, dx) in enumerate(o)])
    truth = b.truth_linear_srgb[y0:y0 + h, x0:x0 + w]
    still = merge(Stack(images=cut(np.zeros_like(offsets)), times=b.times), method="stabilized",
                  motion=MotionOptions(reference=4))
    moved = merge(Stack(images=cut(offsets), times=b.times), method="stabilized", motion=MotionOptions(reference=4))
    np.testing.assert_array_equal(moved.info["alignment"]["shifts"], -offsets)   # the engine registered them
    assert np.isfinite(moved.radiance).all()
    ps, pm = psnr_rgbl(still.radiance, truth), psnr_rgbl(moved.radiance, truth)
    assert pm["L"] >= ps["L"] - 0.5, (ps, pm)


def test_memorial_stack(memorial_dir):
    """Debevec's Memorial PNGs (film-like response, 16 exposures), downsampled 6x."""
    import cv2

    from derender.io.images import read_stack
    from derender.io.rgbe import read_hdr

    paths = sorted(memorial_dir.glob("memorial00*.png"))
    st = read_stack(paths, times_file=memorial_dir / "memorial.hdr_image_list.txt", times_file_inverse=True)
    small = np.stack([cv2.resize(im, (im.shape[1] // 6, im.shape[0] // 6), interpolation=cv2.INTER_AREA)
                      for im in st.images])
    res = merge(Stack(images=small, times=st.times), method="stabilized")
    assert np.isfinite(res.radiance).all()
    ref = read_hdr(memorial_dir / "memorial.hdr").astype(np.float32)
    ref = cv2.resize(ref, (small.shape[2], small.shape[1]), interpolation=cv2.INTER_AREA)
    lum = lambda x: np.log(np.maximum(x.astype(np.float64) @ [0.2126, 0.7152, 0.0722], 1e-9)).ravel()  # noqa: E731
    assert np.corrcoef(lum(res.radiance), lum(ref))[0, 1] >= 0.97


# --------------------------------------------------------------------------- components
def test_select_reference_fewest_badly_exposed():
    z = np.full((4, 10, 10, 3), 0.5, dtype=np.float32)
    z[0, :6] = 0.0          # 60 % under
    z[1, :2] = 1.0          # 20 % over
    z[2, :1] = 0.01         # 10 % under
    z[3, :3] = 0.99         # 30 % over
    over, under = RF.exposure_fractions(z)
    np.testing.assert_allclose(over, [0, 0.2, 0, 0.3])
    np.testing.assert_allclose(under, [0.6, 0, 0.1, 0])
    assert RF.select_reference(z) == 2
    st = Stack(images=z, times=[1, 2, 4, 8])
    with pytest.raises(InputError):
        S.stabilize(st, reference=7)


def test_fit_frame_matrix_recovers_matrix_despite_outliers():
    rng = np.random.default_rng(0)
    lin_src = rng.uniform(0.01, 0.4, size=(400, 3))      # keeps every destination code below 1
    h_true = np.array([[1.9, 0.15, -0.05], [0.1, 2.1, 0.05], [0.0, 0.2, 1.7]])
    g_src, g_dst = 2.0, 2.4
    src = lin_src ** (1 / g_src)
    dst = np.clip(lin_src @ h_true.T, 1e-6, None) ** (1 / g_dst)
    bad = rng.choice(400, 60, replace=False)
    dst[bad] = rng.uniform(0.1, 0.9, size=(60, 3))
    h, inl = S.fit_frame_matrix(src, dst, g_src, g_dst, seed=3, ridge=0.0)
    np.testing.assert_allclose(h, h_true, atol=1e-3)
    assert inl[bad].sum() <= 2 and inl.sum() >= 330             # a random "outlier" may fall on the model
    h2, _ = S.fit_frame_matrix(src, dst, g_src, g_dst, seed=3, ridge=0.0)
    np.testing.assert_array_equal(h, h2)                            # seeded: byte-identical
    h3, _ = S.fit_frame_matrix(src, dst, g_src, g_dst, seed=3)      # default ridge: small bias
    np.testing.assert_allclose(h3, h_true, atol=0.03)


def test_curve_roundtrip_and_derivative():
    table = np.log(np.linspace(0.0, 1.0, 256) ** 2.2 + 1e-4)
    for c in (S.Curve(1.0, gamma=2.2), S.Curve(1.1, gamma=2.2), S.Curve(1.05, log_table=table)):
        j = np.random.default_rng(1).uniform(0.05, 0.95, size=(50, 3))
        np.testing.assert_allclose(c.code(c.lin(j)), j, atol=1e-6)
        eps = 1e-5
        np.testing.assert_allclose(c.dlin(j), (c.lin(j + eps) - c.lin(j - eps)) / (2 * eps), rtol=2e-3)


def test_power_law_plausibility():
    t = 2.0 ** np.arange(9)
    assert S.power_law_plausible([2.0, 2.3, 2.1, 1.9, 2.5, 2.2, 2.0, 2.4, 2.1], t)
    assert not S.power_law_plausible(np.geomspace(1.5, 3.5, 9), t)        # steady drift
    assert not S.power_law_plausible([1.0, 2.2, 2.2, 2.2, 2.2, 2.2, 2.2, 2.2, 2.2], t)  # on the bound


def test_registered_methods_and_bad_options(auto_simple):
    from derender.hdr.registry import METHODS

    assert "stabilized" in METHODS and "stabilized-joint" in METHODS
    st = auto_simple["outdoor"]["stack"]
    with pytest.raises(InputError):
        merge(st, options={"response": "spline"}, method="stabilized")
    with pytest.raises(InputError):
        merge(st, method="stabilized", motion=MotionOptions(align="optical-flow"))


def test_blocks_gathered_without_full_copies_match_block_view():
    """make_blocks gathers only the kept blocks; they equal the full block view's."""
    rng = np.random.default_rng(4)
    imgs = rng.random((3, 37, 51, 3))
    valid = rng.random((3, 37, 51)) > 0.05
    blocks = SB.make_blocks(imgs, valid, 2, 200, seed=5)
    full = np.stack([SB._block_view(imgs[j], 2) for j in range(3)])
    vfull = np.stack([SB._block_view(np.repeat(valid[j][..., None], 3, axis=2).astype(float), 2).min(axis=(1, 2)) > 0.5
                      for j in range(3)])
    # the kept blocks are a subset of the full view's, in order, with matching validity
    flat = full.reshape(3, full.shape[1], -1)
    keep = [int(np.flatnonzero((flat[0] == b.ravel()).all(axis=1))[0]) for b in blocks.codes[0]]
    assert keep == sorted(keep) and len(set(keep)) == 200
    np.testing.assert_array_equal(blocks.codes, full[:, keep])
    np.testing.assert_array_equal(blocks.valid, vfull[:, keep])


def test_fit_frame_matrix_scores_hypotheses_on_a_subset():
    """Preemptive RANSAC: ranking on 300 of 3000 correspondences still finds H and all inliers."""
    rng = np.random.default_rng(6)
    lin_src = rng.uniform(0.01, 0.4, size=(3000, 3))
    h_true = np.array([[1.9, 0.15, -0.05], [0.1, 2.1, 0.05], [0.0, 0.2, 1.7]])
    src = lin_src ** (1 / 2.2)
    dst = np.clip(lin_src @ h_true.T, 1e-6, None) ** (1 / 2.4)
    bad = rng.choice(3000, 600, replace=False)
    dst[bad] = rng.uniform(0.1, 0.9, size=(600, 3))
    h, inl = S.fit_frame_matrix(src, dst, 2.2, 2.4, seed=1, ridge=0.0, max_score=300)
    np.testing.assert_allclose(h, h_true, atol=3e-3)      # a few random "outliers" fall on the model
    assert inl[bad].sum() <= 10 and inl.sum() >= 2350
    h_all, inl_all = S.fit_frame_matrix(src, dst, 2.2, 2.4, seed=1, ridge=0.0, max_score=3000)
    np.testing.assert_allclose(h, h_all, atol=1e-6)       # same answer as ranking on all of them
    np.testing.assert_array_equal(inl, inl_all)


def test_joint_ignores_a_frame_without_usable_pixels(tmp_path):
    """An all-white middle frame shares no pixels: it must not take the whole rendering
    (the constraint mean K_j = I once put K = 5 I on it and ~0 on the others)."""
    from derender.evaluation.metrics import psnr_rgbl

    b = simulate_bracket(size=(128, 96), exposures=6, seed=7)
    codes = b.jpeg_codes.copy()
    codes[3] = 255
    st = Stack(images=codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
    joint = merge(st, "stabilized-joint")
    ref = merge(st, "stabilized")
    assert psnr_rgbl(joint.radiance, b.truth_linear_srgb)["L"] > psnr_rgbl(ref.radiance, b.truth_linear_srgb)["L"] - 6


def test_grey_frame_in_colour_bracket_does_not_crash():
    """R = G = B in one frame makes the unregularised pair fit singular: minimum-norm map instead of a traceback."""
    b = simulate_bracket(size=(96, 64), exposures=4, seed=2)
    codes = b.jpeg_codes.copy()
    codes[1] = codes[1].mean(axis=-1, keepdims=True).round().astype(np.uint8)
    st = Stack(images=codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
    for method in ("stabilized", "stabilized-joint"):
        r = merge(st, method)
        assert np.all(np.isfinite(r.radiance)) and r.radiance.max() > 0


def test_scalar_solvers_match_scipy():
    """The bounded minimiser takes scipy's steps exactly; the root finder lands within xtol."""
    from scipy.optimize import brentq, minimize_scalar

    fs = [lambda x: (x - 0.3) ** 2, lambda x: np.cos(3 * x) + 0.1 * x, lambda x: abs(x - 0.123456),
          lambda x: np.exp(x) - 2 * x, lambda x: (x - 5) ** 4, lambda x: 1.0]
    for f in fs:
        for lo, hi in [(-1.0, 1.0), (0.0, 2.0), (-3.5, 0.2)]:
            for xatol in (1e-5, 1e-3):
                ref = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
                assert SV.minimize_bounded(f, lo, hi, xatol) == ref.x
    for g, lo, hi in [(lambda x: x ** 3 - 2, 0.0, 3.0), (lambda x: np.cos(x) - x, 0.0, 1.0),
                      (lambda x: np.exp(x) - 5, -2.0, 4.0), (lambda x: x - 0.25, 0.0, 1.0)]:
        for xtol in (1e-12, 1e-5):
            assert abs(SV.find_root(g, lo, hi, xtol) - brentq(g, lo, hi, xtol=1e-14)) <= 2 * xtol
    with pytest.raises(ValueError):
        SV.find_root(lambda x: x * x + 1, -1.0, 1.0)


def test_batched_pair_searches_equal_one_pair_at_a_time():
    """The lock-step exponent searches with batched power-law costs give the one-pair costs
    (to rounding) and the same log ratios, errors and inliers as :func:`_pair_log_ratio`."""
    rng = np.random.default_rng(0)
    items, reqs = [], []
    mix = np.array([[1.0, 0.05, 0.0], [0.02, 0.95, 0.03], [0.0, 0.1, 1.0]])
    for i in range(5):
        nb = int(rng.integers(30, 70))
        base = rng.uniform(0.05, 0.8, (nb, 1, 3)) * rng.uniform(0.9, 1.1, (nb, 4, 3))
        pj = np.clip(base, 0, 1) ** (1 / 2.2)
        pk = np.clip((base * 1.8) @ mix.T, 0, 1) ** (1 / rng.uniform(1.8, 2.6))
        items.append((pj, pk, 2.2, 2.2))
        gk = S.Curve(1.0, gamma=2.2) * np.exp(rng.uniform(-0.3, 0.3))
        sel = None if i % 2 else rng.random(nb) > 0.2
        reqs.append((pj, pk, SP.effective_codes(pj, 2.2), S.Curve(1.0, gamma=2.2), gk, sel))
    batched = SP.pair_costs_power(reqs)
    single = [SP.pair_cost(pj, pk, cj, ck, sel, jj) for pj, pk, jj, cj, ck, sel in reqs]
    np.testing.assert_allclose(batched, single, rtol=1e-12)
    together = SX._run_pair_searches(items, np.log(4.0), 2, batched=True)
    for (pj, pk, bj, bk), (lr, se, sel) in zip(items, together):
        lr1, se1, sel1 = SX._pair_log_ratio(pj, pk, bj, np.log(4.0), rounds=2, base_k=bk)
        assert abs(lr - lr1) < 1e-9 and abs(se - se1) < 1e-9 * max(se1, 1.0)
        np.testing.assert_array_equal(sel, sel1)
