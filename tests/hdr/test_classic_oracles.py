"""The classic merges against real oracles (issue 16 items 5-6): the simulator's exact truth,
OpenCV's Debevec and Robertson as peers, the shape of the recovered curves, and neutral
colours staying neutral.

Two simulator brackets (auto pipeline; outdoor/camera style and indoor/simple style;
128x96, 6 exposures) are merged once per module, in memory from the camera's codes.
Measured at this size (PSNR L, dB): debevec 40.13 / 42.93, OpenCV's 35.47 / 38.56;
robertson 40.55 / 40.45 (40.39 / 39.31 before its calibration's log-domain,
``w``-weighted leave-one-out radiance and variance-weighted smoothing), OpenCV's 33.86 / 32.57. On the 8 brackets of docs/paper1.md
(192x128, 7 exposures, JPEG files) robertson and debevec both average 42.4 dB.
"""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.types import Stack
from derender.engine.tables import code_values

BRACKETS = (("outdoor", "camera", 0), ("indoor", "simple", 1))


def _opencv(codes: np.ndarray, times: np.ndarray, kind: str) -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    imgs = [np.ascontiguousarray(c[..., ::-1]) for c in codes]
    t = np.asarray(times, np.float32)
    if kind == "debevec":
        out = cv2.createMergeDebevec().process(imgs, t, cv2.createCalibrateDebevec().process(imgs, t))
    else:
        out = cv2.createMergeRobertson().process(imgs, t, cv2.createCalibrateRobertson().process(imgs, t))
    return np.asarray(out[..., ::-1], dtype=np.float64)


def _neutral_error(rad: np.ndarray, neutral: np.ndarray) -> float:
    """Median |ln R - ln G| + median |ln B - ln G| over the truth's neutral pixels."""
    lr = np.log(np.maximum(rad[neutral].astype(np.float64), 1e-12))
    return float(np.median(np.abs(lr[:, 0] - lr[:, 1])) + np.median(np.abs(lr[:, 2] - lr[:, 1])))


@pytest.fixture(scope="module", params=BRACKETS, ids=lambda b: "-".join(map(str, b)))
def sim(request):
    from derender.camera import simulate_bracket
    from derender.evaluation.metrics import psnr_rgbl
    from derender.hdr.classic import merge_debevec, merge_robertson
    from derender.response.debevec1997 import calibrate_debevec
    from derender.response.robertson2003 import calibrate_robertson

    kind, style, seed = request.param
    b = simulate_bracket(kind=kind, size=(128, 96), exposures=6, pipeline="auto", style=style, seed=seed)
    st = Stack(images=code_values()[b.jpeg_codes], times=b.times)
    truth = b.truth_linear_srgb
    rad = {"debevec": merge_debevec(st), "robertson": merge_robertson(st)}
    rad = {k: v.radiance for k, v in rad.items()} | {"curves": {k: v.info["curves"] for k, v in rad.items()}}
    rad["debevec-unbalanced"] = merge_debevec(st, options={"curves": calibrate_debevec(st, balance=False)}).radiance
    # the paper's channels: solved independently (tie=0), each anchored at g(128) = 0
    rad["robertson-unbalanced"] = merge_robertson(st, options={"curves": calibrate_robertson(st, balance=False,
                                                                                             tie=0)}).radiance
    rad["opencv-debevec"] = _opencv(b.jpeg_codes, b.times, "debevec")
    rad["opencv-robertson"] = _opencv(b.jpeg_codes, b.times, "robertson")
    psnr = {k: psnr_rgbl(v, truth)["L"] for k, v in rad.items() if k != "curves"}
    tn = truth / np.maximum(truth.mean(-1, keepdims=True), 1e-12)
    neutral = (np.abs(tn - 1).max(-1) < 0.05) & (truth.mean(-1) > 0)
    return {"stack": st, "truth": truth, "rad": rad, "psnr": psnr, "neutral": neutral}


