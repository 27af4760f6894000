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


def _bracket(seed=0, n=4, h=40, w=56, low=-4.5):
    rng = np.random.default_rng(seed)
    radiance = np.exp(rng.uniform(low, -0.5, (h, w, 3)))
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


def test_a_film_base_is_a_black_clip():
    """Frames whose codes stop at a base (a film scan) while the map goes darker: with the
    bracket's floor (:func:`bracket_black`, the classic merges' rule) the base pixels are not
    scored; without it they miss by up to the base's height."""
    from derender.evaluation.roundtrip import bracket_black

    radiance, times, lin, frames = _bracket(seed=3, n=5, h=64, w=64, low=-9.0)
    base = np.array([14, 18, 16], np.uint8)
    based = np.maximum(frames, base)                                    # the film base
    with np.errstate(divide="ignore"):
        logv = np.log(lin)[None] - np.log(times)[:, None, None]
    weights = np.ones((256, 3))
    weights[[0, 255]] = 0.0
    plan = TablePlan(values=logv.astype(np.float32), weights=weights, domain="log")
    black = bracket_black(based, times)
    assert np.all(np.asarray(black) >= base) and np.all(np.asarray(black) <= base + 2)
    plain = round_trip(plan, based, radiance)
    assert plain.p95[0] > 4.0                                           # the shortest frame: mostly base
    floored = round_trip(plan, based, radiance, black=black)
    assert floored.black == black
    assert np.all(floored.p95[floored.pixels > 100] <= 0.75)            # what is left: 8-bit rounding
    assert np.all(floored.pixels < plain.pixels)


def test_the_reference_is_scored_where_ghost_removal_left_the_others_out(tmp_path):
    """Three objects move on a tripod bracket (the simulator): ghost removal leaves the other
    frames out there, never the reference, so the round trip scores the reference's codes on
    every pixel it exposes (a ghost in the output shows in its row) and the others' off the
    ghost mask."""
    import cv2

    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec

    b = simulate_bracket("nikon-d5100", kind="outdoor", size=(128, 96), exposures=3, seed=0, family="camera",
                         motion=MotionSpec(objects=3, shake=3).tripod())
    paths = []
    for j, codes in enumerate(b.jpeg_codes):
        paths.append(tmp_path / f"f{j}.png")
        cv2.imwrite(str(paths[-1]), cv2.cvtColor(np.ascontiguousarray(codes), cv2.COLOR_RGB2BGR))
    rt, res, names = bracket_round_trip(paths, "debevec", times=list(b.times),
                                        motion=MotionOptions(reference=1, align="none", deghost=True))
    ref = int(res.info["reference"])
    ghost = res.ghosts > 0
    assert ref == 1 and ghost.mean() > 0.01
    codes = np.asarray(b.jpeg_codes)[np.argsort(b.times, kind="stable")]
    inside = np.all((codes > 0) & (codes < 255), axis=-1)
    assert rt.pixels[ref] > (inside[ref] & ~ghost).sum()               # scored on the ghost mask too
    for j in (0, 2):
        assert rt.pixels[j] <= (inside[j] & ~ghost).sum()


def _frames_by_time(paths):
    from derender.io.exif import file_times
    from derender.io.images import read_codes

    t = np.asarray(file_times(paths, None, None, False), dtype=np.float64)
    return np.stack([read_codes(paths[i]) for i in np.argsort(t, kind="stable")])


@pytest.mark.shared_data
@pytest.mark.parametrize("method", ["debevec", "robertson", "stabilized", "stabilized-joint"])
def test_frobisher_renders_back_its_frames(method):
    """Issue 36's per-frame line, pixel by pixel (no tolerance, no means), on every method:
    measured medians 0.07-0.71, p95 0.9-2.8 codes."""
    folder = require_shared("colour-hdri-frobisher")
    rt, res, names = bracket_round_trip([folder], method, motion=MotionOptions(reference=1, align="none"))
    assert len(names) == 3 and rt.black == [0, 0, 0]                    # a digital bracket: no floor
    assert rt.share.sum() == pytest.approx(1.0)
    assert rt.weighted_median <= 1.5 and rt.weighted_p95 <= 4.0        # measured 0.17-0.25 / 1.6-2.0
    for row in rt.rows(names):
        assert row["pixels"] > 10_000, row
        assert row["median"] <= 1.5 and row["p95"] <= 4.0, row


