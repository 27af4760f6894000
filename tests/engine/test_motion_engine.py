"""The engine's reference frame, alignment and ghost removal (issue 23), against exact truth and oracles.

Oracles: the simulator's moving brackets and their still twins (same truth, nothing moving);
for the kernels' ``valid`` planes, the same plan merged without the excluded frame (a pixel
where frame j does not take part must equal the merge of the other frames); for the ghost
statistic, a NumPy transcription of its interval rule.
"""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.errors import InputError, StackError
from derender.core.types import Stack
from derender.engine.motion.run import MotionOptions
from derender.engine.options import OutputOptions


def _bracket(family="camera", setting="tripod", size=(128, 96), exposures=5, seed=0):
    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec

    spec = MotionSpec(objects=3, shake=3)
    spec = {"tripod": spec.tripod(), "handheld": spec, "still": spec.still()}[setting]
    return simulate_bracket("nikon-d5100", kind="outdoor", size=size, exposures=exposures, seed=seed,
                            family=family, motion=spec)


def _stack(b):
    return Stack(images=b.jpeg_codes.astype(np.float32) / np.float32(255), times=b.times)


def test_valid_planes_exclude_a_frame_exactly_in_every_kernel():
    """Where ``valid`` leaves frame j out, each kernel's result is the merge of the other frames
    with the same plan (table, matrix and Gaussian plans)."""
    from derender.engine.frames import ArrayFrames, merge_held
    from derender.engine.motion.run import _access
    from derender.hdr.classic import DebevecMethod, DebevecOptions
    from derender.hdr.registry import method_options
    from derender.hdr.stabilize.method import StabilizedMethod

    b = _bracket(size=(96, 64))
    codes, t = b.jpeg_codes, b.times
    n, h, w = codes.shape[:3]
    src = ArrayFrames(codes, t)
    frames = np.ascontiguousarray(codes)
    j = 1
    valid = np.ones((n, h, w), np.uint8)
    valid[j, :, : w // 2] = 0                          # frame j out of the left half
    keep = [k for k in range(n) if k != j]
    methods = [DebevecMethod(DebevecOptions()), StabilizedMethod("stabilized", method_options("stabilized"))]
    for method in methods:
        plan = method.plan(_access(method, src, frames, None, n // 2, 1))
        full = merge_held(plan, frames, t, threads=1, valid=valid)
        sub_plan = _subset_plan(plan, keep)
        sub = merge_held(sub_plan, frames[keep], t[keep], threads=1)
        np.testing.assert_allclose(full.radiance[:, : w // 2], sub.radiance[:, : w // 2], rtol=2e-6, atol=1e-7)
        np.testing.assert_array_equal(full.mask[:, : w // 2], sub.mask[:, : w // 2])
        ref = merge_held(plan, frames, t, threads=1)
        np.testing.assert_array_equal(full.radiance[:, w // 2:], ref.radiance[:, w // 2:])


def _subset_plan(plan, keep):
    import dataclasses

    from derender.engine.plans import MatrixPlan, TablePlan

    if isinstance(plan, TablePlan):
        wts = np.asarray(plan.weights)
        return dataclasses.replace(plan, values=plan.values[keep], weights=wts[keep] if wts.ndim == 3 else wts,
                                   image_weights=None if plan.image_weights is None else plan.image_weights[keep])
    assert isinstance(plan, MatrixPlan)
    return dataclasses.replace(plan, values=plan.values[keep], matrices=plan.matrices[keep], shifts=plan.shifts[keep],
                               inverse_variance=None if plan.inverse_variance is None else plan.inverse_variance[keep],
                               inverse_variance_k=None if plan.inverse_variance_k is None
                               else plan.inverse_variance_k[keep])


@pytest.fixture
def tiny_model():
    """A small GP de-rendering model of the simulated camera (paper 2.s merge needs one)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "hdr"))
    from test_probabilistic_properties import _model

    return _model("gp")


def test_gaussian_kernel_valid_planes_exclude_a_frame_exactly(tiny_model):
    from derender.engine.frames import ArrayFrames
    from derender.engine.gaussian import merge_gaussian_frames
    from derender.engine.motion.run import _access
    from derender.hdr.probabilistic import ProbabilisticMethod
    from derender.hdr.registry import method_options

    b = _bracket(size=(64, 48))
    codes, t = np.ascontiguousarray(b.jpeg_codes), b.times
    n, h, w = codes.shape[:3]
    method = ProbabilisticMethod(method_options("probabilistic", {"model": tiny_model}))
    plan = method.plan(_access(method, ArrayFrames(codes, t), codes, None, n // 2, 1))
    valid = np.ones((n, h, w), np.uint8)
    valid[0, h // 2:] = 0
    full = merge_gaussian_frames(codes, plan, threads=1, valid=valid)
    import dataclasses

    sub = merge_gaussian_frames(np.ascontiguousarray(codes[1:]), dataclasses.replace(plan, log_scales=plan.log_scales[1:]),
                                threads=1)
    np.testing.assert_allclose(full.radiance[h // 2:], sub.radiance[h // 2:], rtol=1e-6)
    # the variance's spatial-mixing term reads the neighbouring rows: the first row of the lower
    # half sees the upper half's (frame 0 included) radiance
    np.testing.assert_allclose(full.variance[h // 2 + 1:], sub.variance[h // 2 + 1:], rtol=1e-6)


@pytest.mark.parametrize("h,w", [(4000, 6000), (37, 53), (101, 64)])
@pytest.mark.parametrize("step", [1, 2, 3, 7, 9])
def test_upsample_into_equals_opencv_nearest(h, w, step):
    """The in-place full-resolution rejection plane equals OpenCV's nearest-neighbour upscale of
    the grid (what ghost removal wrote before), on the bench's 24 MP size and odd sizes."""
    import cv2

    from derender.engine.motion.ghost_kernels import upsample_into

    rng = np.random.default_rng(step)
    hs, ws = -(-h // step), -(-w // step)
    grid = (rng.random((hs, ws)) < 0.3).astype(np.uint8)
    want = cv2.resize(grid, (ws * step, hs * step), interpolation=cv2.INTER_NEAREST)[:h, :w].astype(bool)
    out = np.ones((h, w), dtype=bool)
    upsample_into(grid, step, out)
    assert np.array_equal(out, want)
    assert np.array_equal(out[::step, ::step], grid.astype(bool))


def test_merge_valid_in_place_reuses_the_rejection_plane():
    from derender.engine.motion.deghost import merge_valid

    rng = np.random.default_rng(0)
    rejected = rng.random((3, 5, 7)) < 0.3
    valid = (rng.random((3, 5, 7)) < 0.8).astype(np.uint8)
    want = merge_valid(valid, rejected)
    got = merge_valid(valid, rejected.copy(), in_place=False)
    assert np.array_equal(got, want) and np.array_equal(want, (valid != 0) & ~rejected)
    plane = rejected.copy()
    got = merge_valid(valid, plane, in_place=True)
    assert np.array_equal(got, want) and np.shares_memory(got, plane)
    plane = rejected.copy()
    got = merge_valid(None, plane, in_place=True)
    assert got.dtype == np.uint8 and np.array_equal(got, ~rejected) and np.shares_memory(got, plane)


@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_deghost_leaves_a_still_bracket_alone(method):
    """Issue 23: on a bracket where nothing moves, ghost removal changes the static-zone median
    error by at most 5 %, and rejects little."""
    import derender as dr
    from derender.evaluation.ghosts import zone_errors

    b = _bracket(setting="still")
    moving = _bracket(setting="tripod")            # its zones label the still twin's pixels too
    plain = dr.merge(_stack(b), method, motion=MotionOptions(reference=2, align="none"))
    clean = dr.merge(_stack(b), method, motion=MotionOptions(reference=2, align="none", deghost=True))
    e0 = zone_errors(plain.radiance, b.truth_linear_srgb, moving.motion_zones)["static"]
    e1 = zone_errors(clean.radiance, b.truth_linear_srgb, moving.motion_zones)["static"]
    assert abs(e1 - e0) <= 0.05 * e0, (e0, e1)
    assert clean.info["deghost"]["rejected"] < 0.05
    assert clean.ghosts.shape == b.jpeg_codes.shape[1:3]


def test_handheld_bracket_aligned_to_the_chosen_reference():
    """A shaken bracket merged with alignment lands on the reference frame's grid: its static
    zone is within 1.25x the tripod twin's; the reference is recorded; uncovered border pixels
    are counted in ``ghosts``; the result is finite and non-negative."""
    import derender as dr
    from derender.evaluation.ghosts import zone_errors

    hand, tri = _bracket(setting="handheld"), _bracket(setting="tripod")
    ref = hand.params["motion"]["reference"]
    r_hand = dr.merge(_stack(hand), "debevec", motion=MotionOptions(reference=ref, align="translation"))
    r_tri = dr.merge(_stack(tri), "debevec", motion=MotionOptions(reference=ref, align="none"))
    e_hand = zone_errors(r_hand.radiance, hand.truth_linear_srgb, hand.motion_zones)["static"]
    e_tri = zone_errors(r_tri.radiance, tri.truth_linear_srgb, tri.motion_zones)["static"]
    unaligned = dr.merge(_stack(hand), "debevec")
    e_raw = zone_errors(unaligned.radiance, hand.truth_linear_srgb, hand.motion_zones)["static"]
    assert e_hand <= 1.25 * e_tri and e_hand < e_raw, (e_hand, e_tri, e_raw)
    assert r_hand.info["reference"] == ref and r_hand.info["reference_input"] == ref
    shifts = np.array(r_hand.info["alignment"]["shifts"])
    assert np.abs(shifts).max() > 0 and r_hand.ghosts.max() >= 1
    assert np.all(np.isfinite(r_hand.radiance)) and r_hand.radiance.min() >= 0


def test_reference_counts_the_images_as_given(tmp_path):
    """``reference`` is an index among the files as given (not by exposure time): the same frame
    chosen from two orders gives the same map, and the EXR header names it."""
    import OpenEXR

    from derender.camera.bracket import write_jpeg
    from derender.hdr.files import merge_files

    b = _bracket(size=(64, 48))
    paths = []
    for k, (codes, t) in enumerate(zip(b.jpeg_codes, b.times)):
        p = tmp_path / f"f{k}.jpg"
        write_jpeg(p, codes, float(t), "derender", "simulated")
        paths.append(p)
    order = [3, 0, 4, 2, 1]
    a = merge_files(paths, method="debevec", motion=MotionOptions(reference=2),
                    output=OutputOptions(output=tmp_path / "a.exr"))
    c = merge_files([paths[k] for k in order], method="debevec", motion=MotionOptions(reference=order.index(2)),
                    output=OutputOptions(output=tmp_path / "c.exr"))
    np.testing.assert_array_equal(a.radiance, c.radiance)
    assert a.info["reference"] == 2 and c.info["reference_input"] == order.index(2)
    header = OpenEXR.InputFile(str(tmp_path / "c.exr")).header()
    ref = header["derender:reference"]
    assert (ref.decode() if isinstance(ref, bytes) else ref) == f"f2.jpg (image {order.index(2) + 1})"


def test_motion_errors_are_clear():
    import derender as dr

    b = _bracket(size=(64, 48))
    st = _stack(b)
    with pytest.raises(InputError, match="out of range"):
        dr.merge(st, "debevec", motion=MotionOptions(reference=7))
    with pytest.raises(InputError, match="align takes none, translation, homography"):
        dr.merge(st, "debevec", motion=MotionOptions(align="rotation"))
    flat = Stack(images=np.full((3, 48, 64, 3), 0.5, np.float32) * np.array([0.2, 1.0, 1.9])[:, None, None, None]
                 .astype(np.float32), times=np.array([0.01, 0.05, 0.1]))
    flat.images[:] = np.round(flat.images * 255) / 255
    with pytest.raises(InputError, match="no features"):
        dr.merge(flat, "debevec", motion=MotionOptions(align="homography"))
    # two different scenes are not one bracket: nothing agrees with the reference
    # the last three exposures of another picture (this one upside down): not one scene
    mixed = Stack(images=np.concatenate([st.images[:2], np.ascontiguousarray(st.images[2:, ::-1, ::-1])]),
                  times=b.times)
    with pytest.raises(StackError, match="do not show one scene"):
        dr.merge(mixed, "debevec", motion=MotionOptions(reference=2, deghost=True))


def test_callers_frames_are_not_modified():
    from derender.engine.frames import ArrayFrames
    from derender.engine.motion.run import MotionOptions, run_motion
    from derender.hdr.classic import DebevecMethod, DebevecOptions

    b = _bracket(setting="handheld", size=(64, 48))
    codes = np.ascontiguousarray(b.jpeg_codes)
    before = codes.copy()
    run_motion(DebevecMethod(DebevecOptions()), ArrayFrames(codes, b.times), MotionOptions(align="translation", deghost=True))
    np.testing.assert_array_equal(codes, before)
