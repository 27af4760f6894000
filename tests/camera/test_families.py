"""Pipeline families of the simulator (issue 16 item 1): bit-identity of ``paper``/``camera`` with
the old calls, determinism per seed, scene.json round trip, the stages really doing what they say."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest
from helpers import run_cli

from derender.camera import load_frame_settings, simulate_bracket, write_bracket
from derender.camera.families import FAMILIES, WB_PRESETS, family_settings
from derender.camera.rendering import camera_rgb_from_mosaic
from derender.camera.stages import (
    FrameSettings,
    apply_lut,
    channel_curve,
    gamut_lut,
    hue_saturation,
    render_frame,
    settings_from_dict,
    settings_to_dict,
    upsample_gain,
)
from derender.core.errors import InputError

SMALL = dict(size=(64, 48), exposures=4)

# sha256 of the codes of simulate_bracket(size=(64, 48), exposures=4, seed=3, style=...) before the
# families existed (commit b86c3e0): the refactoring of the JPEG engine changed no byte.
GOLDEN = {"simple": "4ea6bc47bcdbd975df6b99aa8c4deb0c8546df3261d48f4a64af189ded7998cd",
          "camera": "518603aa989c1c6c768d8e9783d60388d48d89802d7dc6a9a42316e5abfb3d86"}


def _sha(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def test_families_are_ordered_and_described():
    assert list(FAMILIES)[:2] == ["paper", "camera"]
    assert {"dslr-lut", "phone-local", "drift"} <= set(FAMILIES)
    assert all(isinstance(v, str) and v and "\n" not in v for v in FAMILIES.values())


@pytest.mark.parametrize("family,style", [("paper", "simple"), ("camera", "camera")])
def test_paper_and_camera_are_bit_identical_to_the_old_calls(family, style):
    old = simulate_bracket(seed=3, style=style, pipeline="auto", **SMALL)
    new = simulate_bracket(seed=3, family=family, **SMALL)
    assert _sha(old.jpeg_codes) == GOLDEN[style]
    assert np.array_equal(old.jpeg_codes, new.jpeg_codes)
    assert np.array_equal(old.mosaics, new.mosaics)
    assert [s.gamma for s in old.settings] == [f.gamma for f in new.frames]
    assert new.family == family and new.params["family"] == family and old.params["family"] is None


@pytest.mark.parametrize("family", list(FAMILIES))
def test_deterministic_per_seed_and_scene_json_rerenders_identical_codes(family, tmp_path):
    a = simulate_bracket(seed=5, family=family, **SMALL)
    b = simulate_bracket(seed=5, family=family, **SMALL)
    c = simulate_bracket(seed=6, family=family, **SMALL)
    assert np.array_equal(a.jpeg_codes, b.jpeg_codes)
    assert [settings_to_dict(f) for f in a.frames] == [settings_to_dict(f) for f in b.frames]
    assert not np.array_equal(a.jpeg_codes, c.jpeg_codes)
    params = write_bracket(a, tmp_path)
    assert params["family"] == family and len(params["frames"]) == SMALL["exposures"]
    frames = load_frame_settings(tmp_path)
    assert [settings_to_dict(f) for f in frames] == [settings_to_dict(f) for f in a.frames]
    for j, fs in enumerate(frames):
        rgb = camera_rgb_from_mosaic(a.mosaics[j], a.camera)
        assert np.array_equal(render_frame(rgb, fs), a.jpeg_codes[j]), f"frame {j}"


def test_old_scene_json_without_frames_still_loads(tmp_path):
    a = simulate_bracket(seed=1, **SMALL)
    params = dict(a.params)
    del params["frames"]
    frames = load_frame_settings(params)
    for j, fs in enumerate(frames):
        assert np.array_equal(render_frame(camera_rgb_from_mosaic(a.mosaics[j], a.camera), fs), a.jpeg_codes[j])


def test_settings_dict_round_trip_is_exact():
    rng = np.random.default_rng(0)
    for fam in FAMILIES:
        for fs in family_settings(fam, 3, rng, [2.0, 1.0, 1.5], [2.1, 1.0, 1.4], np.eye(3)):
            d = settings_to_dict(fs)
            assert settings_to_dict(settings_from_dict(d)) == d
    with pytest.raises(InputError):
        settings_from_dict({"gain": 1.0})


def test_unknown_family_is_an_input_error(capsys):
    with pytest.raises(InputError, match="dslr-lut"):
        simulate_bracket(family="nope", **SMALL)
    code, out, err = run_cli(["simulate", "/nonexistent/x", "--render", "nope"], capsys)
    assert code == 2 and "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("error:") and "phone-local" in err


def test_cli_help_lists_the_families_and_render_writes_one(tmp_path, capsys):
    code, out, _ = run_cli(["simulate", "--help"], capsys)
    flat = " ".join(out.split())
    assert code == 0 and all(f in flat for f in FAMILIES)
    code, out, err = run_cli(["simulate", tmp_path / "s", "--render", "phone-local", "-n", "2", "--size", "48x32"], capsys)
    assert code == 0, err
    frames = load_frame_settings(tmp_path / "s")
    assert [f.style for f in frames] == ["local", "local"] and frames[0].gain_map is not None


# --------------------------------------------------------------------------- the stages do what they say
def test_dslr_white_balance_switches_between_presets():
    switched = 0
    for seed in range(4):
        b = simulate_bracket(seed=seed, family="dslr-lut", size=(48, 32), exposures=5)
        presets = [f.wb_preset for f in b.frames]
        assert set(presets) <= set(WB_PRESETS) and len(set(presets)) >= 2
        for f in b.frames:  # each frame's WB is the scene's times its preset's multipliers
            assert np.allclose(np.asarray(f.wb) / np.asarray(f.wb_as_shot), WB_PRESETS[f.wb_preset])
        j = next(i for i in range(1, 5) if presets[i] != presets[i - 1])
        assert not np.allclose(b.frames[j].wb, b.frames[j - 1].wb)
        switched += 1
    assert switched == 4


def test_dslr_gamut_map_is_nonlinear_keeps_neutrals_and_curves_differ():
    b = simulate_bracket(seed=2, family="dslr-lut", size=(48, 32), exposures=2)
    fs = b.frames[0]
    lut = gamut_lut(fs.gamut)
    u = np.random.default_rng(0).uniform(0.05, 0.95, (2000, 3))
    d = apply_lut(lut, u)
    assert np.abs(d).max() > 0.005                       # really moves colours
    assert np.allclose(d.sum(axis=1), 0.0, atol=1e-12)   # never along the neutral axis
    nodes = np.repeat(np.linspace(0, 1, int(fs.gamut["nodes"]))[:, None], 3, axis=1)
    assert np.abs(apply_lut(lut, nodes)).max() < 1e-12   # neutrals stay neutral on the LUT's nodes,
    grey = np.repeat(np.linspace(0, 1, 101)[:, None], 3, axis=1)
    assert np.abs(apply_lut(lut, grey)).max() < 0.25 * np.abs(d).max()   # and near neutral between them
    # the map is monotone: a small step along a channel never reverses it
    du = 1e-3
    for c in range(3):
        v = u.copy()
        v[:, c] += du
        assert np.all((v + apply_lut(lut, v) - u - apply_lut(lut, u))[:, c] > 0)
    x = np.linspace(0, 1, 101)
    curves = [channel_curve(x, p) for p in fs.curves]
    assert all(np.all(np.diff(cv) > 0) for cv in curves)
    assert np.abs(curves[0] - curves[1]).max() > 0.01 and np.abs(curves[1] - curves[2]).max() > 0.01
    # hue-dependent saturation: the chroma gain differs between hues and keeps luminance
    cols = np.array([[0.5, 0.2, 0.2], [0.2, 0.5, 0.2], [0.2, 0.2, 0.5]])
    out = hue_saturation(cols, fs.hue_sat)
    w = np.array([0.2126, 0.7152, 0.0722])
    assert np.allclose(out @ w, cols @ w)
    gains = np.linalg.norm(out - (out @ w)[:, None], axis=1) / np.linalg.norm(cols - (cols @ w)[:, None], axis=1)
    assert gains.max() - gains.min() > 1e-3


def test_phone_local_gain_map_varies_in_space_and_between_frames():
    b = simulate_bracket(seed=1, family="phone-local", size=(96, 64), exposures=4)
    maps = [np.asarray(f.gain_map) for f in b.frames]
    assert all(m.shape == (6, 8) for m in maps)
    ratios = [m.max() / m.min() for m in maps]
    assert min(ratios) > 1.05 and max(ratios) > 2.0      # spatially varying (strongly in mid exposures)
    for m in maps:
        g = upsample_gain(m, (64, 96))
        assert np.abs(np.diff(g, axis=1)).max() < 0.25 * g.max()   # smooth in space (no jumps)
    assert not np.allclose(maps[0], maps[-1])
    # the same camera RGB with and without the gain map renders differently where the gain is not 1
    rgb = np.full((64, 96, 3), 0.05)
    fs = b.frames[1]
    flat = replace(fs, gain_map=np.ones_like(maps[1]).tolist())
    diff = render_frame(rgb, fs).astype(int) - render_frame(rgb, flat).astype(int)
    assert diff.max() - diff.min() > 5
    assert len({f.gamma for f in b.frames}) == 4 and len({f.gain for f in b.frames}) == 4


def test_drift_white_balance_drifts_more_than_auto():
    spread = {}
    for fam in ("camera", "drift"):
        b = simulate_bracket(seed=0, family=fam, size=(48, 32), exposures=7)
        r_over_b = np.log([f.wb[0] / f.wb[2] for f in b.frames])
        spread[fam] = r_over_b.max() - r_over_b.min()
    assert spread["drift"] > spread["camera"]


def test_frame_settings_wrap_render_settings():
    from derender.camera.rendering import RenderSettings

    rs = RenderSettings(wb=[2.0, 1.0, 1.5], gain=1.2, gamma=2.0, saturation=0.9, style="simple")
    fs = FrameSettings.from_render_settings(rs, [2.0, 1.0, 1.5], np.eye(3))
    assert fs.render_settings() == rs
