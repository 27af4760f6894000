"""Tests for derender.io: stacks, EXIF, times, EXR, Radiance HDR, previews, atomic outputs."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import write_png_codes
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from derender.core.errors import InputError, StackError
from derender.core.types import Stack
from derender.io.exif import parse_times, read_times_file
from derender.io.exr import read_exr, write_exr
from derender.io.files import atomic_output
from derender.io.images import read_image, read_stack
from derender.io.preview import write_png, write_preview
from derender.io.raw import read_raw
from derender.io.rgbe import read_hdr


def _codes(seed=0, shape=(12, 16, 3), dtype=np.uint8):
    rng = np.random.default_rng(seed)
    hi = 256 if dtype == np.uint8 else 65536
    return rng.integers(0, hi, size=shape, dtype=np.int64).astype(dtype)


def test_read_image_png_8_and_16_bit(tmp_path):
    c8 = _codes(1)
    c16 = _codes(2, dtype=np.uint16)
    img8, d8 = read_image(write_png_codes(tmp_path / "a.png", c8))
    img16, d16 = read_image(write_png_codes(tmp_path / "b.png", c16))
    assert (d8, d16) == (8, 16)
    assert img8.dtype == np.float32 and img8.shape == (12, 16, 3)
    np.testing.assert_array_equal(np.rint(img8 * 255).astype(np.uint8), c8)
    np.testing.assert_array_equal(np.rint(img16.astype(np.float64) * 65535).astype(np.uint16), c16)


def test_read_image_tiff_grey_and_rgba(tmp_path):
    import tifffile

    grey = _codes(3, shape=(10, 11), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "g.tif", grey)
    img, depth = read_image(tmp_path / "g.tif")
    assert depth == 16 and img.shape == (10, 11, 3)
    np.testing.assert_allclose(img[..., 0], grey / 65535.0, atol=1e-6)
    rgba = np.dstack([_codes(4), np.full((12, 16), 255, np.uint8)])
    tifffile.imwrite(tmp_path / "o.tif", rgba, photometric="rgb", extrasamples=["unassalpha"])
    img, _ = read_image(tmp_path / "o.tif")
    np.testing.assert_array_equal(np.rint(img * 255).astype(np.uint8), rgba[..., :3])
    rgba[0, 0, 3] = 10
    tifffile.imwrite(tmp_path / "t.tif", rgba, photometric="rgb", extrasamples=["unassalpha"])
    with pytest.raises(InputError, match="alpha"):
        read_image(tmp_path / "t.tif")


def test_read_image_errors(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "empty.jpg").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_image(tmp_path / "empty.jpg")
    (tmp_path / "text.png").write_text("hello, not an image")
    with pytest.raises(InputError, match="not a readable image"):
        read_image(tmp_path / "text.png")
    good = write_png_codes(tmp_path / "good.png", _codes(5))
    (tmp_path / "trunc.png").write_bytes(good.read_bytes()[:40])
    with pytest.raises(InputError):
        read_image(tmp_path / "trunc.png")


def test_parse_times_and_times_file(tmp_path):
    assert parse_times("0.01, 1/30 2") == pytest.approx([0.01, 1 / 30, 2.0])
    with pytest.raises(InputError):
        parse_times("0.1,abc")
    with pytest.raises(InputError):
        parse_times("1/0")
    f = tmp_path / "t.txt"
    f.write_text("# comment\na.jpg 0.5\nb.jpg 1/4\n")
    assert read_times_file(f) == {"a.jpg": 0.5, "b.jpg": 0.25}
    assert read_times_file(f, inverse=True) == {"a.jpg": 2.0, "b.jpg": 4.0}
    f.write_text("a.jpg\n")
    with pytest.raises(InputError, match="FILENAME SECONDS"):
        read_times_file(f)
    f.write_text("a.jpg 1\na.jpg 2\n")
    with pytest.raises(InputError, match="twice"):
        read_times_file(f)


def _stack_files(tmp_path, n=3, shape=(8, 10, 3)):
    paths = []
    for i in range(n):
        paths.append(write_png_codes(tmp_path / f"im{i}.png", _codes(10 + i, shape=shape)))
    return paths


def test_read_stack_sorts_by_time(tmp_path):
    paths = _stack_files(tmp_path)
    stack = read_stack(paths, times=[0.4, 0.1, 0.2])
    np.testing.assert_array_equal(stack.times, [0.1, 0.2, 0.4])
    assert [p.split("/")[-1] for p in stack.paths] == ["im1.png", "im2.png", "im0.png"]
    np.testing.assert_array_equal(stack.images[0], read_image(paths[1])[0])
    assert stack.codes().dtype == np.uint8


def test_read_stack_times_file_inverse(tmp_path):
    paths = _stack_files(tmp_path)
    f = tmp_path / "list.txt"
    f.write_text("im0.png 4\nim1.png 2\nim2.png 1\n")
    stack = read_stack(paths, times_file=f, times_file_inverse=True)
    np.testing.assert_allclose(stack.times, [0.25, 0.5, 1.0])


def test_read_stack_errors(tmp_path):
    paths = _stack_files(tmp_path)
    with pytest.raises(InputError, match="EXIF ExposureTime"):
        read_stack(paths)
    with pytest.raises(InputError, match="duplicate"):
        read_stack(paths, times=[0.1, 0.1, 0.2])
    with pytest.raises(InputError, match="3 image"):
        read_stack(paths, times=[0.1, 0.2])
    with pytest.raises(InputError, match="at least two"):
        read_stack(paths[:1], times=[0.1])
    with pytest.raises(InputError, match="twice"):
        read_stack([paths[0], paths[0]], times=[0.1, 0.2])
    other = write_png_codes(tmp_path / "big.png", _codes(1, shape=(9, 10, 3)))
    with pytest.raises(InputError, match="differ in size"):
        read_stack([paths[0], other], times=[0.1, 0.2])
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8garbage")
    with pytest.raises(InputError, match="not a readable image"):
        read_stack([paths[0], bad], times=[0.1, 0.2])
    with pytest.raises(InputError, match="positive"):
        read_stack(paths, times=[0.1, -1, 0.2])
    f = tmp_path / "list.txt"
    f.write_text("im0.png 1\n")
    with pytest.raises(InputError, match="no entry"):
        read_stack(paths, times_file=f)


def test_stack_dataclass_validation():
    imgs = np.zeros((2, 4, 4, 3), np.float32)
    with pytest.raises(StackError):
        Stack(imgs[:1], [0.1])
    with pytest.raises(InputError):
        Stack(imgs[..., :2], [0.1, 0.2])
    with pytest.raises(InputError):
        Stack(imgs, [0.1, np.nan])


def test_exr_round_trip_float_and_half(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.random((7, 9, 3)) * 1e4).astype(np.float32)
    write_exr(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), img)
    write_exr(tmp_path / "h.exr", img / 1e4, half=True)
    np.testing.assert_allclose(read_exr(tmp_path / "h.exr"), img / 1e4, rtol=1e-3, atol=1e-4)
    mono = rng.random((5, 6)).astype(np.float32)
    write_exr(tmp_path / "m.exr", mono)
    np.testing.assert_array_equal(read_exr(tmp_path / "m.exr"), mono)
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError):
        write_exr(tmp_path / "n.exr", bad)
    assert not (tmp_path / "n.exr").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_read_exr_errors(tmp_path):
    (tmp_path / "x.exr").write_text("nope")
    with pytest.raises(InputError, match="OpenEXR"):
        read_exr(tmp_path / "x.exr")


def test_hdr_reader_matches_radiance_pvalue(tmp_path):
    """Radiance's own pvalue defines the decoding (mantissa + 0.5); OpenCV's reader drops the
    0.5 and so stays within half a mantissa step of ours."""
    import cv2
    from radiance_tools import pvalue_pixels

    rng = np.random.default_rng(1)
    img = np.exp(rng.normal(0, 3, size=(20, 40, 3))).astype(np.float32)
    cv2.imwrite(str(tmp_path / "a.hdr"), img[..., ::-1])
    ours = read_hdr(tmp_path / "a.hdr")
    np.testing.assert_allclose(ours, pvalue_pixels(tmp_path / "a.hdr"), rtol=2e-3)   # pvalue prints 4 digits
    ref = cv2.imread(str(tmp_path / "a.hdr"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    step = np.max(ours, axis=-1, keepdims=True) / 128.0                              # one mantissa step, or less
    assert np.all(np.abs(ours - ref) <= 0.5 * step + 1e-12)
    # RGBE shares one exponent per pixel: error is relative to the largest channel
    assert np.all(np.abs(ours - img) <= 0.01 * img.max(axis=-1, keepdims=True))
    # tolerant: a line before the magic number (as in Debevec's memorial.hdr)
    data = (tmp_path / "a.hdr").read_bytes()
    (tmp_path / "b.hdr").write_bytes(b"VIEW= -vtv\n" + data)
    np.testing.assert_allclose(read_hdr(tmp_path / "b.hdr"), ours, rtol=1e-6)
    (tmp_path / "c.hdr").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError):
        read_hdr(tmp_path / "c.hdr")


def test_hdr_writer_read_by_radiance(tmp_path):
    """write_hdr's header and pixels as Radiance's getinfo and pvalue read them."""
    from radiance_tools import getinfo, pvalue_pixels

    from derender.io.rgbe import SRGB_PRIMARIES, write_hdr

    rng = np.random.default_rng(2)
    img = (np.exp(rng.normal(0, 2, size=(30, 50, 1))) * rng.uniform(0.3, 1.0, (30, 50, 3))).astype(np.float32)
    write_hdr(tmp_path / "m.hdr", img, exposure=0.25, view="-vta -vh 180 -vv 180")
    info = getinfo(tmp_path / "m.hdr")
    assert "FORMAT=32-bit_rle_rgbe" in info and "EXPOSURE=0.25" in info
    assert "VIEW= -vta -vh 180 -vv 180" in info
    assert "PRIMARIES= " + " ".join(f"{v:.4f}" for v in SRGB_PRIMARIES) in info
    assert getinfo(tmp_path / "m.hdr", "-d").strip().endswith("-Y 30 +X 50")
    back = pvalue_pixels(tmp_path / "m.hdr")            # -o: EXPOSURE undone, as radiance
    top = img.max(axis=-1, keepdims=True)
    assert np.all(np.abs(back - img) <= top / 128.0)      # RGBE: one shared exponent, 8-bit mantissas
    np.testing.assert_allclose(read_hdr(tmp_path / "m.hdr"), back, rtol=2e-3)
    for bad, needle in ((img * -1.0, "non-negative"), (img.astype(np.float32) * np.inf, "non-negative")):
        with pytest.raises(InputError, match=needle):
            write_hdr(tmp_path / "x.hdr", bad)
    with pytest.raises(InputError, match="view option"):
        write_hdr(tmp_path / "x.hdr", img, view="-vta; rm -rf /")
    assert not (tmp_path / "x.hdr").exists()


@pytest.mark.shared_data
def test_read_memorial_hdr(memorial_dir):
    img = read_hdr(memorial_dir / "memorial.hdr")
    assert img.shape == (768, 512, 3)
    assert np.all(np.isfinite(img)) and img.max() > 100 and img.min() >= 0
    ldr, _ = read_image(memorial_dir / "memorial0066.png")
    # orientation: the bright windows of the PNG are bright in the map
    lum_png = ldr.mean(-1)
    lum_hdr = img.mean(-1)
    assert np.corrcoef(lum_png.ravel(), np.log(lum_hdr.ravel() + 1e-3))[0, 1] > 0.5


@pytest.mark.shared_data
def test_exif_times_of_real_jpegs(frobisher_dir):
    stack = read_stack(sorted(frobisher_dir.glob("*.jpg")))
    np.testing.assert_allclose(stack.times, [1 / 8, 1, 8])
    assert "5D Mark II" in stack.metadata[0]["Model"]


def test_atomic_output_never_overwrites_input(tmp_path):
    src = write_png_codes(tmp_path / "in.png", _codes(0))
    before = src.read_bytes()
    with pytest.raises(InputError, match="overwrite"):
        write_png(src, np.zeros((4, 4, 3)), inputs=[src])
    assert src.read_bytes() == before
    with pytest.raises(RuntimeError):
        with atomic_output(tmp_path / "out.png") as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("boom")
    assert not (tmp_path / "out.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.png"]


def test_preview_is_finite_and_in_range(tmp_path):
    rad = np.exp(np.random.default_rng(0).normal(0, 4, (16, 16, 3))).astype(np.float32)
    write_preview(tmp_path / "p.png", rad)
    img, _ = read_image(tmp_path / "p.png")
    assert img.shape == (16, 16, 3) and 0 <= img.min() and img.max() <= 1
    write_preview(tmp_path / "z.png", np.zeros((4, 4, 3), np.float32))


def test_reinhard_matches_formula():
    from derender.core.colorimetry import luminance
    from derender.io.preview import reinhard_photographic

    rad = np.exp(np.random.default_rng(3).normal(0, 2, (8, 8, 3))).astype(np.float32)
    out = reinhard_photographic(rad, key=0.18)
    lw = luminance(rad.astype(np.float64))
    lbar = np.exp(np.mean(np.log(1e-6 + lw)))
    l = 0.18 * lw / lbar
    lwhite = l.max()
    ld = l * (1 + l / lwhite**2) / (1 + l)
    unclipped = out.max(axis=-1) < 1.0  # channels clipped at display white change luminance
    assert unclipped.mean() > 0.5
    np.testing.assert_allclose(luminance(out.astype(np.float64))[unclipped], ld[unclipped], rtol=2e-3, atol=1e-5)


def test_read_raw_rejects_non_raw(tmp_path):
    (tmp_path / "x.dng").write_bytes(b"II*\x00garbage" * 10)
    with pytest.raises(InputError, match="cannot read RAW"):
        read_raw(tmp_path / "x.dng")
    (tmp_path / "y.cr2").write_text("text")
    with pytest.raises(InputError):
        read_raw(tmp_path / "y.cr2")


@pytest.mark.shared_data
def test_read_real_dng(colorchecker_dng):
    frame = read_raw(colorchecker_dng)
    assert frame.cfa_pattern == "RGGB"
    assert frame.mosaic.shape == (1156, 1734) and frame.mosaic.dtype == np.uint16
    np.testing.assert_array_equal(frame.black_level, 2056)
    assert frame.white_level == 15000
    np.testing.assert_allclose(frame.xyz_to_camera[0], [0.6461, -0.1164, -0.0857], atol=1e-4)
    assert frame.exposure_time is None  # EXIF time is 0 in this file
    assert frame.as_shot_wb[1] == 1.0 and np.all(frame.as_shot_wb > 0)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(min_size=0, max_size=2048))
def test_hostile_bytes_never_crash_readers(tmp_path, data):
    for name in ("h.png", "h.jpg", "h.tif", "h.hdr", "h.exr", "h.dng"):
        p = tmp_path / name
        p.write_bytes(data)
        reader = {".hdr": read_hdr, ".exr": read_exr, ".dng": read_raw}.get(p.suffix, read_image)
        try:
            out = reader(p)
        except InputError:
            continue
        arr = out[0] if isinstance(out, tuple) else getattr(out, "mosaic", out)
        assert np.all(np.isfinite(np.asarray(arr, dtype=np.float64)))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(times=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=0, max_size=5))
def test_hostile_times_give_clear_errors(tmp_path, times):
    paths = _stack_files(tmp_path, n=2, shape=(4, 4, 3))
    try:
        stack = read_stack(paths, times=times)
    except (InputError, StackError):
        return
    assert np.all(np.isfinite(stack.times)) and np.all(np.diff(stack.times) > 0)


def test_srgb8_table_matches_the_power_function_within_a_code():
    """The preview's table encoder agrees with the exact sRGB encoding to within one code
    (rounding boundaries only), exactly at black and white, and is monotone."""
    from derender.io.preview import encode_srgb, encode_srgb8

    x = np.concatenate([np.linspace(0.0, 1.0, 200001, dtype=np.float32),
                        np.random.default_rng(0).random(100000, dtype=np.float32) ** 4])
    exact = np.rint(encode_srgb(x) * 255.0).astype(int)
    fast = encode_srgb8(x).astype(int)
    assert fast.dtype == int and np.abs(fast - exact).max() <= 1
    assert np.mean(fast != exact) < 0.01
    ramp = encode_srgb8(np.linspace(0, 1, 5000, dtype=np.float32)).astype(int)
    assert ramp[0] == 0 and ramp[-1] == 255 and np.all(np.diff(ramp) >= 0)
    assert encode_srgb8(np.array([-1.0, np.float32(2.0)])).tolist() == [0, 255]


def test_merge_writes_radiance_hdr_that_radiance_reads(tmp_path, capsys):
    """``derender merge -o map.hdr --view ...``: the EXR's radiance within RGBE precision as
    Radiance's pvalue reads it, and the view in the header getinfo prints."""
    from helpers import run_cli
    from radiance_tools import getinfo, pvalue_pixels

    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.io.exr import read_exr

    write_bracket(simulate_bracket(size=(64, 48), exposures=3, pipeline="fixed", seed=6), tmp_path / "b")
    ins = bracket_paths(tmp_path / "b", "jpeg")
    code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "m.exr"], capsys)
    assert code == 0, err
    code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "m.hdr", "--view", "-vta -vh 180 -vv 180"], capsys)
    assert code == 0, err
    exr = read_exr(tmp_path / "m.exr")
    back = pvalue_pixels(tmp_path / "m.hdr")
    assert np.all(np.abs(back - exr) <= exr.max(axis=-1, keepdims=True) / 128.0 + 1e-30)
    assert "VIEW= -vta -vh 180 -vv 180" in getinfo(tmp_path / "m.hdr")
    code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "x.exr", "--view", "-vta"], capsys)
    assert code == 2 and err.startswith("error:") and ".hdr" in err and not (tmp_path / "x.exr").exists()
