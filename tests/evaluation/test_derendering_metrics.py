"""Error measures of de-rendering predictions (``derender.evaluation.derendering_metrics``)."""

from __future__ import annotations

import numpy as np
import pytest

from derender.evaluation.derendering_metrics import (
    interval_coverage,
    max_colour_share,
    median_relative_error,
    relative_rmse,
    rmse,
)


def test_metrics_on_known_values():
    truth = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    pred = np.array([[1.1, 0.0, 0.0], [0.0, 2.0, 0.4]])
    assert relative_rmse(pred, truth) == pytest.approx(np.sqrt((0.01 + 0.04) / 2))
    assert rmse(pred, truth) == pytest.approx(np.sqrt((0.01 + 0.16) / 2))
    assert median_relative_error(pred, truth) == pytest.approx(0.15)
    assert max_colour_share(pred, truth) == pytest.approx(0.04 / 0.05)   # squared errors 0.01 and 0.04
    assert max_colour_share(truth, truth) == 0.0
    rng = np.random.default_rng(0)
    sd = rng.uniform(0.5, 2.0, (200000, 3))
    x = rng.standard_normal((200000, 3)) * sd
    cov = interval_coverage(np.zeros_like(x), sd ** 2, x, level=0.95)
    np.testing.assert_allclose(cov, 0.95, atol=0.003)
    assert interval_coverage(np.zeros_like(x), sd ** 2, x, level=0.5) == pytest.approx(0.5, abs=0.005)
