"""Stabilised merges on pipeline families they were not tuned on (issue 16 item 4, issue 18 item 3).

Tuning families: ``paper``, ``camera``; held out: ``dslr-lut``, ``phone-local``, ``drift``
(:mod:`derender.camera.families`). 192x128 brackets of 7 exposures (nikon-d5100), indoor
seed 0. Saturation rendered below white: the ``phone-local`` family's codes scaled so that
white renders at code 200 (a phone that keeps highlights below white); PSNR L debevec with the
paper's system (``censor=False``) 34.25, stabilized 41.36, and about 23.6 without
:mod:`derender.hdr.stabilize.saturation`'s mask. Debevec's bound-aware top (issue 36, the default)
censors the codes stuck at 200 itself and reaches 41.77 there: the stabilised merges' mask is
compared with the paper's Debevec & Malik, the baseline it was built against. dslr-lut: debevec
25.13, stabilized 44.39.
"""

from __future__ import annotations

import numpy as np
import pytest

from derender.camera import simulate_bracket
from derender.core.types import Stack
from derender.evaluation.metrics import psnr_rgbl
from derender.hdr.registry import merge_seeded
from derender.hdr.stabilize.saturation import HIDDEN_FRACTION, hidden_fraction, hidden_saturation, saturation_mask

SIZE = (192, 128)


def _stack(b) -> Stack:
    return Stack(images=b.jpeg_codes.astype(np.float32) / 255.0, times=b.times)


def _bracket(family: str, kind: str = "indoor", seed: int = 0):
    return simulate_bracket("nikon-d5100", kind=kind, size=SIZE, exposures=7, seed=seed, family=family)


def test_hidden_saturation_flags_stagnant_codes_below_white():
    # radiance ramp, exposure ratio 4, display gamma 2.2, sensor clip at 1 rendered at 0.6 of white
    x = np.linspace(0.01, 1.0, 64)[None, :, None] * np.ones((8, 1, 3))
    times = np.array([1.0, 4.0, 16.0])
    imgs = np.stack([0.6 * np.minimum(x * t, 1.0) ** (1 / 2.2) for t in times]).astype(np.float32)
    mask = hidden_saturation(imgs, times)
    clipped = np.stack([np.broadcast_to((x * t).max(axis=-1) >= 1.0, mask.shape[1:]) for t in times])
    near = np.stack([np.broadcast_to((x * t).max(axis=-1) >= 0.95, mask.shape[1:]) for t in times])
    # every flagged pixel is clipped or within 5 % of it (its code can grow by < 2 steps);
    # every pixel clipped in two consecutive frames is flagged
    assert not np.any(mask & ~near)
    assert np.all(mask[1][clipped[0]]) and np.all(mask[0][clipped[0]])
    assert hidden_fraction(mask, imgs) > HIDDEN_FRACTION
    # the same bracket clipping at white: nothing hidden below FIT_HIGH
    white = np.stack([np.minimum(x * t, 1.0) ** (1 / 2.2) for t in times]).astype(np.float32)
    m2, frac = saturation_mask(white, times)
    assert m2 is None and frac == 0.0


def test_tuning_families_keep_the_unmasked_merge():
    """Pipelines that clip at white stay below HIDDEN_FRACTION (their merges run as before, on the engine)."""
    for family in ("paper", "camera"):
        b = simulate_bracket("nikon-d5100", kind="indoor", size=(96, 64), exposures=5, seed=0, family=family)
        st = _stack(b)
        mask, frac = saturation_mask(st.images, st.times)
        assert mask is None and frac < HIDDEN_FRACTION / 10, (family, frac)


@pytest.fixture(scope="module")
def phone():
    """phone-local with white rendered at code 200: sensor-clipped highlights sit below white."""
    b = _bracket("phone-local")
    codes = np.round(b.jpeg_codes.astype(np.float32) * np.float32(200 / 255)).astype(np.uint8)
    b.jpeg_codes = codes
    # the paper's Debevec & Malik system (no censored top): the baseline the mask was built against
    deb = psnr_rgbl(merge_seeded(_stack(b), "debevec", 0, options={"censor": False}).radiance, b.truth_linear_srgb)["L"]
    return b, deb


@pytest.mark.parametrize("method", ["stabilized", "stabilized-joint"])
def test_saturation_below_white_is_masked(phone, method, monkeypatch):
    """Clipped highlights rendered at code 200 stop rising with exposure; masking them lifts the
    stabilised merges by ~15 dB over the unmasked merge (23.6 dB) and above the paper's debevec."""
    import derender.hdr.stabilize.saturation as saturation

    b, deb = phone
    st = _stack(b)
    res = merge_seeded(st, method, 0)
    r = res.radiance
    assert np.all(np.isfinite(r)) and r.min() >= 0.0
    assert res.info["hidden_saturation"]["masked"]
    psnr = psnr_rgbl(r, b.truth_linear_srgb)["L"]
    monkeypatch.setattr(saturation, "HIDDEN_FRACTION", 2.0)
    unmasked = psnr_rgbl(merge_seeded(st, method, 0).radiance, b.truth_linear_srgb)["L"]
    assert psnr > unmasked + 10.0, (psnr, unmasked)
    assert psnr > deb + 3.0, (psnr, deb)


