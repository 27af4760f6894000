"""The round trip (issue 36): a merge rendered back through its method's forward model gives back
the frames' codes. Oracles: frames rendered from a known radiance through known tables (exact
up to 8-bit rounding); a map changed in one region must fail there; Frobisher's real bracket
meets the issue's line (median |d code| <= 1.5, p95 <= 4) with debevec and stabilized, per frame
and pooled with the merge's weights."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require_shared

from derender.engine.motion.run import MotionOptions
from derender.engine.plans import MatrixPlan, TablePlan
from derender.evaluation.roundtrip import bracket_round_trip, round_trip


def _bracket(seed=0, n=4, h=40, w=56):
    rng = np.random.default_rng(seed)
    radiance = np.exp(rng.uniform(-4.5, -0.5, (h, w, 3)))
    times = 2.0 ** np.arange(n) / 4.0
    z = np.arange(256) / 255.0
    lin = np.stack([z ** 2.2 * s for s in (1.0, 0.9, 1.1)], axis=-1)          # f^-1 per channel
    frames = np.empty((n, h, w, 3), np.uint8)
    for j, t in enumerate(times):
        x = radiance * t
        for c in range(3):
            frames[j, ..., c] = np.clip(np.rint(255.0 * np.clip(x[..., c] / lin[-1, c], 0, 1) ** (1 / 2.2)), 0, 255)
    return radiance, times, lin, frames


def test_a_table_plan_renders_its_exact_radiance_back():
    radiance, times, lin, frames = _bracket()
    with np.errstate(divide="ignore"):
        logv = np.log(lin)[None] - np.log(times)[:, None, None]
    weights = np.ones((256, 3))
    weights[[0, 255]] = 0.0
    plan = TablePlan(values=logv.astype(np.float32), weights=weights, domain="log")
    rt = round_trip(plan, frames, radiance * 7.0)        # any global scale
    assert np.all(rt.pixels > 200)
    assert np.all(rt.median <= 0.5) and np.all(rt.p95 <= 0.75)       # 8-bit rounding, no more
    assert rt.share.sum() == pytest.approx(1.0) and np.all(rt.share > 0.05)
    assert rt.weighted_median <= 0.5 and rt.weighted_p95 <= 0.75
    wrong = radiance.copy()
    wrong[:6] *= 1.3                                                    # the top rows 30 % too bright
    bad = round_trip(plan, frames, wrong)
    assert bad.fail[:6].mean() > 0.5 and bad.fail[10:].max() == 0
    assert bad.weighted_p95 > 2.0                                       # 15 % of the pixels, 30 % off
    top = bad.regions[:, 0]                                             # the first row of regions (10 rows)
    assert np.all(top[np.isfinite(top)] > 1.0) and np.nanmax(bad.regions[:, 1:]) <= 0.5


def test_a_matrix_plan_inverts_its_matrices():
    radiance, times, lin, frames = _bracket(seed=1)
    # frame j is rendered from radiance * t_j through lin; its matrix maps its linear values back
    mats = np.stack([np.eye(3) / t for t in times])
    weights = np.ones((256, 3))
    weights[[0, 255]] = 0.0
    plan = MatrixPlan(values=np.repeat(lin[None], len(times), axis=0).astype(np.float32), matrices=mats,
                      weights=weights, shifts=np.zeros((len(times), 2), np.int64))
    rt = round_trip(plan, frames, radiance)
    assert np.all(rt.median <= 0.5) and np.all(rt.p95 <= 0.75)


def test_a_tolerance_forgives_a_misregistration_not_a_wrong_map():
    """A frame one pixel off (a handheld bracket's misregistration) fails the plain round trip
    and passes with a 1 px tolerance (one shift per block); a map 30 % too bright on half the
    image still fails with a 2 px tolerance and 5x5 means."""
    radiance, times, lin, frames = _bracket(seed=2, h=64, w=64)
    with np.errstate(divide="ignore"):
        logv = np.log(lin)[None] - np.log(times)[:, None, None]
    weights = np.ones((256, 3))
    weights[[0, 255]] = 0.0
    plan = TablePlan(values=logv.astype(np.float32), weights=weights, domain="log")
    moved = frames.copy()
    moved[2, :, 1:] = frames[2, :, :-1]                                  # frame 2 one pixel to the right
    plain = round_trip(plan, moved, radiance)
    assert plain.p95[2] > 4.0 and np.all(np.delete(plain.p95, 2) <= 0.75)
    tol = round_trip(plan, moved, radiance, tolerance=1)
    assert tol.tolerance == 1.0 and np.all(tol.p95 <= 0.75)             # only 8-bit rounding is left
    wrong = radiance.copy()
    wrong[:32] *= 1.3
    bad = round_trip(plan, frames, wrong, tolerance=2, scale=5)
    assert bad.scale == 5 and np.all(bad.p95[bad.pixels > 200] > 2.0)
    good = round_trip(plan, frames, radiance, tolerance=2, scale=5)
    assert np.all(good.p95 <= 0.75)


@pytest.mark.shared_data
@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_frobisher_renders_back_its_frames(method):
    folder = require_shared("colour-hdri-frobisher")
    rt, res, names = bracket_round_trip([folder], method, motion=MotionOptions(reference=1, align="none"))
    assert len(names) == 3
    assert rt.share.sum() == pytest.approx(1.0)
    assert rt.weighted_median <= 1.5 and rt.weighted_p95 <= 4.0        # measured 0.17-0.25 / 1.6-2.0
    for row in rt.rows(names):
        assert row["pixels"] > 10_000, row
        assert row["median"] <= 1.5 and row["p95"] <= 4.0, row


@pytest.mark.shared_data
def test_diagnose_round_trip_prints_every_frame_and_writes_the_fail_map(tmp_path, capsys):
    import cv2
    from helpers import run_cli

    folder = require_shared("colour-hdri-frobisher")
    fig, fail = tmp_path / "fig.png", tmp_path / "fail.png"
    code, out, err = run_cli(["diagnose", str(folder), "-o", str(fig), "--round-trip", "debevec",
                              "--reference", "2", "--fail-map", str(fail)], capsys)
    assert code == 0, err
    assert out.count("median") >= 3 and "IMG_2601.jpg" in out
    img = cv2.imread(str(fail))
    frame = cv2.imread(str(folder / "IMG_2600.jpg"))
    assert img is not None and img.shape == frame.shape
    assert (img > 0).mean() < 0.2          # Frobisher re-renders: few pixels miss
    code, out, err = run_cli(["diagnose", str(folder), "-o", str(tmp_path / "x.png"), "--fail-map", str(fail)], capsys)
    assert code == 2 and err.startswith("error:") and "--round-trip" in err
    assert not (tmp_path / "x.png").exists()


@pytest.mark.shared_data
def test_memorial_renders_back_its_frames_where_the_weight_is():
    """The proposed pooled line on a film bracket (issue 36): Memorial (16 frames, one film, one
    rendering) merged by the stabilised method renders back its frames, each residual counted by
    its merge weight: measured median 1.63, p95 7.0 codes (the issue's per-frame 1.5 / 4 is not
    met); the test holds the proposed line (median <= 2, p95 <= 8) and that every frame carries
    some of the weight. Before the
    round trip took the merge's own scale it read 27-44 codes on the long frames."""
    from derender.evaluation.consistency import bracket_inputs

    paths, kw = bracket_inputs("memorial")          # reference 8, no alignment, the times file (1/t)
    rt, res, names = bracket_round_trip(paths, "stabilized", **kw)
    assert len(names) == 16 and np.all(rt.share > 0.01)
    assert rt.weighted_median <= 2.0 and rt.weighted_p95 <= 8.0
