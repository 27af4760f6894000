"""HEIC/HEIF and AVIF brackets (the iPhone's default format) and folders as image arguments.

The HEIC and AVIF files are made in the test from a simulated bracket's JPEGs (libheif /
libavif encoders shipped with pillow-heif and Pillow), with EXIF exposure time, camera and
orientation, so every stage is checked against a known answer: the times and camera read
back, the pixels against the JPEG they were encoded from, and the merged radiance against
the merge of the JPEGs themselves and against the simulator's exact radiance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli

#: pillow-heif's lossless RGB encoding (no YCbCr, no chroma subsampling): the codes round-trip.
_LOSSLESS = dict(quality=-1, chroma=444, matrix_coefficients=0)


def _simulated(tmp_path: Path) -> tuple[list[Path], Path]:
    from derender.camera import bracket_paths, simulate_bracket, write_bracket

    write_bracket(simulate_bracket(size=(96, 64), exposures=5, pipeline="fixed", seed=3), tmp_path / "sim")
    jpegs = bracket_paths(tmp_path / "sim", "jpeg")
    return jpegs, tmp_path / "sim" / "truth.exr"


def _convert(jpegs: list[Path], folder: Path, suffix: str, orientation: int = 1, **save) -> list[Path]:
    """Re-encode each JPEG as ``suffix`` with EXIF ExposureTime/Make/Model; with an
    ``orientation`` other than 1 the pixels are stored rotated and the tag says how to undo it."""
    from derender.io.exif import read_exif
    from derender.io.headers import pillow_image

    Image = pillow_image()
    folder.mkdir()
    out = []
    for p in jpegs:
        t = read_exif(p)["ExposureTime"]
        with Image.open(p) as im:
            im = im.convert("RGB")
            if orientation == 6:   # displayed = stored rotated 90 degrees clockwise: store it rotated back
                im = im.transpose(Image.Transpose.ROTATE_90)
            ex = Image.Exif()
            ex[0x010F], ex[0x0110], ex[0x0112] = "Apple", "iPhone 12", orientation
            ex.get_ifd(0x8769)[0x829A] = t
            q = folder / (p.stem + suffix)
            im.save(q, exif=ex.tobytes(), **save)
        out.append(q)
    return out


def test_heic_bracket_reads_times_camera_and_pixels(tmp_path):
    from derender.io.exif import read_exif
    from derender.io.headers import probe_image
    from derender.io.images import read_codes

    jpegs, _ = _simulated(tmp_path)
    heics = _convert(jpegs, tmp_path / "heic", ".HEIC", orientation=6, **_LOSSLESS)
    for j, h in zip(jpegs, heics):
        exif = read_exif(h)
        assert exif["ExposureTime"] == pytest.approx(read_exif(j)["ExposureTime"], rel=1e-6)
        assert exif["Model"] == "iPhone 12"
        info = probe_image(h)
        assert (info.format, info.width, info.height) == ("heif", 96, 64)
        a, b = read_codes(j).astype(int), read_codes(h).astype(int)
        assert a.shape == b.shape == (64, 96, 3)          # upright, as the JPEG
        np.testing.assert_array_equal(a, b)            # lossless RGB HEIC: the JPEG's codes exactly


def test_avif_orientation_applied(tmp_path):
    from derender.io.images import read_codes

    jpegs, _ = _simulated(tmp_path)
    avifs = _convert(jpegs[:2], tmp_path / "avif", ".avif", orientation=6, quality=100)
    a, b = read_codes(jpegs[0]).astype(int), read_codes(avifs[0]).astype(int)
    assert b.shape == a.shape
    assert np.abs(a - b).mean() < 3.0


def test_folder_of_heic_merges_like_the_jpegs(tmp_path, capsys):
    from derender.evaluation.metrics import hdr_scores
    from derender.io.rgbe import read_radiance

    jpegs, truth = _simulated(tmp_path)
    _convert(jpegs, tmp_path / "heic", ".heic", **_LOSSLESS)
    code, _, err = run_cli(["merge", tmp_path / "heic", "-o", tmp_path / "h.exr"], capsys)
    assert code == 0, err
    code, _, err = run_cli(["merge", *jpegs, "-o", tmp_path / "j.exr"], capsys)
    assert code == 0, err
    t = read_radiance(truth)
    h, j = read_radiance(tmp_path / "h.exr"), read_radiance(tmp_path / "j.exr")
    assert np.isfinite(h).all() and h.min() >= 0
    sh, sj = hdr_scores(h, t), hdr_scores(j, t)
    np.testing.assert_array_equal(h, j)                 # the same codes, the same times: the same map
    assert sh["L"] == sj["L"] and sh["L"] > 35.0


def test_folder_of_jpegs_is_expanded(tmp_path, capsys):
    jpegs, _ = _simulated(tmp_path)
    # the simulator's folder (images in jpeg/) and the jpeg/ folder itself give the file list's result
    for arg in (tmp_path / "sim", tmp_path / "sim" / "jpeg"):
        out = tmp_path / f"{arg.name}.exr"
        code, _, err = run_cli(["merge", arg, "-o", out, "--method", "stabilized"], capsys)
        assert code == 0, err
    code, _, err = run_cli(["merge", *jpegs, "-o", tmp_path / "files.exr", "--method", "stabilized"], capsys)
    assert code == 0, err
    from derender.io.rgbe import read_radiance

    ref = read_radiance(tmp_path / "files.exr")
    for name in ("sim.exr", "jpeg.exr"):
        np.testing.assert_array_equal(read_radiance(tmp_path / name), ref)


def test_folder_without_images_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "notes.txt").write_text("no images here")
    code, out, err = run_cli(["merge", tmp_path / "photos", "-o", tmp_path / "o.exr"], capsys)
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: folder") and "holds no images" in lines[0]
    assert ".heic" in lines[0]
    assert not (tmp_path / "o.exr").exists()


def test_damaged_heic_is_one_error_line(tmp_path, capsys):
    jpegs, _ = _simulated(tmp_path)
    heics = _convert(jpegs[:3], tmp_path / "heic", ".heic", quality=90)
    data = heics[1].read_bytes()
    heics[1].write_bytes(data[: len(data) // 2])
    code, out, err = run_cli(["merge", *heics, "-o", tmp_path / "o.exr"], capsys)
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "01.heic" in lines[0]
    assert not (tmp_path / "o.exr").exists()


@pytest.mark.parametrize("suffix", [".heic", ".avif"])
def test_damaged_heic_and_avif_are_errors_not_crashes(tmp_path, suffix):
    """Truncated and byte-flipped files (seeded): every read returns an upright 8-bit image or
    raises InputError naming the file; libheif / libavif never take the process down (measured
    by hand in subprocesses first: 0 crashes in 40 + 40)."""
    from derender.core.errors import InputError
    from derender.io.headers import pillow_image
    from derender.io.images import read_codes

    rng = np.random.default_rng(7)
    codes = (rng.random((40, 56, 3)) * 255).astype(np.uint8)
    src = tmp_path / f"src{suffix}"
    pillow_image().fromarray(codes).save(src, quality=80)
    data = src.read_bytes()
    outcomes = {"ok": 0, "error": 0}
    for i in range(24):
        b = bytearray(data)
        if i % 2 == 0:
            b = b[: int(rng.integers(8, len(b)))]
        else:
            for _ in range(6):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
        p = tmp_path / f"d{i}{suffix}"
        p.write_bytes(bytes(b))
        try:
            img = read_codes(p)
        except InputError as exc:
            assert p.name in str(exc)
            outcomes["error"] += 1
        else:
            assert img.dtype == np.uint8 and img.shape == (40, 56, 3)
            outcomes["ok"] += 1
    assert outcomes["error"] >= 10          # the truncations at least are refused
