"""Adding a merge method: one decorated function registers it for the API, the CLI and the listing.

Issue 26 asks that a new method touch at most its module, its test and one registration line.
Here a toy method (the exposure-normalised mean of the well-exposed frames, linear codes) is
defined in this test file alone; it merges through ``dr.merge`` and ``merge_files``, takes its
options from ``--option``, and ``derender methods`` lists it with its output colour space.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli


@pytest.fixture
def toy_method():
    """The toy method registered for one test and removed after it (the registry is process-wide:
    the demo and the families tables run every registered method)."""
    from derender.hdr.registry import METHODS

    _register_toy()
    yield "toy-mean"
    METHODS.pop("toy-mean", None)


def _register_toy():
    from derender.core.types import HDRResult
    from derender.hdr.registry import register_method

    @register_method("toy-mean", output_space="the codes taken as linear, divided by the exposure time")
    def merge_toy(stack, low: float = 0.05, high: float = 0.95) -> HDRResult:
        """Toy merge: the mean of each frame's codes over its exposure time, where well exposed."""
        imgs = np.asarray(stack.images, dtype=np.float64)
        t = np.asarray(stack.times, dtype=np.float64)[:, None, None, None]
        ok = (imgs > low) & (imgs < high)
        num = np.where(ok, imgs / t, 0.0).sum(0)
        den = ok.sum(0)
        rad = np.where(den > 0, num / np.maximum(den, 1), imgs[0] / t[0])
        return HDRResult(radiance=rad.astype(np.float32), mask=np.zeros(rad.shape[:2], np.uint8),
                         info={"method": "toy-mean", "low": low})


def test_a_method_defined_outside_the_package_works_everywhere(tmp_path, capsys, toy_method):
    import derender as dr
    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.io.exr import read_exr

    write_bracket(simulate_bracket(size=(64, 48), exposures=3, pipeline="fixed", style="simple", seed=3),
                  tmp_path / "b")
    paths = bracket_paths(tmp_path / "b", "jpeg")
    res = dr.merge(dr.read_stack(paths), options={"low": 0.1}, method="toy-mean")
    assert res.info["low"] == 0.1 and np.isfinite(res.radiance).all()
    code, out, err = run_cli(["merge", *paths, "-o", tmp_path / "t.exr", "--method", "toy-mean",
                              "--option", "low=0.1"], capsys)
    assert code == 0, err
    np.testing.assert_array_equal(read_exr(tmp_path / "t.exr"), res.radiance)
    code, out, err = run_cli(["merge", *paths, "-o", tmp_path / "u.exr", "--method", "toy-mean",
                              "--option", "lo=0.1"], capsys)
    assert code == 2 and "low (float, default 0.05)" in err
    code, out, err = run_cli(["methods"], capsys)
    assert "toy-mean" in out.splitlines() and "divided by the exposure time" in out
    assert "Options (--option NAME=VALUE): low = 0.05; high = 0.95." in out
