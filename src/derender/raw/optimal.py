"""The noise-optimal RAW merge: censored maximum likelihood on the mosaic, a variance, one demosaic.

Every photosite of frame ``j`` (exposure ``t_j``) gives ``d_j = y_j - black_j`` (DN, the
black level per CFA colour and per frame, from LibRaw). Under the Poisson-Gaussian model of
:mod:`derender.raw.noise`, ``d_j ~ N(X t_j, v_j)``, ``v_j = g X t_j + sigma^2``, for the
radiance ``X`` (DN/s). A sample at or above its frame's white level is *censored*: it says
only ``X t_j + noise >= c_j`` (``c_j = white_j - black_j``), which is information, not a
missing value (Aguerrebere, Delon, Gousseau & Muse 2014, "Best algorithms for HDR image
generation. A study of performance bounds", SIAM J. Imaging Sci. 7(1), Sec. 3-4). The
log-likelihood

    L(X) = sum_unsat -(d_j - X t_j)^2 / (2 v_j) + sum_sat log Q((c_j - X t_j) / sqrt(v_j))

(``Q = 1 - Phi``) is maximised per photosite by Newton steps with ``v_j`` held at the current
``X`` (iteratively reweighted; concave in ``X`` for fixed ``v_j``):

    X <- X + S / I,  S = sum_unsat t_j (d_j - X t_j) / v_j + sum_sat t_j lambda(z_j) / sqrt(v_j),
                     I = sum_unsat t_j^2 / v_j + sum_sat t_j^2 lambda(z_j) (lambda(z_j) - z_j) / v_j

with ``z_j = (c_j - X t_j) / sqrt(v_j)`` and the inverse Mills ratio ``lambda = phi / Q``.
Without censored samples this is the inverse-variance weighted mean of ``d_j / t_j`` with
weights ``t_j^2 / v_j`` -- the minimum-variance unbiased merge of Granados et al. 2010
(CVPR, eq. 9) and Hanji et al. 2020 (eq. 6). The variance of ``X`` is ``1 / I`` (the Fisher
information, the censored samples' share included). Where every frame is saturated the
estimate is the bound ``X = c / t_min`` (mask 1) with variance ``X^2`` (sigma = 100 %:
it is a lower bound, not a measurement). ``g`` and ``sigma^2`` come from the bracket
(:func:`derender.raw.noise.estimate_noise`) unless given.

Then, in every output space, one path: the mosaic is white-balanced (one multiplier ``w_c``
per CFA colour), demosaiced once (Malvar, He & Cutler 2004, a linear filter, by default; or
Menon, Andriani & Calvagno 2007; or AHD) and put in the output space by one 3x3 matrix,

    o = M diag(u / w) D(W x),

``W x`` the balanced mosaic, ``D`` the demosaic, ``u`` the balance the output keeps and ``M``
the file's own matrix: ``camera_rgb`` (``M = I``, ``u = 1``: the balance is divided out after
the demosaic), ``linear_srgb`` (``M = XYZ_TO_LINEAR_SRGB @ camera_to_xyz``, as
:func:`derender.raw.groundtruth.raw_ground_truth`, ``u = w``) or ``xyz`` (D65, ``u = w``).
The balance ``w`` is the user's (``wb``, ``wb_patch``) or the file's as-shot one (AsShotNeutral,
else the camera multipliers); where the file states none, ``u = 1`` and ``w`` is the grey-world
estimate of the merged mosaic (:func:`white_balances`). Demosaicing the balanced mosaic is what
dcraw and LibRaw do: the demosaics' colour-difference and gradient terms assume that a neutral
surface gives equal channels; in ``camera_rgb`` it takes 0.1-0.4 points off the median
relative error against the scene on simulated DNG brackets (docs/results-raw.md). All three
steps are linear, so the variance goes through them exactly for independent photosites:
``Var[o] = sum_p (sum_c M'_oc K_c(p))^2 w_p^2 Var[X_p]`` with ``M' = M diag(u / w)``,
Malvar's kernels ``K_c`` per CFA phase and the multipliers ``w_p`` (:func:`demosaic_variance`). Menon's
demosaic is linear once its direction per red and blue photosite is chosen: its ``K_c(p)``
are the weights given the directions, a fixed filter bank indexed by the directions near the
pixel, plus ``P(flip) (out' - out)^2`` for a direction the noise may have chosen wrongly
(:mod:`derender.raw.menon`). At 24 MP the demosaic with its variance takes about 1 s with
Malvar's kernels and about 4x that with Menon's (benchmarks/bench_raw.py ``--demosaic-speed``;
docs/results-raw.md). The radiance is in units of the white level per second,
``X / (white - black)``, as :func:`derender.raw.mosaic.merge_raw_mosaics` gives it.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Sequence

import numpy as np

from derender.core.colorimetry import XYZ_TO_LINEAR_SRGB, camera_to_xyz_matrix
from derender.core.errors import InputError
from derender.core.types import HDRResult, RawFrame
from derender.raw.interpolation import VARIANCE_TERMS
from derender.raw.mosaic import (
    MASK_RADIUS,
    cfa_channel_index,
    demosaic_bayer,
    demosaic_name,
    sorted_raw_frames,
    spread_mask,
    wb_from_patch,
)
from derender.raw.noise import NoiseModel, estimate_noise, estimate_noise_frames

__all__ = [
    "OUTPUT_SPACES",
    "mosaic_observations",
    "merge_mosaic_optimal",
    "demosaic_variance",
    "linear_demosaic_kernels",
    "output_matrix",
    "grey_world_wb",
    "white_balances",
    "compiled_frames",
    "merge_compiled",
    "interleave",
    "demosaic_compiled",
    "raw_merge",
]

#: Output colour spaces of :func:`raw_merge`.
OUTPUT_SPACES = ("linear_srgb", "camera_rgb", "xyz")

#: Saturated samples further than this many sigma below their expected value carry no information.
_NEAR = 8.0


#: Newton steps of the censored likelihood (converged to < 1e-6 relative on simulated brackets).
_ITERATIONS = 6


#: The compiled merge stops a photosite's Newton steps once a step is below this many sigma
#: (the float64 reference :func:`merge_mosaic_optimal` always takes :data:`_ITERATIONS`).
_NEWTON_TOL = 1e-6


def _black_mosaic(frame: RawFrame, shape: tuple[int, int]) -> np.ndarray:
    bl = np.asarray(frame.black_level, dtype=np.float64)
    bl = np.broadcast_to(bl.reshape(-1)[0], (2, 2)) if bl.size == 1 else bl.reshape(2, 2)
    h, w = shape
    return np.tile(bl, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def mosaic_observations(frames: Sequence[RawFrame]) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Per frame: ``d`` (DN above black, float64), the saturated samples (``y >= white``) and
    the censoring level ``c = white - black`` (DN above black), black and white read per frame."""
    ds, sats, cs = [], [], []
    shared: dict = {}                  # frames with the same levels share one ceiling array
    for f in frames:
        y = np.asarray(f.mosaic)
        key = (tuple(np.asarray(f.black_level, dtype=np.float64).reshape(-1).tolist()), float(f.white_level))
        if key not in shared:
            black = _black_mosaic(f, y.shape)
            shared[key] = (black, float(f.white_level) - black)
        black, ceiling = shared[key]
        ds.append(y.astype(np.float64) - black)
        sats.append(y >= float(f.white_level))
        cs.append(ceiling)
    return ds, sats, cs


