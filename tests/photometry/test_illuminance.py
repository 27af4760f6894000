"""Lens projections and vertical illuminance, against closed forms and Radiance's evalglare."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from helpers import run_cli
from radiance_tools import radiance_bin


@pytest.mark.parametrize("view, expected", [
    ("-vta -vh 180 -vv 180", 2 * np.pi),                                          # a hemisphere
    ("-vta -vh 120 -vv 120", 2 * np.pi * (1 - np.cos(np.radians(60)))),           # a cone of half-angle 60
    ("-vtv -vh 60 -vv 40", 4 * np.arcsin(np.sin(np.radians(30)) * np.sin(np.radians(20)))),   # a pyramid
])
def test_solid_angle_of_the_view(view, expected):
    from derender.photometry.projection import parse_view, pixel_directions, pixel_solid_angles

    v = parse_view(view)
    d, inside = pixel_directions(v, 401, 401)
    omega = pixel_solid_angles(v, 401, 401)
    assert np.all(omega >= 0)
    front = inside & (d[..., 2] > 0)
    got = omega[front].sum() if v.kind == "a" and v.horizontal == 180 else omega.sum()
    if v.kind == "a" and v.horizontal < 180:
        got = omega[inside & (np.degrees(np.arccos(np.clip(d[..., 2], -1, 1))) <= v.horizontal / 2)].sum()
    assert got == pytest.approx(expected, rel=2e-3)


def test_uniform_sky_gives_pi_l():
    """A uniform luminance L over the hemisphere in front gives Ev = pi L exactly."""
    from derender.photometry.illuminance import vertical_illuminance
    from derender.photometry.projection import parse_view

    rad = np.full((300, 300, 3), 100.0 / 179.0)
    res = vertical_illuminance(rad, parse_view("-vta -vh 180 -vv 180"))
    assert res.ev == pytest.approx(np.pi * 100.0, rel=1e-4)


def _scene(h=240, w=240):
    y, x = np.mgrid[0:h, 0:w]
    lum = 0.05 + 3 * (x / w) ** 2 + 50 * np.exp(-((x - 0.66 * w) ** 2 + (y - 0.27 * h) ** 2) / (0.0022 * w * h))
    return (lum[..., None] * np.ones(3)).astype(np.float32)


@pytest.mark.parametrize("view, tol", [("-vta -vh 180 -vv 180", 1e-4), ("-vth -vh 180 -vv 180", 1e-2)])
def test_illuminance_agrees_with_evalglare(tmp_path, capsys, view, tol):
    """``derender illuminance`` on a map written by derender, against ``evalglare -V`` on the
    same file: the angular fisheye to 1e-4, the hemispherical one within 1 % (its rim
    pixels, where the projection compresses, are weighed differently)."""
    from derender.io.rgbe import write_hdr

    write_hdr(tmp_path / "m.hdr", _scene(), view=view)
    # evalglare prints Ev and exits with 1 after its low-brightness notices: read what it prints
    run = subprocess.run([str(radiance_bin("evalglare")), "-V", str(tmp_path / "m.hdr")], capture_output=True,
                         text=True)
    ref = float(run.stdout.split()[0])
    code, out, err = run_cli(["illuminance", tmp_path / "m.hdr", "--json"], capsys)
    assert code == 0, err
    import json

    got = json.loads(out)["ev_lx"]
    assert got == pytest.approx(ref, rel=tol)


def test_illuminance_sd_matches_monte_carlo():
    from derender.photometry.illuminance import vertical_illuminance
    from derender.photometry.projection import parse_view

    v = parse_view("-vta -vh 180 -vv 180")
    mean = _scene(64, 64).astype(np.float64)
    var = (0.1 * mean) ** 2
    res = vertical_illuminance(mean, v, variance=var)
    rng = np.random.default_rng(0)
    draws = [vertical_illuminance(mean + rng.normal(size=mean.shape) * np.sqrt(var), v).ev for _ in range(300)]
    assert np.std(draws) == pytest.approx(res.ev_sd, rel=0.15)
    assert np.mean(draws) == pytest.approx(res.ev, rel=0.01)


def test_luminance_weights_of_the_primaries():
    from derender.photometry.illuminance import RADIANCE_LUMINANCE_WEIGHTS, luminance_weights

    np.testing.assert_allclose(luminance_weights("0.640 0.330 0.300 0.600 0.150 0.060 0.3127 0.3290"),
                               [0.2126, 0.7152, 0.0722], atol=2e-4)
    # Radiance's standard primaries (color.h: CIE_x_r .640 ... white 1/3) give its own row
    np.testing.assert_allclose(luminance_weights("0.640 0.330 0.290 0.600 0.150 0.060 0.3333 0.3333"),
                               RADIANCE_LUMINANCE_WEIGHTS, atol=2e-3)


def test_illuminance_errors(tmp_path, capsys):
    from derender.io.exr import write_exr

    write_exr(tmp_path / "m.exr", _scene(32, 32))
    for args, needle in ((["illuminance", tmp_path / "m.exr"], "--view"),
                         (["illuminance", tmp_path / "m.exr", "--view", "-vtq -vh 10"], "not supported"),
                         (["illuminance", tmp_path / "m.exr", "--view", "-vtv -vh 200 -vv 30"], "(0, 180)")):
        code, out, err = run_cli(args, capsys)
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], err
