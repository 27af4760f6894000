"""Tests for derender.groundtruth (paper 1, Sec. 4.2, eq. 11, Algorithm 2)."""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.colorimetry import (
    D65_XYZ,
    LINEAR_SRGB_TO_XYZ,
    XYZ_TO_LINEAR_SRGB,
    camera_to_linear_srgb_matrix,
    camera_to_xyz_matrix,
)
from derender.core.errors import InputError
from derender.core.types import HDRResult, RawFrame
from derender.raw.groundtruth import raw_ground_truth, raw_to_camera_rgb
from derender.raw.mosaic import demosaic_bayer, merge_raw_mosaics, wb_from_patch, white_balance_mosaic

# A plausible XYZ -> camera matrix (DNG ColorMatrix semantics, un-normalised): Canon-like.
XYZ_TO_CAMERA = np.array([[0.6461, -0.1164, -0.0857],
                          [-0.3825, 1.1597, 0.2534],
                          [-0.0416, 0.1540, 0.6039]])
BLACK = np.array([[2048.0, 2050.0], [2049.0, 2047.0]])
WHITE = 15000.0


def _frame(values, times=None, black=0.0, white=10000.0, pattern="RGGB"):
    m = np.asarray(values, dtype=np.uint16)
    return RawFrame(mosaic=m, cfa_pattern=pattern, black_level=np.full((2, 2), black), white_level=white,
                    as_shot_wb=np.ones(3), xyz_to_camera=XYZ_TO_CAMERA, exposure_time=times)


def _psnr(x, ref):
    return 10 * np.log10(ref.max() ** 2 / np.mean((x - ref) ** 2))


# --------------------------------------------------------------------------- eq. 11 exactness
def test_merge_eq11_values_and_thresholds():
    black, span = 100.0, 10000.0
    # counts above black per photosite for two exposures (t = 0.5 s and 2 s)
    short = np.array([[8, 7, 9200, 9201], [4000, 0, 2000, 9999]])
    long_ = np.array([[32, 28, 9999, 9999], [9999, 0, 8000, 9999]])
    f1 = _frame(short + black, 0.5, black, black + span)
    f2 = _frame(long_ + black, 2.0, black, black + span)
    hdr, mask = merge_raw_mosaics([f2, f1])  # order does not matter
    v1, v2 = short / span, long_ / span
    exp = np.zeros((2, 4))
    exp[0, 0] = (v1[0, 0] / 0.5 + v2[0, 0] / 2.0) / 2  # 8 counts == low: inclusive
    exp[0, 1] = v2[0, 1] / 2.0                          # 7 counts < low: only the long frame
    exp[0, 2] = v1[0, 2] / 0.5                          # 9200 == high: inclusive
    exp[0, 3] = min(v1[0, 3], 1.0) / 0.5                # over in both -> shortest (bright)
    exp[1, 0] = v1[1, 0] / 0.5                          # long saturated
    exp[1, 1] = v2[1, 1] / 2.0                          # under in both -> longest (dark)
    exp[1, 2] = (v1[1, 2] / 0.5 + v2[1, 2] / 2.0) / 2
    exp[1, 3] = min(v1[1, 3], 1.0) / 0.5
    np.testing.assert_allclose(hdr, exp, rtol=1e-6, atol=1e-9)
    assert hdr.dtype == np.float32
    np.testing.assert_array_equal(mask, [[0, 0, 0, 1], [0, 2, 0, 1]])


def test_merge_custom_thresholds_and_per_cfa_black():
    m = np.array([[1100, 1200], [1300, 1400]])
    f = RawFrame(mosaic=m.astype(np.uint16), cfa_pattern="RGGB", black_level=np.array([[100, 200], [300, 400]]),
                 white_level=2100, as_shot_wb=np.ones(3), xyz_to_camera=None, exposure_time=None)
    hdr, mask = merge_raw_mosaics(f, low=0.0, high=1.0)
    np.testing.assert_allclose(hdr, [[1000 / 2000, 1000 / 1900], [1000 / 1800, 1000 / 1700]], rtol=1e-6)
    np.testing.assert_array_equal(mask, 0)


