"""Tests for derender.diagnose: the constant-response check of paper 1, Fig. 2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from derender.core.errors import StackError
from derender.core.types import Stack
from derender.evaluation.diagnose import diagnose_constant_response, plot_diagnose

GAMMAS, KNEES = (2.0, 2.2, 2.5), (0.4, 0.5, 0.6)


def _render(per_exposure=None, h=90, w=120, n=8, noise=2e-4, seed=0):
    """Known radiance through one fixed per-channel response (optionally altered per exposure)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    base = 10 ** (3.0 * (x - 0.5) + 0.5 * np.sin(6 * y))
    e = np.stack([base * (0.6 + 0.4 * np.cos(3 * y * (c + 1) + 2 * x)) for c in range(3)], -1)
    times = 2.0 ** (np.arange(n) - (n - 1))
    e = e / e.max() / times[0] * 0.8
    imgs = []
    for j, t in enumerate(times):
        xe = e * t
        if per_exposure is not None:
            xe = per_exposure(j, xe)
        xe = np.clip(xe + rng.normal(0, noise, xe.shape), 0, 1)
        yv = np.stack([(xe[..., c] ** (1 / GAMMAS[c])) for c in range(3)], -1)
        yv = yv * (1 + np.array(KNEES)) / (yv + np.array(KNEES))
        imgs.append(np.rint(yv * 255) / 255)
    return Stack(images=np.stack(imgs).astype(np.float32), times=times)


def test_fixed_response_small_spread_changing_pipeline_large_spread(tmp_path):
    fixed = diagnose_constant_response(_render())
    rng = np.random.default_rng(5)
    n = 8
    wb = rng.uniform(0.8, 1.25, (n, 3))  # white balance changes per exposure
    gamma = rng.uniform(0.85, 1.15, n)  # and so does the tone curve
    changing = diagnose_constant_response(_render(lambda j, x: (x * wb[j]) ** gamma[j]))
    assert fixed.rms_stops < 0.1, fixed.rms_stops
    assert changing.rms_stops > 4 * fixed.rms_stops, (fixed.rms_stops, changing.rms_stops)
    assert changing.median_stops > 10 * fixed.median_stops, (fixed.median_stops, changing.median_stops)
    assert 0 < fixed.median_stops <= fixed.rms_stops
    assert fixed.log_estimates.shape == (n, fixed.log_radiance.shape[0], 3)
    assert fixed.rms_stops_per_exposure.shape == (n,) and fixed.offset_stops.shape == (n, 3)
    json.dumps(changing.summary(), allow_nan=False)
    out = plot_diagnose(changing, tmp_path / "fig2.png")
    assert out.stat().st_size > 5000
    assert [p.name for p in tmp_path.iterdir()] == ["fig2.png"]


def test_single_exposure_gain_change_shows_in_its_offset():
    # exposure 4 has its red channel gained by +0.7 stop (e.g. a white-balance change)
    gain = 2 ** 0.7
    res = diagnose_constant_response(_render(lambda j, x: x * np.array([gain, 1, 1]) if j == 4 else x))
    off = res.offset_stops
    assert off[4, 0] > 0.2, off[:, 0]
    assert np.argmax(np.abs(off[:, 0])) == 4
    assert np.abs(off[:, 1:]).max() < 0.1


def test_unusable_stack_raises():
    st = Stack(images=np.ones((3, 6, 6, 3), np.float32), times=[0.1, 0.2, 0.4])
    with pytest.raises(StackError):
        diagnose_constant_response(st)


@pytest.mark.shared_data
def test_memorial_is_close_to_constant_response(memorial_dir):
    """Debevec's film stack had one fixed response: small spread on well-exposed codes."""
    from derender.io.images import read_stack

    st = read_stack(sorted(memorial_dir.glob("memorial00*.png")),
                    times_file=memorial_dir / "memorial.hdr_image_list.txt", times_file_inverse=True)
    res = diagnose_constant_response(Stack(images=st.images[:, ::2, ::2], times=st.times), n_samples=1000)
    assert res.median_stops < 0.12, res.median_stops
    assert res.rms_stops < 0.35, res.rms_stops
