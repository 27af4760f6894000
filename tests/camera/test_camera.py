"""Tests for the camera simulator: physics, real files, determinism, truth."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from derender.camera import (
    RenderSettings,
    bracket_paths,
    bracket_times,
    expose_mosaic,
    gamut_compress,
    isp_render,
    make_scene,
    scene_camera_rgb,
    simulate_bracket,
    write_bracket,
)
from derender.camera.spectral import load_camera
from derender.core.colorimetry import LINEAR_SRGB_TO_XYZ
from derender.core.errors import InputError
from derender.io.exr import read_exr
from derender.io.images import read_stack
from derender.io.raw import read_raw


@pytest.fixture(scope="module")
def camera():
    return load_camera("nikon-d5100")


@pytest.fixture(scope="module")
def small_bracket():
    return simulate_bracket(size=(96, 64), exposures=5, pipeline="auto", seed=1)


def test_doubled_exposure_doubles_raw_signal(camera):
    rng = np.random.default_rng(0)
    signal = np.full((200, 200), 0.1)
    a = expose_mosaic(signal, camera, 1.0, rng).astype(np.float64) - camera.black_level
    b = expose_mosaic(signal, camera, 2.0, rng).astype(np.float64) - camera.black_level
    assert b.mean() / a.mean() == pytest.approx(2.0, rel=0.005)


def test_noise_follows_poisson_gaussian_model(camera):
    rng = np.random.default_rng(1)
    gain = (camera.white_level - camera.black_level) / camera.full_well  # DN per electron
    for level in (0.0, 0.01, 0.2):
        dn = expose_mosaic(np.full((300, 300), level), camera, 1.0, rng).astype(np.float64)
        mean_dn = level * camera.full_well * gain
        expected_var = mean_dn * gain + camera.read_noise**2 + 1 / 12  # shot + read + quantisation
        assert dn.mean() - camera.black_level == pytest.approx(mean_dn, abs=0.05 + 0.002 * mean_dn)
        assert dn.var() == pytest.approx(expected_var, rel=0.03)


def test_clipping_at_white_level(camera):
    dn = expose_mosaic(np.full((10, 10), 5.0), camera, 1.0, np.random.default_rng(0))
    assert np.all(dn == camera.white_level)


def test_bracket_times_peak_percentile_covers_small_highlight():
    """A highlight of 0.05 % of the frame: the 99.9th percentile leaves it above white at
    ``t_min`` (it clips in every exposure); ``peak_percentile=100`` puts it at exactly
    ``peak_level`` of white, and the dark end still reaches 25 % at the longest exposure."""
    rng = np.random.default_rng(0)
    cam = rng.uniform(0.5, 2.0, (100, 200, 3))          # 20000 px
    cam[:2, :5] = 1000.0                                  # 10 px = 0.05 %
    dark = np.percentile(cam.mean(-1), 2.0)
    t_min = 1 / 2000
    times, scale = bracket_times(cam, 5, t_min=t_min)
    assert 1000.0 * scale * t_min > 1.0                  # default: the highlight clips at t_min
    times, scale = bracket_times(cam, 5, t_min=t_min, peak_percentile=100.0)
    assert 1000.0 * scale * t_min == pytest.approx(0.6, rel=1e-12)
    times, scale = bracket_times(cam, 5, t_min=t_min, peak_percentile=100.0, peak_level=0.3)
    assert 1000.0 * scale * t_min == pytest.approx(0.3, rel=1e-12)
    assert dark * scale * times[-1] == pytest.approx(0.25, rel=1e-4)   # times are EXIF rationals
    assert times[0] == pytest.approx(t_min) and np.all(np.diff(np.log(times)) > 0)
    with pytest.raises(InputError):
        bracket_times(cam, 5, peak_percentile=0.0)


def test_simulated_bracket_with_peak_percentile_100_never_clips_raw_at_t_min():
    b = simulate_bracket(size=(64, 48), exposures=3, pipeline="fixed", seed=3, peak_percentile=100.0, noise=False)
    cam = b.camera
    norm = (b.mosaics[0].astype(np.float64) - cam.black_level) / (cam.white_level - cam.black_level)
    assert 0.55 < norm.max() <= 0.6 + 1e-3 and b.params["peak_percentile"] == 100.0


def test_scene_spans_four_decades_and_no_exposure_captures_it(small_bracket):
    illum = small_bracket.scene.illumination.sum(-1)
    assert illum.max() / np.percentile(illum, 1) > 1e4
    cam = small_bracket.camera
    for mosaic in small_bracket.mosaics:
        norm = (mosaic.astype(np.float64) - cam.black_level) / (cam.white_level - cam.black_level)
        clipped = (mosaic >= cam.white_level).mean()
        dark = (norm < 2e-3).mean()
        assert clipped > 0 or dark > 0.001


def test_truth_is_white_balanced_camera_rgb_through_colour_matrix(small_bracket):
    b = small_bracket
    expected = (b.camera_rgb_per_s * b.wb_true) @ b.camera_to_srgb.T
    np.testing.assert_allclose(b.truth_linear_srgb, expected, rtol=1e-6)
    # the normalised matrix maps white-balanced camera white to sRGB white
    np.testing.assert_allclose(b.camera_to_srgb @ np.ones(3), np.ones(3), atol=1e-9)


def test_colour_matrix_is_accurate_for_reflectances(camera):
    """The fitted ColorMatrix reproduces CIE XYZ of the ColorChecker under D65 (colour-science)."""
    import colour

    from derender.camera import fit_xyz_to_camera
    from derender.camera.spectral import cmfs_xyz, illuminant_spd, reflectance_library

    names, lib, groups = reflectance_library()
    refl = lib[groups["colorchecker24"]] * illuminant_spd("D65")
    xyz = refl @ cmfs_xyz()
    cam = refl @ camera.sensitivities
    est = cam @ np.linalg.inv(fit_xyz_to_camera(camera)).T
    lab = colour.XYZ_to_Lab(xyz, colour.XYZ_to_xy(LINEAR_SRGB_TO_XYZ @ np.ones(3)))
    lab_est = colour.XYZ_to_Lab(est, colour.XYZ_to_xy(LINEAR_SRGB_TO_XYZ @ np.ones(3)))
    de = colour.delta_E(lab, lab_est, method="CIE 2000")
    assert np.mean(de) < 3.0


def test_gamut_compression_preserves_hue_and_removes_negatives():
    rng = np.random.default_rng(0)
    x = rng.normal(0.4, 0.5, size=(1000, 3))
    x = x[(x @ [0.2126, 0.7152, 0.0722]) > 0.05]
    y = gamut_compress(x)
    assert y.min() >= -1e-9
    lum_x = x @ [0.2126, 0.7152, 0.0722]
    lum_y = y @ [0.2126, 0.7152, 0.0722]
    np.testing.assert_allclose(lum_x, lum_y, rtol=1e-9)
    cx, cy = x - lum_x[:, None], y - lum_y[:, None]
    cos = np.sum(cx * cy, 1) / (np.linalg.norm(cx, axis=1) * np.linalg.norm(cy, axis=1) + 1e-12)
    assert np.all(cos[np.linalg.norm(cx, axis=1) > 1e-6] > 0.999999)


def test_simple_render_is_paper_model(camera):
    """--render simple is exactly (alpha S M WB x)^(1/gamma), clipped and quantised."""
    from derender.camera import fit_xyz_to_camera, saturation_matrix
    from derender.core.colorimetry import camera_to_linear_srgb_matrix

    m = camera_to_linear_srgb_matrix(fit_xyz_to_camera(camera))
    from derender.camera import mosaic_signal

    rng = np.random.default_rng(2)
    s = RenderSettings(wb=[1.3, 1.0, 1.6], gain=1.1, gamma=2.4, saturation=0.9, style="simple")
    exact = 0
    for _ in range(20):
        flat = rng.uniform(0.0, 0.7, size=3)
        norm = np.broadcast_to(flat, (32, 32, 3))
        span = camera.white_level - camera.black_level
        mosaic = np.rint(camera.black_level + mosaic_signal(norm) * span).astype(np.uint16)
        codes = isp_render(mosaic, camera, m, s)
        x = (np.rint(camera.black_level + flat * span) - camera.black_level) / span
        lin = 1.1 * saturation_matrix(0.9) @ m @ np.minimum(x * [1.3, 1.0, 1.6], 1.0)
        expected = np.rint(np.clip(lin, 0, 1) ** (1 / 2.4) * 255)
        assert np.all(np.abs(codes[16, 16] - expected) <= 1)  # float rounding at .5 boundaries
        exact += int(np.array_equal(codes[16, 16], expected))
    assert exact >= 18


def test_written_files_are_real_and_deterministic(tmp_path):
    kw = dict(size=(64, 48), exposures=3, pipeline="auto", seed=1)
    b = simulate_bracket(**kw)
    write_bracket(b, tmp_path / "a")
    write_bracket(simulate_bracket(**kw), tmp_path / "b")
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) == 8
    for rel in files_a:
        da = hashlib.sha256((tmp_path / "a" / rel).read_bytes()).hexdigest()
        db = hashlib.sha256((tmp_path / "b" / rel).read_bytes()).hexdigest()
        assert da == db, rel
    # DNG read by rawpy/LibRaw: mosaic and tags
    for j, p in enumerate(bracket_paths(tmp_path / "a", "raw")):
        f = read_raw(p)
        np.testing.assert_array_equal(f.mosaic, b.mosaics[j])
        assert f.cfa_pattern == "RGGB"
        assert f.white_level == b.camera.white_level
        np.testing.assert_array_equal(f.black_level, b.camera.black_level)
        np.testing.assert_allclose(f.as_shot_wb, b.wb_true, rtol=1e-4)
        np.testing.assert_allclose(f.xyz_to_camera, b.xyz_to_camera, atol=1e-4)
        assert f.exposure_time == pytest.approx(b.times[j], rel=1e-9)
    # JPEGs: EXIF times read back, pixels close to the rendered codes
    stack = read_stack(bracket_paths(tmp_path / "a", "jpeg"))
    np.testing.assert_allclose(stack.times, b.times, rtol=1e-9)
    diff = stack.codes().astype(np.float64) - b.jpeg_codes
    psnr = 10 * np.log10(255.0**2 / np.mean(diff**2, axis=(1, 2, 3)))
    assert np.all(psnr > 28), psnr  # JPEG q95 4:2:2 of the rendered codes
    np.testing.assert_array_equal(read_exr(tmp_path / "a" / "truth.exr"), b.truth_linear_srgb)


def test_different_seeds_differ():
    a = simulate_bracket(size=(48, 40), exposures=2, seed=1)
    b = simulate_bracket(size=(48, 40), exposures=2, seed=2)
    assert not np.array_equal(a.mosaics, b.mosaics)


def test_auto_pipeline_changes_processing_fixed_does_not():
    fixed = simulate_bracket(size=(48, 40), exposures=4, pipeline="fixed", seed=3)
    auto = simulate_bracket(size=(48, 40), exposures=4, pipeline="auto", seed=3)
    assert len({(tuple(s.wb), s.gain, s.gamma, s.saturation) for s in fixed.settings}) == 1
    gammas = [s.gamma for s in auto.settings]
    assert len(set(gammas)) == 4 and all(1.8 <= g <= 2.6 for g in gammas)


@pytest.mark.shared_data
def test_rawtoaces_camera_file(rawtoaces_dir):
    cam = load_camera("canon-powershot-s90", search_dirs=(rawtoaces_dir / "data" / "camera",))
    assert "S90" in cam.model and cam.sensitivities.shape == (81, 3)
    b = simulate_bracket(camera=cam, size=(48, 40), exposures=2, seed=0)
    assert np.all(np.isfinite(b.truth_linear_srgb))


def test_scene_kinds_render_finite(camera):
    for kind in ("outdoor", "indoor", "night"):
        sc = make_scene(kind, (64, 48), seed=5)
        rgb = scene_camera_rgb(sc, camera)
        assert np.all(np.isfinite(rgb)) and rgb.min() >= 0