def test_merge_single_frame_without_time_uses_dt_1():
    f = _frame([[0, 500], [9500, 12000]], None, 0.0, 10000.0)
    hdr, mask = merge_raw_mosaics([f])
    np.testing.assert_allclose(hdr, [[0.0, 0.05], [0.95, 1.0]], rtol=1e-6)  # bright clipped at 1
    np.testing.assert_array_equal(mask, [[2, 0], [1, 1]])
    f.exposure_time = 0.25
    hdr4, _ = merge_raw_mosaics(f)
    np.testing.assert_allclose(hdr4, hdr * 4, rtol=1e-6)


def test_merge_never_nan_and_rejects_bad_input():
    rng = np.random.default_rng(0)
    frames = [_frame(rng.integers(0, 65535, (6, 8)), t, 500.0, 4000.0) for t in (0.1, 0.2, 0.4)]
    hdr, mask = merge_raw_mosaics(frames)
    assert np.all(np.isfinite(hdr)) and set(np.unique(mask)) <= {0, 1, 2}
    with pytest.raises(InputError):
        merge_raw_mosaics([_frame(np.zeros((4, 4)), None), _frame(np.zeros((4, 4)), 0.1)])
    with pytest.raises(InputError):
        merge_raw_mosaics([_frame(np.zeros((4, 4)), 0.1), _frame(np.zeros((4, 4)), 0.1)])
    with pytest.raises(InputError):
        merge_raw_mosaics([_frame(np.zeros((4, 4)), 0.1), _frame(np.zeros((4, 6)), 0.2)])
    with pytest.raises(InputError):
        merge_raw_mosaics([])
    with pytest.raises(InputError):
        merge_raw_mosaics(_frame(np.zeros((4, 4))), low=0.5, high=0.1)