def _inverse_mills(z: np.ndarray) -> np.ndarray:
    """``phi(z) / (1 - Phi(z))``, stable for every z (erfcx)."""
    from scipy.special import erfcx

    with np.errstate(over="ignore"):
        return np.sqrt(2.0 / np.pi) / erfcx(z / np.sqrt(2.0))


def merge_mosaic_optimal(d: list[np.ndarray], saturated: list[np.ndarray], ceilings: list[np.ndarray],
                         times: np.ndarray, noise: NoiseModel, censored: bool = True,
                         iterations: int = _ITERATIONS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The censored maximum-likelihood radiance per photosite (DN/s), its variance and mask.

    Returns ``(x, var, mask)``: (H, W) float64 ``X``, its variance ``1 / I`` ((DN/s)^2) and
    uint8 mask (1 where every frame is saturated: ``X`` is the bound ``c / t_min``).
    ``censored=False`` leaves saturated samples out (treated as missing, for comparison)."""
    times = np.asarray(times, dtype=np.float64)
    g, s2 = float(noise.gain), float(noise.read_variance)
    num = np.zeros(d[0].shape, np.float64)
    den = np.zeros(d[0].shape, np.float64)
    for dj, sj, tj in zip(d, saturated, times):
        num += np.where(sj, 0.0, dj)
        den += np.where(sj, 0.0, tj)
    allsat = den == 0
    x = np.divide(num, den, out=np.zeros_like(num), where=~allsat)      # pooled Poisson start
    bound = np.max([c / t for c, t in zip(ceilings, times)], axis=0)
    x[allsat] = bound[allsat]
    # two reweighted rounds on every photosite (exact for those without a censored sample) ...
    info = np.zeros_like(x)
    for _ in range(2):
        score = np.zeros_like(x)
        info = np.zeros_like(x)
        for dj, sj, tj in zip(d, saturated, times):
            w = np.where(sj, 0.0, tj / (g * np.maximum(x * tj, 0.0) + s2))
            score += w * (dj - x * tj)
            info += w * tj
        x = np.where(allsat, x, x + np.divide(score, info, out=np.zeros_like(score), where=info > 0))
    # ... then Newton steps on the censored likelihood where some but not every sample saturated
    # (only where a saturated sample lies within 8 sigma of its level: elsewhere lambda(z) < 1e-14)
    near = np.zeros(x.shape, bool)
    if censored:
        for sj, cj, tj in zip(saturated, ceilings, times):
            near |= sj & (cj - x * tj > -_NEAR * np.sqrt(g * np.maximum(x * tj, 0.0) + s2))
    cen = np.flatnonzero(near & ~allsat)
    if cen.size:
        xs = x.ravel()[cen]
        ds = [dj.ravel()[cen] for dj in d]
        ss = [sj.ravel()[cen] for sj in saturated]
        cs = [cj.ravel()[cen] for cj in ceilings]
        inf_s = np.zeros_like(xs)
        for _ in range(max(int(iterations), 1)):
            score = np.zeros_like(xs)
            inf_s = np.zeros_like(xs)
            for dj, sj, cj, tj in zip(ds, ss, cs, times):
                v = g * np.maximum(xs * tj, 0.0) + s2
                u = ~sj
                score += np.where(u, tj * (dj - xs * tj) / v, 0.0)
                inf_s += np.where(u, tj * tj / v, 0.0)
                if np.any(sj):
                    sd = np.sqrt(v)
                    z = (cj - xs * tj) / sd
                    lam = _inverse_mills(z)
                    score += np.where(sj, tj * lam / sd, 0.0)
                    inf_s += np.where(sj, tj * tj * lam * np.clip(lam - z, 0.0, None) / v, 0.0)
            xs = xs + np.divide(score, inf_s, out=np.zeros_like(score), where=inf_s > 0)
        x.ravel()[cen] = xs
        info.ravel()[cen] = inf_s
    var = np.divide(1.0, info, out=np.zeros_like(info), where=info > 0)
    var[allsat] = bound[allsat] ** 2
    mask = np.zeros(x.shape, np.uint8)
    mask[allsat] = HDRResult.MASK_BRIGHT
    return x, var, mask


@lru_cache(maxsize=8)
def _malvar_kernels(pattern: str, method: str) -> np.ndarray:
    """(2, 2, 3, 5, 5): the demosaic's linear kernel for output phase (py, px) and channel c,
    read off its responses to unit impulses (Malvar 2004 is linear and shift-invariant per phase)."""
    if method in ("menon2007", "ahd"):
        raise InputError(f"{method} is not one linear filter per CFA phase: its variance is computed "
                         "in demosaic_compiled, given its directions")
    n = 16
    k = np.zeros((2, 2, 3, 5, 5))
    for py in range(2):
        for px in range(2):
            cy, cx = 8 + py, 8 + px
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    imp = np.zeros((n, n))
                    imp[cy + dy, cx + dx] = 1.0
                    k[py, px, :, dy + 2, dx + 2] = demosaic_bayer(imp, pattern, method)[cy, cx]
    return k


def linear_demosaic_kernels(pattern: str, method: str = "malvar2004") -> np.ndarray:
    """(2, 2, 3, 5, 5): a linear demosaic's kernel for output CFA phase (py, px) and channel c
    (correlation offsets -2..2), read off its responses to unit impulses (Malvar 2004 by
    default; ``bilinear`` too; Menon 2007 is not linear)."""
    return _malvar_kernels(pattern.upper(), demosaic_name(method))


def demosaic_variance(var_mosaic: np.ndarray, pattern: str, matrix: np.ndarray | None = None,
                      method: str = "malvar2004") -> np.ndarray:
    """(H, W, 3) variance of ``matrix @ demosaic(mosaic)`` for independent photosites of variance
    ``var_mosaic``: ``sum_p (sum_c M_oc K_c(p))^2 var(p)`` with the demosaic's kernels per CFA
    phase (borders reflected, as the demosaic does)."""
    from scipy.ndimage import correlate

    m = np.eye(3) if matrix is None else np.asarray(matrix, dtype=np.float64)
    ker = _malvar_kernels(pattern.upper(), method)
    combined = np.einsum("oc,yxcij->yxoij", m, ker) ** 2
    var_mosaic = np.asarray(var_mosaic, dtype=np.float64)
    h, w = var_mosaic.shape
    out = np.empty((h, w, 3), np.float32)
    for py in range(2):
        for px in range(2):
            for o in range(3):
                full = correlate(var_mosaic, combined[py, px, o], mode="reflect")
                out[py::2, px::2, o] = full[py::2, px::2]
    return out


def output_matrix(frame: RawFrame, output_space: str,
                  xyz_to_camera: np.ndarray | None = None) -> np.ndarray:
    """The 3x3 matrix from white-balanced camera RGB to ``output_space`` (identity for ``camera_rgb``)."""
    if output_space not in OUTPUT_SPACES:
        raise InputError(f"output_space must be one of {', '.join(OUTPUT_SPACES)}, got {output_space!r}")
    if output_space == "camera_rgb":
        return np.eye(3)
    m = frame.xyz_to_camera if xyz_to_camera is None else xyz_to_camera
    if m is None:
        raise InputError(f"{frame.path or 'RAW frame'} has no colour matrix (ColorMatrix); "
                         "use output_space camera_rgb")
    c2x = camera_to_xyz_matrix(m)
    return c2x if output_space == "xyz" else XYZ_TO_LINEAR_SRGB @ c2x


def grey_world_wb(mosaic: np.ndarray, pattern: str, mask: np.ndarray | None = None) -> np.ndarray:
    """White-balance multipliers (R, G, B), G = 1, that make the mean of each CFA colour equal
    over the measured photosites (``mask == 0``) of a linear ``mosaic``: the grey-world neutral
    estimate, used to balance the demosaic of a file that states no white balance (ones where a
    colour's mean is not positive)."""
    m = np.asarray(mosaic, dtype=np.float64)
    idx = cfa_channel_index(m.shape, pattern)
    ok = np.ones(m.shape, bool) if mask is None else (np.asarray(mask) == 0)
    means = np.array([float(np.mean(m[(idx == c) & ok])) if np.any((idx == c) & ok) else 0.0 for c in range(3)])
    if not np.all(np.isfinite(means)) or np.any(means <= 0):
        return np.ones(3)
    return means[1] / means


def white_balances(frame: RawFrame, output_space: str, wb=None, wb_patch=None, mosaic: np.ndarray | None = None,
                   pattern: str = "RGGB", mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(demosaic_wb, output_wb)``: the multipliers (R, G, B) the mosaic is balanced with before
    the demosaic, and those the output keeps (module docstring, "one path").

    The balance is ``wb`` if given, else the neutral region ``wb_patch`` of the merged
    ``mosaic``, else the file's as-shot multipliers (AsShotNeutral, else LibRaw's camera
    multipliers). ``output_wb`` is that balance in ``linear_srgb`` and ``xyz`` (ones when the
    file states none, the matrix then taking camera RGB as it is) and ones in ``camera_rgb``.
    ``demosaic_wb`` is that balance in every space; for a file that states none
    (``frame.extra["as_shot_wb_missing"]``, :func:`derender.io.raw.read_raw`) it is the grey-world
    estimate of the merged ``mosaic`` (:func:`grey_world_wb`)."""
    def checked(m) -> np.ndarray:
        m = np.asarray(m, dtype=np.float64).reshape(-1)
        if m.size != 3 or not np.all(np.isfinite(m)) or np.any(m <= 0):
            raise InputError(f"white-balance multipliers must be 3 positive numbers (R, G, B), got {m.tolist()}")
        return m

    missing = bool((frame.extra or {}).get("as_shot_wb_missing")) and wb is None and wb_patch is None
    if wb_patch is not None:
        balance = wb_from_patch(mosaic, pattern, wb_patch, mask)
    else:
        balance = checked(frame.as_shot_wb if wb is None else wb)
    output_wb = np.ones(3) if output_space == "camera_rgb" else balance
    demosaic_wb = grey_world_wb(mosaic, pattern, mask) if missing and mosaic is not None else balance
    return demosaic_wb, output_wb


#: Arrays above this many bytes are allocated in transparent huge pages where the kernel
#: allows it (madvise): first-touch page faults of a 24 MP (H, W, 3) float32 output cost
#: 0.3-0.5 s of CPU here with 4 KB pages, 0.14-0.17 s with 2 MB pages.
_HUGE_BYTES = 64 << 20


def _empty(shape: tuple, dtype) -> np.ndarray:
    """``np.empty``, in huge pages (an anonymous mmap, ``MADV_HUGEPAGE``) for large arrays on Linux."""
    import mmap

    dtype = np.dtype(dtype)
    size = int(np.prod(shape)) * dtype.itemsize
    if size < _HUGE_BYTES or not hasattr(mmap, "MADV_HUGEPAGE"):
        return np.empty(shape, dtype)
    try:
        buf = mmap.mmap(-1, size)
        buf.madvise(mmap.MADV_HUGEPAGE)
    except (OSError, ValueError):
        return np.empty(shape, dtype)
    return np.frombuffer(buf, dtype=dtype).reshape(shape)


def compiled_frames(frames: Sequence[RawFrame]):
    """The compiled kernels' view of frames: a numba typed list of the (H, W) mosaics (uint16 as
    LibRaw gives them, else float64), ``black`` (N, 2, 2) per CFA phase and ``white`` (N,)."""
    from numba.typed import List

    dtype = np.uint16 if all(np.asarray(f.mosaic).dtype == np.uint16 for f in frames) else np.float64
    mosaics = List([np.ascontiguousarray(f.mosaic, dtype=dtype) for f in frames])
    black = np.empty((len(frames), 2, 2))
    for j, f in enumerate(frames):
        bl = np.asarray(f.black_level, dtype=np.float64)
        black[j] = np.broadcast_to(bl.reshape(-1)[0], (2, 2)) if bl.size == 1 else bl.reshape(2, 2)
    return mosaics, black, np.array([float(f.white_level) for f in frames])


def merge_compiled(mosaics, black: np.ndarray, white: np.ndarray, exposures: np.ndarray, noise: NoiseModel, *,
                   censored: bool = True, iterations: int = _ITERATIONS,
                   scale: np.ndarray | float = 1.0,
                   valid: np.ndarray | None = None,
                   variance_factor: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`merge_mosaic_optimal` on :func:`compiled_frames` in one compiled pass
    (:func:`derender.raw.kernels.merge_rows`), with the noise model per frame
    (:meth:`~derender.raw.noise.NoiseModel.per_frame`). Returns ``(x, var, mask)``: ``X``
    and its variance times ``scale`` (per CFA phase, (2, 2), or a number) and its square,
    float32 split by CFA phase ((2, 2, ceil(H/2), ceil(W/2)); :func:`interleave` makes the
    mosaic), and the (H, W) uint8 mask. ``valid`` (N, H, W) bool: where each frame takes part
    (None: everywhere); ``variance_factor`` (N, 2, 2): per frame and CFA phase, the factor on
    the model's variance of its samples (resampled frames; None: 1)."""
    from derender.raw.kernels import KERNEL_LOCK, merge_rows

    h, w = mosaics[0].shape
    g, s2 = noise.per_frame(len(mosaics))
    f = np.ones((len(mosaics), 2, 2)) if variance_factor is None else np.asarray(variance_factor, np.float64)
    g = np.ascontiguousarray(g[:, None, None] * f)
    s2 = np.ascontiguousarray(s2[:, None, None] * f)
    scale = np.broadcast_to(np.asarray(scale, np.float64), (2, 2)).copy()
    x = _empty((2, 2, (h + 1) // 2, (w + 1) // 2), np.float32)
    var = _empty(x.shape, np.float32)
    if h % 2 or w % 2:                 # the planes' padding is never written by the merge
        x[...] = 0.0
        var[...] = 0.0
    mask = np.empty((h, w), np.uint8)
    valid = np.ones((len(mosaics), 1, 1), np.uint8) if valid is None else np.ascontiguousarray(valid, np.uint8)
    with KERNEL_LOCK:
        merge_rows(mosaics, valid, black, np.asarray(white, np.float64), np.asarray(exposures, np.float64), g, s2,
                   bool(censored), int(iterations), _NEAR, _NEWTON_TOL, scale, x, var, mask, HDRResult.MASK_BRIGHT)
    return x, var, mask


def interleave(planes: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The (H, W) mosaic of phase planes ``planes[a, b] = mosaic[a::2, b::2]`` (2, 2, ceil(H/2), ceil(W/2))."""
    h, w = shape
    out = np.empty((h, w), planes.dtype)
    for a in range(2):
        for b in range(2):
            sub = out[a::2, b::2]
            sub[...] = planes[a, b, :sub.shape[0], :sub.shape[1]]
    return out


@lru_cache(maxsize=8)
def _tap_table(pattern: str, method: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The demosaic's non-zero taps per CFA phase: counts (2, 2), offsets dy, dx (2, 2, 25), kernels (2, 2, 25, 3)."""
    ker = _malvar_kernels(pattern, method)
    ntaps = np.zeros((2, 2), np.int64)
    dy = np.zeros((2, 2, 25), np.int64)
    dx = np.zeros((2, 2, 25), np.int64)
    k = np.zeros((2, 2, 25, 3))
    for py in range(2):
        for px in range(2):
            t = 0
            for i in range(5):
                for j in range(5):
                    if np.any(ker[py, px, :, i, j] != 0):
                        dy[py, px, t], dx[py, px, t] = i - 2, j - 2
                        k[py, px, t] = ker[py, px, :, i, j]
                        t += 1
            ntaps[py, px] = t
    return ntaps, dy, dx, k


def demosaic_compiled(x: np.ndarray, var: np.ndarray | None, shape: tuple[int, int], pattern: str,
                      multipliers: np.ndarray, matrix: np.ndarray, method: str = "malvar2004",
                      clip_negative: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """White balance (``multipliers`` R, G, B per CFA colour), demosaic, ``matrix`` and the
    variance of :func:`demosaic_variance` in one compiled pass
    (:func:`derender.raw.kernels.demosaic_rows`) of the phase planes ``x`` and ``var`` of an
    (H, W) = ``shape`` mosaic (as :func:`merge_compiled` gives them): ``(radiance, variance)``,
    (H, W, 3) float32, finite (negatives 0 with ``clip_negative``); the variance None when
    ``var`` is."""
    from derender.raw.kernels import KERNEL_LOCK, demosaic_rows

    p = pattern.upper()
    if method == "menon2007":
        return _menon_compiled(x, var, shape, p, multipliers, matrix, clip_negative)
    if method == "ahd":
        from derender.raw.ahd import ahd_planes

        return ahd_planes(x, var, shape, p, multipliers, matrix, clip_negative)
    ntaps, dy, dx, k = _tap_table(p, method)
    taps = np.ascontiguousarray(np.einsum("oc,yxtc->yxto", np.asarray(matrix, np.float64), k))
    lut = {"R": 0, "G": 1, "B": 2}
    mult = np.asarray(multipliers, np.float64)[[[lut[p[0]], lut[p[1]]], [lut[p[2]], lut[p[3]]]]]
    tap_mult = mult[(np.arange(2)[:, None, None] + dy) & 1, (np.arange(2)[None, :, None] + dx) & 1]
    folded = taps * tap_mult[..., None]
    h, w = shape
    x = np.ascontiguousarray(x, np.float32)
    out = _empty((h, w, 3), np.float32)
    if var is None:
        var_planes, var_out = x, np.empty((1, 1, 3), np.float32)
    else:
        var_planes, var_out = np.ascontiguousarray(var, np.float32), _empty((h, w, 3), np.float32)
    with KERNEL_LOCK:
        demosaic_rows(x, var_planes, mult, ntaps, dy, dx, taps, taps * taps, folded, folded * folded,
                      bool(clip_negative), var is not None, out, var_out)
    return out, (var_out if var is not None else None)


def _menon_compiled(x, var, shape, pattern, multipliers, matrix, clip_negative):
    """:func:`demosaic_compiled` for ``method="menon2007"``: the white-balanced mosaic (and its
    variance) through :func:`derender.raw.menon.menon_demosaic`."""
    from derender.raw.menon import menon_demosaic

    lut = {"R": 0, "G": 1, "B": 2}
    chan = np.array([[lut[pattern[0]], lut[pattern[1]]], [lut[pattern[2]], lut[pattern[3]]]], np.int64)
    mult = np.asarray(multipliers, np.float32)[chan]
    h, w = shape
    xm = interleave(np.asarray(x, np.float32), shape)
    for a in range(2):
        for b in range(2):
            xm[a::2, b::2] *= mult[a, b]
    out = _empty((h, w, 3), np.float32)
    vm = var_out = None
    if var is not None:
        vm = interleave(np.asarray(var, np.float32), shape)
        for a in range(2):
            for b in range(2):
                vm[a::2, b::2] *= mult[a, b] * mult[a, b]
        var_out = _empty((h, w, 3), np.float32)
    menon_demosaic(xm, vm, pattern, matrix, clip_negative, out, var_out)
    return out, var_out


def _with_interpolation(x, out, var_out, shape, pattern, *, mult, mat, demosaic, clip_negative):
    """``var_out`` plus the interpolation term (:func:`derender.raw.interpolation.interpolation_variance`:
    the other demosaics of the same planes and the colour texture of eq. 2; added in place in one compiled pass,
    :func:`derender.raw.kernels.interpolation_rows`) and each term's median share of a pixel's
    variance (on every 4th row: ample)."""
    from derender.raw.interpolation import CHROMA_ESTIMATES, INTERPOLATION_ESTIMATES, chroma_phase_matrices
    from derender.raw.kernels import KERNEL_LOCK, interpolation_rows

    (name0, k0), (name1, k1) = INTERPOLATION_ESTIMATES[demosaic]
    o0 = demosaic_compiled(x, None, shape, pattern, mult, mat, name0, clip_negative)[0]
    o1 = demosaic_compiled(x, None, shape, pattern, mult, mat, name1, clip_negative)[0]
    source, phase, kc = np.zeros((1, 1, 3), np.float32), np.zeros((2, 2, 3, 3), np.float32), 0.0
    if demosaic in CHROMA_ESTIMATES:                  # eq. 2's colour texture, where it has one
        name, kc = CHROMA_ESTIMATES[demosaic]
        source = {demosaic: out, name0: o0, name1: o1}.get(name)
        if source is None:
            source = demosaic_compiled(x, None, shape, pattern, mult, mat, name, clip_negative)[0]
        phase = chroma_phase_matrices(mat, pattern)
    h, w = shape
    ratio = np.empty(((h + 3) // 4, w, 3))
    total = np.ascontiguousarray(var_out, np.float32)
    with KERNEL_LOCK:
        interpolation_rows(np.ascontiguousarray(out, np.float32), np.ascontiguousarray(o0, np.float32),
                           np.ascontiguousarray(o1, np.float32), np.ascontiguousarray(source, np.float32), phase,
                           float(k0), float(k1), float(kc), total, 4, ratio)
    del o0, o1, source
    r = ratio[ratio >= 0.0]
    if r.size == 0:
        return total, {"noise": 0.0, "interpolation": 0.0}
    share = float(np.median(r))
    return total, {"noise": 1.0 - share, "interpolation": share}


def raw_merge(frames: RawFrame | Sequence[RawFrame], *, output_space: str = "linear_srgb",
              gain: float | None = None, read_noise: float | None = None, wb: Sequence[float] | None = None,
              wb_patch: tuple[int, int, int, int] | None = None, demosaic: str = "malvar2004",
              variance: bool = True, clip_negative: bool = True, censored: bool = True,
              xyz_to_camera: np.ndarray | None = None, valid: Sequence[np.ndarray] | None = None,
              noise: NoiseModel | None = None, variance_factor: Sequence[np.ndarray] | None = None,
              variance_terms: str = "total") -> HDRResult:
    """Noise-optimal merge of RAW frames: censored Poisson-Gaussian ML on the mosaic, demosaiced once.

    ``gain`` (DN per electron) and ``read_noise`` (DN, read noise and quantisation) default to
    estimates from the frames themselves (:func:`derender.raw.noise.estimate_noise`); give both
    to use known values. A single frame takes its DNG ``NoiseProfile`` when it has one, else
    the green-pair estimate, an upper bound where the scene has texture. White balance: ``wb``
    multipliers (R, G, B), default the as-shot ones of the middle frame of the time-sorted
    stack, or ``wb_patch`` ``(x, y, w, h)``, a neutral region of the merged mosaic; it is
    applied on the mosaic before demosaicing in every output space, as
    :func:`derender.raw.groundtruth.raw_ground_truth` does, and divided out again after the
    demosaic in ``camera_rgb`` (:func:`white_balances`; a file without one: a grey-world
    estimate for the demosaic). ``censored=False``
    drops saturated samples instead (for comparison). ``info["noise"]`` holds the noise model
    used. The ``variance`` is that of ``radiance`` before negative values are clipped to 0.

    Parameters
    ----------
    frames : RawFrame or sequence of RawFrame
        The bracket (:func:`derender.io.raw.read_raw_stack`), with exposure times.
    output_space : str
        ``"linear_srgb"``, ``"camera_rgb"`` (no matrix; the white balance divided out after the
        demosaic) or ``"xyz"``.
    gain, read_noise : float, optional
        The noise model (DN per electron; DN), both or neither.
    wb : sequence of 3 floats, optional
        White-balance multipliers (R, G, B) (in ``camera_rgb``: the demosaic's balance only).
    wb_patch : (x, y, w, h), optional
        A neutral region of the merged mosaic that sets the white balance.
    demosaic : str
        ``"malvar2004"`` (default), ``"menon2007"`` (closer to the scene; its variance exact
        given its directions; its pass with the variance about 4x Malvar's), ``"ahd"`` (Hirakawa &
        Parks 2005, dcraw's; :mod:`derender.raw.ahd`; about 13x Malvar's) or ``"bilinear"``
        (aliases ``malvar``, ``menon``).
    variance : bool
        Also give the per-pixel variance of the radiance.
    clip_negative : bool
        Set negative radiance to 0.
    censored : bool
        Saturated samples count as censored observations (else they are dropped).
    xyz_to_camera : (3, 3) array, optional
        The camera's ColorMatrix, replacing the frames'.
    valid : sequence of (H, W) bool arrays, optional
        Per frame (in the order given), where it takes part: an aligned frame's border, the
        photosites ghost removal rejects (:func:`derender.hdr.raw.merge_raw` with ``motion``).
    noise : NoiseModel, optional
        The noise model to use (instead of ``gain`` and ``read_noise`` or an estimate from
        ``frames``: resampled frames would bias the estimate low).
    variance_factor : sequence of (2, 2) arrays, optional
        Per frame (in the order given) and CFA phase, the factor on the noise model's
        variance of its samples (a resampled frame's ``sum w^2``,
        :func:`derender.raw.register.resample_mosaic`; None: 1).
    variance_terms : {"total", "noise"}
        ``"total"`` (default): the merge's noise plus the demosaic's interpolation error
        estimated from the mosaic (:func:`derender.raw.interpolation.interpolation_variance`),
        the variance that holds against the scene; ``"noise"``: the noise only (exact against
        the demosaiced true mosaic, faster).

    Returns
    -------
    HDRResult
        ``radiance`` (H, W, 3) float32 in ``output_space`` (relative units), finite and
        non-negative; ``variance`` (H, W, 3) float32 when asked for; ``mask``; ``info``
        with ``noise``, the white balance of the demosaic (``wb_multipliers``), the one the
        output keeps (``output_wb_multipliers``) and the matrix after the demosaic
        (``output_matrix``).

    Raises
    ------
    InputError
        An unknown ``output_space`` or demosaicing method, only one of ``gain`` and
        ``read_noise``, malformed white-balance multipliers, a frame without a colour
        matrix when one is needed.

    Examples
    --------
    With a known noise model (gain 0.5 DN per electron, read noise 2 DN), in camera RGB:

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
    >>> result = derender.raw_merge(frames, output_space="camera_rgb", gain=0.5, read_noise=2.0)
    >>> result.radiance.shape, result.variance.shape, result.variance.dtype
    ((32, 32, 3), (32, 32, 3), dtype('float32'))
    >>> bool(np.all(result.variance > 0))
    True
    """
    given = [frames] if isinstance(frames, RawFrame) else list(frames)
    frames, times = sorted_raw_frames(given)
    valid_stack = None
    factor_stack = None
    if variance_factor is not None:
        if len(variance_factor) != len(given):
            raise InputError(f"variance_factor has {len(variance_factor)} entries for {len(given)} frames")
        by_id = {id(f): np.broadcast_to(np.asarray(v, np.float64), (2, 2)) for f, v in zip(given, variance_factor)}
        factor_stack = np.stack([by_id[id(f)] for f in frames])
    if valid is not None:
        if len(valid) != len(given):
            raise InputError(f"valid has {len(valid)} masks for {len(given)} frames")
        by_id = {id(f): np.asarray(v, bool) for f, v in zip(given, valid)}
        valid_stack = np.stack([by_id[id(f)] for f in frames])
        if valid_stack.shape[1:] != np.asarray(frames[0].mosaic).shape:
            raise InputError(f"valid masks must be {np.asarray(frames[0].mosaic).shape}, got {valid_stack.shape[1:]}")
    pattern = frames[0].cfa_pattern.upper()
    if (gain is None) != (read_noise is None):
        raise InputError("give both gain and read_noise, or neither (then they are estimated from the frames)")
    demosaic = demosaic_name(demosaic)
    if variance_terms not in VARIANCE_TERMS:
        raise InputError(f"variance_terms must be one of {', '.join(VARIANCE_TERMS)}, got {variance_terms!r}")
    mosaics, black, white = compiled_frames(frames)
    profile = frames[0].extra.get("noise_profile") if frames[0].extra else None
    if noise is not None:
        pass
    elif gain is None and len(frames) == 1 and profile is not None:
        span0 = float(np.median(white[0] - black[0]))
        noise = NoiseModel(profile[0] * span0, profile[1] * span0 ** 2, "NoiseProfile")
    elif gain is None and len(frames) == 1:
        d, sat, ceil = mosaic_observations(frames)
        noise = estimate_noise(d, sat, ceil, times, pattern)
        del d, sat, ceil
    elif gain is None:
        isos = [(f.extra or {}).get("iso") for f in frames]
        noise = estimate_noise_frames(mosaics, black, white, times, isos)
    else:
        noise = NoiseModel(float(gain), float(read_noise) ** 2, "given")
    top = int(np.argmax(white))
    span = white[top] - black[top]                       # (2, 2): white - black per CFA phase
    x, var, mmask = merge_compiled(mosaics, black, white, times, noise, censored=censored, scale=1.0 / span,
                                   valid=valid_stack, variance_factor=factor_stack)
    del mosaics
    ref = frames[len(frames) // 2]
    colour = output_matrix(ref, output_space, xyz_to_camera)
    mosaic = interleave(x, mmask.shape) if (wb_patch is not None or (ref.extra or {}).get("as_shot_wb_missing")) \
        else None
    mult, out_wb = white_balances(ref, output_space, wb, wb_patch, mosaic, pattern, mmask)
    del mosaic
    mat = colour @ np.diag(out_wb / mult)            # the balance divided out (camera_rgb), or kept
    out, var_out = demosaic_compiled(x, var if variance else None, mmask.shape, pattern, mult, mat, demosaic,
                                     clip_negative)
    shares = None
    if variance and variance_terms == "total":
        var_out, shares = _with_interpolation(x, out, var_out, mmask.shape, pattern, mult=mult, mat=mat,
                                              demosaic=demosaic, clip_negative=clip_negative)
    info = {"colour_space": output_space, "exposure_times": times.tolist(), "demosaic": demosaic,
            "cfa_pattern": pattern, "noise": noise.as_dict(), "censored": bool(censored),
            "units": "white level per second", "white_minus_black_dn": float(np.median(span)),
            "mosaic_mask": mmask, "n_frames": len(frames), "wb_multipliers": mult.tolist(),
            "output_wb_multipliers": out_wb.tolist(), "output_matrix": mat.tolist()}
    if variance:
        info["variance_terms"] = variance_terms
    if shares is not None:
        info["variance_sources"] = shares
    return HDRResult(radiance=out, mask=spread_mask(mmask, MASK_RADIUS[demosaic]), variance=var_out, info=info)
