"""AHD (derender.raw.ahd, Hirakawa & Parks 2005 as dcraw computes it) against its peer, LibRaw's
AHD through rawpy, and its variance against Monte Carlo and the simulator's exact truth."""

import numpy as np
import pytest

from derender.camera import simulate_bracket
from derender.camera.spectral import load_camera
from derender.core.errors import InputError
from derender.evaluation.raw_merge import bracket_raw_frames, demosaiced_truth, raw_scores
from derender.raw.ahd import ahd_demosaic, ahd_greens, ahd_rows
from derender.raw.optimal import demosaic_compiled, demosaic_variance, raw_merge


def _directional(x, pattern):
    """Our two directional images and their mean: LibRaw's AHD outputs one of them at every pixel."""
    lut = {"R": 0, "G": 1, "B": 2}
    chan = np.array([[lut[pattern[0]], lut[pattern[1]]], [lut[pattern[2]], lut[pattern[3]]]], np.int64)
    red_row = np.array([np.any(chan[0] == 0), np.any(chan[1] == 0)])
    h, w = x.shape
    x = np.ascontiguousarray(x, np.float32)
    gh = np.empty((h, w), np.float32)
    gv = np.empty((h, w), np.float32)
    clamps = np.empty((h, w), np.uint8)
    ahd_greens(x, chan, gh, gv, clamps)
    out = []
    for d in range(2):
        homo = np.zeros((2, h, w), np.uint8)
        homo[d] = 1                                   # every pixel more homogeneous in direction d
        o = np.empty((h, w, 3), np.float32)
        ahd_rows(x, x, gh, gv, clamps, homo, chan, red_row, np.eye(3), False, False, o, np.empty((1, 1, 3), np.float32),
                 np.empty((h, w), np.uint8))
        out.append(o.astype(np.float64))
    return out + [0.5 * (out[0] + out[1])]


@pytest.mark.parametrize("kind", ["outdoor", "indoor"])
def test_ahd_is_libraw_ahd(tmp_path, kind):
    """The peer: LibRaw's AHD (rawpy ``DemosaicAlgorithm.AHD``, camera RGB, linear, no auto-bright,
    unit white balance) on a simulated 14-bit DNG whose colour matrix makes LibRaw's camera-to-sRGB
    matrix the identity (so its CIELab is ours), the scene's mosaic raised to the power 0.4 to keep
    it above LibRaw's 16-bit steps. 6 border pixels left out (LibRaw fills 5 bilinearly).
    Measured (outdoor, indoor): median relative difference 2.7e-4, 1.8e-4 (LibRaw rounds to 16
    bits); 1.5 %, 1.1 % of the pixels differ by more than 1 % -- every one of them is our other
    direction (or the mean): LibRaw's integer CIELab breaks near-ties otherwise; at the 99.9th
    percentile LibRaw is within 3.3e-5 of one of our two directional images or their mean;
    Malvar's filter is 2.2 % from LibRaw's AHD, Menon's 0.7 %."""
    rawpy = pytest.importorskip("rawpy")
    from derender.camera.dng import write_dng
    from derender.camera.sensor import mosaic_signal
    from derender.core.colorimetry import XYZ_TO_LINEAR_SRGB

    b = simulate_bracket("nikon-d5100", kind=kind, size=(192, 128), exposures=2, seed=1, style="simple",
                         pipeline="fixed", noise=False)
    sig = np.clip(mosaic_signal(b.camera_rgb_per_s) / np.percentile(mosaic_signal(b.camera_rgb_per_s), 99.5),
                  0, 1) ** 0.4 * 0.9
    black, white = 600, 16383
    mosaic = np.round(black + sig * (white - black)).astype(np.uint16)
    path = write_dng(tmp_path / "a.dng", mosaic, cfa_pattern="RGGB", black_level=black, white_level=white,
                     xyz_to_camera=XYZ_TO_LINEAR_SRGB, as_shot_neutral=np.ones(3), exposure_time=0.01,
                     make="Sim", model="Cam", bits=14)
    with rawpy.imread(str(path)) as r:
        np.testing.assert_allclose(r.color_matrix[:, :3], np.eye(3), atol=1e-3)
        lib = r.postprocess(demosaic_algorithm=rawpy.DemosaicAlgorithm.AHD, output_color=rawpy.ColorSpace.raw,
                            gamma=(1, 1), no_auto_bright=True, output_bps=16, user_wb=[1, 1, 1, 1], user_flip=0,
                            highlight_mode=rawpy.HighlightMode.Clip, adjust_maximum_thr=0.0)
    lib = lib.astype(np.float64) / 65535
    x = (mosaic.astype(np.float64) - black) / (white - black)
    out, _, _ = ahd_demosaic(x, "RGGB", scale=1.0)        # LibRaw's CIELab puts its white level at 1
    sl = (slice(6, -6), slice(6, -6))
    norm = np.maximum(np.linalg.norm(lib[sl], axis=-1), 1e-6)
    rel = np.linalg.norm(out[sl] - lib[sl], axis=-1) / norm
    assert np.median(rel) < 1e-3
    assert np.mean(rel > 0.01) < 0.03
    nearest = np.min([np.abs(c[sl] - lib[sl]).max(axis=-1) for c in _directional(x, "RGGB")], axis=0)
    assert np.percentile(nearest, 99.9) < 1e-4
    from derender.raw.mosaic import demosaic_bayer

    malvar = np.linalg.norm(demosaic_bayer(x, "RGGB")[sl] - lib[sl], axis=-1) / norm
    assert np.median(malvar) > 20 * np.median(rel)       # the comparison can tell demosaics apart


