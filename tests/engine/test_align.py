"""Registration (derender.engine.motion.align, derender.engine.motion.ward2003): Ward's MTB and homography alignment on simulated brackets."""

from __future__ import annotations

import numpy as np
import pytest

from derender.camera import simulate_bracket
from derender.core.errors import InputError
from derender.engine.motion.align import align_images, shift_image
from derender.engine.motion.ward2003 import median_threshold_bitmaps, mtb_shift, to_grey8


@pytest.fixture(scope="module")
def wide_bracket():
    """A 9-exposure auto-pipeline bracket rendered 32 px larger than the frames cut from it."""
    b = simulate_bracket(kind="outdoor", size=(224, 160), pipeline="auto", style="simple", seed=0)
    return b.jpeg_codes.astype(np.float32) / 255.0


def _cut(images, offsets, h=128, w=192, y0=16, x0=16):
    """Frame j = window of the scene displaced by offsets[j] (dy, dx)."""
    return np.stack([images[j, y0 + dy:y0 + dy + h, x0 + dx:x0 + dx + w] for j, (dy, dx) in enumerate(offsets)])


def test_mtb_recovers_known_integer_shifts_exactly(wide_bracket):
    rng = np.random.default_rng(1)
    offsets = rng.integers(-6, 7, size=(9, 2))
    offsets[4] = 0
    frames = _cut(wide_bracket, offsets)
    al = align_images(frames, "translation", reference=4)
    # reference content at p sits in frame j at p - offset_j
    np.testing.assert_array_equal(al.shifts, -offsets)
    np.testing.assert_allclose(al.transforms[:, 0, 2], -offsets[:, 1])
    np.testing.assert_allclose(al.transforms[:, 1, 2], -offsets[:, 0])
    # aligned frames equal the unshifted cut wherever valid
    ref_frames = _cut(wide_bracket, np.zeros_like(offsets))
    for j in range(9):
        v = al.valid[j]
        assert v.mean() > 0.8
        np.testing.assert_array_equal(al.images[j][v], ref_frames[j][v])


def test_mtb_keeps_a_tripod_bracket_in_place(wide_bracket):
    al = align_images(wide_bracket, "translation", reference=4)
    np.testing.assert_array_equal(al.shifts, 0)
    assert al.valid.all()


def test_shift_borders_are_finite_and_masked():
    img = np.arange(5 * 7 * 3, dtype=np.float32).reshape(5, 7, 3)
    out, valid = shift_image(img, 2, -3)
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(out[1, 4], img[3, 1])             # out[y, x] = img[y + 2, x - 3]
    assert valid.sum() == (5 - 2) * (7 - 3)
    assert not valid[4].any() and not valid[:, :3].any()
    np.testing.assert_array_equal(out[4, 0], img[4, 0])             # replicated border


def test_mtb_pair_same_and_different_exposure(wide_bracket):
    """Ward's median bitmaps recover a (3, -5) displacement between two cuts of one
    exposure and between neighbouring exposures (different gain, gamma, white balance)."""
    a = to_grey8(wide_bracket[4, 16:144, 16:208])
    for k in (4, 3):
        b = to_grey8(wide_bracket[k, 19:147, 11:203])                # reference content at p is at p + (-3, 5)
        assert mtb_shift(a, b) == (-3, 5)


def test_median_threshold_bitmaps_exclusion():
    g = np.array([[0, 10, 12, 14, 200]], dtype=np.uint8)
    tb, eb = median_threshold_bitmaps(g, exclusion=4)               # median 12
    np.testing.assert_array_equal(tb, [[False, False, False, True, True]])
    np.testing.assert_array_equal(eb, [[True, False, False, False, True]])


def test_homography_alignment_on_translated_frames(wide_bracket):
    offsets = np.array([[0, 0], [0, 0], [2, -3], [-1, 4], [0, 0], [3, 2], [-2, -2], [0, 0], [0, 0]])
    frames = _cut(wide_bracket, offsets)
    al = align_images(frames, "homography", reference=4, seed=3)
    assert np.isfinite(al.images).all()
    centre = np.array([96.0, 64.0, 1.0])
    for j in (2, 3, 5, 6):
        p = al.transforms[j] @ centre
        disp = p[:2] / p[2] - centre[:2]
        np.testing.assert_allclose(disp, [-offsets[j, 1], -offsets[j, 0]], atol=0.75)


def test_align_rejects_bad_arguments(wide_bracket):
    with pytest.raises(InputError):
        align_images(wide_bracket, "optical-flow")
    with pytest.raises(InputError):
        align_images(wide_bracket, "translation", reference=12)


