"""Outputs written straight from band buffers (engine.overlap.OutputRing): same files, no whole arrays."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from helpers import write_png_codes

from derender.camera import simulate_bracket
from derender.engine.options import OutputOptions
from derender.engine.overlap import OutputRing


@pytest.fixture(scope="module")
def tall_bracket(tmp_path_factory):
    """5 frames of 700 x 400 px: five 160-row bands, so the ring's 3 slots are reused."""
    d = tmp_path_factory.mktemp("ring")
    b = simulate_bracket(size=(100, 175), exposures=5, pipeline="auto", style="simple", seed=1)
    paths = [write_png_codes(d / f"f{j}.png", np.repeat(np.repeat(b.jpeg_codes[j], 4, axis=0), 4, axis=1))
             for j in range(5)]
    return paths, [float(t) for t in b.times]


@pytest.mark.parametrize("method,half", [("debevec", False), ("robertson", False), ("stabilized", False),
                                         ("stabilized-joint", False), ("stabilized", True)])
def test_ring_writes_the_same_file_without_holding_the_radiance(tall_bracket, tmp_path, monkeypatch, method, half):
    import derender.engine.run as run_mod
    from derender.hdr.files import merge_files

    monkeypatch.setattr(run_mod, "KERNEL_MIN_PIXEL_FRAMES", 0)     # the compiled kernels at test size
    paths, times = tall_bracket
    held = merge_files(paths, times, method, output=OutputOptions(output=tmp_path / "held.exr", half=half))
    ring = merge_files(paths, times, method, output=OutputOptions(output=tmp_path / "ring.exr", hold_outputs=False,
                                                                  half=half))
    assert held.info["outputs_held"] and held.radiance.shape == (700, 400, 3)
    assert not ring.info["outputs_held"] and ring.radiance is None and ring.variance is None
    assert (tmp_path / "held.exr").read_bytes() == (tmp_path / "ring.exr").read_bytes()
    assert np.array_equal(held.mask, ring.mask)


def test_ring_slots_wait_for_every_writer_and_a_failure_releases_them():
    ring = OutputRing(h=100, w=4, step=10, make=lambda: (np.zeros((3, 10, 4), np.float32),), writers=2, slots=3)
    assert ring.wait_free(0) and ring.wait_free(20)            # the first three bands have their own slots
    (a,), row0 = ring.slot(30)
    assert row0 == 30 and a is ring.slot(0)[0][0]             # band 3 reuses band 0's slot ...
    started = threading.Event()
    got: list = []

    def merge() -> None:
        started.set()
        got.append(ring.wait_free(30))                       # ... once both writers read rows 0:10

    th = threading.Thread(target=merge)
    th.start()
    started.wait()
    ring.read(0, 10)
    th.join(0.2)
    assert th.is_alive()                                      # one writer is not enough
    ring.read(1, 16)
    th.join(5)
    assert got == [True]
    th = threading.Thread(target=lambda: got.append(ring.wait_free(60)))
    th.start()
    ring.fail()
    th.join(5)
    assert got == [True, False]
    # rows crossing a band boundary come from two slots
    ring2 = OutputRing(h=40, w=2, step=10, make=lambda: (np.zeros((3, 10, 2), np.float32),), slots=4)
    for y0 in range(0, 40, 10):
        (a,), r0 = ring2.slot(y0)
        a[:] = np.arange(y0, y0 + 10)[None, :, None]
    pieces = list(ring2.segments(0, 6, 23))
    assert [(ya, yb) for ya, yb, _ in pieces] == [(6, 10), (10, 20), (20, 23)]
    assert np.array_equal(np.concatenate([v[:, 0, 0] for _, _, v in pieces]), np.arange(6, 23))


def test_a_failing_writer_stops_the_ring_merge_with_its_error(tall_bracket, tmp_path, monkeypatch):
    """The writer dies after its first rows: the merge, waiting for free slots, stops and raises
    the writer's error (no hang), and nothing is left behind."""
    import derender.engine.run as run_mod
    import derender.io.exr as exr
    from derender.hdr.files import merge_files

    monkeypatch.setattr(run_mod, "KERNEL_MIN_PIXEL_FRAMES", 0)
    real = exr.write_exr_lines

    def failing(path, width, height, lines, **kw):
        def lines_then_fail(y0, y1, buf):
            if y0 >= 32:
                raise OSError(28, "No space left on device")
            lines(y0, y1, buf)
        return real(path, width, height, lines_then_fail, **kw)

    monkeypatch.setattr(exr, "write_exr_lines", failing)
    paths, times = tall_bracket
    result: list = []

    def go() -> None:
        try:
            merge_files(paths, times, "stabilized", output=OutputOptions(output=tmp_path / "x.exr", hold_outputs=False))
        except OSError as exc:
            result.append(exc)

    th = threading.Thread(target=go)
    th.start()
    th.join(60)
    assert not th.is_alive(), "the merge hung after its writer failed"
    assert result and "No space left" in str(result[0])
    assert list(tmp_path.iterdir()) == []
