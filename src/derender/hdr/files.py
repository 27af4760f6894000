"""Merging image files: the product path of ``derender merge``.

:func:`merge_files` reads the exposure times without decoding, sorts the frames and runs
the method on the engine (:func:`derender.engine.run.run`, or
:func:`derender.engine.motion.run.run_motion` when a reference frame, alignment or ghost removal
is asked for: the choice is made here): the method's
:class:`~derender.engine.plans.EngineMethod` (registered with it, see
:func:`derender.hdr.registry.register_method`) says whether the frames stream (Debevec,
Robertson: two passes, a few frames held) or are held once as 8-bit codes (paper 1's and
paper 2's methods). Inputs the engine cannot take (16-bit files, warped alignment,
raw-space de-rendering models, methods without an engine form) are read into memory
(:func:`derender.io.images.read_stack`) and merged by :func:`derender.hdr.registry.merge`
on the float reference engine. ``info["engine_path"]`` says which ran.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult, check_brightness_order
from derender.engine.frames import FileFrames, NotStreamable
from derender.engine.outputs import write_outputs
from derender.engine.run import run
from derender.hdr.registry import merge, method_options, method_spec
from derender.hdr.summary import attach_summary
from derender.io.exif import file_times
from derender.io.headers import DEFAULT_MAX_MEGAPIXELS

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


def _merge_raw_paths(spec, paths, times, times_file, times_file_inverse, output, variance_output, half, inputs,
                     threads, compression, t_start, options) -> HDRResult:
    """:func:`merge_files` for a bracket of RAW files: the method's own file path (no engine yet)."""
    from derender.hdr.registry import MOTION_OPTIONS
    from derender.io.exif import read_times_file

    asked = [k for k in MOTION_OPTIONS if options.get(k) not in (None, False)]
    if asked:
        raise InputError(f"--{asked[0].replace('_', '-')} is not available on RAW brackets yet (the RAW merge runs "
                         "outside the engine); merge without it")
    options = {k: v for k, v in options.items() if k not in MOTION_OPTIONS and k != "seed"}
    if variance_output is not None:
        options["variance"] = True
    method_options(spec.name, options)
    all_inputs = list(paths) + list(inputs) + ([Path(times_file)] if times_file else [])
    for out in (output, variance_output):
        if out is not None:
            from derender.io.files import check_not_input

            if Path(out).suffix.lower() != ".exr":
                raise InputError(f"output must end in .exr, got {Path(out).name}")
            check_not_input(out, all_inputs)
    if times is None and times_file is not None:
        table = read_times_file(times_file, inverse=times_file_inverse)
        missing = [Path(p).name for p in paths if Path(p).name not in table]
        if missing:
            raise InputError(f"times file {times_file} has no entry for: {', '.join(missing)}")
        times = [table[Path(p).name] for p in paths]
    res = spec.files_function()(paths, times, output=output, variance_output=variance_output, half=half,
                               compression=compression, inputs=all_inputs, threads=threads, **options)
    res.info.setdefault("outputs_held", True)
    if times is None:                     # the times the merge read from the files, as given
        by_name = dict(zip(res.info.get("frames", []), res.info.get("exposure_times", [])))
        times = [float(by_name.get(Path(p).name, 0.0)) for p in paths]
    attach_summary(res, paths, times, spec.name, (output, variance_output))   # one record for the CLI, files, report
    res.info["total_seconds"] = time.perf_counter() - t_start
    return res


