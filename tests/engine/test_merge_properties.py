"""Property-based tests: the merge methods on random and hostile stacks never crash with a
traceback-worthy error and never produce NaN or inf."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from derender.core.errors import DerenderError
from derender.core.types import Stack
from derender.engine.float_merge import merge_linear
from derender.hdr.registry import merge

_codes = st.sampled_from(["random", "zeros", "full", "binary", "one-channel-dead", "ramp"])


def _make(kind: str, n: int, h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "random":
        c = rng.integers(0, 256, (n, h, w, 3))
    elif kind == "zeros":
        c = np.zeros((n, h, w, 3), int)
    elif kind == "full":
        c = np.full((n, h, w, 3), 255)
    elif kind == "binary":
        c = rng.choice([0, 255], size=(n, h, w, 3))
    elif kind == "one-channel-dead":
        c = rng.integers(0, 256, (n, h, w, 3))
        c[..., 2] = 0
    else:
        base = np.linspace(0, 1, h * w).reshape(h, w, 1)
        c = np.stack([np.clip(base * 2 ** j * 255, 0, 255) * np.ones(3) for j in range(n)])
    return np.asarray(c, dtype=np.uint8)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=_codes, n=st.integers(2, 5), h=st.integers(4, 24), w=st.integers(4, 24),
       seed=st.integers(0, 10_000), method=st.sampled_from(["debevec", "robertson"]),
       times=st.lists(st.floats(1e-5, 1e4), min_size=5, max_size=5, unique=True))
def test_merge_is_finite_or_a_clear_error(kind, n, h, w, seed, method, times):
    codes = _make(kind, n, h, w, seed)
    try:
        stack = Stack(images=codes / 255.0, times=times[:n])
        res = merge(stack, method=method)
    except DerenderError as exc:
        assert str(exc)  # a one-line message for the user
        return
    assert res.radiance.shape == (h, w, 3)
    assert np.all(np.isfinite(res.radiance))
    assert res.mask.shape == (h, w)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 4),
       bad=st.sampled_from([np.nan, np.inf, -np.inf, -1.0, 0.0, 1e30]))
def test_engine_tolerates_non_finite_linearisation(seed, n, bad):
    rng = np.random.default_rng(seed)
    imgs = rng.random((n, 6, 7, 3)).astype(np.float32)
    lin = rng.random((n, 6, 7, 3)) * 10
    lin[0, 0, 0, 0] = bad
    lin[-1, 2, 3, 1] = bad
    res = merge_linear(lin, np.geomspace(0.01, 1, n), imgs, "hat")
    assert np.all(np.isfinite(res.radiance))
