"""RAW mosaics: the binary-weight merge of paper 1 (Sec. 4.2, eq. 11), white balance, demosaicing.

1. :func:`merge_raw_mosaics` -- eq. 11: every frame is normalised,
   ``v = (mosaic - black) / (white - black)``, weighted with the binary weight
   ``w = 1`` where ``low <= v <= high`` (0.8e-3 and 0.92 in the paper) and merged as
   ``HDR_L = sum_i w_i v_i / dt_i / sum_i w_i`` on the Bayer mosaic.
2. :func:`white_balance_mosaic` / :func:`wb_from_patch` -- one multiplier per CFA colour.
3. :func:`demosaic_bayer` -- Malvar, He & Cutler (2004) via ``colour_demosaicing`` (paper 1's
   choice), or Menon, Andriani & Calvagno (2007, without its refining step; the noise-optimal
   merge's default, :func:`derender.raw.optimal.raw_merge`), or bilinear; or Hirakawa & Parks
   (2005, AHD, dcraw's and LibRaw's; :mod:`derender.raw.ahd`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.types import HDRResult, RawFrame, validate_times

__all__ = [
    "LOW",
    "HIGH",
    "DEMOSAIC_METHODS",
    "setting_factors",
    "sorted_raw_frames",
    "cfa_channel_index",
    "merge_raw_mosaics",
    "white_balance_mosaic",
    "wb_from_patch",
    "DEMOSAIC_ALIASES",
    "demosaic_name",
    "demosaic_bayer",
    "spread_mask",
    "finite_float32",
    "MASK_RADIUS",
]


#: Paper 1, Sec. 4.2: binary weight keeps normalised values in [0.8e-3, 0.92] (lower bound).
LOW = 0.8e-3


#: Upper bound of the normalised values the binary weight keeps (paper 1, Sec. 4.2).
HIGH = 0.92


#: Demosaicing methods accepted by :func:`demosaic_bayer`.
DEMOSAIC_METHODS = ("malvar2004", "bilinear", "menon2007", "ahd")


#: Short names accepted for :data:`DEMOSAIC_METHODS` (``-O demosaic=malvar``).
DEMOSAIC_ALIASES = {"malvar": "malvar2004", "menon": "menon2007", "ddfapd": "menon2007", "ahd2005": "ahd"}


#: Half-width of the neighbourhood a mask flag is spread over after demosaicing, per method
#: (Malvar's kernels are 5x5; Menon's outputs combine photosites up to 4 away, AHD's up to 3).
MASK_RADIUS = {"malvar2004": 2, "bilinear": 1, "menon2007": 4, "ahd": 3}


def demosaic_name(method: str | None, default: str = "malvar2004") -> str:
    """The :data:`DEMOSAIC_METHODS` name of ``method`` (an alias of :data:`DEMOSAIC_ALIASES` or
    None for ``default``); an unknown name is an :class:`InputError` naming the choices."""
    if method is None:
        return default
    name = DEMOSAIC_ALIASES.get(str(method).lower(), str(method).lower())
    if name not in DEMOSAIC_METHODS:
        raise InputError(f"unknown demosaicing method {method!r}; choose one of "
                         f"{', '.join(DEMOSAIC_METHODS + tuple(DEMOSAIC_ALIASES))}")
    return name


# --------------------------------------------------------------------------- helpers
def setting_factors(frames: Sequence[RawFrame]) -> np.ndarray:
    """Per frame ``(S_j / S_0) (N_0 / N_j)^2``: the ISO ``S`` and f-number ``N`` of each frame
    (``extra["iso"]``, ``extra["fnumber"]``, read from the file) relative to the first frame
    given, as :func:`derender.io.exif.exposure_factors` does for rendered frames; 1 for a
    setting that does not vary, and ``extra["exposure_factor"]`` where it is set (exposures
    given whole). A setting that varies must be known for every frame (else one error that
    names the frames without it)."""
    n = len(frames)
    factors = np.ones(n)
    fixed = [bool(f.extra) and f.extra.get("exposure_factor") is not None for f in frames]
    for key, power, what in (("iso", 1.0, "ISO speed"), ("fnumber", -2.0, "f-number")):
        values = [(f.extra or {}).get(key) for f in frames]
        present = {v for v, fx in zip(values, fixed) if v is not None and not fx}
        if len(present) <= 1:
            continue
        lacking = [Path(f.path).name if f.path else f"frame {j}" for j, (f, v) in enumerate(zip(frames, values))
                   if v is None and not fixed[j]]
        if lacking:
            raise InputError(f"the RAW frames' {what} varies but {', '.join(lacking)} does not state it; "
                             "give the exposures with --times (t S / N^2, relative)")
        ref = next(v for v, fx in zip(values, fixed) if not fx)
        for j, v in enumerate(values):
            if not fixed[j]:
                factors[j] *= (float(v) / float(ref)) ** power
    for j, f in enumerate(frames):
        if fixed[j]:
            factors[j] = float(f.extra["exposure_factor"])
    return factors


def sorted_raw_frames(frames: RawFrame | Sequence[RawFrame]) -> tuple[list[RawFrame], np.ndarray]:
    """Validate frames; return them sorted by exposure ``t S / N^2`` (:func:`setting_factors`:
    relative to the first frame given), with the exposures (seconds at the first frame's ISO and
    f-number)."""
    if isinstance(frames, RawFrame):
        frames = [frames]
    frames = list(frames)
    if not frames:
        raise InputError("no RAW frames given")
    if not all(isinstance(f, RawFrame) for f in frames):
        raise InputError("raw ground truth needs RawFrame objects (see derender.read_raw)")
    shapes = {np.asarray(f.mosaic).shape for f in frames}
    if len(shapes) > 1:
        raise InputError(f"RAW frames differ in size: {sorted(shapes)}")
    shape = shapes.pop()
    if len(shape) != 2 or min(shape) < 2:
        raise InputError(f"a RAW mosaic must be a 2-D array of at least 2x2, got shape {shape}")
    patterns = {f.cfa_pattern.upper() for f in frames}
    if len(patterns) > 1:
        raise InputError(f"RAW frames have different CFA patterns: {sorted(patterns)}")
    pattern = patterns.pop()
    if len(pattern) != 4 or sorted(pattern) != ["B", "G", "G", "R"]:
        raise InputError(f"unsupported CFA pattern {pattern!r}; expected a Bayer pattern such as 'RGGB'")
    for f in frames:
        bl = np.asarray(f.black_level, dtype=np.float64)
        if bl.size not in (1, 4) or not np.all(np.isfinite(bl)) or not np.isfinite(f.white_level) \
                or np.any(float(f.white_level) <= bl):
            raise InputError(f"bad black/white level in {f.path or 'RAW frame'}: "
                             f"black {bl.ravel().tolist()}, white {f.white_level}")
    if len(frames) == 1:
        t = frames[0].exposure_time
        times = np.array([1.0 if t is None else float(t)])
        if not (np.isfinite(times[0]) and times[0] > 0):
            raise InputError(f"exposure time must be positive finite seconds, got {t}")
        return frames, times
    missing = [i for i, f in enumerate(frames) if f.exposure_time is None]
    if missing:
        raise InputError(f"{len(missing)} of {len(frames)} RAW frames have no exposure time; "
                         "merging several frames needs every time")
    times = validate_times([f.exposure_time * k for f, k in zip(frames, setting_factors(frames))], len(frames))
    order = np.argsort(times, kind="stable")
    return [frames[i] for i in order], times[order]


def _normalised(frame: RawFrame) -> np.ndarray:
    """(H, W) float32 ``(mosaic - black) / (white - black)`` with a scalar or (2, 2) black."""
    h, w = frame.mosaic.shape
    bl = np.asarray(frame.black_level, dtype=np.float32)
    bl = np.broadcast_to(bl.reshape(-1)[0], (2, 2)) if bl.size == 1 else bl.reshape(2, 2)
    blm = np.tile(bl, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    return (frame.mosaic.astype(np.float32) - blm) / (np.float32(frame.white_level) - blm)


def cfa_channel_index(shape: tuple[int, int], pattern: str) -> np.ndarray:
    """(H, W) int8 map: 0 for R, 1 for G, 2 for B at every photosite of a Bayer ``pattern``."""
    lut = {"R": 0, "G": 1, "B": 2}
    p = pattern.upper()
    if len(p) != 4 or sorted(p) != ["B", "G", "G", "R"]:
        raise InputError(f"unsupported CFA pattern {pattern!r}; expected a Bayer pattern such as 'RGGB'")
    tile = np.array([[lut[p[0]], lut[p[1]]], [lut[p[2]], lut[p[3]]]], dtype=np.int8)
    h, w = shape
    return np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


# --------------------------------------------------------------------------- eq. 11
def merge_raw_mosaics(frames: RawFrame | Sequence[RawFrame], low: float = LOW,
                      high: float = HIGH) -> tuple[np.ndarray, np.ndarray]:
    """Merge RAW mosaics into one linear mosaic, paper 1 eq. 11.

    ``HDR_L = sum_i w_i v_i / dt_i / sum_i w_i`` with ``v_i = (mosaic_i - black_i) /
    (white_i - black_i)`` and the binary weight ``w_i = 1`` iff ``low <= v_i <= high``.
    A single frame without exposure time uses ``dt = 1``; several frames must all have
    distinct times (else :class:`InputError`).

    Pixels no frame exposes well (zero total weight): if the shortest exposure is
    over-exposed (``v > high``) the pixel takes ``min(v, 1) / dt`` of the shortest
    exposure (mask 1, ``HDRResult.MASK_BRIGHT``); otherwise it takes ``v / dt`` of the
    longest exposure (mask 2, ``MASK_DARK``; values below black are kept, not clipped,
    so dark averages stay unbiased).

    Returns ``(hdr_mosaic, mask)``: (H, W) float32 (finite everywhere) and (H, W) uint8
    with 0 = merged from well-exposed values, 1 = bright, 2 = dark.
    """
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise InputError(f"merge thresholds need low < high, got low={low}, high={high}")
    frames, times = sorted_raw_frames(frames)
    low32, high32 = np.float32(low), np.float32(high)
    num = None
    den = None
    for f, t in zip(frames, times):
        v = _normalised(f)
        w = (v >= low32) & (v <= high32)
        contrib = np.where(w, v * np.float32(1.0 / t), np.float32(0.0))
        if num is None:
            num, den = contrib, w.astype(np.float32)
        else:
            num += contrib
            den += w
    hdr = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    empty = den == 0
    mask = np.zeros(hdr.shape, dtype=np.uint8)
    if np.any(empty):
        v_short = _normalised(frames[0])
        bright = empty & (v_short > high32)
        dark = empty & ~bright
        if np.any(bright):
            hdr[bright] = np.minimum(v_short[bright], np.float32(1.0)) * np.float32(1.0 / times[0])
            mask[bright] = HDRResult.MASK_BRIGHT
        if np.any(dark):
            v_long = v_short if len(frames) == 1 else _normalised(frames[-1])
            hdr[dark] = v_long[dark] * np.float32(1.0 / times[-1])
            mask[dark] = HDRResult.MASK_DARK
    return np.nan_to_num(hdr, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32, copy=False), mask


# --------------------------------------------------------------------------- white balance, demosaic
def white_balance_mosaic(mosaic: np.ndarray, pattern: str, multipliers: np.ndarray) -> np.ndarray:
    """Multiply each photosite by the (R, G, B) multiplier of its CFA colour (Algorithm 2, step 2)."""
    mult = np.asarray(multipliers, dtype=np.float64).reshape(-1)
    if mult.size != 3 or not np.all(np.isfinite(mult)) or np.any(mult <= 0):
        raise InputError(f"white-balance multipliers must be 3 positive numbers (R, G, B), got {mult.tolist()}")
    mosaic = np.asarray(mosaic, dtype=np.float32)
    idx = cfa_channel_index(mosaic.shape, pattern)
    return mosaic * mult.astype(np.float32)[idx]


def wb_from_patch(mosaic: np.ndarray, pattern: str, patch: tuple[int, int, int, int],
                  mask: np.ndarray | None = None) -> np.ndarray:
    """White-balance multipliers (R, G, B), G = 1, from a neutral region of a linear mosaic.

    ``patch = (x, y, w, h)`` in photosite units. Multiplier of colour c is
    ``mean_G / mean_c`` over the photosites of that colour in the patch (only those with
    ``mask == 0`` when a mask is given and at least one such photosite exists).
    """
    mosaic = np.asarray(mosaic, dtype=np.float32)
    try:
        x, y, w, h = (int(v) for v in patch)
    except (TypeError, ValueError):
        raise InputError(f"wb_patch must be (x, y, width, height), got {patch!r}") from None
    hh, ww = mosaic.shape
    if w < 2 or h < 2 or x < 0 or y < 0 or x + w > ww or y + h > hh:
        raise InputError(f"wb_patch {(x, y, w, h)} must be at least 2x2 and lie inside the {ww}x{hh} mosaic")
    sub = mosaic[y:y + h, x:x + w]
    idx = cfa_channel_index(mosaic.shape, pattern)[y:y + h, x:x + w]
    ok = np.ones(sub.shape, bool) if mask is None else (np.asarray(mask)[y:y + h, x:x + w] == 0)
    means = np.empty(3)
    for c in range(3):
        sel = idx == c
        use = sel & ok
        means[c] = float(np.mean(sub[use if np.any(use) else sel]))
    if not np.all(np.isfinite(means)) or np.any(means <= 0):
        raise InputError(f"wb_patch {(x, y, w, h)} is not a usable neutral region (channel means {means.tolist()})")
    return means[1] / means


def demosaic_bayer(mosaic: np.ndarray, pattern: str, method: str = "malvar2004") -> np.ndarray:
    """Demosaic a linear Bayer mosaic to (H, W, 3) float32 (Algorithm 2, step 3).

    ``method``: ``"malvar2004"`` (Malvar, He & Cutler 2004, the paper's choice),
    ``"menon2007"`` (Menon, Andriani & Calvagno 2007, DDFAPD, without its refining step) or
    ``"bilinear"``, all from ``colour_demosaicing``, or ``"ahd"`` (Hirakawa & Parks 2005 as dcraw
    computes it, :func:`derender.raw.ahd.ahd_demosaic`; aliases: :data:`DEMOSAIC_ALIASES`).
    """
    import colour_demosaicing as cd

    p = pattern.upper()
    cfa_channel_index((2, 2), p)  # validates the pattern
    method = demosaic_name(method)
    if method == "malvar2004":
        out = cd.demosaicing_CFA_Bayer_Malvar2004(np.asarray(mosaic, dtype=np.float64), p)
    elif method == "menon2007":
        out = cd.demosaicing_CFA_Bayer_Menon2007(np.asarray(mosaic, dtype=np.float64), p, refining_step=False)
    elif method == "bilinear":
        out = cd.demosaicing_CFA_Bayer_bilinear(np.asarray(mosaic, dtype=np.float64), p)
    elif method == "ahd":
        from derender.raw.ahd import ahd_demosaic

        out = ahd_demosaic(mosaic, p)[0]
    else:
        raise InputError(f"unknown demosaicing method {method!r}; choose one of {', '.join(DEMOSAIC_METHODS)}")
    return np.asarray(out, dtype=np.float32)


def spread_mask(mosaic_mask: np.ndarray, radius: int = 2) -> np.ndarray:
    """Spread the per-photosite mask over the demosaicing support (``radius``:
    :data:`MASK_RADIUS` of the demosaic); bright (1) wins over dark (2)."""
    from scipy.ndimage import maximum_filter

    if not np.any(mosaic_mask):
        return np.zeros(mosaic_mask.shape, dtype=np.uint8)
    size = 2 * int(radius) + 1
    bright = maximum_filter((mosaic_mask == HDRResult.MASK_BRIGHT).view(np.uint8), size=size, mode="nearest")
    dark = maximum_filter((mosaic_mask == HDRResult.MASK_DARK).view(np.uint8), size=size, mode="nearest")
    out = np.zeros(mosaic_mask.shape, dtype=np.uint8)
    out[dark > 0] = HDRResult.MASK_DARK
    out[bright > 0] = HDRResult.MASK_BRIGHT
    return out


def finite_float32(img: np.ndarray, clip_negative: bool) -> np.ndarray:
    """``img`` as contiguous float32 with NaN and inf set to 0 (and negatives to 0 if ``clip_negative``)."""
    img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    if clip_negative:
        np.maximum(img, 0.0, out=img)
    return np.ascontiguousarray(img, dtype=np.float32)
