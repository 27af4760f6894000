"""Small dataclasses passed between pipeline stages.

:class:`Stack` holds a bracket of rendered (8/16-bit) images as float32 in [0, 1];
:class:`RawFrame` one RAW mosaic with the metadata needed to linearise and colour it;
:class:`HDRResult` the output of every merge method.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from derender.core.errors import InputError, StackError

__all__ = [
    "validate_times",
    "Stack",
    "RawFrame",
    "HDRResult",
]


def validate_times(times: Any, n_images: int) -> np.ndarray:
    """Check exposure times: one per image, finite, positive, distinct.

    Returns them as a float64 array (seconds). Raises :class:`InputError` otherwise.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.size != n_images:
        raise InputError(f"{t.size} exposure time(s) given for {n_images} image(s)")
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise InputError(f"exposure times must be positive finite seconds, got {t.tolist()}")
    uniq, counts = np.unique(t, return_counts=True)
    if np.any(counts > 1):
        dup = ", ".join(f"{v:g}" for v in uniq[counts > 1])
        raise InputError(f"duplicate exposure time(s): {dup} s; every exposure needs its own time")
    return t


def check_brightness_order(times: Any, brightness: Any, names: list[str] | None = None, hint: str = "") -> None:
    """Refuse a bracket whose images get darker as the exposure time grows.

    ``times`` (s) and ``brightness`` (the mean 8-bit code of each image) in the same
    order. The images whose brightness is informative (mean code in (2, 253): not all
    black, not all clipped) must not be ordered against their times: with the times
    sorted, more neighbouring pairs that get darker by over 2 codes than pairs that get
    brighter means the times are in the wrong order or inverted (a list of ``1/t``).
    Camera gain changes between exposures cannot cause it in a bracket whose gain changes
    are smaller than its steps. Raises :class:`InputError` naming the first offending
    pair, followed by ``hint``.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    b = np.asarray(brightness, dtype=np.float64).reshape(-1)
    order = np.argsort(t, kind="stable")
    keep = [int(i) for i in order if 2.0 < b[i] < 253.0]
    if len(keep) < 2:
        return
    d = np.diff(b[keep])
    darker, brighter = int(np.sum(d < -2.0)), int(np.sum(d > 2.0))
    if darker == 0 or darker <= brighter:
        return
    k = int(np.flatnonzero(d < -2.0)[0])
    i, j = keep[k], keep[k + 1]

    def label(m: int) -> str:
        return names[m] if names else f"image {m}"

    raise InputError(f"exposure times contradict the images: {label(i)} ({t[i]:.6g} s) is brighter than {label(j)} "
                     f"({t[j]:.6g} s, mean code {b[i]:.0f} vs {b[j]:.0f})" + (f"; {hint}" if hint else ""))


@dataclass
class Stack:
    """A bracketed exposure stack of rendered images, sorted by exposure time.

    Attributes
    ----------
    images : numpy.ndarray
        (N, H, W, 3) float32, code values divided by the maximum code (255 or 65535).
    times : numpy.ndarray
        (N,) float64 exposure times in seconds, strictly increasing.
    bit_depth : int
        8 or 16 for files; 0 when built from float arrays.
    paths : tuple of str
        Source file per image ("" for in-memory images).
    metadata : tuple of dict
        Per-image dict (camera make/model, EXIF fields found, ...).

    Raises
    ------
    InputError
        Images not of shape (N, H, W, 3), or exposure times that are missing, not positive,
        not finite or repeated.
    StackError
        Fewer than two images.

    Examples
    --------
    Two exposures of an 8x8 grey ramp through a gamma-2.2 camera, given longest first (the
    stack sorts them):

    >>> import numpy as np
    >>> import derender
    >>> radiance = np.linspace(0.05, 1.0, 64).reshape(8, 8, 1).repeat(3, axis=2)
    >>> times = np.array([1.0, 0.25])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> stack = derender.Stack((codes / 255).astype(np.float32), times)
    >>> stack.n, stack.shape, stack.times.tolist()
    (2, (8, 8), [0.25, 1.0])
    >>> stack.codes().dtype, int(stack.codes().max())
    (dtype('uint8'), 255)
    """

    images: np.ndarray
    times: np.ndarray
    bit_depth: int = 8
    paths: tuple[str, ...] = ()
    metadata: tuple[dict, ...] = ()

    def __post_init__(self) -> None:
        imgs = np.asarray(self.images)
        if imgs.ndim != 4 or imgs.shape[-1] != 3:
            raise InputError(f"a stack needs images of shape (N, H, W, 3), got {imgs.shape}")
        if imgs.shape[0] < 2:
            raise StackError("an exposure stack needs at least two images")
        self.images = np.ascontiguousarray(imgs, dtype=np.float32)
        t = validate_times(self.times, imgs.shape[0])
        order = np.argsort(t, kind="stable")
        if np.any(order != np.arange(t.size)):
            self.images = np.ascontiguousarray(self.images[order])
            if self.paths:
                self.paths = tuple(self.paths[i] for i in order)
            if self.metadata:
                self.metadata = tuple(self.metadata[i] for i in order)
        self.times = t[order]
        if not self.paths:
            self.paths = ("",) * self.n
        if not self.metadata:
            self.metadata = tuple({} for _ in range(self.n))

    @property
    def n(self) -> int:
        """Number of exposures."""
        return int(self.images.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of every image."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    @property
    def max_code(self) -> int:
        """Largest code value of the source files (255 for 8-bit)."""
        return 65535 if self.bit_depth == 16 else 255

    def codes(self) -> np.ndarray:
        """Integer code values (uint8 for 8-bit stacks, else uint16), shape (N, H, W, 3)."""
        dtype = np.uint16 if self.bit_depth == 16 else np.uint8
        return np.rint(np.clip(self.images, 0.0, 1.0) * self.max_code).astype(dtype)


@dataclass
class RawFrame:
    """One RAW (Bayer) frame and the metadata to turn it into linear colour.

    Attributes
    ----------
    mosaic : numpy.ndarray
        (H, W) uint16 sensor values (visible area).
    cfa_pattern : str
        4-letter Bayer pattern of the top-left 2x2 block, e.g. ``"RGGB"``.
    black_level : numpy.ndarray
        Per-CFA-position black level, (2, 2) float in mosaic layout.
    white_level : float
        Saturation value (sensor counts).
    as_shot_wb : numpy.ndarray
        (3,) white-balance multipliers for R, G, B (G = 1) as shot.
    xyz_to_camera : numpy.ndarray or None
        (3, 3) matrix mapping CIE XYZ to camera RGB (DNG ColorMatrix semantics, before any
        normalisation) or None when the file has none.
    exposure_time : float or None
        Seconds, or None when unknown.
    path, make, model : str
        Source file, camera make and model ("" when unknown).
    extra : dict
        Other metadata of the file.

    Examples
    --------
    A 4x4 RGGB mosaic with a black level of 64 and a white level of 1088:

    >>> import numpy as np
    >>> import derender
    >>> frame = derender.RawFrame(
    ...     mosaic=np.full((4, 4), 576, np.uint16), cfa_pattern="RGGB",
    ...     black_level=np.full((2, 2), 64.0), white_level=1088.0,
    ...     as_shot_wb=np.array([2.0, 1.0, 1.5]), xyz_to_camera=None, exposure_time=0.01)
    >>> frame.cfa_channel_index()[:2, :2].tolist()
    [[0, 1], [1, 2]]
    >>> round(float(frame.normalised()[0, 0]), 3)
    0.5
    """

    mosaic: np.ndarray
    cfa_pattern: str
    black_level: np.ndarray
    white_level: float
    as_shot_wb: np.ndarray
    xyz_to_camera: np.ndarray | None
    exposure_time: float | None = None
    path: str = ""
    make: str = ""
    model: str = ""
    extra: dict = field(default_factory=dict)

    def cfa_channel_index(self) -> np.ndarray:
        """(H, W) int array: 0 for R, 1 for G, 2 for B at every photosite."""
        lut = {"R": 0, "G": 1, "B": 2}
        tile = np.array([[lut[self.cfa_pattern[0]], lut[self.cfa_pattern[1]]],
                         [lut[self.cfa_pattern[2]], lut[self.cfa_pattern[3]]]])
        h, w = self.mosaic.shape
        return np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]

    def black_level_map(self) -> np.ndarray:
        """(H, W) float32 black level at every photosite."""
        h, w = self.mosaic.shape
        bl = np.asarray(self.black_level, dtype=np.float32).reshape(2, 2)
        return np.tile(bl, ((h + 1) // 2, (w + 1) // 2))[:h, :w]

    def normalised(self) -> np.ndarray:
        """(H, W) float32 ``(mosaic - black) / (white - black)`` (not clipped)."""
        bl = self.black_level_map()
        return (self.mosaic.astype(np.float32) - bl) / (np.float32(self.white_level) - bl)


@dataclass
class HDRResult:
    """Output of a merge.

    Attributes
    ----------
    radiance : numpy.ndarray
        (H, W, 3) float32 linear radiance (relative units), finite everywhere; None when a
        file merge wrote it without holding it (``merge_files(..., output=OutputOptions(..., hold_outputs=False))``).
    mask : numpy.ndarray
        (H, W) uint8, 0 = well exposed somewhere, 1 = taken from the shortest exposure
        (over-exposed everywhere), 2 = from the longest (under-exposed); the class
        constants ``MASK_OK``, ``MASK_BRIGHT``, ``MASK_DARK`` name them.
    variance : numpy.ndarray or None
        (H, W, 3) float32 per-pixel variance of ``radiance`` (probabilistic methods), else None
        (also when written without being held, as ``radiance``).
    info : dict
        Free-form details (curves, gammas, matrices, reference index, timings).
    ghosts : numpy.ndarray or None
        (H, W) uint8, how many frames did not take part at each pixel with their own codes
        because they disagreed with the reference frame (ghost removal: left out, or replaced by
        their motion-compensated view) or did not cover it after alignment; None
        when the engine neither aligned nor removed ghosts (:mod:`derender.engine.motion`).
    plan : object or None
        The engine's plan the map was merged with (:mod:`derender.engine.plans`: how each
        frame's codes become radiance); None for merges outside the engine. The round trip
        (:mod:`derender.evaluation.roundtrip`) renders the map back through it.

    Examples
    --------
    Every merge returns one (:func:`derender.hdr.registry.merge`):

    >>> import numpy as np
    >>> import derender
    >>> radiance = np.linspace(0.05, 1.0, 64).reshape(8, 8, 1).repeat(3, axis=2)
    >>> times = np.array([0.25, 1.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> result = derender.merge(derender.Stack((codes / 255).astype(np.float32), times), "debevec")
    >>> isinstance(result, derender.HDRResult)
    True
    >>> result.radiance.shape, result.radiance.dtype, result.mask.shape
    ((8, 8, 3), dtype('float32'), (8, 8))
    >>> result.variance is None   # unless asked for (variance=True)
    True
    """

    radiance: np.ndarray
    mask: np.ndarray
    variance: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    ghosts: np.ndarray | None = None
    plan: Any = None

    MASK_OK = 0
    MASK_BRIGHT = 1
    MASK_DARK = 2
