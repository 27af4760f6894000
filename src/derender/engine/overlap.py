"""Merging and writing at once: a merge produces bands of rows, a writer thread writes the finished ones.

:func:`merge_writing` runs ``band(y0, y1)`` over consecutive bands of a result in the
calling thread and ``write(result, done)`` in a thread meanwhile; the writer reads row
``y`` only after ``done.wait(y + 1)`` (:class:`RowsDone`). The EXR writer
(:func:`derender.io.exr.write_exr_lines`) compresses and writes a band's 16-line blocks
while the next band merges. Bytes are those of merging first and writing after.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

__all__ = ["OVERLAP_ROWS", "RowsDone", "merge_writing", "run_bands"]

#: Rows per band when a merge's output is written while it merges.
OVERLAP_ROWS = 160


class RowsDone:
    """Rows of a result finished so far (a merge producing bands, a writer waiting for them)."""

    def __init__(self) -> None:
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


def merge_writing(h: int, step: int, band: Callable[[int, int], None], result: Any,
                  write: Callable[[Any, RowsDone], None] | None) -> None:
    """``band(y0, y1)`` over rows ``0:h`` in bands of ``step`` (one band without ``write``),
    with ``write(result, done)`` in a thread meanwhile; the writer's error, or the merge's,
    is raised here once both have stopped."""
    done = RowsDone()
    errors: list[BaseException] = []

    def writer() -> None:
        try:
            write(result, done)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    th = None
    if write is not None:
        th = threading.Thread(target=writer, name="derender-exr-writer", daemon=True)
        th.start()
    else:
        step = h
    try:
        for y0 in range(0, h, max(1, step)):
            y1 = min(h, y0 + step)
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
