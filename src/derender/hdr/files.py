"""Merging image files: the product path of ``derender merge``.

:func:`merge_files` checks every record (the method's options, the motion, the outputs, the
engine's settings) before any file is read, reads the exposure times without decoding, and
hands the frames to the registry (:func:`derender.hdr.registry.run_engine`), which chooses the
engine's plain run, its motion run, or none: the method's
:class:`~derender.engine.plans.EngineMethod` says whether the frames stream (Debevec,
Robertson: two passes, a few frames held) or are held once as 8-bit codes (paper 1's and
paper 2's methods). Inputs the engine cannot take (16-bit files, raw-space de-rendering
models, methods without an engine form) are read into memory
(:func:`derender.io.images.read_stack`) and merged on the float reference engine
(:func:`derender.hdr.registry.merge_stack`). ``info["engine_path"]`` says which ran. RAW
brackets go to the RAW method's own file path (:func:`derender.hdr.raw.merge_raw_files`).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult, check_brightness_order
from derender.engine.frames import FileFrames
from derender.engine.motion.run import MotionOptions
from derender.engine.options import EngineOptions, OutputOptions
from derender.engine.outputs import write_outputs
from derender.hdr.registry import merge_stack, method_options, method_spec, run_engine
from derender.hdr.summary import attach_summary
from derender.io.exif import file_times

__all__ = ["merge_files", "check_raw_bracket"]


def check_raw_bracket(paths: Sequence[Path], method: str) -> bool:
    """Whether the bracket is of RAW files (:data:`derender.io.files.RAW_SUFFIXES`); one error line
    when it mixes RAW and rendered frames, or when the method does not take the kind given."""
    from derender.io.files import RAW_SUFFIXES

    raw = [p for p in paths if Path(p).suffix.lower() in RAW_SUFFIXES]
    spec = method_spec(method)
    if raw and len(raw) != len(paths):
        other = next(p for p in paths if Path(p).suffix.lower() not in RAW_SUFFIXES)
        raise InputError(f"the bracket mixes RAW and rendered frames ({Path(raw[0]).name}, {Path(other).name}); "
                         "merge each kind on its own")
    if raw and spec.inputs != "raw":
        raise InputError(f"{Path(raw[0]).name} is a RAW file: merge RAW brackets with --method raw "
                         f"(method {method!r} merges rendered images)")
    if not raw and spec.inputs == "raw":
        raise InputError(f"method {method!r} merges RAW files (DNG, CR2, NEF, ...); {Path(paths[0]).name} is not one")
    return bool(raw)


def _raw_files(spec, paths: list, times, record, motion, out: OutputOptions, engine: EngineOptions, *,
               inputs: list, times_file, times_file_inverse: bool) -> tuple[HDRResult, list]:
    """:func:`merge_files` for a bracket of RAW files: the method's own file path (``spec.files``,
    which decides what it does with ``motion``). Returns the result and the exposure times."""
    from derender.io.exif import read_times_file

    if times is None and times_file is not None:
        table = read_times_file(times_file, inverse=times_file_inverse)
        missing = [Path(p).name for p in paths if Path(p).name not in table]
        if missing:
            raise InputError(f"times file {times_file} has no entry for: {', '.join(missing)}")
        times = [table[Path(p).name] for p in paths]
    res = spec.files_function()(paths, times, record, motion, out, engine, inputs=inputs)
    if times is None:                     # the times the merge read from the files, as given
        by_name = dict(zip(res.info.get("frames", []), res.info.get("exposure_times", [])))
        times = [float(by_name.get(Path(p).name, 0.0)) for p in paths]
    return res, times


def _order_hint(times, times_file, times_file_inverse: bool) -> str:
    """What the brightness-order error suggests, from where the times came."""
    if times is not None:
        return "check the order of the times (one per image, in the order the images are given)"
    if times_file is not None:
        return ("did you mean --times-inverse? (the file may list 1/t)" if not times_file_inverse else
                "the file may list times, not 1/t: drop --times-inverse?")
    return "the EXIF exposure times disagree with the images; give the times with --times"


def _merge_stack_of_files(spec, paths: list, t, record, out: OutputOptions, engine: EngineOptions, *,
                          inputs: list, hint: str) -> HDRResult:
    """What :func:`derender.hdr.registry.run_engine` leaves to :func:`merge_files`: the images read
    into memory (their brightness order checked) and merged on the float reference engine, the
    outputs written."""
    from derender.io.images import read_stack

    stack = read_stack(paths, times=t, max_megapixels=engine.max_megapixels)
    names = [paths[i].name for i in np.argsort(t, kind="stable")]
    check_brightness_order(stack.times, [255.0 * float(im[::8, ::8].mean()) for im in stack.images], names, hint)
    res = merge_stack(spec, stack, record)
    shortest = stack.images[int(np.argmin(stack.times))]
    res.info["n_clipped"] = int(np.count_nonzero(np.any(shortest >= 1.0, axis=-1)))   # as the engine counts
    res.info.setdefault("engine", "stack")
    write_outputs(res, out.output, out.variance_output, half=out.half, compression=out.compression, inputs=inputs,
                  threads=engine.threads, name=spec.name)
    return res


def _records(spec, options, motion, output, engine) -> tuple:
    """The merge's records, each checked once: the method's options (with ``variance`` when a
    variance file is asked for), the motion, the outputs, the engine's settings."""
    for value, cls, name in ((motion, MotionOptions, "motion"), (output, OutputOptions, "output"),
                             (engine, EngineOptions, "engine")):
        if value is not None and not isinstance(value, cls):
            raise InputError(f"{name} must be a {cls.__name__}, got {type(value).__name__}")
    out, engine = output or OutputOptions(), engine or EngineOptions()
    record = method_options(spec.name, options)
    if out.variance_output is not None and spec.has_option("variance") and not record.variance:
        record = dataclasses.replace(record, variance=True)   # the classic and stabilised merges compute it when asked
    return record, out, engine