@pytest.mark.parametrize("shape", [(16, 20), (17, 23), (5, 6)])
def test_ahd_borders_and_patterns(shape):
    """Every Bayer pattern, odd sizes and borders (mirrored): finite, a flat field stays flat,
    and the merge's phase-plane entry (demosaic_compiled) is the mosaic's (white balance first,
    the matrix after)."""
    from derender.raw.mosaic import cfa_channel_index

    rng = np.random.default_rng(0)
    m = np.array([[1.8, -0.6, -0.2], [-0.2, 1.5, -0.3], [0.0, -0.5, 1.5]])
    mult = np.array([2.0, 1.0, 1.5])
    for pattern in ("RGGB", "GRBG", "BGGR", "GBRG"):
        flat, _, _ = ahd_demosaic(np.full(shape, 0.3), pattern)
        np.testing.assert_allclose(flat, 0.3, rtol=1e-6)
        x = rng.uniform(0, 1, shape).astype(np.float32) ** 3
        v = rng.uniform(0.1, 1, shape).astype(np.float32) * 1e-3
        gains = mult[cfa_channel_index(shape, pattern)]
        ref, ref_var, _ = ahd_demosaic(x * gains, pattern, v * gains ** 2, m)
        planes = np.zeros((2, 2, (shape[0] + 1) // 2, (shape[1] + 1) // 2), np.float32)
        vplanes = np.zeros_like(planes)
        for i in range(2):
            for j in range(2):
                sub = x[i::2, j::2]
                planes[i, j, :sub.shape[0], :sub.shape[1]] = sub
                vplanes[i, j, :sub.shape[0], :sub.shape[1]] = v[i::2, j::2]
        out, var = demosaic_compiled(planes, vplanes, shape, pattern, mult, m, "ahd", clip_negative=False)
        np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6)
        np.testing.assert_allclose(var, ref_var, rtol=1e-5, atol=0)
        assert np.all(np.isfinite(out)) and np.all(var >= 0)


def test_ahd_variance_is_exact_given_its_directions():
    """Given its directions (and clamps) AHD is linear in the photosites: the variance of ahd_rows
    against Monte Carlo of small perturbations (3000 draws; the ratio's sampling error is ~2.6 %
    per pixel), at the pixels whose direction no draw changed (the direction term is then
    P(flip) Delta^2 with Delta of the noise's size, included in the prediction). Measured: median
    ratio 1.000, 5th-95th percentile 0.95-1.05; borders included."""
    rng = np.random.default_rng(2)
    shape = (24, 22)
    x = rng.uniform(0, 1, shape) ** 3 + 0.1
    v = rng.uniform(0.5, 1.5, shape) * 1e-10
    m = np.array([[1.2, -0.1, -0.1], [-0.2, 1.1, 0.1], [0.0, -0.3, 1.3]])
    out, var, choice = ahd_demosaic(x, "GRBG", v, m)
    draws, same = [], np.ones(shape, bool)
    for _ in range(3000):
        o, _, c = ahd_demosaic(x + rng.standard_normal(shape) * np.sqrt(v), "GRBG", None, m)
        draws.append(o.astype(np.float64) - out)
        same &= c == choice
    ratio = (np.var(draws, axis=0) / var)[same]
    assert same.mean() > 0.9
    assert abs(np.median(ratio) - 1) < 0.01
    assert 0.93 < np.percentile(ratio, 5) and np.percentile(ratio, 95) < 1.07
    with pytest.raises(InputError):
        demosaic_variance(v, "GRBG", m, "ahd")          # not one linear filter per phase


def test_ahd_merge_sigma_covers():
    """``raw_merge(..., demosaic="ahd")`` on simulated DNG brackets (exact truth and noise; a RAW
    merge does not see the rendering: no tuning family applies): its noise-only sigma against the merge's
    noise-free output (the true mosaic through the same AHD) covers 0.93-0.97 at 95 % and
    0.45-0.55 at 50 %. Measured: nikon-d5100 outdoor 0.935 / 0.502, sigma-sd-merrill night
    0.934 / 0.509 (Menon's: 0.937 / 0.494, 0.934 / 0.500)."""
    for cam, bits, kind in (("nikon-d5100", 14, "outdoor"), ("sigma-sd-merrill", 12, "night")):
        b = simulate_bracket(load_camera(cam).with_bits(bits), kind=kind, size=(128, 96), exposures=5, seed=3,
                             style="simple", pipeline="fixed")
        est = raw_merge(bracket_raw_frames(b), clip_negative=False, demosaic="ahd", output_space="camera_rgb",
                        variance_terms="noise")
        assert est.info["demosaic"] == "ahd"
        s = raw_scores(est.radiance, demosaiced_truth(b, est.info), est.mask, est.variance)
        assert 0.93 <= s["coverage95"] <= 0.97, s
        assert 0.45 <= s["coverage50"] <= 0.55, s
