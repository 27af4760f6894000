"""Camera profiles: a calibration saved on one bracket and reused on another, against the simulator's truth.

Oracle: two simulated brackets of the same camera and fixed pipeline (different scenes and
seeds). The truth in cd/m2 is the simulator's radiance per second times an arbitrary 317.0,
the same for both brackets (the simulator's radiance is the camera's signal per second, one
scale for one camera). Bracket A is labelled f/5.6, ISO 100 with its true times; bracket B's
frames are labelled with other times, f-numbers and ISO speeds giving the same exposure
``t S / N^2`` (what that camera would have recorded with those settings). The profile holds
A's curves and its spot factor; B is merged with it and no spot.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, write_exif_jpeg

TRUTH_SCALE = 317.0
APERTURES = [16.0, 5.6, 2.8, 8.0, 4.0, 11.0, 5.6]
ISOS = [400, 100, 100, 200, 800, 1600, 200]


def _bracket(folder: Path, seed: int, kind: str, vary: bool, model: str = "Camera"):
    from derender.camera import simulate_bracket

    b = simulate_bracket(size=(192, 128), exposures=7, pipeline="fixed", seed=seed, kind=kind)
    folder.mkdir(parents=True)
    files = []
    for j, (codes, t) in enumerate(zip(b.jpeg_codes, b.times)):
        n, s = (APERTURES[j], ISOS[j]) if vary else (5.6, 100)
        t_label = float(t) * (n / 5.6) ** 2 * (100 / s)        # the same t S / N^2 as at f/5.6, ISO 100
        files.append(write_exif_jpeg(folder / f"{j:02d}.jpg", codes, t_label, n, s, model))
    return b, files


def _truth_luminance(b):
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    truth = b.truth_linear_srgb.astype(np.float64) * TRUTH_SCALE
    return truth, luminance_cd_m2(truth, SRGB_PRIMARIES)


def _score(path: Path, b) -> dict:
    from derender.evaluation.families import smooth_mask
    from derender.io.exr import read_exr
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    truth, lum_true = _truth_luminance(b)
    lum = luminance_cd_m2(read_exr(path), SRGB_PRIMARIES)
    ok = (lum_true > 1e-3 * lum_true.max()) & smooth_mask(truth)
    err = np.abs(lum[ok] / lum_true[ok] - 1.0)
    return {"median": float(np.median(err)), "p90": float(np.percentile(err, 90)),
            "ratio": float(np.median(lum[ok] / lum_true[ok])), "n": int(ok.sum())}


def _spot(b) -> str:
    from test_spot import _smoothest_window

    _, lum_true = _truth_luminance(b)
    x, y = _smoothest_window(lum_true)
    return f"{x},{y},8,8={float(lum_true[y:y + 8, x:x + 8].mean()):.6f}"


@pytest.fixture(scope="module")
def brackets(tmp_path_factory):
    root = tmp_path_factory.mktemp("profile")
    a = _bracket(root / "a", seed=7, kind="outdoor", vary=False)
    b = _bracket(root / "b", seed=11, kind="indoor", vary=True)
    return root, a, b


@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_profile_saved_on_one_bracket_makes_another_absolute(brackets, capsys, method):
    """A profile saved on one bracket, reused without a spot on another whose aperture and ISO
    vary (192x128, 7 frames, fixed pipeline, camera style, tuning family; A seed 7 outdoor, B seed
    11 indoor; the truth's scale is an arbitrary 317 and A's spot a textured 8x8 patch). Issue 28's
    line (median <= 5 %) is tested with exact truth on the luminance family's grey card
    (:func:`test_profile_from_the_grey_card_reused_on_an_aperture_iso_bracket`); here the bound is
    5.5 % for stabilized and 9 % for debevec: its merge's smoothness lambda 60
    (``MERGE_LAMBDA``, was 30) moved this pair from 4.3 % to 5.2 % (p90 8.4 -> 8.6 %), while over
    ``benchmarks/bench_profiles.py``'s five fixed-pipeline pairs the mean went from 6.9 % to 5.7 %
    (docs/results-luminance.md); the bound-aware top of its curve (issues 36/37) moved it to 8.5 % (p90
    13.1 %; with the sequential rule alone 5.9 %): on A's filmic shoulder the residual test leaves
    out top codes that the curve then extrapolates, and A's spot patch, seen at codes 76 and 184,
    reads 2 % brighter against the rest of A (after the spot, median ratio 0.921 against 0.939),
    while the merges' PSNR L against the truth is 44.06 dB against 44.07 on A and 41.33 against
    39.49 on B. Over ``bench_profiles.py``'s five fixed pairs the bound-aware top is better on
    average in every column (B with A's profile: mean 5.3 % against 5.7 %; B with its own spot
    4.3 % against 7.6 %; A with its own spot 4.8 % against 5.7 %): this pair is its worst case.
    Stabilized measured 4.85 % at c402d4d (median ratio 1.048, p90 8.5 %) and 5.11 % since issue
    36 item 2 (ratio 1.051, p90 8.8 %): B, one rendering, now takes the graph gains of
    :func:`derender.hdr.stabilize.colour_matrices.graph_gains` (diagonal ratio 1.049), A the
    per-reference fits (1.103), and the 0.3 % is mostly the transferred scale."""
    root, (ba, fa), (bb, fb) = brackets
    prof = root / f"{method}.json"
    code, _, err = run_cli(["merge", *fa, "-o", root / f"a-{method}.exr", "--method", method, "--spot", _spot(ba),
                            "--save-profile", prof], capsys)
    assert code == 0, err
    doc = json.loads(prof.read_text())
    assert doc["format"] == "derender-camera-profile" and doc["version"] == 1
    assert doc["camera"]["make"] == "Test" and doc["camera"]["model"] == "Camera"
    assert (doc["response"] is not None) == (method == "debevec")
    out = root / f"b-{method}.exr"
    code, _, err = run_cli(["merge", *fb, "-o", out, "--method", method, "--profile", prof], capsys)
    assert code == 0, err
    assert "from the profile" in err
    s = _score(out, bb)
    print(f"{method}: profile reused on B: {s}")
    assert s["median"] <= (0.09 if method == "debevec" else 0.055), s
    assert s["p90"] <= (0.14 if method == "debevec" else 0.10), s
    # without the aperture/ISO transfer (the factor used as it was saved) the map would be off by
    # the first frames' S / N^2: 400 / 16^2 against 100 / 5.6^2, a factor 2.04
    from derender.io.exr import read_exr

    header = _exr_header(out)
    assert header["whiteLuminance"] == pytest.approx(179.0)
    assert "profile" in header["derender:photometry"]
    assert read_exr(out).min() >= 0


def _exr_header(path: Path) -> dict:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return dict(f.header())


def test_profile_curves_are_used_instead_of_fitting(brackets, capsys):
    """The profile's curves reach the merge: a Debevec merge with them equals the library's
    merge with the same curves given, and differs from a merge that fits its own."""
    root, (ba, fa), (bb, fb) = brackets
    prof = root / "curves.json"
    assert run_cli(["merge", *fa, "-o", root / "c.exr", "--save-profile", prof], capsys)[0] == 0
    from derender.hdr.files import merge_files
    from derender.io.exr import read_exr
    from derender.photometry.profile import load_profile

    p = load_profile(prof)
    assert p.factor is None
    assert run_cli(["merge", *fb, "-o", root / "c1.exr", "--profile", prof], capsys)[0] == 0
    ref = merge_files(fb, options={"curves": p.curves}, method="debevec")
    own = merge_files(fb, method="debevec")
    got = read_exr(root / "c1.exr")
    np.testing.assert_allclose(got, ref.radiance, rtol=1e-5, atol=1e-9)
    assert np.max(np.abs(got / np.maximum(own.radiance, 1e-9) - 1)) > 1e-3


def test_profile_from_another_camera_warns_or_fails(brackets, tmp_path, capsys):
    root, (ba, fa), (bb, fb) = brackets
    prof = root / "cam.json"
    assert run_cli(["merge", *fa, "-o", tmp_path / "a.exr", "--spot", _spot(ba), "--save-profile", prof],
                   capsys)[0] == 0
    other, files = _bracket(tmp_path / "o", seed=3, kind="outdoor", vary=False, model="Other")
    code, _, err = run_cli(["merge", *files, "-o", tmp_path / "w.exr", "--profile", prof], capsys)
    assert code == 0 and "warning:" in err and "another camera" in err, err
    code, _, err = run_cli(["merge", *files, "-o", tmp_path / "s.exr", "--profile", prof, "--strict-camera"], capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error:") and "another camera" in lines[0], err
    assert not (tmp_path / "s.exr").exists()


def test_profile_round_trip_and_versions(tmp_path, capsys):
    from derender.core.errors import InputError
    from derender.photometry.profile import CameraProfile, load_profile, save_profile
    from derender.photometry.vignetting import Vignetting
    from derender.response.curves import ResponseCurves

    g = np.log(np.linspace(0.01, 1.0, 256))[:, None] + np.array([0.1, 0.0, -0.1])
    prof = CameraProfile(make="A", model="B", lens="C", curves=ResponseCurves(g), factor=123.4,
                         factor_method="debevec", vignetting=Vignetting((-0.3, 0.1, 0.0), (10.0, 8.0), (20, 16), 0.01),
                         view="-vta -vh 180 -vv 180")
    save_profile(prof, tmp_path / "p.json")
    back = load_profile(tmp_path / "p.json")
    np.testing.assert_allclose(back.curves.log_inverse, g, atol=1e-8)
    assert (back.make, back.model, back.lens, back.factor, back.view) == ("A", "B", "C", 123.4, prof.view)
    assert back.vignetting == prof.vignetting
    doc = json.loads((tmp_path / "p.json").read_text())
    doc["version"] = 2
    (tmp_path / "v2.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="version 2"):
        load_profile(tmp_path / "v2.json")


def test_factor_transfers_with_aperture_and_iso():
    from derender.photometry.profile import factor_at_reference, factor_for_bracket

    f = factor_at_reference(2.0, 5.6, 100)
    # one stop more aperture area (f/4) at the same ISO: the map doubles, the factor halves
    assert factor_for_bracket(f, 5.6 / np.sqrt(2), 100) == pytest.approx(1.0)
    assert factor_for_bracket(f, 5.6, 400) == pytest.approx(0.5)
    assert factor_for_bracket(f, 5.6, 100) == pytest.approx(2.0)


def test_absolute_exif_follows_the_meter_equation(brackets, capsys):
    """--absolute exif: in every frame with 64 pixels rendered near mid-grey (luma code 118),
    those pixels read C N^2 / (t S) cd/m2 (C = 10 / 0.65: no EXIF SensitivityType, so taken as
    an SOS rating) in the stabilized map within 6 % (measured
    0.97-1.01 on 4 frames), on the bracket whose aperture and ISO vary (f/2.8-16, ISO 100-1600):
    a wrong power of N or S would spread the frames by up to 30x. (Debevec's map: 0.87-1.04,
    its linearity error.) The header records the convention and its uncertainty."""
    root, _, (bb, fb) = brackets
    out = root / "exif.exr"
    code, _, err = run_cli(["merge", *fb, "-o", out, "--absolute", "exif", "--method", "stabilized"], capsys)
    assert code == 0, err
    assert "nominal from EXIF" in err and "unstated rating" in err and "44 %" in err
    from derender.io.exif import read_exif
    from derender.io.exr import read_exr
    from derender.io.images import read_codes
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    lum = luminance_cd_m2(read_exr(out), SRGB_PRIMARIES)
    checked = 0
    for f in fb:
        ex, c = read_exif(f), read_codes(f).astype(np.float32)
        luma = c @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        sel = (np.abs(luma - 118) <= 6) & (c.max(-1) < 250)
        if sel.sum() < 64:
            continue
        expected = 10 / 0.65 * ex["FNumber"] ** 2 / (ex["ExposureTime"] * ex["ISO"])
        assert np.median(lum[sel]) == pytest.approx(expected, rel=0.06), f.name
        checked += 1
    assert checked >= 3
    header = _exr_header(out)
    assert "uncertainty 0.44" in header["derender:photometry"] and header["whiteLuminance"] == 179.0


def test_relative_map_has_chromaticities_and_no_white_luminance(brackets, capsys):
    """Every EXR the merge writes states its primaries (linear sRGB / Rec. 709, D65), read by
    the OpenEXR package; a relative map has no whiteLuminance, nor has any variance file."""
    root, (ba, fa), _ = brackets
    out = root / "rel.exr"
    assert run_cli(["merge", *fa, "-o", out], capsys)[0] == 0
    h = _exr_header(out)
    np.testing.assert_allclose(h["chromaticities"], (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290), atol=1e-6)
    assert "whiteLuminance" not in h
    code, _, err = run_cli(["merge", *fa, "-o", root / "abs.exr", "--method", "stabilized-joint", "--spot",
                            _spot(ba)], capsys)
    assert code == 0, err
    assert _exr_header(root / "abs.exr")["whiteLuminance"] == 179.0
    from derender.core.types import HDRResult
    from derender.engine.outputs import write_outputs

    ones = np.ones((8, 8, 3), np.float32)
    res = HDRResult(radiance=ones, mask=np.zeros((8, 8), np.uint8), variance=ones,
                    info={"white_luminance": 179.0, "colour_space": "camera_rgb"})
    write_outputs(res, root / "r.exr", root / "v.exr")
    assert _exr_header(root / "r.exr")["whiteLuminance"] == 179.0
    assert "chromaticities" not in _exr_header(root / "r.exr")            # camera RGB states no primaries
    assert "whiteLuminance" not in _exr_header(root / "v.exr")


@pytest.mark.parametrize("text,needle", [
    ("{", "not JSON"),
    ('{"format": "derender-camera-profile", "version": 7}', "version 7"),
    ('{"format": "something-else", "version": 1}', "not a derender camera profile"),
    ('{"format": "derender-camera-profile", "version": 1, "photometric": {"factor": -3}}', "not a readable"),
    ('{"format": "derender-camera-profile", "version": 1, "response": {"log_inverse": [[0, 0, 0]]}}',
     "not a readable"),
])
def test_malformed_profile_is_one_error_and_no_output(brackets, tmp_path, capsys, text, needle):
    _, (ba, fa), _ = brackets
    (tmp_path / "p.json").write_text(text)
    code, _, err = run_cli(["merge", *fa, "-o", tmp_path / "o.exr", "--profile", tmp_path / "p.json"], capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], err
    assert not (tmp_path / "o.exr").exists()


def test_profile_view_and_factor_in_a_radiance_file(brackets, capsys):
    """A profile saved with --view gives later .hdr maps its VIEW= line and their absolute scale,
    as Radiance's getinfo and pvalue read them (within RGBE precision of the EXR)."""
    from radiance_tools import getinfo, pvalue_pixels

    from derender.io.exr import read_exr

    root, (ba, fa), (bb, fb) = brackets
    prof = root / "view.json"
    code, _, err = run_cli(["merge", *fa, "-o", root / "v.hdr", "--spot", _spot(ba), "--view",
                            "-vta -vh 180 -vv 180", "--save-profile", prof], capsys)
    assert code == 0, err
    assert json.loads(prof.read_text())["view"] == "-vta -vh 180 -vv 180"
    for out in ("vb.hdr", "vb.exr"):
        code, _, err = run_cli(["merge", *fb, "-o", root / out, "--profile", prof], capsys)
        assert code == 0, err
    info = getinfo(root / "vb.hdr")
    assert "VIEW= -vta -vh 180 -vv 180" in info and "DERENDER_PHOTOMETRY= absolute" in info, info
    exr, back = read_exr(root / "vb.exr"), pvalue_pixels(root / "vb.hdr")
    assert np.all(np.abs(back - exr) <= exr.max(axis=-1, keepdims=True) / 128.0 + 1e-30)