def test_debevec_at_least_opencv(sim):
    p = sim["psnr"]
    assert p["debevec"] >= p["opencv-debevec"] - 0.3, p


def test_robertson_near_debevec_and_far_above_the_literal_algorithm(sim):
    p = sim["psnr"]
    # measured -3.6 to +0.3 dB from debevec here; literal Robertson (OpenCV) 6-10 dB below
    assert p["robertson"] >= p["debevec"] - 4.0, p
    assert p["robertson"] >= p["opencv-robertson"] + 4.0, p


def test_neutral_colours_stay_neutral(sim):
    """The truth's grey pixels (channels within 5 %) are nearer grey with the balanced (and, since
    issue 27, tied) curves than with the paper's independent channels anchored at code 128."""
    rad, neutral = sim["rad"], sim["neutral"]
    assert neutral.sum() > 500
    for m in ("debevec", "robertson"):
        assert _neutral_error(rad[m], neutral) < _neutral_error(rad[f"{m}-unbalanced"], neutral), m
    curves = sim["rad"]["curves"]
    assert curves["debevec"].log_inverse[128, 1] == 0 and curves["robertson"].log_inverse[128, 1] == 0
    assert curves["debevec"].params["balance"] in ("neutral", "grey-axis")


def test_robertson_curve_smooth_and_strictly_increasing(sim):
    g = sim["rad"]["curves"]["robertson"].log_inverse
    d = np.diff(g, axis=0)
    assert np.all(d > 0)  # no flat step anywhere, clipped ends included
    core = d[30:225]
    assert np.all(core.max(axis=0) < 4 * np.median(core, axis=0)), core.max(axis=0) / np.median(core, axis=0)


def test_robertson_fills_codes_no_pixel_hits():
    """Only even codes occur: the odd ones are interpolated, the curve stays smooth (no staircase)."""
    from derender.response.robertson2003 import calibrate_robertson

    rng = np.random.default_rng(0)
    h, w, n = 60, 80, 6
    e = np.exp(rng.uniform(-3, 1, (h, w, 1))) * np.array([1.0, 0.8, 0.6])
    times = 2.0 ** np.arange(n) / 16
    codes = [2 * np.rint(np.clip(e * t, 0, 1) ** (1 / 2.2) * 127.5) for t in times]
    st = Stack(images=(np.clip(np.stack(codes), 0, 254) / 255).astype(np.float32), times=times)
    g = calibrate_robertson(st, balance=False).log_inverse
    assert np.all(np.diff(g, axis=0) > 0)
    mid = g[40:220]
    # odd codes sit halfway between their even neighbours (linear interpolation of a smooth curve)
    assert np.max(np.abs(g[41:220:2] - 0.5 * (g[40:219:2] + g[42:221:2]))) < 0.01
    # and the curve is the gamma-2.2 one (up to its anchor)
    z = np.arange(40, 220) / 255
    want = 2.2 * np.log(z) - 2.2 * np.log(128 / 255)
    assert np.max(np.abs(mid[:, 1] - want)) < 0.1


def test_robertson_reference_engine_uses_the_same_weights(sim):
    """The table engine (8-bit) and the float reference engine give the same ML merge."""
    from derender.hdr.classic import merge_robertson

    st, curves = sim["stack"], sim["rad"]["curves"]["robertson"]
    a = np.asarray(merge_robertson(st, options={"curves": curves, "engine": "table"}).radiance, dtype=np.float64)
    b = np.asarray(merge_robertson(st, options={"curves": curves, "engine": "reference"}).radiance, dtype=np.float64)
    assert np.max(np.abs(a - b) / np.maximum(np.abs(b).max(-1, keepdims=True), 1e-30)) < 1e-4


