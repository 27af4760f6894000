"""engine.overlap: merging bands while a writer thread writes them; the compiled colour bitmap (issue 17)."""

from __future__ import annotations

import numpy as np
import pytest

from derender.engine.overlap import RowsDone, merge_writing


def test_writer_reads_only_finished_rows():
    h = 1000
    out = np.full(h, -1)
    seen = []

    def band(y0, y1):
        out[y0:y1] = np.arange(y0, y1)

    def write(res, done: RowsDone):
        for y0 in range(0, h, 16):
            y1 = min(h, y0 + 16)
            done.wait(y1)
            seen.append(res[y0:y1].copy())

    merge_writing(h, 160, band, out, write)
    np.testing.assert_array_equal(np.concatenate(seen), np.arange(h))


def test_errors_of_either_side_are_raised():
    def bad_band(y0, y1):
        if y0 >= 100:
            raise ValueError("merge broke")

    def write(res, done):
        done.wait(1000)

    with pytest.raises(ValueError, match="merge broke"):
        merge_writing(1000, 50, bad_band, None, write)

    def bad_write(res, done):
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        merge_writing(1000, 50, lambda a, b: None, None, bad_write)


def test_mark_colours_held_equals_the_builder():
    from derender.derendering.apply import ColourIndexBuilder
    from derender.engine.gaussian import mark_colours_held

    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (5, 37, 23, 3), dtype=np.uint8)
    frames[:, :, :5] //= 17                       # repeated colours too
    a = ColourIndexBuilder()
    for f in frames:
        a.add(f)
    for threads in (1, 2, 3):
        b = ColourIndexBuilder()
        assert mark_colours_held(frames, b.present, threads)
        np.testing.assert_array_equal(a.finish().packed, b.finish().packed)
    assert not mark_colours_held(frames[:, :, ::2], ColourIndexBuilder().present)   # not contiguous: caller falls back