# --------------------------------------------------------------------------- colour matrices
def test_camera_to_xyz_normalisation():
    c2x = camera_to_xyz_matrix(XYZ_TO_CAMERA)
    np.testing.assert_allclose(c2x @ np.ones(3), D65_XYZ, rtol=1e-12)  # balanced white -> D65, Y = 1
    assert abs((c2x @ np.ones(3))[1] - 1.0) < 1e-6
    # XYZ -> camera direction up to the per-row (white-balance) scaling
    cam = XYZ_TO_CAMERA @ np.array([0.3, 0.5, 0.2])
    norm = cam / (XYZ_TO_CAMERA @ D65_XYZ)
    np.testing.assert_allclose(c2x @ norm, [0.3, 0.5, 0.2], rtol=1e-12)
    c2s = camera_to_linear_srgb_matrix(XYZ_TO_CAMERA)
    np.testing.assert_allclose(c2s.sum(axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(c2s, XYZ_TO_LINEAR_SRGB @ c2x)
    with pytest.raises(InputError):
        camera_to_xyz_matrix(np.zeros((3, 3)))
    with pytest.raises(InputError):
        camera_to_xyz_matrix(np.eye(2))


def test_camera_to_linear_srgb_matches_libraw(colorchecker_dng):
    rawpy = pytest.importorskip("rawpy")
    from derender.io.raw import read_raw

    frame = read_raw(colorchecker_dng)
    with rawpy.imread(str(colorchecker_dng)) as raw:
        rgb_cam = np.asarray(raw.color_matrix, dtype=np.float64)[:3, :3]
    np.testing.assert_allclose(camera_to_linear_srgb_matrix(frame.xyz_to_camera), rgb_cam, atol=1e-6)


# --------------------------------------------------------------------------- synthetic end-to-end
def _smooth_scene(h=96, w=128):
    """Smooth linear-sRGB scene (positive, in gamut), ~500:1 range, with a neutral grey block."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 0.5 + 0.35 * np.sin(2 * np.pi * x / 90.0) * np.cos(2 * np.pi * y / 110.0)
    g = 0.5 + 0.35 * np.cos(2 * np.pi * (x + y) / 130.0)
    b = 0.5 + 0.35 * np.sin(2 * np.pi * (x - 0.5 * y) / 100.0 + 1.0)
    level = np.exp(np.log(500.0) * (x / (w - 1)) - np.log(500.0))  # 1/500 .. 1
    scene = np.stack([r, g, b], axis=-1) * level[..., None] * 32.0
    scene[8:24, 96:120] = 0.5 * 32.0 * level[8:24, 96:120, None].mean()  # neutral block (x=96.., y=8..)
    return scene


def _simulate_frames(scene_srgb, times, pattern="RGGB", seed=0):
    """Camera under D65: raw = ColorMatrix @ XYZ; AsShotNeutral = ColorMatrix @ D65 (DNG semantics)."""
    rng = np.random.default_rng(seed)
    xyz = scene_srgb @ LINEAR_SRGB_TO_XYZ.T
    cam = xyz @ XYZ_TO_CAMERA.T
    neutral = XYZ_TO_CAMERA @ D65_XYZ
    wb = neutral[1] / neutral
    lut = {"R": 0, "G": 1, "B": 2}
    h, w, _ = cam.shape
    idx = np.tile(np.array([[lut[pattern[0]], lut[pattern[1]]], [lut[pattern[2]], lut[pattern[3]]]]),
                  (h // 2, w // 2))
    mos = np.take_along_axis(cam, idx[..., None], axis=2)[..., 0]
    blm = np.tile(BLACK, (h // 2, w // 2))
    frames = []
    for t in times:
        counts = blm + mos * t * (WHITE - blm) + rng.normal(0, 0.3, mos.shape)
        counts = np.clip(np.rint(counts), 0, WHITE).astype(np.uint16)
        frames.append(RawFrame(mosaic=counts, cfa_pattern=pattern, black_level=BLACK.copy(), white_level=WHITE,
                               as_shot_wb=wb, xyz_to_camera=XYZ_TO_CAMERA, exposure_time=float(t)))
    # pipeline output = k * true linear sRGB, k = G of the neutral (the WB keeps G), per unit exposure
    return frames[::-1], neutral[1]


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG"])
def test_raw_ground_truth_recovers_synthetic_scene(pattern):
    scene = _smooth_scene()
    times = [1 / 64, 1 / 16, 1 / 4]
    frames, k = _simulate_frames(scene, times, pattern)
    res = raw_ground_truth(frames)  # unsorted input is sorted by time
    assert isinstance(res, HDRResult) and res.radiance.dtype == np.float32
    assert res.radiance.shape == scene.shape and np.all(np.isfinite(res.radiance))
    assert res.info["exposure_times"] == sorted(times)
    truth = k * scene
    inner = (slice(2, -2), slice(2, -2))
    assert _psnr(res.radiance[inner], truth[inner]) > 40.0  # includes Malvar errors at the grey block's edges
    smooth = np.zeros(scene.shape[:2], bool)
    smooth[2:-2, 2:-2] = True
    smooth[4:28, 92:124] = False  # leave out the sharp-edged grey block
    assert _psnr(res.radiance[smooth], truth[smooth]) > 60.0
    # every pixel is well exposed in some frame: empty mask; units exact (no scale fitting)
    assert np.all(res.mask == 0)
    # the shortest frame alone: same units, noisier shadows
    single = raw_ground_truth([frames[-1]])
    assert single.info["exposure_times"] == [times[0]]
    assert 40.0 < _psnr(single.radiance[smooth], truth[smooth]) < _psnr(res.radiance[smooth], truth[smooth])


def test_wb_patch_matches_as_shot_and_explicit_wb():
    scene = _smooth_scene()
    frames, k = _simulate_frames(scene, [1 / 32, 1 / 8])
    as_shot = raw_ground_truth(frames).radiance
    patch = raw_ground_truth(frames, wb_patch=(96, 8, 24, 16))
    np.testing.assert_allclose(patch.info["wb_multipliers"], frames[0].as_shot_wb, rtol=5e-3)
    assert _psnr(patch.radiance, as_shot) > 45.0
    explicit = raw_ground_truth(frames, wb=tuple(frames[0].as_shot_wb)).radiance
    np.testing.assert_array_equal(explicit, as_shot)
    # no white balance: a neutral grey comes out tinted (camera white is not neutral)
    grey = raw_ground_truth(frames, wb=None).radiance[10:22, 100:116].reshape(-1, 3).mean(0)
    assert np.ptp(grey / grey.mean()) > 0.2
    with pytest.raises(InputError):
        raw_ground_truth(frames, wb="auto")
    with pytest.raises(InputError):
        raw_ground_truth(frames, wb=(1.0, 0.0, 1.0))
    with pytest.raises(InputError):
        raw_ground_truth(frames, wb_patch=(120, 90, 16, 16))
    with pytest.raises(InputError):
        raw_ground_truth(frames, demosaic="nope")


def test_wb_from_patch_exact():
    mos = np.tile(np.array([[2.0, 1.0], [1.0, 4.0]], np.float32), (4, 4))
    np.testing.assert_allclose(wb_from_patch(mos, "RGGB", (2, 2, 4, 4)), [0.5, 1.0, 0.25])
    np.testing.assert_allclose(wb_from_patch(mos, "BGGR", (0, 0, 2, 2)), [0.25, 1.0, 0.5])


def test_saturated_and_dark_regions_are_masked_and_finite():
    scene = _smooth_scene()
    scene[40:60, 10:30] = 1e4   # over-exposed in every frame
    scene[40:60, 60:80] = 0.0   # black: under-exposed in every frame
    frames, _ = _simulate_frames(scene, [1 / 64, 1 / 16])
    res = raw_ground_truth(frames, clip_negative=False)
    assert np.all(np.isfinite(res.radiance))
    assert np.all(res.mask[44:56, 14:26] == HDRResult.MASK_BRIGHT)
    assert np.all(res.mask[44:56, 64:76] == HDRResult.MASK_DARK)
    assert np.mean(res.mask[:, 90:] == 0) > 0.95
    clipped = raw_ground_truth(frames)
    assert clipped.radiance.min() >= 0.0
    assert res.radiance.min() < 0.0  # noise below black survives without clipping


def test_raw_to_camera_rgb_is_demosaiced_merge():
    """Camera RGB on the one path of every RAW output: the merged mosaic balanced with the
    as-shot multipliers, demosaiced, the balance divided out again."""
    scene = _smooth_scene()
    frames, _ = _simulate_frames(scene, [1 / 64, 1 / 16])
    res = raw_to_camera_rgb(frames, clip_negative=False)
    hdr, _ = merge_raw_mosaics(frames)
    wb = np.asarray(frames[1].as_shot_wb, np.float64)
    assert np.ptp(wb) > 0.1 and res.info["wb_multipliers"] == wb.tolist()
    ref = demosaic_bayer(white_balance_mosaic(hdr, "RGGB", wb), "RGGB") / wb.astype(np.float32)
    np.testing.assert_allclose(res.radiance, ref, rtol=1e-6, atol=0)
    cam = (scene @ LINEAR_SRGB_TO_XYZ.T) @ XYZ_TO_CAMERA.T  # raw camera RGB per unit exposure
    inner = (slice(2, -2), slice(2, -2))
    assert _psnr(res.radiance[inner], cam[inner]) > 40.0
    assert res.info["colour_space"] == "camera_rgb"


def test_missing_colour_matrix_is_an_input_error():
    f = _frame(np.full((4, 4), 5000), None)
    f.xyz_to_camera = None
    with pytest.raises(InputError):
        raw_ground_truth(f)
    out = raw_ground_truth(f, xyz_to_camera=XYZ_TO_CAMERA)
    assert out.radiance.shape == (4, 4, 3)


# --------------------------------------------------------------------------- real DNG vs published chart
# Patch centres (x, y) in mosaic pixels of colorchart.dng (1734x1156, Canon 550D): the standard
# 24-patch side of the Passport is the lower half of the frame, upright (dark skin top-left).
# Annotated by hand on a preview PNG of our ground truth (boxes overlaid and checked by eye).
CHART_XS = (714, 822, 930, 1036, 1144, 1252)
CHART_YS = (624, 722, 822, 926)
PATCH_CENTRES = tuple((x, y) for y in CHART_YS for x in CHART_XS)  # row-major, ColorChecker order
PATCH_HALF = 16  # 32x32 sampling box (patches are ~85 px wide; the image is out of focus)
NEUTRALS = slice(18, 24)  # row 4: white .. black


def _patch_means(img):
    h = PATCH_HALF
    return np.array([img[y - h:y + h, x - h:x + h].reshape(-1, 3).mean(0) for x, y in PATCH_CENTRES],
                    dtype=np.float64)


def _chart_delta_e(linear_srgb_patches, colour):
    """Mean CIEDE2000 after one least-squares gain per channel on the neutral patches (D65 Lab)."""
    cc = colour.CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"]
    xyz_d50 = colour.xyY_to_XYZ(np.array(list(cc.data.values())))
    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    xyz_ref = colour.adaptation.chromatic_adaptation_VonKries(
        xyz_d50, colour.xy_to_XYZ(cc.illuminant), colour.xy_to_XYZ(d65), transform="Bradford")
    ref = xyz_ref @ XYZ_TO_LINEAR_SRGB.T
    m = linear_srgb_patches
    gains = (m[NEUTRALS] * ref[NEUTRALS]).sum(0) / (m[NEUTRALS] ** 2).sum(0)
    lab = colour.XYZ_to_Lab((m * gains) @ LINEAR_SRGB_TO_XYZ.T, d65)
    lab_ref = colour.XYZ_to_Lab(xyz_ref, d65)
    return colour.delta_E(lab, lab_ref, method="CIE 2000")


def test_colorchecker_dng_matches_chart_as_well_as_libraw(colorchecker_dng):
    rawpy = pytest.importorskip("rawpy")
    colour = pytest.importorskip("colour")
    from derender.io.raw import read_raw

    frame = read_raw(colorchecker_dng)
    ours = raw_ground_truth(frame)
    assert ours.radiance.shape == (1156, 1734, 3) and np.all(np.isfinite(ours.radiance))
    p_ours = _patch_means(ours.radiance)
    # annotation sanity: neutral row decreases monotonically in every channel
    assert np.all(np.diff(p_ours[NEUTRALS], axis=0) < 0)

    with rawpy.imread(str(colorchecker_dng)) as raw:
        libraw = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
                                 output_color=rawpy.ColorSpace.sRGB)
    assert libraw.shape[:2] == ours.radiance.shape[:2]
    p_libraw = _patch_means(libraw.astype(np.float64) / 65535.0)

    de_ours = _chart_delta_e(p_ours, colour)
    de_libraw = _chart_delta_e(p_libraw, colour)
    print(f"ColorChecker mean CIEDE2000: derender {de_ours.mean():.3f}, LibRaw {de_libraw.mean():.3f}")
    # measured: derender 3.83, LibRaw 3.82 (flare and noise of this dim, defocused shot dominate);
    # dropping the colour matrix or the white balance gives ~8.2 / ~8.1, so the margin of 1.0 has teeth
    assert de_ours.mean() <= de_libraw.mean() + 1.0
    assert de_ours.mean() < 6.0 and de_libraw.mean() < 6.0  # the annotation really hits the patches
