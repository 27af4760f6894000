"""Tests for derender.evaluate: the HDR PSNR protocol of DESIGN.md."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from derender.core.errors import InputError
from derender.core.types import HDRResult
from derender.evaluation.metrics import PSNR_CAP, fit_scale, psnr_rgbl


def _reference_psnr(result, truth, remap):
    """Independent re-implementation: plain Python float loops, closed-form scale."""
    h, w, _ = truth.shape
    planes = {}
    for c, name in enumerate("RGB"):
        planes[name] = ([float(result[y, x, c]) for y in range(h) for x in range(w)],
                        [float(truth[y, x, c]) for y in range(h) for x in range(w)])

    def lum(img, y, x):
        return 0.2126 * float(img[y, x, 0]) + 0.7152 * float(img[y, x, 1]) + 0.0722 * float(img[y, x, 2])

    planes["L"] = ([lum(result, y, x) for y in range(h) for x in range(w)],
                   [lum(truth, y, x) for y in range(h) for x in range(w)])
    out = {}
    for name, (r, g) in planes.items():
        if remap == "lstsq":
            k = sum(a * b for a, b in zip(r, g)) / sum(a * a for a in r)
            rr = [k * a for a in r]
        else:
            lo, hi, glo, ghi = min(r), max(r), min(g), max(g)
            rr = [(a - lo) / (hi - lo) * (ghi - glo) + glo for a in r]
        mse = sum((a - b) ** 2 for a, b in zip(rr, g)) / len(g)
        out[name] = 10 * math.log10(max(g) ** 2 / mse)
    return out


@pytest.mark.parametrize("remap", ["lstsq", "minmax"])
def test_psnr_rgbl_matches_independent_implementation(remap):
    rng = np.random.default_rng(0)
    truth = (10 ** rng.uniform(-2, 2, (17, 13, 3))).astype(np.float32)
    result = (truth * 3.7 * np.exp(rng.normal(0, 0.1, truth.shape))).astype(np.float32)
    got = psnr_rgbl(result, truth, remap=remap)
    ref = _reference_psnr(result, truth, remap)
    assert set(got) == {"R", "G", "B", "L"}
    for k in "RGBL":
        assert abs(got[k] - ref[k]) < 0.01, (k, got[k], ref[k])
        assert isinstance(got[k], float)


def test_closed_form_values_and_scale():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 4, (10, 20, 3))
    noise = np.where(rng.random(truth.shape) < 0.5, 0.01, -0.01)
    noise -= noise.mean(axis=(0, 1))  # zero-mean per channel
    # result = truth / 5 + noise / 5 -> best scale close to 5; MSE known in closed form after the exact scale
    result = (truth + noise) / 5.0
    k = fit_scale(result[..., 0], truth[..., 0])
    r, g = result[..., 0].ravel(), truth[..., 0].ravel()
    assert np.isclose(k, r @ g / (r @ r))
    mse = np.mean((k * r - g) ** 2)
    assert np.isclose(psnr_rgbl(result, truth)["R"], 10 * np.log10(g.max() ** 2 / mse))
    # a perfect result (up to scale) is capped, finite, JSON-safe
    perfect = psnr_rgbl(truth, truth)
    assert all(v == PSNR_CAP for v in perfect.values())
    assert all(v > 120 for v in psnr_rgbl(truth * 0.01, truth).values())
    perfect_mm = psnr_rgbl(truth * 2 + 1, truth, remap="minmax")
    assert all(v > 100 for v in perfect_mm.values())
    json.dumps(perfect, allow_nan=False)
    # the scale does not matter for lstsq, it does for nothing else
    a = psnr_rgbl(result, truth)
    b = psnr_rgbl(result * 1000, truth)
    for kk in "RGBL":
        assert abs(a[kk] - b[kk]) < 1e-6


def test_luminance_scaled_separately_and_mask():
    rng = np.random.default_rng(2)
    truth = rng.uniform(0.1, 1, (8, 8, 3))
    # each channel off by a different scale: R, G, B perfect after per-channel scaling, L is not
    result = truth * np.array([1.0, 2.0, 0.5])
    scores = psnr_rgbl(result, truth)
    assert min(scores["R"], scores["G"], scores["B"]) > 120
    assert scores["L"] < 60
    bad = result.copy()
    bad[0, 0] = 50.0
    mask = np.ones((8, 8), bool)
    mask[0, 0] = False
    assert psnr_rgbl(bad, truth)["R"] < 40
    assert psnr_rgbl(bad, truth, mask=mask)["R"] > 120
    hdr = HDRResult(radiance=result.astype(np.float32), mask=np.zeros((8, 8), np.uint8))
    assert psnr_rgbl(hdr, truth)["G"] > 120


def test_input_errors():
    a = np.ones((4, 4, 3))
    with pytest.raises(InputError):
        psnr_rgbl(a, np.ones((4, 5, 3)))
    with pytest.raises(InputError):
        psnr_rgbl(np.ones((4, 4)), np.ones((4, 4)))
    nan = a.copy()
    nan[1, 1, 1] = np.nan
    with pytest.raises(InputError):
        psnr_rgbl(nan, a)
    with pytest.raises(InputError):
        psnr_rgbl(a, nan)
    with pytest.raises(InputError):
        psnr_rgbl(a, a, remap="quantile")
    with pytest.raises(InputError):
        psnr_rgbl(a, a, mask=np.zeros((4, 4), np.uint8))  # HDRResult masks are not evaluation masks
    with pytest.raises(InputError):
        psnr_rgbl(a, np.zeros((4, 4, 3)))  # PSNR undefined without a positive peak