@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_factor_transfer_is_exact_across_aperture_and_iso(brackets, tmp_path, capsys, method):
    """The transfer alone, without the spot's or the merge's error: bracket B's codes labelled at
    A's settings (f/5.6, ISO 100, true times) and labelled with varying f-numbers and ISO speeds
    (first frame f/16, ISO 400) merge with the same profile to the same absolute map (1e-4)."""
    root, (ba, fa), (bb, fb) = brackets
    prof = root / f"{method}.json"
    if not prof.exists():
        assert run_cli(["merge", *fa, "-o", tmp_path / "a.exr", "--method", method, "--spot", _spot(ba),
                        "--save-profile", prof], capsys)[0] == 0
    (tmp_path / "same").mkdir()
    same = [write_exif_jpeg(tmp_path / "same" / f"{j:02d}.jpg", c, float(t), 5.6, 100)
            for j, (c, t) in enumerate(zip(bb.jpeg_codes, bb.times))]
    for name, files in (("same", same), ("vary", fb)):
        code, _, err = run_cli(["merge", *files, "-o", tmp_path / f"{name}.exr", "--method", method,
                                "--profile", prof], capsys)
        assert code == 0, err
    from derender.io.exr import read_exr

    np.testing.assert_allclose(read_exr(tmp_path / "vary.exr"), read_exr(tmp_path / "same.exr"), rtol=1e-4,
                               atol=1e-6)


