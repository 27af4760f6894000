"""Compiled and OpenCV shortcuts (derender.engine.kernels, ward2003.grey8_codes and _half) against their NumPy definitions."""

import numpy as np
import pytest
from helpers import write_png_codes

from derender.engine.motion.ward2003 import _half, grey8_codes, to_grey8
from derender.engine.options import EngineOptions
from derender.hdr.files import merge_files as merge_files_fast


def test_grey8_codes_equal_rint_of_ward_weights_for_every_colour():
    """All 2^24 colours, in chunks: round half to even exactly as np.rint of the float32 sum."""
    codes = np.arange(1 << 24, dtype=np.uint32)
    for c0 in range(0, codes.size, 1 << 22):
        c = codes[c0:c0 + (1 << 22)]
        rgb = np.stack([(c >> 16) & 255, (c >> 8) & 255, c & 255], axis=-1).astype(np.uint8).reshape(-1, 1024, 3)
        f = rgb.astype(np.float32)
        expect = np.clip(np.rint((np.float32(54) * f[..., 0] + np.float32(183) * f[..., 1]
                                  + np.float32(19) * f[..., 2]) / np.float32(256)), 0, 255).astype(np.uint8)
        np.testing.assert_array_equal(grey8_codes(rgb), expect)


def test_to_grey8_same_bytes_for_codes_and_floats():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    np.testing.assert_array_equal(to_grey8(rgb), to_grey8(rgb.astype(np.float32) / np.float32(255)))


@pytest.mark.parametrize("shape", [(2, 2), (7, 9), (64, 33), (301, 480)])
def test_half_equals_box_average(shape):
    rng = np.random.default_rng(shape[0])
    g = rng.integers(0, 256, shape, dtype=np.uint8)
    h, w = shape[0] // 2 * 2, shape[1] // 2 * 2
    u = g[:h, :w].astype(np.uint16)
    expect = ((u[0::2, 0::2] + u[1::2, 0::2] + u[0::2, 1::2] + u[1::2, 1::2] + 2) // 4).astype(np.uint8)
    np.testing.assert_array_equal(_half(g), expect)
    np.testing.assert_array_equal(_half(np.asfortranarray(g)), expect)     # any memory layout


def test_stabilized_merge_bytes_do_not_depend_on_threads(tmp_path):
    from derender.camera import simulate_bracket

    b = simulate_bracket(kind="outdoor", size=(96, 64), exposures=5, seed=2)
    paths = []
    for j, codes in enumerate(b.jpeg_codes):
        p = tmp_path / f"{j}.png"
        write_png_codes(p, codes)
        paths.append(p)
    one = merge_files_fast(paths, b.times, method="stabilized", engine=EngineOptions(threads=1))
    two = merge_files_fast(paths, b.times, method="stabilized", engine=EngineOptions(threads=2))
    assert one.info["engine_path"] == two.info["engine_path"] == "streaming"
    np.testing.assert_array_equal(one.radiance, two.radiance)
    np.testing.assert_array_equal(one.mask, two.mask)
    assert np.all(np.isfinite(one.radiance))


@pytest.mark.parametrize("percentile,step", [(50.0, 1), (30.0, 3), (80.0, 2)])
def test_compiled_mtb_counts_equal_bitmap_counts(percentile, step):
    """The compiled banded MTB scorer (greys in, packed words) counts exactly what the NumPy
    scorer counts on explicit bitmaps, for every candidate shift (width not a multiple of 64)."""
    import cv2

    from derender.engine.motion import ward2003 as A

    rng = np.random.default_rng(int(percentile))
    h, w = 300, 901
    base = cv2.GaussianBlur(rng.integers(0, 256, (h + 20, w + 20)).astype(np.float64), (0, 0), 3)
    a = np.clip(base[5:5 + h, 7:7 + w] * 1.3, 0, 255).astype(np.uint8)
    b = np.clip(base[8:8 + h, 4:4 + w] + rng.normal(0, 3, (h, w)), 0, 255).astype(np.uint8)
    cands = sorted({(dy, dx) for dy in range(-4, 5) for dx in range(-5, 5)})
    ca, cb = (np.cumsum(np.bincount(g.ravel(), minlength=256)) for g in (a, b))
    ma, mb = A._grey_threshold(a, percentile, ca), A._grey_threshold(b, percentile, cb)
    lazy = [(A._RowBitmaps(a, ma, 4), A._RowBitmaps(b, mb, 4))]
    explicit = [(A.median_threshold_bitmaps(a, 4, percentile, ca), A.median_threshold_bitmaps(b, 4, percentile, cb))]
    got = A._mtb_counts_bands(lazy, cands, step)
    assert got == A._mtb_counts_bands(explicit, cands, step)
    best = min(cands, key=lambda c: got[cands.index(c)][0][0] / max(got[cands.index(c)][0][1], 1))
    assert best == (-3, 3)      # a(y, x) = base(y + 5, x + 7) = b(y - 3, x + 3)


def test_compiled_mtb_counts_with_shifts_across_words():
    """Horizontal shifts of 63-130 px move the packed words by one or two (and bits across
    them): the compiled scorer still counts exactly what the NumPy scorer counts."""
    import cv2

    from derender.engine.motion import ward2003 as A

    rng = np.random.default_rng(7)
    h, w = 96, 301
    a = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.float64), (0, 0), 2).astype(np.uint8)
    b = np.roll(a, 65, axis=1)
    cands = [(dy, dx) for dy in (-1, 0, 1) for dx in (-130, -65, -64, -63, -1, 0, 1, 63, 64, 65, 128)]
    ca, cb = (np.cumsum(np.bincount(g.ravel(), minlength=256)) for g in (a, b))
    ma, mb = A._grey_threshold(a, 50.0, ca), A._grey_threshold(b, 50.0, cb)
    lazy = [(A._RowBitmaps(a, ma, 4), A._RowBitmaps(b, mb, 4))]
    explicit = [(A.median_threshold_bitmaps(a, 4, 50.0, ca), A.median_threshold_bitmaps(b, 4, 50.0, cb))]
    got = A._mtb_counts_bands(lazy, cands, 1)
    assert got == A._mtb_counts_bands(explicit, cands, 1)
    assert got[cands.index((0, 65))][0][0] == 0      # b(y, x + 65) = a(y, x) where both exist