@pytest.mark.shared_data
def test_frobisher_fails_on_a_wrong_map_with_the_loosest_scoring():
    """The line can fail: the debevec map of Frobisher 30 % too bright on its left half misses
    the line on every frame even at a 2 px tolerance on 5x5 means."""
    from derender.evaluation.roundtrip import round_trip as rt_of
    from derender.io.files import expand_image_paths

    folder = require_shared("colour-hdri-frobisher")
    paths = expand_image_paths([folder])
    good, res, names = bracket_round_trip(paths, "debevec", motion=MotionOptions(reference=1, align="none"),
                                          tolerance=2, scale=5)
    assert np.all(good.p95 <= 4.0) and np.all(good.median <= 1.5)
    wrong = np.array(res.radiance, dtype=np.float64)
    wrong[:, : wrong.shape[1] // 2] *= 1.3
    bad = rt_of(res.plan, _frames_by_time(paths), wrong, tolerance=2, scale=5, black=good.black)
    assert np.all(bad.p95 > 4.0), bad.p95
    assert bad.fail[:, : wrong.shape[1] // 2].mean() > 5 * bad.fail[:, wrong.shape[1] // 2:].mean()


@pytest.mark.shared_data
def test_frobisher_round_trip_replays_a_flow_registration():
    """``--align flow`` (dense residual flow after the shifts): the round trip warps the frames
    again as the merge did (:func:`replay_alignment`, checked against the merge's record) and the
    stabilised merge still meets the line (measured medians 0.07-0.51, p95 0.9-2.5)."""
    folder = require_shared("colour-hdri-frobisher")
    rt, res, names = bracket_round_trip([folder], "stabilized", motion=MotionOptions(reference=1, align="flow"))
    assert res.info["alignment"]["align"] == "flow" and "flow" in res.info["alignment"]
    for row in rt.rows(names):
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
@pytest.mark.parametrize("method", ["stabilized", "stabilized-joint"])
def test_memorial_meets_the_line_on_every_frame_that_carries_the_merge(method):
    """Memorial (one film, 16 frames), the stabilised merges, 5x5 means, the film base a black clip
    (found: codes 15/20/19): every frame carrying at least 1 % of the merge's weight meets the
    per-frame line (measured: the 8 longest, 2.5-19 % of the weight each, medians 0.53-0.72, p95
    2.1-3.0). The 7 short frames (<= 0.7 % each) are only their windows above the base and miss
    (p95 4.4-24: the map there is pulled down by near-clipped and film-base codes the stabilised
    merge weights; docs/results.md)."""
    from derender.evaluation.consistency import bracket_inputs

    paths, kw = bracket_inputs("memorial")
    rt, res, names = bracket_round_trip(paths, method, scale=5, **kw)
    assert rt.black == [15, 20, 19]
    heavy = rt.share >= 0.01
    assert heavy.sum() >= 8 and rt.share[heavy].sum() >= 0.95
    assert np.all(rt.median[heavy] <= 1.5) and np.all(rt.p95[heavy] <= 4.0), (rt.median, rt.p95)
    assert rt.weighted_median <= 1.0 and rt.weighted_p95 <= 3.0          # measured 0.63 / 2.59


@pytest.mark.shared_data
def test_memorial_renders_back_its_frames_where_the_weight_is():
    """The pooled line, pixel by pixel, on a film bracket: Memorial merged by the stabilised
    method renders back its frames, each residual counted by its merge weight, the film base a
    black clip: measured median 1.31, p95 6.69 codes (1.63 / 7.0 with the base scored; the
    per-frame 1.5 / 4 is met on no frame pixel by pixel). Before the round trip took the merge's
    own scale it read 27-44 codes on the long frames."""
    from derender.evaluation.consistency import bracket_inputs

    paths, kw = bracket_inputs("memorial")          # reference 8, no alignment, the times file (1/t)
    rt, res, names = bracket_round_trip(paths, "stabilized", **kw)
    assert len(names) == 16 and np.all(rt.share > 0.001) and rt.share.sum() == pytest.approx(1.0)
    assert rt.weighted_median <= 1.5 and rt.weighted_p95 <= 8.0