def test_profile_vignetting_is_divided_out(brackets, tmp_path, capsys):
    """A profile's vignetting model acts as '--vignetting' does (the same map), and an explicit
    --vignetting file takes precedence over the profile's."""
    from derender.io.exr import read_exr
    from derender.photometry.profile import CameraProfile, save_profile
    from derender.photometry.vignetting import Vignetting, save_vignetting

    _, (ba, fa), _ = brackets
    vig = Vignetting((-0.35, 0.05, -0.1), (96.0, 64.0), (192, 128), 0.01)
    save_vignetting(vig, tmp_path / "v.json")
    save_profile(CameraProfile(make="Test", model="Camera", vignetting=vig), tmp_path / "p.json")
    save_profile(CameraProfile(vignetting=Vignetting((-0.1, 0.0, 0.0), (96.0, 64.0), (192, 128), 0.01)),
                 tmp_path / "q.json")
    for name, extra in (("v", ["--vignetting", tmp_path / "v.json"]), ("p", ["--profile", tmp_path / "p.json"]),
                        ("q", ["--profile", tmp_path / "q.json", "--vignetting", tmp_path / "v.json"]),
                        ("n", [])):
        code, _, err = run_cli(["merge", *fa, "-o", tmp_path / f"{name}.exr", *extra], capsys)
        assert code == 0, err
    v, p, q, n = (read_exr(tmp_path / f"{x}.exr") for x in "vpqn")
    np.testing.assert_array_equal(p, v)
    np.testing.assert_array_equal(q, v)
    np.testing.assert_allclose(n[0, 0] / v[0, 0], vig.gain()[0, 0], rtol=1e-5)


