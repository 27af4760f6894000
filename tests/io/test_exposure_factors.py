"""Brackets that vary aperture and ISO as well as time: a frame's exposure is t S / N^2.

Oracle: the same simulated 8-bit codes written twice, once labelled with the true times at a
fixed aperture and ISO, once with other times, f-numbers and ISO speeds that give the same
exposure ``t S / N^2``; both must read as the same relative exposures and merge to the same map.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli, write_exif_jpeg


def _two_labellings(tmp_path):
    from derender.camera import simulate_bracket

    b = simulate_bracket(size=(96, 64), exposures=5, pipeline="fixed", seed=5)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    apertures = [5.6, 16.0, 2.8, 8.0, 4.0]
    isos = [100, 400, 100, 200, 800]
    a, c = [], []
    for j, (codes, t) in enumerate(zip(b.jpeg_codes, b.times)):
        a.append(write_exif_jpeg(tmp_path / "a" / f"{j:02d}.jpg", codes, float(t), 5.6, 100))
        # the same exposure t S / N^2 as frame j at f/5.6 and ISO 100
        t_label = float(t) * (apertures[j] / 5.6) ** 2 * (100 / isos[j])
        c.append(write_exif_jpeg(tmp_path / "b" / f"{j:02d}.jpg", codes, t_label, apertures[j], isos[j]))
    return b, a, c


def test_relative_exposure_from_time_aperture_and_iso(tmp_path):
    from derender.io.exif import file_times

    b, a, c = _two_labellings(tmp_path)
    np.testing.assert_allclose(file_times(a), b.times, rtol=1e-6)
    np.testing.assert_allclose(file_times(c), b.times, rtol=1e-6)


@pytest.mark.parametrize("method", ["debevec", "stabilized"])
def test_aperture_and_iso_bracket_merges_like_the_time_bracket(tmp_path, capsys, method):
    b, a, c = _two_labellings(tmp_path)
    for name, files in (("a", a), ("b", c)):
        code, _, err = run_cli(["merge", *files, "-o", tmp_path / f"{name}.exr", "--method", method], capsys)
        assert code == 0, err
    from derender.io.exr import read_exr

    np.testing.assert_allclose(read_exr(tmp_path / "b.exr"), read_exr(tmp_path / "a.exr"), rtol=1e-4, atol=1e-7)


def test_varying_aperture_without_exif_everywhere_is_an_error(tmp_path, capsys):
    b, a, c = _two_labellings(tmp_path)
    from PIL import Image

    with Image.open(c[2]) as im:                      # frame 2 loses its EXIF f-number and ISO
        ex = im.getexif()
        sub = ex.get_ifd(0x8769)
        del sub[0x829D]
        im.save(tmp_path / "b" / "02x.jpg", format="JPEG", quality=95, exif=ex.tobytes())
    c[2].unlink()
    files = sorted((tmp_path / "b").glob("*.jpg"))
    code, _, err = run_cli(["merge", *files, "-o", tmp_path / "o.exr"], capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and "f-number varies" in lines[0] and "02x.jpg" in lines[0]
    assert not (tmp_path / "o.exr").exists()