def test_mtb_band_scoring_on_large_frames_recovers_shifts(wide_bracket, monkeypatch):
    """Levels above MTB_PIXELS are scored on bands of rows (lazy bitmaps); forced here on
    small frames, the shifts are still recovered exactly."""
    import derender.engine.motion.ward2003 as A

    monkeypatch.setattr(A, "MTB_PIXELS", 4096)
    rng = np.random.default_rng(2)
    offsets = rng.integers(-6, 7, size=(9, 2))
    offsets[4] = 0
    al = align_images(_cut(wide_bracket, offsets), "translation", reference=4)
    np.testing.assert_array_equal(al.shifts, -offsets)
    tripod = align_images(wide_bracket, "translation", reference=4)
    np.testing.assert_array_equal(tripod.shifts, 0)


@pytest.fixture(scope="module")
def parallax_bracket():
    """A bracket rendered larger than its frames, for two depth layers moving apart."""
    b = simulate_bracket(kind="outdoor", size=(448, 352), pipeline="auto", style="simple", seed=4)
    return b.jpeg_codes.astype(np.float32) / 255.0


def _parallax_cut(images, far, h=288, w=384, split=112, y0=32, x0=32):
    """Frame j: rows above ``split`` (the far layer: a skyline through a window) cut at offset
    ``far[j]`` (dy, dx), the rows below (the room, most of the frame) at offset 0: a hand that
    moved between the exposures shifts the two depths by different amounts (parallax)."""
    out = []
    for j, (dy, dx) in enumerate(far):
        f = images[j, y0:y0 + h, x0:x0 + w].copy()
        f[:split] = images[j, y0 + dy:y0 + dy + split, x0 + dx:x0 + dx + w]
        out.append(f)
    return np.stack(out)


def test_flow_alignment_registers_both_depths_of_a_parallax_bracket(parallax_bracket):
    """Exact truth: every frame's scene on the reference's grid is its cut at offset 0. The
    translation registers one layer or a compromise (the room, or 1-2 px off it in the darkest
    frames); ``"flow"`` recovers that residual (flow = -offset there, within 0.25 px on the layer's
    unclipped interior) and the aligned far layer matches the truth to a fraction of the translation's
    error, while the room is within one code of the truth."""
    from derender.engine.motion.align import residual_flow

    far = np.array([[3, -2], [2, 3], [0, 0], [-3, 2], [1, -3]])
    frames = _parallax_cut(parallax_bracket[2:7], far)
    truth = _parallax_cut(parallax_bracket[2:7], np.zeros_like(far))
    trans = align_images(frames, "translation", reference=2)
    flow = align_images(frames, "flow", reference=2)
    interior = (slice(12, 112 - 16), slice(16, 192))                # the far layer, away from its edges and
                                                                    # from the lamp's glare (clipped in 4, 5)
    room = (slice(112 + 16, 288 - 16), slice(16, 384 - 16))
    for j in (0, 1, 3, 4):
        assert flow.info["flow"][j]["warped"]
        f, _ = residual_flow(to_grey8(truth[j + 1 if j < 2 else j - 1]), to_grey8(frames[j]))
        np.testing.assert_allclose(np.median(f[interior].reshape(-1, 2), axis=0), [-far[j, 1], -far[j, 0]], atol=0.5)
        err_t = np.abs(trans.images[j][interior] - truth[j][interior]).mean()
        err_f = np.abs(flow.images[j][interior] - truth[j][interior]).mean()
        room_f = np.abs(flow.images[j][room] - truth[j][room]).mean()
        assert err_f < 0.25 * err_t, (j, err_t, err_f)
        assert room_f < 1.5 / 255
        assert np.isfinite(flow.images[j]).all()


def test_a_kept_residual_flow_is_the_computed_one(parallax_bracket):
    """The process keeps residual flows by the frames' bytes (:data:`FLOW_CACHE_BYTES`): asked
    again, :func:`residual_flow` gives exactly what :func:`flow_from_greys` computes, as a new
    array each time (writing into one does not change the next), and a different pair is not
    confused with it."""
    from derender.engine.motion import align as al

    far = np.array([[3, -2], [2, 3], [0, 0], [-3, 2], [1, -3]])
    frames = _parallax_cut(parallax_bracket[2:7], far)
    a, b = to_grey8(frames[2]), to_grey8(frames[1])
    exact, details = al.flow_from_greys(a, b)
    assert exact is not None
    first, d1 = al.residual_flow(a, b)
    first[:] = 99.0
    again, d2 = al.residual_flow(a, b)
    np.testing.assert_array_equal(again, exact)
    assert d1 == d2 == details
    other, _ = al.residual_flow(a, to_grey8(frames[3]))
    other_exact, _ = al.flow_from_greys(a, to_grey8(frames[3]))
    np.testing.assert_array_equal(other, other_exact)


def test_flow_alignment_keeps_a_tripod_bracket_exact(wide_bracket):
    """Nothing moved: no frame's residual flow reaches FLOW_MIN_PX, the frames stay as they were."""
    al = align_images(wide_bracket, "flow", reference=4)
    np.testing.assert_array_equal(al.images, wide_bracket)
    assert al.valid.all()
    assert not any(d["warped"] for d in al.info["flow"].values())