@pytest.fixture(scope="module")
def luminance_brackets(tmp_path_factory):
    """The luminance family's gamma-2.2 camera (tuning rendering): A a time bracket (f/16, ISO 100,
    seed 0) with its grey card's exact luminance, B another seed's aperture-iso bracket (f/4-16,
    ISO 100-800 per frame; the times out of order against brightness)."""
    from derender.camera import bracket_paths, write_bracket
    from derender.camera.luminance import simulate_luminance

    root = tmp_path_factory.mktemp("lumprof")
    ba = simulate_luminance(mode="time", render="gamma", seed=0)
    bb = simulate_luminance(mode="aperture-iso", render="gamma", seed=1)
    write_bracket(ba, root / "a")
    write_bracket(bb, root / "b")
    return root, ba, bb, bracket_paths(root / "a", "jpeg"), bracket_paths(root / "b", "jpeg")


@pytest.mark.parametrize("method", ["debevec", "robertson", "stabilized", "stabilized-joint"])
def test_profile_from_the_grey_card_reused_on_an_aperture_iso_bracket(luminance_brackets, capsys, method):
    """Issue 28's done-when "a profile saved on one bracket, reused without a spot on another whose
    aperture and ISO vary: median <= 5 %", on the luminance family (absolute truth 1..1e6 cd/m2):
    the profile calibrated with --spot on A's grey card (its exact luminance), B merged with the
    profile only, scored on the smooth pixels off the card with truth >= 1 cd/m2. Measured
    (seeds 0/1): median 1.7 / 2.3 / 3.7 / 2.8 %, p90 4.0 / 5.1 / 5.7 / 5.8 % (debevec, robertson,
    stabilized, stabilized-joint); seeds 2/3 and 4/5 1.2-3.7 % (benchmarks/bench_profiles.py)."""
    from helpers import profile_reuse_ratios

    root, ba, bb, fa, fb = luminance_brackets
    ratio = profile_reuse_ratios(fa, fb, ba, bb, (root / f"{method}.json", root / f"{method}-a.exr",
                                                  root / f"{method}-b.exr"), capsys, extra=("--method", method))
    assert float(np.median(np.abs(ratio - 1.0))) <= 0.05
    assert 0.95 <= float(np.median(ratio)) <= 1.05
