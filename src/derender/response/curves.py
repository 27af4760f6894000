"""Camera response curves: Debevec & Malik (1997) and Robertson et al. (2003).

A response curve here is ``g = ln f^-1`` per channel, tabulated on ``n_levels`` code
levels (256 for 8-bit stacks): ``exp(g(z))`` is proportional to the exposure
``radiance * t`` that produced code ``z``. Each channel is recovered independently,
and each is anchored by ``g(mid) = 0`` with ``mid = n_levels // 2`` (Debevec & Malik
1997, Sec. 2.1: the curves are known up to one scale factor each). Consequently the
three channels are tied by the convention that the mid code ``(128, 128, 128)`` is
neutral: the radiance map's white balance is that of the camera's rendered grey, and
the relative scale of R, G, B is otherwise unknown (the paper white-balances
afterwards; the PSNR protocol fits one scale per channel). The classic merges
(:mod:`derender.hdr.classic`) instead keep ``g_G(mid) = 0`` and offset R and B so that
neutral colours stay neutral across the bracket (:func:`balance_channels`: near-neutral,
well-exposed sampled pixels of every frame come out grey); the calibration functions do so
with ``balance=True``.

16-bit stacks are reduced to ``n_levels`` by binning: code ``z in [0, 1]`` goes to
level ``rint(z * (n_levels - 1))`` for calibration; the merge interpolates ``g``
linearly between levels, so the full 16-bit precision is kept there.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from derender.core.errors import InputError, StackError
from derender.core.memory import N_CODES
from derender.core.types import Stack
from derender.engine.weights import get_weight, weight_hat

__all__ = [
    "histogram_samples",
    "check_usable_histograms",
    "check_usable_samples",
    "DEFAULT_LAMBDA",
    "DEFAULT_SAMPLES",
    "CHANNELS",
    "ResponseCurves",
    "to_codes",
    "stack_codes",
    "check_usable",
    "raise_unusable",
    "grid_positions",
    "sample_pixels",
    "level_weights",
    "isotonic_increasing",
    "make_monotonic",
    "isotonic_weighted",
    "smooth_log_curve",
    "log_slope",
    "neutral_offsets",
    "balance_channels",
    "DEFAULT_TIE",
    "tie_matrix",
    "solve_tied",
    "as_stack",
    "plot_response",
]


def histogram_samples(hists: np.ndarray, n_samples: int) -> np.ndarray:
    """Grossberg & Nayar histogram samples from per-image histograms (N, 3, 256): as ``sample_pixels(method="histogram")``."""
    n_img = hists.shape[0]
    u = np.linspace(0.0, 1.0, int(n_samples))
    out = np.empty((n_img, u.size, 3), dtype=np.int32)
    for j in range(n_img):
        for c in range(3):
            cdf = np.cumsum(hists[j, c]).astype(np.float64)
            cdf /= cdf[-1]
            out[j, :, c] = np.argmin(np.abs(cdf[None, :] - u[:, None]), axis=1)
    return out


def check_usable_histograms(hists: np.ndarray) -> None:
    """:func:`check_usable` from per-image histograms (N, 3, 256)."""
    raise_unusable(hists[:, :, 1:N_CODES - 1].sum(axis=(0, 2)) > 0)


def check_usable_samples(samples: np.ndarray, hists_fn: Callable[[], np.ndarray]) -> None:
    """:func:`check_usable` from sampled codes (N, P, 3): they settle it unless some channel
    shows no usable code among them, then the per-image histograms (``hists_fn()``) do."""
    if not np.all(((samples > 0) & (samples < N_CODES - 1)).any(axis=(0, 1))):
        check_usable_histograms(hists_fn())


#: Smoothness weight lambda of the Debevec system (the data rows have hat weights <= 1).
DEFAULT_LAMBDA = 30.0


#: Number of sampled pixel positions per channel for the Debevec system.
DEFAULT_SAMPLES = 256


#: Channel order of the curves (columns of ``ResponseCurves.log_inverse``).
CHANNELS = "RGB"


@dataclass
class ResponseCurves:
    """Inverse camera response per channel.

    Attributes
    ----------
    log_inverse : numpy.ndarray
        (n_levels, 3) float64, ``g = ln f^-1`` (natural log), ``g[n_levels // 2] = 0`` (in G
        only for colour-balanced curves, see :func:`balance_channels`).
    method : str
        ``"debevec"``, ``"robertson"`` or ``"external"``.
    params : dict
        How it was obtained (lambda, samples, sampling, seed, iterations ...).
    """

    log_inverse: np.ndarray
    method: str = "external"
    params: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        g = np.asarray(self.log_inverse, dtype=np.float64)
        if g.ndim == 1:
            g = np.repeat(g[:, None], 3, axis=1)
        if g.ndim != 2 or g.shape[1] != 3 or g.shape[0] < 2:
            raise InputError(f"response curves must have shape (n_levels, 3), got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise InputError("response curves contain NaN or inf")
        self.log_inverse = g

    @property
    def n_levels(self) -> int:
        """Number of tabulated code levels."""
        return int(self.log_inverse.shape[0])

    def inverse(self) -> np.ndarray:
        """``f^-1 = exp(g)`` per channel, (n_levels, 3), relative exposure units."""
        return np.exp(self.log_inverse)

    def log_linearise(self, image: np.ndarray) -> np.ndarray:
        """``g(z)`` of an (..., 3) image in [0, 1], linearly interpolated between levels, float32."""
        z = np.asarray(image, dtype=np.float32)
        if z.shape[-1] != 3:
            raise InputError(f"expected (..., 3) image, got {z.shape}")
        lv = self.n_levels
        x = np.clip(z, 0.0, 1.0) * np.float32(lv - 1)
        i0 = np.minimum(x.astype(np.int32), lv - 2)
        frac = x - i0.astype(np.float32)
        g = self.log_inverse.astype(np.float32)
        flat_idx = i0 * 3 + np.arange(3, dtype=np.int32)
        g0 = np.take(g.ravel(), flat_idx)
        dg = np.take(np.diff(g, axis=0).ravel(), flat_idx)
        return g0 + frac * dg

    def linearise(self, image: np.ndarray) -> np.ndarray:
        """``exp(g(z))``: values proportional to exposure (radiance * time), float32."""
        return np.exp(self.log_linearise(image))


# --------------------------------------------------------------------------- inputs
def to_codes(arr: np.ndarray, n_levels: int) -> np.ndarray:
    """int32 code levels in ``[0, n_levels - 1]``: integer arrays checked, float arrays in [0, 1] binned."""
    if arr.dtype.kind in "ui":
        if arr.size and (arr.min() < 0 or arr.max() > n_levels - 1):
            raise InputError(f"integer codes must lie in [0, {n_levels - 1}]")
        return arr.astype(np.int32)
    return np.rint(np.clip(arr, 0.0, 1.0) * (n_levels - 1)).astype(np.int32)


def _images_of(stack_or_images: Any) -> np.ndarray:
    arr = stack_or_images.images if isinstance(stack_or_images, Stack) else np.asarray(stack_or_images)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"expected images of shape (N, H, W, 3), got {arr.shape}")
    return arr


def stack_codes(stack_or_images: Any, n_levels: int = 256) -> np.ndarray:
    """Integer code levels (N, H, W, 3) in ``[0, n_levels - 1]`` of a Stack or array.

    Float arrays are taken as values in [0, 1] and binned with ``rint(z * (n_levels - 1))``;
    integer arrays are used as they are (and must lie in range).
    """
    return to_codes(_images_of(stack_or_images), n_levels)


def check_usable(stack_or_codes: Any, n_levels: int = 256) -> None:
    """Raise :class:`StackError` unless every channel has some code strictly inside (0, n_levels - 1).

    Float images count as usable where ``rint(z * (n_levels - 1))`` is neither 0 nor
    ``n_levels - 1``.
    """
    arr = _images_of(stack_or_codes)
    if arr.dtype.kind in "ui":
        lo, hi = 0.5, n_levels - 1.5
    else:
        lo, hi = 0.5 / (n_levels - 1), 1.0 - 0.5 / (n_levels - 1)
    usable = np.zeros(3, dtype=bool)
    for j in range(arr.shape[0]):
        zj = arr[j]
        usable |= ((zj > lo) & (zj < hi)).any(axis=(0, 1))
        if usable.all():
            return
    raise_unusable(usable)


def raise_unusable(usable: np.ndarray) -> None:
    """Raise :class:`StackError` for per-channel usability flags (3,) that are not all true."""
    if usable.all():
        return
    if not usable.any():
        raise StackError("no pixel of any image is exposed within the usable range "
                         "(every value is black or clipped); nothing to merge")
    bad = ", ".join(CHANNELS[c] for c in range(3) if not usable[c])
    raise StackError(f"channel {bad} is black or clipped in every pixel of every image; cannot recover its response")


def grid_positions(h: int, w: int, n: int, seed: int, border: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid of about ``n`` positions, ``border`` fraction away from the edges, jittered by ``seed``."""
    n = max(1, int(n))
    ny = max(1, int(round(np.sqrt(n * h / max(w, 1)))))
    nx = max(1, int(np.ceil(n / ny)))
    ny, nx = min(ny, h), min(nx, w)
    y0, y1 = border * (h - 1), (1 - border) * (h - 1)
    x0, x1 = border * (w - 1), (1 - border) * (w - 1)
    rng = np.random.default_rng(seed)
    jy, jx = rng.uniform(-0.5, 0.5, size=2)
    sy, sx = (y1 - y0) / ny, (x1 - x0) / nx
    ys = np.clip(np.rint(y0 + (np.arange(ny) + 0.5 + 0.5 * jy) * sy), 0, h - 1).astype(int)
    xs = np.clip(np.rint(x0 + (np.arange(nx) + 0.5 + 0.5 * jx) * sx), 0, w - 1).astype(int)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return yy.ravel()[:n], xx.ravel()[:n]


