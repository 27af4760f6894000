"""Ground-truth linear radiance from RAW frames (paper 1, Sec. 4.2, eq. 11 and Algorithm 2).

Pipeline of :func:`raw_ground_truth`:

1. :func:`merge_raw_mosaics` -- eq. 11: every frame is normalised,
   ``v = (mosaic - black) / (white - black)``, weighted with the binary weight
   ``w = 1`` where ``low <= v <= high`` (0.8e-3 and 0.92 in the paper) and merged as
   ``HDR_L = sum_i w_i v_i / dt_i / sum_i w_i`` on the Bayer mosaic.
2. White balance on the mosaic (one multiplier per CFA colour).
3. Demosaic (Malvar, He & Cutler 2004, via ``colour_demosaicing``).
4. Colour: ``linear_srgb = XYZ_TO_LINEAR_SRGB @ camera_to_xyz @ camera_rgb``
   (:func:`camera_to_linear_srgb_matrix`).

Algorithm 2 step 1 ("scale the min of HDR_L to the dark value and the max to the
saturation value") is *not* applied: the radiance is relative (known up to one scale,
which the evaluation protocol fits), and mapping the minimum to zero would add an
offset that biases dark pixels. ``HDR_L`` stays in units of normalised sensor value
per second (per unit exposure when times are unknown).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from derender.core.colorimetry import camera_to_linear_srgb_matrix, camera_to_xyz_matrix
from derender.core.errors import InputError
from derender.core.types import HDRResult, RawFrame
from derender.raw.mosaic import (
    HIGH,
    LOW,
    MASK_RADIUS,
    demosaic_bayer,
    demosaic_name,
    finite_float32,
    merge_raw_mosaics,
    sorted_raw_frames,
    spread_mask,
    wb_from_patch,
    white_balance_mosaic,
)

__all__ = [
    "raw_to_camera_rgb",
    "raw_ground_truth",
]


# --------------------------------------------------------------------------- public pipelines
def raw_to_camera_rgb(frames: RawFrame | Sequence[RawFrame], demosaic: str = "malvar2004",
                      low: float = LOW, high: float = HIGH, clip_negative: bool = True) -> HDRResult:
    """Merged (eq. 11) and demosaiced *camera RGB*: no colour matrix, the white balance divided out.

    The one path of every RAW output (:mod:`derender.raw.optimal`): the merged mosaic is
    white-balanced with the file's as-shot multipliers ``w`` (the middle frame of the
    time-sorted stack; a grey-world estimate for a file that states none,
    :func:`derender.raw.optimal.white_balances`), demosaiced, and divided by ``w`` again:
    ``diag(1 / w) D(W x)``, camera RGB as the sensor saw it, demosaiced as dcraw does (the
    demosaics' colour-difference terms assume that a neutral surface gives equal channels).
    ``radiance`` is (H, W, 3) float32 linear camera RGB (relative units); ``mask`` as in
    :func:`merge_raw_mosaics`, spread over the 5x5 demosaicing support (bright wins).
    Negative values (demosaic overshoot, noise below black) are set to 0 unless
    ``clip_negative=False``. Useful as the target of de-rendering models.

    Parameters
    ----------
    frames : RawFrame or sequence of RawFrame
        The bracket (:func:`derender.io.raw.read_raw_stack`), with exposure times.
    demosaic : str
        ``"malvar2004"`` (paper 1's), ``"menon2007"`` or ``"bilinear"`` (:data:`~derender.raw.mosaic.DEMOSAIC_METHODS`).
    low, high : float
        The normalised values eq. 11's binary weight keeps (paper 1, Sec. 4.2).
    clip_negative : bool
        Set negative values to 0.

    Returns
    -------
    HDRResult
        ``radiance`` (H, W, 3) float32 linear camera RGB: normalised sensor signal per
        second; ``mask``; ``info`` with ``colour_space="camera_rgb"``, the times, the
        demosaic's balance ``wb_multipliers`` and ``output_matrix`` ``diag(1 / w)``.

    Raises
    ------
    InputError
        Frames without exposure times, or an unknown demosaicing method.

    Examples
    --------
    A grey ramp whose brightest part clips in the long exposure; the merge recovers the
    signal per second everywhere:

    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> from derender.camera.dng import write_dng
    >>> signal = np.linspace(0.02, 2.0, 32 * 32).reshape(32, 32)   # of white, in 0.04 s
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     paths = [write_dng(os.path.join(folder, f"{t}.dng"),
    ...                        np.round(64 + np.clip(signal * t / 0.04, 0, 1) * 4031).astype(np.uint16),
    ...                        cfa_pattern="RGGB", black_level=64, white_level=4095,
    ...                        xyz_to_camera=np.eye(3), as_shot_neutral=np.ones(3), exposure_time=t,
    ...                        make="Sim", model="Cam", bits=12) for t in (0.04, 0.01)]
    ...     frames = derender.read_raw_stack(paths)
    >>> result = derender.raw_to_camera_rgb(frames)
    >>> result.radiance.shape, result.radiance.dtype, result.info["colour_space"]
    ((32, 32, 3), dtype('float32'), 'camera_rgb')
    >>> print(result.radiance[16, 16].round(2), round(signal[16, 16] / 0.04, 2))
    [26.05 26.05 26.05] 26.05
    """
    from derender.raw.optimal import white_balances

    frames, times = sorted_raw_frames(frames)
    hdr, mmask = merge_raw_mosaics(frames, low, high)
    pattern = frames[0].cfa_pattern.upper()
    mult, _ = white_balances(frames[len(frames) // 2], "camera_rgb", mosaic=hdr, pattern=pattern, mask=mmask)
    rgb = demosaic_bayer(white_balance_mosaic(hdr, pattern, mult), pattern, demosaic) / mult.astype(np.float32)
    rgb = finite_float32(rgb, clip_negative)
    info = {"colour_space": "camera_rgb", "exposure_times": times.tolist(), "demosaic": demosaic,
            "low": low, "high": high, "cfa_pattern": pattern, "mosaic_mask": mmask,
            "wb_multipliers": mult.tolist(), "output_matrix": np.diag(1.0 / mult).tolist()}
    return HDRResult(radiance=rgb, mask=spread_mask(mmask, MASK_RADIUS[demosaic_name(demosaic)]), info=info)


def raw_ground_truth(frames: RawFrame | Sequence[RawFrame], wb: str | Sequence[float] | None = "as_shot",
                     wb_patch: tuple[int, int, int, int] | None = None, demosaic: str = "malvar2004",
                     low: float = LOW, high: float = HIGH, clip_negative: bool = True,
                     xyz_to_camera: np.ndarray | None = None) -> HDRResult:
    """Linear-sRGB ground truth from RAW frames: paper 1 Sec. 4.2, eq. 11 + Algorithm 2.

    Steps: merge (:func:`merge_raw_mosaics`), white balance on the mosaic, demosaic
    (Malvar 2004 by default), then ``XYZ_TO_LINEAR_SRGB @ camera_to_xyz``
    (:func:`camera_to_xyz_matrix`, dcraw normalisation: the balanced white becomes D65).

    ``wb``: ``"as_shot"`` (multipliers of the middle frame of the time-sorted stack, the
    paper's reference exposure), explicit (R, G, B) multipliers, or ``None`` (no
    balance). ``wb_patch = (x, y, w, h)``, if given, overrides ``wb``: multipliers from
    the per-CFA-colour means of that neutral region of the merged mosaic
    (:func:`wb_from_patch`). ``xyz_to_camera`` overrides the frames' ColorMatrix; a
    frame without one raises :class:`InputError` (use :func:`raw_to_camera_rgb`).

    Negative values (Malvar overshoot at edges, noise below black, colours outside the
    sRGB gamut) are clipped to 0 by default, since rendered images -- the results this
    ground truth is compared with -- cannot hold them; pass ``clip_negative=False`` to
    keep them. The result is finite everywhere; ``mask`` marks pixels taken from the
    shortest (1) or longest (2) exposure, spread over the 5x5 demosaicing support.

    Parameters
    ----------
    frames : RawFrame or sequence of RawFrame
        The bracket (:func:`derender.io.raw.read_raw_stack`), with exposure times.
    wb : "as_shot", sequence of 3 floats, or None
        White balance (above).
    wb_patch : (x, y, w, h), optional
        A neutral region of the merged mosaic that sets the white balance (overrides ``wb``).
    demosaic : str
        ``"malvar2004"`` (paper 1's), ``"menon2007"`` or ``"bilinear"`` (:data:`~derender.raw.mosaic.DEMOSAIC_METHODS`).
    low, high : float
        The normalised values eq. 11's binary weight keeps (paper 1, Sec. 4.2).
    clip_negative : bool
        Set negative values to 0.
    xyz_to_camera : (3, 3) array, optional
        The camera's ColorMatrix, replacing the frames'.

    Returns
    -------
    HDRResult
        ``radiance`` (H, W, 3) float32 linear sRGB (relative units), finite and
        non-negative; ``mask``; ``info`` with the white balance and matrices used.

    Raises
    ------
    InputError
        A frame without a colour matrix (and no ``xyz_to_camera``), a malformed ``wb`` or
        ``wb_patch``, frames without exposure times, an unknown demosaicing method.

    Examples
    --------
    A grey ramp from a camera whose ColorMatrix is the identity (camera RGB = XYZ):

    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> from derender.camera.dng import write_dng
    >>> signal = np.linspace(0.02, 2.0, 32 * 32).reshape(32, 32)   # of white, in 0.04 s
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     paths = [write_dng(os.path.join(folder, f"{t}.dng"),
    ...                        np.round(64 + np.clip(signal * t / 0.04, 0, 1) * 4031).astype(np.uint16),
    ...                        cfa_pattern="RGGB", black_level=64, white_level=4095,
    ...                        xyz_to_camera=np.eye(3), as_shot_neutral=np.ones(3), exposure_time=t,
    ...                        make="Sim", model="Cam", bits=12) for t in (0.04, 0.01)]
    ...     frames = derender.read_raw_stack(paths)
    >>> truth = derender.raw_ground_truth(frames)
    >>> truth.radiance.shape, truth.radiance.dtype, int(truth.mask.max())
    ((32, 32, 3), dtype('float32'), 0)
    >>> bool(np.all(np.isfinite(truth.radiance)) and truth.radiance.min() >= 0)
    True
    """
    frames, times = sorted_raw_frames(frames)
    pattern = frames[0].cfa_pattern.upper()
    ref = frames[len(frames) // 2]
    m = ref.xyz_to_camera if xyz_to_camera is None else xyz_to_camera
    if m is None:
        raise InputError(f"{ref.path or 'RAW frame'} has no colour matrix (ColorMatrix); "
                         "pass xyz_to_camera or use raw_to_camera_rgb")
    cam_to_srgb = camera_to_linear_srgb_matrix(m)
    hdr, mmask = merge_raw_mosaics(frames, low, high)
    if wb_patch is not None:
        mult = wb_from_patch(hdr, pattern, wb_patch, mmask)
    elif wb is None:
        mult = np.ones(3)
    elif isinstance(wb, str):
        if wb != "as_shot":
            raise InputError(f"wb must be 'as_shot', three multipliers or None, got {wb!r}")
        mult = np.asarray(ref.as_shot_wb, dtype=np.float64).reshape(-1)
    else:
        mult = np.asarray(wb, dtype=np.float64).reshape(-1)
    balanced = white_balance_mosaic(hdr, pattern, mult)
    del hdr
    cam = demosaic_bayer(balanced, pattern, demosaic)
    del balanced
    h, w, _ = cam.shape
    srgb = (cam.reshape(-1, 3) @ cam_to_srgb.T.astype(np.float32)).reshape(h, w, 3)
    info = {"colour_space": "linear_srgb", "exposure_times": times.tolist(), "demosaic": demosaic,
            "wb_multipliers": np.asarray(mult, dtype=np.float64).tolist(),
            "camera_to_xyz": camera_to_xyz_matrix(m), "camera_to_linear_srgb": cam_to_srgb,
            "low": low, "high": high, "cfa_pattern": pattern, "mosaic_mask": mmask}
    return HDRResult(radiance=finite_float32(srgb, clip_negative), mask=spread_mask(mmask, MASK_RADIUS[demosaic_name(demosaic)]), info=info)