def merge_files(paths: Sequence[str | os.PathLike], times: Sequence[float] | None = None,
                method: str = "debevec", *, times_file: str | os.PathLike | None = None,
                times_file_inverse: bool = False, output: str | os.PathLike | None = None,
                variance_output: str | os.PathLike | None = None, half: bool = False,
                inputs: Iterable[str | os.PathLike] = (), threads: int | None = None, keep_frames: int | None = None,
                keep_bytes: int = 256 << 20, compression: str = "zip",
                max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS, hold_outputs: bool = True,
                **options: Any) -> HDRResult:
    """Merge image files into a radiance map; optionally write ``output`` (and ``variance_output``), .exr.

    Every file's header is read before any pixel (:func:`derender.io.headers.probe_images`):
    truncated files, sizes above ``max_megapixels`` and stacks that need more memory than is
    available are refused first. Methods with an engine form run on the engine
    (:func:`derender.engine.run.run`: 8-bit frames decoded in threads, streamed or held);
    others read the stack into memory and call :func:`derender.hdr.registry.merge`. The
    result equals ``merge(read_stack(paths), method, ...)``.

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
    times_file, times_file_inverse
        A text file of times (one per image), or of ``1/t`` with ``times_file_inverse``.
    output, variance_output : path-like, optional
        OpenEXR files for the radiance and (methods that give one) its variance, written
        atomically; ``half`` stores half floats, ``compression`` names the EXR compression.
    inputs : iterable of path-like
        Further input files the outputs must not overwrite.
    threads, keep_frames, keep_bytes
        The engine's decoding threads, and the frames a streamed method keeps between its
        two passes (default: as many as fit in ``keep_bytes``).
    max_megapixels : float or None
        The largest frame accepted (None: no limit).
    hold_outputs : bool
        False (with ``output``): the outputs may go from the merge straight into the files
        through band buffers, never held whole; the result's ``radiance`` and ``variance``
        are then None (``info["outputs_held"]`` False).
    **options
        The method's own options (as :func:`derender.hdr.registry.merge` takes them), and the
        engine's ``reference`` (an index among ``paths`` as given, from 0, or ``"auto"``),
        ``align``, ``deghost``, ``ghost_threshold``, ``ghost_fill``, ``ghost_consensus``
        (:func:`derender.hdr.registry.split_motion`, :mod:`derender.engine.motion`).

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
    >>> radiance = np.geomspace(0.01, 1.0, 16 * 16).reshape(16, 16, 1).repeat(3, axis=2)   # 100:1
    >>> times = np.array([0.25, 1.0, 4.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     paths = [derender.write_png(os.path.join(folder, f"{i}.png"), frame.astype(np.uint8))
    ...              for i, frame in enumerate(codes)]
    ...     result = derender.merge_files(paths, times, "debevec", output=os.path.join(folder, "hdr.exr"))
    ...     written = derender.read_exr(os.path.join(folder, "hdr.exr"))
    >>> result.radiance.shape, bool(np.array_equal(written, result.radiance))
    ((16, 16, 3), True)
    >>> bool(abs(result.radiance[15, 15, 1] / result.radiance[0, 0, 1] / 100 - 1) < 0.02)
    True
    """
    t_start = time.perf_counter()
    from derender.io.files import expand_image_paths

    spec = method_spec(method)   # an unknown method is an error before any file is read
    paths = expand_image_paths(paths, raw=spec.inputs == "raw")
    raw_paths = check_raw_bracket(paths, method)
    if raw_paths:
        return _merge_raw_paths(spec, paths, times, times_file, times_file_inverse, output, variance_output, half,
                                inputs, threads, compression, t_start, options)
    t = file_times(paths, times, times_file, times_file_inverse)
    all_inputs = list(paths) + list(inputs) + ([Path(times_file)] if times_file else [])
    for out in (output, variance_output):
        if out is not None:
            from derender.io.files import check_not_input

            if Path(out).suffix.lower() != ".exr":
                raise InputError(f"output must end in .exr, got {Path(out).name}")
            check_not_input(out, all_inputs)
    seed = options.pop("seed", 0)   # every caller may pass one; only methods that take a seed get it
    if variance_output is not None and spec.has_option("variance"):
        options["variance"] = True   # the classic and stabilised merges compute a variance only when asked
    from derender.hdr.registry import split_motion

    motion, options = split_motion(method, {**options, "seed": seed}, engine_reference=True)
    options.pop("seed", None)
    if spec.has_option("seed"):
        options["seed"] = seed
    opts = method_options(method, options)
    if times is not None:
        hint = "check the order of the times (one per image, in the order the images are given)"
    elif times_file is not None:
        hint = ("did you mean --times-inverse? (the file may list 1/t)" if not times_file_inverse else
                "the file may list times, not 1/t: drop --times-inverse?")
    else:
        hint = "the EXIF exposure times disagree with the images; give the times with --times"
    res = None
    factory = spec.engine_factory()
    on_reference = getattr(opts, "engine", "auto") == "reference"
    if motion is not None and (factory is None or on_reference):
        raise InputError(f"merge method {method!r} with these options runs outside the engine: reference, "
                         "align and deghost need the engine")
    if factory is not None and not on_reference:
        try:
            engine_method = factory(opts)
            source = FileFrames(paths, t, max_megapixels)
            if motion is None:           # the plain run
                res = run(engine_method, source, threads=threads, keep_frames=keep_frames, keep_bytes=keep_bytes,
                          output=output, variance_output=variance_output, half=half, compression=compression,
                          inputs=all_inputs, order_hint=hint, hold_outputs=hold_outputs or output is None)
            else:                        # reference frame, alignment, ghost removal: the motion run
                from derender.engine.motion.run import run_motion

                res = run_motion(engine_method, source, motion, threads=threads, order_hint=hint, output=output,
                                 variance_output=variance_output, half=half, compression=compression,
                                 inputs=all_inputs)
        except NotStreamable as exc:
            if motion is not None:
                raise InputError(f"merge method {method!r} cannot align or remove ghosts on these images "
                                 f"({exc})") from None
            res = None
    if res is None:
        from derender.io.images import read_stack

        stack = read_stack(paths, times=t, max_megapixels=max_megapixels)
        names = [paths[i].name for i in np.argsort(t, kind="stable")]
        check_brightness_order(stack.times, [255.0 * float(im[::8, ::8].mean()) for im in stack.images],
                               names, hint)
        res = merge(stack, method=method, **options)        # options carry the seed when the method takes one
        shortest = stack.images[int(np.argmin(stack.times))]
        res.info["n_clipped"] = int(np.count_nonzero(np.any(shortest >= 1.0, axis=-1)))   # as the engine counts
        res.info.setdefault("engine", "stack")
        res.info["engine_path"] = "stack"
        write_outputs(res, output, variance_output, half=half, compression=compression, inputs=all_inputs,
                      threads=threads, name=method)
    res.info.setdefault("outputs_held", True)
    attach_summary(res, paths, t, method, (output, variance_output))    # one record for the CLI, files, report
    res.info["total_seconds"] = time.perf_counter() - t_start
    return res