def test_dslr_lut_held_out_beats_debevec():
    """Held out: white-balance presets switching within the bracket break debevec's fixed
    per-channel response (25.1 dB); the per-frame colour matrices do not (44.4 dB)."""
    b = _bracket("dslr-lut")
    st = _stack(b)
    deb = psnr_rgbl(merge_seeded(st, "debevec", 0).radiance, b.truth_linear_srgb)["L"]
    r = merge_seeded(st, "stabilized", 0).radiance
    assert np.all(np.isfinite(r)) and r.min() >= 0.0
    psnr = psnr_rgbl(r, b.truth_linear_srgb)["L"]
    assert psnr > deb + 15.0, (psnr, deb)


def test_engine_gate_on_codes_and_row_subsample(phone):
    """The engine's gate reads aligned uint8 codes (every k-th row on large frames): the same
    fraction as the float frames, and close to it on a row subsample."""
    from derender.hdr.stabilize.method import CodeFrameRows, ShiftedFrames
    from derender.hdr.stabilize.saturation import saturation_fraction

    b, _ = phone
    view = ShiftedFrames(b.jpeg_codes, np.zeros((len(b.times), 2), dtype=int))
    full = saturation_fraction(_stack(b).images, b.times)
    assert saturation_fraction(CodeFrameRows(view), b.times) == pytest.approx(full, abs=1e-9)
    assert saturation_fraction(CodeFrameRows(view, 3), b.times) == pytest.approx(full, abs=0.03)


def test_exposure_offsets_reach_the_oracle_on_the_camera_family(monkeypatch):
    """The default ``exposure_rounds=3`` (per-frame exposure offsets fitted with the common curve,
    :mod:`derender.hdr.stabilize.filmic`) on the ``camera`` family (a tuning family), outdoor
    seed 0, with independent channel curves (``CURVE_TIE = 0``, the default): the auto pipeline's gain and
    white-balance changes bend the plain common curve (``exposure_rounds=0``: stabilized PSNR L
    39.93 dB against the oracle's 43.66); with the offsets 44.02 (measured). With the default
    channel tie (issue 27) the plain curve no longer bends (43.11) and the offsets give 42.77.
    Finite, non-negative radiance."""
    import derender.hdr.stabilize.filmic as F
    from derender.evaluation.oracle import oracle_merge_bracket

    assert F.CURVE_TIE == 0.0

    b = _bracket("camera", kind="outdoor", seed=0)
    st = _stack(b)
    oracle = psnr_rgbl(oracle_merge_bracket(b).radiance, b.truth_linear_srgb)["L"]
    plain = merge_seeded(st, "stabilized", 0, options={"exposure_rounds": 0})
    fitted = merge_seeded(st, "stabilized", 0)
    rad = np.asarray(fitted.radiance)
    assert np.all(np.isfinite(rad)) and rad.min() >= 0
    assert fitted.info["response"] == "curve"
    p_plain = psnr_rgbl(plain.radiance, b.truth_linear_srgb)["L"]
    p_fit = psnr_rgbl(rad, b.truth_linear_srgb)["L"]
    assert p_fit >= oracle - 0.3 and p_fit >= p_plain + 2.0, (p_plain, p_fit, oracle)


@pytest.mark.parametrize("render, follows", [("gamma", True), ("paper", False)])
def test_gamma_level_follows_the_times_only_on_one_rendering(render, follows):
    """The gammas' level (:func:`derender.hdr.stabilize.exponents.estimate_gammas_blocks`): on the
    luminance family's fixed gamma-2.2 camera (9 frames, 2 EV, seed 0, tuning) the pairs' gains at
    their own colours follow the times within :data:`~derender.hdr.stabilize.exponents.TIME_FOLLOW`,
    so the level is theirs and the matrices' luminance scale is the times' (``lum(H_j 1) = t_ref /
    t_j``); on ``paper`` (a hidden gain per frame, tuning) they do not, and paper 1's white-gain
    level and fitted scales stay (its merge unchanged). Measured largest residual: 0.006 / 0.18."""
    from derender.camera.luminance import simulate_luminance
    from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709

    b = simulate_luminance(render=render, size=SIZE, exposures=9, stops=2.0, seed=0)
    res = merge_seeded(_stack(b), "stabilized", 0)
    lev = res.info["gamma_level"]
    assert lev["follows_times"] is follows and lev["level_gain"] == ("data" if follows else "white")
    worst = float(np.max(np.abs(lev["time_residuals"])))
    t, ref = np.asarray(b.times), res.info["reference"]
    lum = np.einsum("c,jcd->j", LUMINANCE_WEIGHTS_REC709, np.asarray(res.info["matrices"])) * t / t[ref]
    if follows:
        assert worst <= 0.015, lev["time_residuals"]
        # anchored, then one grey-balance diagonal on every matrix: the scales follow the times
        assert np.ptp(lum / lum[ref]) <= 0.01, lum
        assert abs(float(np.median(res.info["gammas"])) / 2.2 - 1.0) <= 0.005, res.info["gammas"]
    else:
        assert worst >= 0.06, lev["time_residuals"]
        assert "anchored_to_times" not in lev
