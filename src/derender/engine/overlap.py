"""Merging and writing at once: a merge produces bands of rows, a writer thread writes the finished ones.

:func:`merge_writing` runs ``band(y0, y1)`` over consecutive bands of a result in the
calling thread and ``write(result, done)`` in a thread meanwhile; the writer reads row
``y`` only after ``done.wait(y + 1)`` (:class:`RowsDone`). The EXR writer
(:func:`derender.io.exr.write_exr_lines`) compresses and writes a band's 16-line blocks
while the next band merges. Bytes are those of merging first and writing after.

With an :class:`OutputRing` the outputs are never held whole: band ``b`` is merged into
slot ``b mod K`` of K band-sized buffers once every writer has read band ``b - K``
(``OutputRing.wait_free``; writers report with ``OutputRing.read``). A 9 x 24 MP merge
that only writes its EXR then needs 3 x 11.5 MB instead of the 288 MB radiance (and as
much again for a variance).
"""

from __future__ import annotations

import threading
from typing import Any, Callable

__all__ = ["OVERLAP_ROWS", "RING_SLOTS", "RowsDone", "OutputRing", "merge_writing", "run_bands"]

#: Rows per band when a merge's output is written while it merges.
OVERLAP_ROWS = 160

#: Band slots of an :class:`OutputRing`: the band being merged, the one being written, one spare.
RING_SLOTS = 3


class RowsDone:
    """Rows of a result finished so far (a merge producing bands, a writer waiting for them);
    ``ring``: the :class:`OutputRing` holding them, or None (the result's own arrays)."""

    def __init__(self, ring: "OutputRing | None" = None) -> None:
        self.ring = ring
        self.rows = 0
        self.failed = False
        self.cv = threading.Condition()

    def advance(self, rows: int) -> None:
        with self.cv:
            self.rows = rows
            self.cv.notify_all()

    def fail(self) -> None:
        with self.cv:
            self.failed = True
            self.cv.notify_all()

    def wait(self, rows: int) -> None:
        with self.cv:
            while self.rows < rows and not self.failed:
                self.cv.wait()
            if self.failed:
                raise RuntimeError("the merge failed")


class OutputRing:
    """Band-sized slots standing in for a merge's whole outputs while they are written.

    ``make()`` gives one slot: a tuple of arrays, each holding ``step`` rows of one output
    (planar ``(3, step, W)`` with ``planar``, else ``(step, W, 3)``). The merge of the band
    starting at row ``y0`` waits for :meth:`wait_free`, then writes rows ``y0:y0 + step`` into
    :meth:`slot` ``(y0)`` at row offset ``y0``; ``writers`` readers (one per output file)
    read them back through :meth:`segments` and report with :meth:`read`."""

    def __init__(self, h: int, w: int, step: int, make: Callable[[], tuple], writers: int = 1,
                 slots: int = RING_SLOTS, planar: bool = True):
        self.h, self.w, self.step, self.planar = int(h), int(w), max(1, int(step)), bool(planar)
        self.slots = [make() for _ in range(max(2, int(slots)))]
        self.rows_read = [0] * max(1, int(writers))
        self.failed = False
        self.cv = threading.Condition()

    def slot(self, y0: int) -> tuple[tuple, int]:
        """The arrays of the band starting at row ``y0`` and the row they start at."""
        b = y0 // self.step
        return self.slots[b % len(self.slots)], b * self.step

    def wait_free(self, y0: int) -> bool:
        """Block until the slot of the band starting at ``y0`` has been read by every writer;
        False if a writer failed meanwhile."""
        need = (y0 // self.step - len(self.slots) + 1) * self.step
        with self.cv:
            while need > 0 and min(self.rows_read) < need and not self.failed:
                self.cv.wait()
            return not self.failed

    def read(self, writer: int, rows: int) -> None:
        """Writer ``writer`` has read rows ``0:rows``."""
        with self.cv:
            self.rows_read[writer] = max(self.rows_read[writer], int(rows))
            self.cv.notify_all()

    def fail(self) -> None:
        with self.cv:
            self.failed = True
            self.cv.notify_all()

    def segments(self, k: int, y0: int, y1: int):
        """Rows ``y0:y1`` of output ``k`` as ``(ya, yb, view)`` pieces, one per band they
        cross; ``view`` is ``(yb - ya, W, 3)``."""
        y = y0
        while y < y1:
            arrays, row0 = self.slot(y)
            yb = min(y1, row0 + self.step)
            a = arrays[k]
            view = a[:, y - row0:yb - row0, :].transpose(1, 2, 0) if self.planar else a[y - row0:yb - row0]
            yield y, yb, view
            y = yb


def merge_writing(h: int, step: int, band: Callable[[int, int], None], result: Any,
                  write: Callable[[Any, RowsDone], None] | None, ring: OutputRing | None = None) -> None:
    """``band(y0, y1)`` over rows ``0:h`` in bands of ``step`` (one band without ``write``),
    with ``write(result, done)`` in a thread meanwhile; the writer's error, or the merge's,
    is raised here once both have stopped. With ``ring`` (its ``step`` the same) a band
    starts once its slot is free."""
    done = RowsDone(ring)
    errors: list[BaseException] = []
    if ring is not None and (write is None or ring.step != step):
        raise ValueError("an output ring needs a writer and the bands' step")

    def writer() -> None:
        try:
            write(result, done)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)
            if ring is not None:
                ring.fail()

    th = None
    if write is not None:
        th = threading.Thread(target=writer, name="derender-exr-writer", daemon=True)
        th.start()
    else:
        step = h
    try:
        for y0 in range(0, h, max(1, step)):
            y1 = min(h, y0 + step)
            if ring is not None and not ring.wait_free(y0):
                break                      # the writer failed: its error is raised below
            band(y0, y1)
            done.advance(y1)
            if errors:
                break
    except BaseException:
        done.fail()
        raise
    finally:
        if th is not None:
            th.join()
    if errors:
        raise errors[0]


def run_bands(executor: Any, nthreads: int, fn: Callable[[int, int], None], bands: list[tuple[int, int]]) -> None:
    """``fn(y0, y1)`` for every band: on ``executor``'s threads when there are several threads
    and bands, otherwise in order on the calling thread (errors are raised either way)."""
    if nthreads > 1 and len(bands) > 1:
        list(executor.map(lambda b: fn(*b), bands))
    else:
        for b in bands:
            fn(*b)
