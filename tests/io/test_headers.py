"""Image headers read before decoding (io.headers) and the one strict decoder (io.images.decode_image).

Oracles: Pillow's header parser for sizes and ``ImageOps.exif_transpose`` for orientation
(a peer implementation of the EXIF rule); the bytes of real files for truncation.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from conftest import require_shared
from PIL import Image, ImageOps

from derender.core.errors import InputError
from derender.io.headers import jpeg_header, orient, probe_image, probe_images
from derender.io.images import decode_image, read_codes, read_image


def _jpeg(path, codes, orientation=None, quality=95):
    im = Image.fromarray(codes)
    kwargs = {"quality": quality}
    if orientation is not None:
        ex = Image.Exif()
        ex[0x0112] = orientation
        kwargs["exif"] = ex
    im.save(path, **kwargs)
    return path


def _codes(h=24, w=36, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x * 255 // w, y * 255 // h, (x + y) * 127 // (w + h)], -1)
    return np.clip(base + rng.integers(-3, 4, base.shape), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_orientation_matches_pillow(tmp_path, orientation):
    p = _jpeg(tmp_path / f"o{orientation}.jpg", _codes(), orientation)
    info = probe_image(p)
    want = np.asarray(ImageOps.exif_transpose(Image.open(p)).convert("RGB"))
    assert info.orientation == orientation and (info.height, info.width) == want.shape[:2]
    got = read_codes(p)
    np.testing.assert_array_equal(got, want)
    img, depth = read_image(p)
    assert depth == 8 and np.array_equal(np.rint(img * 255).astype(np.uint8), want)
    # the engine's buffer reuse gives the same upright frame
    buf = np.zeros_like(want)
    assert np.array_equal(read_codes(p, out=buf), want)


def test_orient_is_the_inverse_of_storing_rotated():
    a = np.arange(12).reshape(3, 4)
    assert np.array_equal(orient(a, 6), np.rot90(a, -1))   # 6: rotate 90 degrees clockwise to display
    assert np.array_equal(orient(a, 8), np.rot90(a, 1))
    assert np.array_equal(orient(a, 3), np.rot90(a, 2))


def test_real_phone_bracket_is_upright():
    d = require_shared("iphone6-bracket")
    info = probe_image(d / "1.JPG")
    assert info.orientation == 6 and (info.width, info.height) == (2448, 3264)
    with Image.open(d / "1.JPG") as im:
        assert im.size == (3264, 2448)   # stored sideways


def test_sizes_agree_with_pillow(tmp_path):
    codes = _codes(17, 29)
    _jpeg(tmp_path / "a.jpg", codes)
    Image.fromarray(codes).save(tmp_path / "a.png")
    Image.fromarray(codes).save(tmp_path / "a.tif")
    for name in ("a.jpg", "a.png", "a.tif"):
        info = probe_image(tmp_path / name)
        assert (info.width, info.height, info.bit_depth) == (29, 17, 8), name


def test_truncated_files_are_refused(tmp_path):
    for name in ("a.jpg", "a.png"):
        full = tmp_path / name
        if name.endswith("jpg"):
            _jpeg(full, _codes(64, 96), quality=100)
        else:
            Image.fromarray(_codes(64, 96)).save(full)
        data = full.read_bytes()
        for cut in (len(data) // 2, len(data) - 3):
            bad = tmp_path / f"cut{cut}{full.suffix}"
            bad.write_bytes(data[:cut])
            with pytest.raises(InputError, match="truncated|not a readable"):
                decode_image(bad)
        assert decode_image(full).shape == (64, 96, 3)


def test_truncated_real_jpeg_is_refused(tmp_path):
    d = require_shared("colour-hdri-frobisher")
    data = (d / "IMG_2601.jpg").read_bytes()
    bad = tmp_path / "half.jpg"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated"):
        read_codes(bad)
    with pytest.raises(InputError, match="truncated"):
        read_image(bad)


def test_forged_sizes_are_refused_before_decoding(tmp_path):
    import cv2

    ok, enc = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))
    b = bytearray(enc.tobytes())
    b[16:24] = struct.pack(">II", 100000, 100000)
    b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])))
    (tmp_path / "f.png").write_bytes(bytes(b))
    ok, enc = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    b = bytearray(enc.tobytes())
    i = b.find(b"\xff\xc0")
    b[i + 5:i + 9] = struct.pack(">HH", 65000, 65000)
    (tmp_path / "f.jpg").write_bytes(bytes(b))
    for name in ("f.png", "f.jpg"):
        with pytest.raises(InputError, match="MP limit"):
            probe_image(tmp_path / name)
        # a raised limit still cannot get past the size the file's bytes can hold
        with pytest.raises(InputError, match="corrupt image"):
            decode_image(tmp_path / name, max_megapixels=None)


def test_budget_and_sizes_of_a_stack(tmp_path):
    _jpeg(tmp_path / "a.jpg", _codes(20, 30))
    _jpeg(tmp_path / "b.jpg", _codes(20, 31))
    with pytest.raises(InputError, match="differ in size"):
        probe_images([tmp_path / "a.jpg", tmp_path / "b.jpg"])
    with pytest.raises(InputError, match="MP limit"):
        probe_image(tmp_path / "a.jpg", max_megapixels=0.0001)


def test_jpeg_header_rejects_garbage():
    with pytest.raises(ValueError):
        jpeg_header(b"\xff\xd8\xff\xe0\x00")
    with pytest.raises(ValueError):
        jpeg_header(b"not a jpeg")


@pytest.mark.parametrize("what,needle", [("dir", "is a folder"), ("loop", "symbolic link loop"),
                                         ("dangling", "broken symbolic link"), ("missing", "no such file")])
def test_input_paths_named_accurately(tmp_path, what, needle):
    p = tmp_path / "x.jpg"
    if what == "dir":
        p.mkdir()
    elif what == "loop":
        p.symlink_to(p)
    elif what == "dangling":
        p.symlink_to(tmp_path / "nowhere.jpg")
    with pytest.raises(InputError, match=needle):
        probe_image(p)