def merge_files(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
                method: str = "debevec", options: Any = None, *, motion: MotionOptions | None = None,
                output: OutputOptions | None = None, engine: EngineOptions | None = None,
                times_file: str | os.PathLike | None = None, times_file_inverse: bool = False,
                inputs: Iterable[str | os.PathLike] = ()) -> HDRResult:
    """Merge image files into a radiance map; optionally write the OpenEXR files of ``output``.

    Every file's header is read before any pixel (:func:`derender.io.headers.probe_images`):
    truncated files, sizes above ``engine.max_megapixels`` and stacks that need more memory
    than is available are refused first. Methods with an engine form run on the engine
    (:func:`derender.hdr.registry.run_engine`: 8-bit frames decoded in threads, streamed or
    held; the motion run when ``motion`` asks); others read the stack into memory and merge
    it on the float reference engine. The result equals
    ``merge(read_stack(paths), method, options, motion=motion)``.

    Parameters
    ----------
    paths : sequence of path-like
        The bracket's images (JPEG, PNG, TIFF, HEIC, AVIF); a folder stands for the images in
        it (:func:`derender.io.files.expand_image_paths`).
    times : sequence of float, optional
        Exposure times in seconds, in the order of ``paths``; else ``times_file``, else EXIF
        (``t S / N^2`` relative to the first frame when aperture or ISO vary).
    method : str
        A name of :data:`~derender.hdr.registry.METHODS`.
    options : options record or mapping, optional
        The method's own options (as :func:`derender.hdr.registry.merge` takes them).
    motion : MotionOptions, optional
        The engine's reference frame (an index among ``paths`` as given, from 0, or
        ``"auto"``), alignment and ghost removal
        (:class:`~derender.engine.motion.run.MotionOptions`).
    output : OutputOptions, optional
        OpenEXR files for the radiance and (methods that give one) its variance, written
        atomically, half floats, compression, and whether the maps stay in memory
        (:class:`~derender.engine.options.OutputOptions`). None: nothing written.
    engine : EngineOptions, optional
        Threads, the frames a streamed method keeps, the largest frame accepted
        (:class:`~derender.engine.options.EngineOptions`).
    times_file, times_file_inverse
        A text file of times (one per image), or of ``1/t`` with ``times_file_inverse``.
    inputs : iterable of path-like
        Further input files the outputs must not overwrite.

    Returns
    -------
    HDRResult
        As :func:`derender.hdr.registry.merge`; the radiance may be an (H, W, 3) view of
        planar float32 memory.

    Raises
    ------
    InputError
        Unreadable or inconsistent files, times that disagree with the images' brightness,
        an output that would overwrite an input, an unknown method or option.

    Examples
    --------
    Three PNG exposures of a 100:1 ramp merged into an OpenEXR file:

    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> from derender.engine.options import OutputOptions
    >>> radiance = np.geomspace(0.01, 1.0, 16 * 16).reshape(16, 16, 1).repeat(3, axis=2)   # 100:1
    >>> times = np.array([0.25, 1.0, 4.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     paths = [derender.write_png(os.path.join(folder, f"{i}.png"), frame.astype(np.uint8))
    ...              for i, frame in enumerate(codes)]
    ...     result = derender.merge_files(paths, times, "debevec",
    ...                                   output=OutputOptions(output=os.path.join(folder, "hdr.exr")))
    ...     written = derender.read_exr(os.path.join(folder, "hdr.exr"))
    >>> result.radiance.shape, bool(np.array_equal(written, result.radiance))
    ((16, 16, 3), True)
    >>> bool(abs(result.radiance[15, 15, 1] / result.radiance[0, 0, 1] / 100 - 1) < 0.02)
    True
    """
    t_start = time.perf_counter()
    from derender.io.files import check_not_input, expand_image_paths

    spec = method_spec(method)   # an unknown method, or a bad option, is an error before any file is read
    record, out, engine = _records(spec, options, motion, output, engine)
    paths = expand_image_paths(paths, raw=spec.inputs == "raw")
    raw = check_raw_bracket(paths, method)
    t = None if raw else file_times(paths, times, times_file, times_file_inverse)
    all_inputs = list(paths) + list(inputs) + ([Path(times_file)] if times_file else [])
    for path in (out.output, out.variance_output):
        if path is not None:
            check_not_input(path, all_inputs)
    if raw:
        res, t = _raw_files(spec, paths, times, record, motion, out, engine, inputs=all_inputs, times_file=times_file,
                            times_file_inverse=times_file_inverse)
    else:                 # the engine (plain or motion run: the registry chooses), else the float reference engine
        hint = _order_hint(times, times_file, times_file_inverse)
        res = run_engine(spec, record, motion, FileFrames(paths, t, engine.max_megapixels), out, engine,
                         inputs=all_inputs, order_hint=hint)
        if res is None:
            res = _merge_stack_of_files(spec, paths, t, record, out, engine, inputs=all_inputs, hint=hint)
    res.info.setdefault("outputs_held", True)
    attach_summary(res, paths, t, method, (out.output, out.variance_output))    # one record for the CLI, files, report
    res.info["total_seconds"] = time.perf_counter() - t_start
    return res
