"""The nominal EXIF factor (``--absolute exif``) under each ISO rating: exact answers on
synthetic cameras built from ISO 12232's definitions, the EXIF tags written and read back,
and the simulator's luminance family (saturation rated) end to end."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli

Q = 0.65


def _srgb_encode(lin: np.ndarray) -> np.ndarray:
    lin = np.clip(lin, 0.0, 1.0)
    v = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    return np.clip(np.rint(255 * v), 0, 255).astype(np.uint8)


def _camera_frames(lum: np.ndarray, rating: str, frames=((1 / 60, 4.0, 100), (1 / 250, 2.8, 400), (1 / 15, 8.0, 200))):
    """Frames of a neutral scene of luminance ``lum`` (cd/m2) from a camera with an sRGB
    rendering whose stated speed S follows ``rating``: SOS renders H = 10 / S at code 118
    (linear 0.181); saturation renders H = 78 / S at white."""
    out = []
    for t, n, s in frames:
        h = Q * lum * t / n ** 2                                   # lx s at the sensor
        lin = h * s / 10.0 * 0.18116424 if rating == "sos" else h * s / 78.0
        codes = _srgb_encode(lin)
        out.append((np.repeat(codes[..., None], 3, axis=-1), t, n, s))
    return out


@pytest.mark.parametrize("rating", ["sos", "saturation"])
def test_exif_factor_inverts_the_rating_definition(rating):
    """A relative map (the truth times an unknown 0.0137) gets the factor 1 / 0.0137 back within
    2 % (the 118 +- 6 code window and 8-bit rounding), from every frame; the wrong rating is off
    by the 0.5 EV between the two definitions."""
    from derender.photometry.calibration import exif_factor

    rng = np.random.default_rng(5)
    lum = np.exp(rng.uniform(np.log(20.0), np.log(4000.0), size=(96, 128)))
    radiance = np.repeat((lum * 0.0137 / 179.0)[..., None], 3, axis=-1).astype(np.float32)
    cal = exif_factor(radiance, _camera_frames(lum, rating), rating=rating, min_pixels=16)
    assert cal.factor == pytest.approx(1 / 0.0137, rel=0.02)
    assert len(cal.per_frame) == 3 and cal.rating == rating
    other = exif_factor(radiance, _camera_frames(lum, rating), rating="saturation" if rating == "sos" else "sos",
                        min_pixels=16)
    assert abs(np.log2(other.factor * 0.0137)) == pytest.approx(np.log2(0.18116 * 78 / 10), abs=0.03)


def test_sensitivity_rating_follows_exif_2_3():
    from derender.photometry.calibration import SENSITIVITY_RATINGS, sensitivity_rating

    assert sensitivity_rating({"ISO": 200}) == ("unknown", 200)
    assert sensitivity_rating({"ISO": 200, "SensitivityType": 1}) == ("sos", 200)
    assert sensitivity_rating({"ISO": 200, "SensitivityType": 5, "SOS": 160}) == ("sos", 160)
    assert sensitivity_rating({"ISO": 200, "SensitivityType": 2, "REI": 250}) == ("rei", 250)
    assert sensitivity_rating({"ISO": 200, "SensitivityType": 3, "ISOSpeed": 100}) == ("saturation", 100)
    assert SENSITIVITY_RATINGS["sos"].constant == pytest.approx(15.38, abs=0.01)
    assert SENSITIVITY_RATINGS["saturation"].constant == pytest.approx(21.74, abs=0.01)
    assert SENSITIVITY_RATINGS["sos"].uncertainty < SENSITIVITY_RATINGS["unknown"].uncertainty


def test_sensitivity_type_written_and_read_back(tmp_path):
    from derender.camera.bracket import write_jpeg
    from derender.io.exif import read_exif

    codes = np.full((16, 16, 3), 118, dtype=np.uint8)
    p = write_jpeg(tmp_path / "a.jpg", codes, 0.01, "Make", "Model", fnumber=4.0, iso=400, sensitivity_type=3)
    e = read_exif(p)
    assert e["SensitivityType"] == 3 and e["ISOSpeed"] == 400 and e["ISO"] == 400
    q = write_jpeg(tmp_path / "b.jpg", codes, 0.01, "Make", "Model", fnumber=4.0, iso=400)
    assert "SensitivityType" not in read_exif(q)


def test_luminance_family_reads_absolute_from_exif(tmp_path, capsys):
    """The luminance family states a saturation-based ISO (EXIF SensitivityType 3). On its pure
    gamma-2.2 rendering (sRGB-like mid-grey, tuning) ``--absolute exif`` reads the truth's cd/m2
    within a third of its stated 44 %; measured 0.98 (debevec; 0.56 with the former K = 12.5 at
    code 118)."""
    import json

    from derender.camera.luminance import truth_luminance_cd_m2
    from derender.evaluation.families import smooth_mask
    from derender.io.exr import read_exr
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    d = tmp_path / "lum"
    code, _, err = run_cli(["simulate", d, "--luminance", "time", "--render", "gamma", "--size", "192x128"], capsys)
    assert code == 0, err
    out = tmp_path / "m.exr"
    code, _, err = run_cli(["merge", *sorted((d / "jpeg").glob("*.jpg")), "-o", out, "--method", "debevec",
                            "--absolute", "exif"], capsys)
    assert code == 0, err
    assert "saturation speed" in err and "44 %" in err
    truth = read_exr(d / "truth.exr")
    lum_true = truth_luminance_cd_m2(truth)
    lum = luminance_cd_m2(read_exr(out), SRGB_PRIMARIES)
    ok = smooth_mask(truth) & (lum_true > 1e-3 * lum_true.max())
    ratio = float(np.median(lum[ok] / lum_true[ok]))
    assert abs(ratio - 1.0) < 0.44 / 3, ratio
    assert json.loads((d / "scene.json").read_text())["luminance"]["render"] == "gamma"