#: Neighbours of a uniform-region sample (:func:`cluster_positions`): offsets -R, 0, +R in y and x.
CLUSTER_REACH = 2


def cluster_positions(h: int, w: int, n: int, seed: int, reach: int = CLUSTER_REACH) -> tuple[np.ndarray, np.ndarray]:
    """Candidates for :func:`uniform_samples`: ``4 n`` grid positions (:func:`grid_positions`), each
    with its 8 neighbours at ``+-reach`` pixels, flattened as ``(4 n) x 9`` positions (centre 5th)."""
    ys, xs = grid_positions(h, w, 4 * int(n), seed)
    ys = np.clip(ys, reach, max(reach, h - 1 - reach))
    xs = np.clip(xs, reach, max(reach, w - 1 - reach))
    d = np.array([-reach, 0, reach])
    dy, dx = np.meshgrid(d, d, indexing="ij")
    yy = np.clip(ys[:, None] + dy.ravel()[None, :], 0, h - 1)
    xx = np.clip(xs[:, None] + dx.ravel()[None, :], 0, w - 1)
    return yy.ravel(), xx.ravel()


def uniform_samples(cluster_codes: np.ndarray, n: int, clip_code: int = 250) -> np.ndarray:
    """The centres of at most ``n`` clusters (:func:`cluster_positions`; ``cluster_codes`` (N, 9 M, 3))
    that never see a clipped neighbour while unclipped themselves: a cluster is dropped if in some
    frame one of its 8 neighbours has a channel at ``clip_code`` or above while the centre's
    channels are all below it. Kept clusters are spread evenly (``n`` of them); if fewer than
    ``n / 4`` pass, the ``n / 4`` with the fewest such frames.

    Why: a pixel beside a much brighter one (the rim of a window or a lamp) receives
    part of its neighbour's signal through demosaicing and chroma noise reduction, and once the
    neighbour clips its codes stop following the exposure. Such samples gave the curve's top
    codes their data and bent it (docs/results-luminance.md). Debevec & Malik (1997, Sec. 2.1) take
    samples in regions of low intensity variance; elsewhere the samples are the plain grid's.
    """
    c = np.asarray(cluster_codes)
    n_img, p, _ = c.shape
    c = c.reshape(n_img, p // 9, 9, 3)
    centre = c[:, :, 4, :]
    worst = np.zeros(p // 9, dtype=np.int64)
    for j in range(n_img):      # one frame at a time: the temporaries stay one frame's size
        top = c[j].max(axis=2)                                   # (M, 9) brightest channel per position
        centre_top = top[:, 4].copy()
        top[:, 4] = 0
        worst += (top.max(axis=1) >= clip_code) & (centre_top < clip_code)
    ok = np.flatnonzero(worst == 0)
    need = max(1, int(n) // 4)
    if ok.size < need:
        ok = np.sort(np.argsort(worst, kind="stable")[:need])
    if ok.size > n:
        ok = ok[np.linspace(0, ok.size - 1, int(n)).round().astype(int)]
    return np.ascontiguousarray(centre[:, ok, :].astype(np.int32))


def sample_pixels(stack_or_codes: Any, n_samples: int = DEFAULT_SAMPLES, method: str = "grid",
                  seed: int = 0, n_levels: int = 256) -> np.ndarray:
    """Samples for response recovery, (N_img, P, 3) int32 code levels.

    ``"grid"``: the codes at ``P = n_samples`` pixel positions on a regular grid over
    the image minus a 5 % border (ny x nx cells with the image's aspect ratio; the
    grid is shifted by up to half a cell by ``seed``). Needs an aligned stack.

    ``"histogram"``: Grossberg & Nayar (2003, Sec. 5) histogram matching: for ``P``
    equally spaced quantiles ``u`` in [0, 1], the code of each image whose cumulative
    histogram is closest to ``u`` (first such code). Codes at equal quantiles
    correspond if the response is monotonic, so no registration is needed; ``seed`` is
    unused. Matches colour-hdri's ``samples_Grossberg2003`` for 8-bit input.
    """
    arr = _images_of(stack_or_codes)
    n_img, h, w, _ = arr.shape
    if n_samples < 1:
        raise InputError(f"n_samples must be positive, got {n_samples}")
    if method == "grid":
        ys, xs = cluster_positions(h, w, n_samples, seed)
        return uniform_samples(to_codes(arr[:, ys, xs, :], n_levels), n_samples)
    if method == "histogram":
        codes = to_codes(arr, n_levels)
        u = np.linspace(0.0, 1.0, int(n_samples))
        out = np.empty((n_img, u.size, 3), dtype=np.int32)
        for j in range(n_img):
            for c in range(3):
                hist = np.bincount(codes[j, :, :, c].ravel(), minlength=n_levels)
                cdf = np.cumsum(hist).astype(np.float64)
                cdf /= cdf[-1]
                out[j, :, c] = np.argmin(np.abs(cdf[None, :] - u[:, None]), axis=1)
        return out
    raise InputError(f"unknown sampling method {method!r}; use 'grid' or 'histogram'")


# --------------------------------------------------------------------------- Debevec
def level_weights(weights: Any, n_levels: int) -> np.ndarray:
    """A weight per code level: a weight name or callable evaluated on ``linspace(0, 1, n_levels)``
    (hat when None), or a table of ``n_levels`` values."""
    if weights is None:
        weights = weight_hat
    if callable(weights) or isinstance(weights, str):
        fn = get_weight(weights)
        return np.asarray(fn(np.linspace(0.0, 1.0, n_levels)), dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.size != n_levels:
        raise InputError(f"weights table has {w.size} entries, expected {n_levels}")
    return w


def isotonic_increasing(y: np.ndarray) -> np.ndarray:
    """Least-squares non-decreasing fit to ``y`` (pool-adjacent-violators), 1-D."""
    y = np.asarray(y, dtype=np.float64)
    vals: list[float] = []
    counts: list[int] = []
    for v in y:
        vals.append(float(v))
        counts.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            c = counts[-2] + counts[-1]
            vals[-2] = (vals[-2] * counts[-2] + vals[-1] * counts[-1]) / c
            counts[-2] = c
            vals.pop()
            counts.pop()
    return np.repeat(np.asarray(vals), counts)


def make_monotonic(g: np.ndarray) -> np.ndarray:
    """Make each column non-decreasing by isotonic regression, then re-anchor ``g(mid) = 0``."""
    out = np.empty_like(g)
    mid = g.shape[0] // 2
    for c in range(g.shape[1]):
        col = g[:, c] if np.all(np.diff(g[:, c]) >= 0) else isotonic_increasing(g[:, c])
        out[:, c] = col - col[mid]
    return out


def isotonic_weighted(y: np.ndarray, w: np.ndarray, min_step: float = 0.0) -> np.ndarray:
    """Weighted least-squares fit to ``y`` with steps ``fit[k+1] - fit[k] >= min_step`` (pool-adjacent-violators).

    Weights ``w >= 0`` (a zero-weight point takes its block's value); ``min_step = 0`` is
    the plain non-decreasing fit. Solved as the isotonic fit of ``y - min_step * k`` plus
    ``min_step * k``.
    """
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    w = np.maximum(np.asarray(w, dtype=np.float64).reshape(-1), 0.0) + 1e-12
    ramp = float(min_step) * np.arange(y.size)
    v = y - ramp
    vals: list[float] = []
    wts: list[float] = []
    counts: list[int] = []
    for yi, wi in zip(v, w):
        vals.append(float(yi))
        wts.append(float(wi))
        counts.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            ws = wts[-2] + wts[-1]
            vals[-2] = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / ws
            wts[-2] = ws
            counts[-2] += counts[-1]
            vals.pop()
            wts.pop()
            counts.pop()
    return np.repeat(np.asarray(vals), counts) + ramp


def smooth_log_curve(y: np.ndarray, w: np.ndarray, lam: float) -> np.ndarray:
    """Whittaker smoother: ``argmin_g sum_z w(z) (g(z) - y(z))^2 + lam sum_z g''(z)^2``, 1-D.

    Zero-weight levels (never observed, or clipped) are filled by the smoothness term:
    interpolated between observed levels, extended linearly beyond them (no flat steps).
    """
    from scipy.linalg import solveh_banded

    y = np.asarray(y, dtype=np.float64).reshape(-1)
    w = np.asarray(w, dtype=np.float64).reshape(-1)
    n = y.size
    # lam D'D (D the second difference, (n-2, n)) + diag(w): symmetric pentadiagonal, upper form
    ab = np.zeros((3, n))
    k = np.arange(n - 2)
    for a_, b_, v in ((0, 0, 1.0), (1, 1, 4.0), (2, 2, 1.0)):
        np.add.at(ab[2], k + a_, lam * v)
    np.add.at(ab[1], k + 1, -2.0 * lam)  # (k, k+1) and (k+1, k+2) entries
    np.add.at(ab[1], k + 2, -2.0 * lam)
    np.add.at(ab[0], k + 2, lam)  # (k, k+2)
    ab[2] += w + 1e-12
    return solveh_banded(ab, w * np.where(w > 0, y, 0.0))


def log_slope(g: np.ndarray, floor: float) -> np.ndarray:
    """``g'(z)`` per level (central differences, one-sided at the ends), at least ``floor``; same shape as ``g``."""
    return np.maximum(np.gradient(np.asarray(g, dtype=np.float64), axis=0), floor)


#: Codes within this many levels of each other count as a neutral (grey) colour.
NEUTRAL_TOLERANCE = 8
#: Fewest neutral observations for :func:`neutral_offsets` to use them (else the grey axis).
NEUTRAL_MIN_COUNT = 16


def neutral_offsets(g: np.ndarray, codes: np.ndarray, weights: Any = "hat", min_weight: float = 0.25,
                    tolerance: int = NEUTRAL_TOLERANCE, min_count: int = NEUTRAL_MIN_COUNT,
                    mode: str = "neutral") -> tuple[np.ndarray, dict]:
    """Per-channel log offsets ``o`` (``o[G] = 0``) that keep neutral colours neutral: ``g_c + o_c``.

    ``codes`` (N, P, 3) int: the sampled pixels of every frame (all three channels at the
    same pixel). A camera renders neutral surfaces with equal codes (that is what its white
    balance does), so the recovered log exposures of such a pixel should be equal:
    ``o_c = median(g_G(z_G) - g_c(z_c))`` over the *near-neutral, well-exposed*
    observations (all codes within ``tolerance`` of each other, every channel's weight at
    least ``min_weight``). With fewer than ``min_count`` of them, over the *grey axis*
    instead: ``median(g_G(z) - g_c(z))`` over the well-exposed green codes ``z`` of every
    observation (equal codes taken as neutral). ``mode="grey-axis"`` always does the latter:
    the choice for tied curves (:func:`solve_tied`), whose differences hardly change with the
    code, so that equal codes give equal radiance over the whole well-exposed range (the
    near-neutral observations, up to ``tolerance`` codes apart, carry the scene's colours'
    bias: 10 % in B on the simulator's nominal rendering). Returns ``(o (3,), info)``.
    """
    if mode not in ("neutral", "grey-axis"):
        raise InputError(f"unknown balance mode {mode!r}: use 'neutral' or 'grey-axis'")
    g = np.asarray(g, dtype=np.float64)
    n_levels = g.shape[0]
    z = np.asarray(codes).reshape(-1, 3).astype(np.int64)
    wl = level_weights(weights, n_levels)
    ok = (wl[z] >= min_weight).all(axis=1)
    neutral = ok & (np.abs(z - z[:, 1:2]).max(axis=1) <= tolerance)
    off = np.zeros(3)
    if mode == "neutral" and int(neutral.sum()) >= min_count:
        zn = z[neutral]
        for c in (0, 2):
            off[c] = float(np.median(g[zn[:, 1], 1] - g[zn[:, c], c]))
        return off, {"balance": "neutral", "neutral_count": int(neutral.sum())}
    zg = z[wl[z[:, 1]] >= min_weight, 1]
    if zg.size == 0:
        return off, {"balance": "none", "neutral_count": int(neutral.sum())}
    for c in (0, 2):
        off[c] = float(np.median(g[zg, 1] - g[zg, c]))
    return off, {"balance": "grey-axis", "neutral_count": int(neutral.sum())}


def balance_channels(g: np.ndarray, codes: np.ndarray, weights: Any = "hat",
                     mode: str = "neutral") -> tuple[np.ndarray, dict]:
    """``g + o`` with the :func:`neutral_offsets` ``o`` of ``codes`` (``mode`` as there); info gains ``channel_offsets``."""
    off, info = neutral_offsets(g, codes, weights, mode=mode)
    info["channel_offsets"] = [float(v) for v in off]
    return np.asarray(g, dtype=np.float64) + off[None, :], info


#: Weight ``mu`` of the channel tie (:func:`solve_tied`) in the classic calibrations: the curves of
#: R, G and B share one shape unless the data insist. Chosen on the tuning families
#: (``paper``, ``camera``; outdoor + indoor x seeds 0-1, 192x128, 7 exposures): Debevec PSNR L
#: 43.48 / 42.74 dB independent, 43.33 / 42.94 at 100, 43.54 / 42.95 at 1000, 43.63 / 42.93 at
#: 10^4; the largest deviation of frame-grey pixels from grey 0.113 / 0.153, 0.104 / 0.097,
#: 0.085 / 0.094, 0.072 / 0.099; Robertson 42.61 / 43.06 independent, 42.65 / 43.64 at 1000,
#: 42.85 / 43.79 at 10^4 (greys 0.110 / 0.129 at 1000, 0.123 / 0.147 at 10^4). The tie assumes
#: channel curves of one shape: a camera whose curves differ (``dslr-lut``'s per-channel gammas,
#: the test suite's synthetic knees) is fitted less well at the ends of the range; see
#: ``docs/paper1.md``.
DEFAULT_TIE = 1000.0


def tie_matrix(n_levels: int) -> np.ndarray:
    """``D1' D1`` (n_levels, n_levels): the sum of squared first differences ``sum_z (x(z+1) - x(z))^2`` as ``x' L x``."""
    d = np.diff(np.eye(n_levels), axis=0)
    return d.T @ d


def solve_tied(blocks: list[np.ndarray], rhs: list[np.ndarray], mu: float) -> np.ndarray:
    """Three per-channel quadratic problems ``min_c x_c' A_c x_c - 2 b_c' x_c`` solved jointly with the tie

    ``mu sum_{c < c'} sum_z [(g_c - g_c')(z + 1) - (g_c - g_c')(z)]^2``:

    the differences between channel curves are penalised for *changing* with the code, not
    for being non-zero, so the channels keep their own offsets (white balance) while equal
    codes of a neutral surface keep giving equal log exposures at every level, unless the
    data (a camera whose channel curves differ) outweigh ``mu``. ``mu = 0`` solves the
    channels independently. Returns the (n_levels, 3) solution; right-hand sides of shape
    (n_levels, k) (k systems at once) give (n_levels, 3, k).
    """
    from derender.core.parallel import one_blas_thread

    with one_blas_thread():     # 256-square systems: threads only wait on a busy machine
        return _solve_tied(blocks, rhs, mu)


def _solve_tied(blocks: list[np.ndarray], rhs: list[np.ndarray], mu: float) -> np.ndarray:
    n = blocks[0].shape[0]
    mu = max(float(mu), 0.0)
    r = [np.asarray(b, dtype=np.float64) for b in rhs]
    if mu == 0.0:
        x = [solve_symmetric(lambda a=a: np.array(a, dtype=np.float64), b) for a, b in zip(blocks, r)]
    else:
        # The system is blockdiag(B_c) - mu (J kron L) with B_c = A_c + 3 mu L (J: 3x3 ones): with
        # s = x_R + x_G + x_B, x_c = B_c^-1 (r_c + mu L s), so (I - mu M L) s = sum_c B_c^-1 r_c
        # with M = sum_c B_c^-1: four n x n systems instead of one 3n x 3n (memory: the engine
        # calibrates while it holds the frames).
        from scipy.linalg import cho_factor, cho_solve

        lap = tie_matrix(n) * mu
        eye = np.eye(n)
        facs, m_sum, q = [], np.zeros((n, n)), 0.0
        for a, b in zip(blocks, r):
            try:
                fac = cho_factor(np.asarray(a, dtype=np.float64) + 3.0 * lap, check_finite=False)
                inv = lambda v, fac=fac: cho_solve(fac, v, check_finite=False)  # noqa: E731
            except np.linalg.LinAlgError:     # not positive definite: least squares
                mat = np.asarray(a, dtype=np.float64) + 3.0 * lap
                inv = lambda v, mat=mat: np.linalg.lstsq(mat, v, rcond=None)[0]  # noqa: E731
            facs.append(inv)
            m_sum += inv(eye)
            q = q + inv(b)
        s_all = solve_symmetric(lambda: eye - m_sum @ lap, q, symmetric=False)
        x = [inv(b + lap @ s_all) for inv, b in zip(facs, r)]
    return np.stack(x, axis=1)


def solve_symmetric(build: Callable[[], np.ndarray], rhs: np.ndarray, symmetric: bool = True) -> np.ndarray:
    """``a x = rhs`` for ``a = build()`` (symmetric unless told), factorised in place (one BLAS
    thread, no copy of ``a``); least squares on a fresh ``build()`` where ``a`` is singular or the
    solution is not finite."""
    from scipy.linalg import LinAlgError, solve

    from derender.core.parallel import one_blas_thread

    with one_blas_thread():
        try:
            if symmetric:
                # a is symmetric: its transpose is the same matrix, in the Fortran order LAPACK
                # overwrites without a copy
                x = solve(build().T, rhs, assume_a="sym", overwrite_a=True, check_finite=False)
            else:
                x = solve(build(), rhs, overwrite_a=True, check_finite=False)
            if not np.all(np.isfinite(x)):
                raise LinAlgError
        except (LinAlgError, ValueError):
            x = np.linalg.lstsq(build(), rhs, rcond=None)[0]
    return x


def as_stack(stack: Any) -> Stack:
    """``stack`` itself if it is a :class:`~derender.core.types.Stack`, else an :class:`InputError`."""
    if not isinstance(stack, Stack):
        raise InputError(f"expected a Stack, got {type(stack).__name__}")
    return stack


# --------------------------------------------------------------------------- plots
def plot_response(curves: ResponseCurves, path: str | os.PathLike, inputs=()) -> Path:
    """Plot ``g = ln f^-1`` per channel against the code level (PNG/PDF/SVG by suffix), atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from derender.io.files import atomic_output

    g = curves.log_inverse
    fig = Figure(figsize=(5.5, 4.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(curves.n_levels)
    for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(x, g[:, c], color=colour, label=CHANNELS[c])
    ax.set_xlabel("code level z")
    ax.set_ylabel("g(z) = ln f$^{-1}$(z)  (relative log exposure)")
    ax.set_title(f"Response curves ({curves.method})")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".").lower() or "png")
    return path
