"""Synthetic calibration pairs and the models fitted to them, shared by the de-rendering tests.

Training pairs come from a known synthetic forward rendering written here (independent of
the simulator): chart-like camera colours (140 patches x 16 illuminants x exposures over
five decades), sensor saturation, fixed white balance, a 3x3 camera->sRGB matrix with
out-of-gamut colours, a *non-separable* hue-preserving gamut mapping (out-of-gamut
colours are pulled towards grey) and highlight roll-off (bright colours desaturate
towards white), clipping, an S-shaped tone curve on the sRGB OETF, 8-bit quantisation.

The fixtures ``data`` (train/test split), ``gp``, ``poly`` and ``rbf`` (models fitted to the
training half) are session-wide, so the models are fitted once however many test files use
them: a test module gets them with ``pytest_plugins = ["synthetic_pairs"]``.
"""

from __future__ import annotations

import numpy as np
import pytest

from derender.derendering.local_gp import LocalGPModel
from derender.derendering.polynomial import PolynomialModel
from derender.derendering.rbf import RBFModel

CAM_TO_SRGB = np.array([[1.55, -0.45, -0.10], [-0.20, 1.45, -0.25], [0.03, -0.40, 1.37]])
WB = np.array([1.9, 1.0, 1.6])
LUM = np.array([0.2126, 0.7152, 0.0722])

GP_TEST_SETTINGS = dict(n_train=1500, max_cluster_points=300, opt_points=150, table_size=28)


def render(raw: np.ndarray) -> np.ndarray:
    """Synthetic camera: raw camera RGB (N,3) -> 8-bit sRGB codes (N,3)."""
    x = np.minimum(raw, 1.0) * WB                          # sensor saturation, white balance
    rgb = x @ CAM_TO_SRGB.T
    lum = np.maximum(rgb @ LUM, 0.2 * x.mean(axis=1) + 1e-12)[:, None]
    mn = rgb.min(axis=1, keepdims=True)                    # gamut mapping towards grey (non-separable)
    rgb = lum + (rgb - lum) * np.where(mn < 0, lum / (lum - mn), 1.0)
    mx = rgb.max(axis=1, keepdims=True)                    # highlight roll-off (non-separable)
    t = np.clip((mx - 0.6) / 0.8, 0, 1) ** 2
    rgb = rgb + (np.maximum(mx, 1.0) - rgb) * t
    v = np.clip(rgb, 0, 1)
    s = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
    s = s + 0.06 * np.sin(2 * np.pi * s)                   # S-shaped tone curve
    return np.round(255 * np.clip(s, 0, 1)).astype(np.uint8)


def make_pairs(seed: int = 0, noise: float = 0.003) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    refl = rng.uniform(0.03, 0.9, (140, 3)) ** rng.uniform(0.5, 2.0, (140, 1))
    sat = rng.random(140) < 0.3
    refl[sat] = 0.05 + 0.9 * rng.dirichlet([2.0, 2.0, 2.0], sat.sum())
    illum = rng.uniform(0.5, 1.0, (16, 3))
    illum /= illum.max(axis=1, keepdims=True)
    base = (refl[None] * illum[:, None] / WB * 0.7).reshape(-1, 3)
    stops = np.arange(-7, 3.01, 0.5)
    raw = (base[None] * (2.0 ** stops)[:, None, None]).reshape(-1, 3)
    raw = raw * (1 + noise * rng.standard_normal(raw.shape))
    return render(raw), raw


@pytest.fixture(scope="session")
def data():
    jpeg, raw = make_pairs()
    perm = np.random.default_rng(1).permutation(jpeg.shape[0])
    tr, te = perm[:2000], perm[-10000:]
    return jpeg[tr], raw[tr], jpeg[te], raw[te]


@pytest.fixture(scope="session")
def gp(data):
    return LocalGPModel(seed=0, **GP_TEST_SETTINGS).fit(data[0], data[1])


@pytest.fixture(scope="session")
def poly(data):
    return PolynomialModel().fit(data[0], data[1])


@pytest.fixture(scope="session")
def rbf(data):
    return RBFModel(n_train=800, table_size=24).fit(data[0], data[1])
