"""Writing a merge's outputs: the radiance and its variance to OpenEXR, after merging or while merging.

* :func:`write_outputs` -- a result's radiance (and variance) written whole
  (:func:`derender.io.exr.write_exr_fast`, blocks of lines compressed in threads).
* :func:`write_while_merging` -- the writer a compiled merge runs in a thread: each block of
  lines written as soon as the merge has finished it (:class:`~derender.engine.overlap.RowsDone`),
  from the result's arrays or from a ring of band buffers
  (:class:`~derender.engine.overlap.OutputRing`).
* :func:`motion_attributes` -- the header attributes that record what the motion run did
  (reference frame, alignment, ghost removal), read from the result's ``info``.

Both the plain run (:func:`derender.engine.run.run`) and the motion run
(:func:`derender.engine.motion.run.run_motion`) write here, and so does the CLI for results it
changes after merging.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Iterable

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult
from derender.engine.overlap import RowsDone
from derender.io.exr import exr_attributes, write_exr_fast

__all__ = ["write_outputs", "write_while_merging", "motion_attributes"]


def motion_attributes(info: dict) -> dict[str, str]:
    """The EXR header attributes that record the engine's reference frame, alignment and ghost
    removal (``derender:reference``: the frame's name and its place among the images as given,
    from 1; ``derender:alignment``; ``derender:deghost``); empty for a plain merge."""
    if info.get("engine_path") != "motion" and "reference_name" not in info:
        return {}
    out = {}
    if info.get("reference_input") is not None:
        out["derender:reference"] = f"{info.get('reference_name', 'frame')} (image {info['reference_input'] + 1})"
    al = info.get("alignment") or {}
    if al.get("align"):
        out["derender:alignment"] = str(al["align"])
    dg = info.get("deghost")
    if dg:
        out["derender:deghost"] = (f"threshold {dg.get('threshold')}, "
                                   f"{100 * float(dg.get('rejected', 0.0)):.2f} % of the other frames' pixels left out")
    return out


def _write_radiance_while_merging(res: HDRResult, done: RowsDone, output, *, half: bool, compression: str,
                                  inputs, threads: int | None, arr: np.ndarray | None = None, k: int = 0) -> None:
    """:func:`write_outputs`' radiance file (or ``arr``, e.g. the variance), each block of lines
    read once the merge has finished it; from ``done.ring`` (output ``k``: 0 radiance, 1
    variance) when the merge fills band slots instead of whole arrays."""
    from derender.io.exr import write_exr_lines

    ring = done.ring
    if ring is None:
        arr = res.radiance if arr is None else arr
        h, w = arr.shape[:2]
    else:
        h, w = ring.h, ring.w

    def bgr_lines(y0: int, y1: int, buf: np.ndarray) -> None:
        done.wait(y1)
        if ring is None:
            for kk, c in enumerate((2, 1, 0)):  # channels in alphabetical order: B, G, R
                buf[:, kk, :] = arr[y0:y1, :, c]
            return
        for ya, yb, view in ring.segments(k, y0, y1):
            for kk, c in enumerate((2, 1, 0)):
                buf[ya - y0:yb - y0, kk, :] = view[:, :, c]

    write_exr_lines(output, w, h, bgr_lines, half=half, inputs=list(inputs), compression=compression, threads=threads,
                    rows_read=None if ring is None else (lambda y: ring.read(k, y)), attributes=exr_attributes(res.info))


def write_while_merging(res: HDRResult, done: RowsDone, *, output, variance_output, half: bool, compression: str,
                         inputs: list, threads: int | None) -> None:
    """The writer a compiled merge runs in a thread (``write(result, rows_done)``): the radiance
    to ``output`` band by band as rows are done and, when the result has a variance from the
    start (or the ring carries one), the variance to ``variance_output`` in a second thread."""
    tw = time.perf_counter()
    var_thread, var_error = None, []
    has_variance = res.variance is not None or (done.ring is not None and len(done.ring.rows_read) > 1)
    if variance_output is not None and has_variance:
        def write_variance() -> None:
            try:
                _write_radiance_while_merging(res, done, variance_output, half=half, compression=compression,
                                              inputs=inputs + [output], threads=threads, arr=res.variance, k=1)
            except BaseException as exc:  # noqa: BLE001 - re-raised below, after the radiance's writer
                var_error.append(exc)
                if done.ring is not None:
                    done.ring.fail()      # the merge waits for this writer's rows

        var_thread = threading.Thread(target=write_variance, name="derender-exr-variance", daemon=True)
        var_thread.start()
    try:
        _write_radiance_while_merging(res, done, output, half=half, compression=compression, inputs=inputs,
                                      threads=threads)
    finally:
        if var_thread is not None:
            var_thread.join()
    if var_error:
        raise var_error[0]
    if var_thread is not None:
        res.info["overlapped_variance_write"] = True
    res.info.setdefault("timings", {})["write_s"] = time.perf_counter() - tw


def write_outputs(res: HDRResult, output: str | os.PathLike | None = None,
                  variance_output: str | os.PathLike | None = None, *, half: bool = False, compression: str = "zip",
                  inputs: Iterable[str | os.PathLike] = (), threads: int | None = None, name: str = "this method") -> None:
    """Write a result's radiance (and variance) to OpenEXR (:func:`derender.io.exr.write_exr_fast`)."""
    inputs = list(inputs)
    if variance_output is not None and res.variance is None:
        raise InputError(f"method {name!r} gives no variance")
    attributes = {**exr_attributes(res.info), **motion_attributes(res.info)}
    if output is not None:
        tw = time.perf_counter()
        write_exr_fast(output, res.radiance, half=half, inputs=inputs, compression=compression, threads=threads,
                       attributes=attributes)
        res.info.setdefault("timings", {})["write_s"] = time.perf_counter() - tw
    if variance_output is not None:
        write_exr_fast(variance_output, res.variance, half=half, inputs=inputs + ([output] if output else []),
                       compression=compression, threads=threads, attributes=dict(attributes, whiteLuminance=None))