@pytest.mark.shared_data
def test_frobisher_robertson_has_no_staircase(frobisher_dir):
    """The real 3-frame bracket: literal Robertson (OpenCV) has ~50-65 flat steps between codes
    30 and 225 and jumps of 0.12-0.2; ours none, and jumps like Debevec's."""
    from derender.io.images import read_stack
    from derender.response.robertson2003 import calibrate_robertson

    st = read_stack(sorted(frobisher_dir.glob("IMG_*.jpg")))
    d = np.diff(calibrate_robertson(st, max_pixels=20_000).log_inverse, axis=0)[30:225]
    assert np.all(d > 0)
    assert d.max() < 0.1, d.max(axis=0)


def _chroma_rings(rad: np.ndarray) -> float:
    """Fraction of the smooth-luminance pixels whose (4 px blurred) log chromaticity changes by more
    than 0.0125 per pixel: the rainbow contour rings of a staircase curve in sky and walls."""
    from scipy import ndimage

    lr = np.log(np.maximum(np.asarray(rad, dtype=np.float64), 1e-9))
    c = ndimage.gaussian_filter(np.stack([lr[..., 0] - lr[..., 1], lr[..., 2] - lr[..., 1]], -1), (4, 4, 0))
    lum = ndimage.gaussian_filter(np.log(np.maximum(np.asarray(rad, dtype=np.float64).mean(-1), 1e-9)), 2)
    smooth = np.hypot(*np.gradient(lum)) < 0.02
    grad = np.hypot(*np.gradient(c[..., 0])) + np.hypot(*np.gradient(c[..., 1]))
    return float(np.mean(grad[smooth] > 0.0125))


@pytest.mark.shared_data
def test_frobisher_robertson_has_no_contour_rings(frobisher_dir):
    """Measured ring fraction: literal Robertson 0.36 (ours before) / 0.35 (OpenCV), now 0.13,
    Debevec 0.08."""
    from derender.hdr.classic import merge_debevec, merge_robertson
    from derender.io.images import read_stack

    st = read_stack(sorted(frobisher_dir.glob("IMG_*.jpg")))
    rob, deb = _chroma_rings(merge_robertson(st).radiance), _chroma_rings(merge_debevec(st).radiance)
    assert rob < 0.2 and rob < deb + 0.1, (rob, deb)


def test_robertson_within_1db_of_debevec_on_the_paper_family():
    """Issue 16: on the ``paper`` family (auto pipeline: a gamma, gain and white balance per frame)
    robertson's PSNR L against the simulator's exact radiance, averaged over 12 brackets
    (outdoor + indoor x seeds 0-5, 192x128, 7 exposures), is within 1 dB of Debevec & Malik's
    (their system, ``censor=False``). Measured: -0.28 dB when written (the calibration's leave-one-out
    radiance a geometric mean of the other frames weighted by ``w``, the smoother's data weighted
    by inverse variance); -0.41 dB with the first alone; -1.11 dB with the merge's ``w / g'^2``
    averaged linearly, which hands that radiance to one frame's pipeline; -0.89 dB at c8b68da
    main (robertson 42.96, debevec 43.85). The debevec merge's bound-aware top (``censor=True``,
    the default) reads 43.84 dB on this family (per bracket -0.33 .. +0.12 dB)."""
    from derender.camera import simulate_bracket
    from derender.evaluation.metrics import psnr_rgbl
    from derender.hdr.classic import merge_debevec, merge_robertson

    diffs = []
    for kind in ("outdoor", "indoor"):
        for seed in range(6):
            b = simulate_bracket("nikon-d5100", kind=kind, size=(192, 128), exposures=7, seed=seed, family="paper")
            st = Stack(images=code_values()[b.jpeg_codes], times=b.times)
            deb, rob = (psnr_rgbl(m(st).radiance, b.truth_linear_srgb)["L"]
                        for m in (lambda s: merge_debevec(s, {"seed": seed, "censor": False}),
                                  lambda s: merge_robertson(s, {"seed": seed})))
            diffs.append(rob - deb)
    assert np.mean(diffs) >= -1.0, np.round(diffs, 2)
