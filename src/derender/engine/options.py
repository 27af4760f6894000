"""The settings of a merge that are not the method's: where its outputs go, and how the engine runs.

Two small frozen records, each checked when it is made (before any file is read), and built
once where the user's input is parsed (``derender merge``, or a caller of
:func:`derender.hdr.files.merge_files`):

* :class:`OutputOptions`: the OpenEXR files of the radiance and its variance, half floats,
  compression, and whether the merged maps stay in memory;
* :class:`EngineOptions`: decoding and merging threads, the frames a two-pass stream keeps,
  the bracket a streamed method holds whole, the largest frame accepted.

The method's own options travel in the method's record (:mod:`derender.hdr.registry`), the
reference frame, alignment and ghost removal in
:class:`~derender.engine.motion.run.MotionOptions`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from derender.core.errors import InputError
from derender.io.exr import EXR_COMPRESSION
from derender.io.headers import DEFAULT_MAX_MEGAPIXELS

__all__ = ["OutputOptions", "EngineOptions", "HOLD_BYTES", "KEEP_BYTES"]

#: Default budget of a streamed method's held frames (8-bit codes of the whole bracket):
#: within it every frame is decoded once and merged by a compiled kernel (13 frames of
#: 24 MP); above it the frames stream in two passes (memory independent of their number).
HOLD_BYTES = 1 << 30

#: Default budget of the frames a two-pass stream keeps between its passes.
KEEP_BYTES = 256 << 20

@dataclass(frozen=True, kw_only=True)
class OutputOptions:
    """Where a merge writes its maps (OpenEXR, atomically, never over an input).

    Attributes
    ----------
    output, variance_output : path-like or None
        The radiance's and (methods that give one) the variance's ``.exr`` file; None: not written.
    half : bool
        Half floats instead of float32.
    compression : {"zip", "none"}
        The EXR compression.
    hold_outputs : bool
        False (with ``output``): the outputs may go from the merge straight into the files
        through band buffers, never held whole; the result's ``radiance`` and ``variance``
        are then None (``info["outputs_held"]`` False).

    Examples
    --------
    >>> from derender.engine.options import OutputOptions
    >>> OutputOptions(output="hdr.exr", half=True).half
    True
    >>> try:
    ...     OutputOptions(output="hdr.png")
    ... except Exception as error:
    ...     print(error)
    output must end in .exr, got hdr.png
    """

    output: str | os.PathLike | None = None
    variance_output: str | os.PathLike | None = None
    half: bool = False
    compression: str = "zip"
    hold_outputs: bool = True

    def __post_init__(self) -> None:
        for path in (self.output, self.variance_output):
            if path is not None and Path(path).suffix.lower() != ".exr":
                raise InputError(f"output must end in .exr, got {Path(path).name}")
        if self.compression not in EXR_COMPRESSION:
            raise InputError(f"compression must be one of {', '.join(EXR_COMPRESSION)}, got {self.compression!r}")

    @property
    def held(self) -> bool:
        """Whether the merged maps stay in memory (always, without an ``output`` file)."""
        return self.hold_outputs or self.output is None


@dataclass(frozen=True, kw_only=True)
class EngineOptions:
    """How the engine runs a merge of files (the numbers never depend on these).

    Attributes
    ----------
    threads : int or None
        Decoding and merging threads (None: every usable CPU).
    keep_frames : int or None
        The frames a two-pass stream keeps between its passes (None: as many as fit in
        ``keep_bytes``; given: the method streams in two passes).
    keep_bytes : int
        That budget in bytes.
    hold_bytes : int
        The largest bracket of codes a streamed method holds whole (decoded once).
    max_megapixels : float or None
        The largest frame accepted, read from the header (None: no limit).

    Examples
    --------
    >>> from derender.engine.options import EngineOptions
    >>> EngineOptions(threads=2).keep_frames is None
    True
    """

    threads: int | None = None
    keep_frames: int | None = None
    keep_bytes: int = KEEP_BYTES
    hold_bytes: int = HOLD_BYTES
    max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS

    def __post_init__(self) -> None:
        for name in ("threads", "keep_frames"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or int(value) != value or value < 1):
                raise InputError(f"{name} must be a positive whole number, got {value!r}")
        for name in ("keep_bytes", "hold_bytes"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be a number of bytes (0 or more), got {getattr(self, name)!r}")
        if self.max_megapixels is not None and not self.max_megapixels > 0:
            raise InputError(f"max_megapixels must be positive, got {self.max_megapixels:g}")
