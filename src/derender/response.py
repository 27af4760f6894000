"""Camera response curves: Debevec & Malik (1997) and Robertson et al. (2003).

A response curve here is ``g = ln f^-1`` per channel, tabulated on ``n_levels`` code
levels (256 for 8-bit stacks): ``exp(g(z))`` is proportional to the exposure
``radiance * t`` that produced code ``z``. Each channel is recovered independently,
and each is anchored by ``g(mid) = 0`` with ``mid = n_levels // 2`` (Debevec & Malik
1997, Sec. 2.1: the curves are known up to one scale factor each). Consequently the
three channels are tied by the convention that the mid code ``(128, 128, 128)`` is
neutral: the radiance map's white balance is that of the camera's rendered grey, and
the relative scale of R, G, B is otherwise unknown (the paper white-balances
afterwards; the PSNR protocol fits one scale per channel).

16-bit stacks are reduced to ``n_levels`` by binning: code ``z in [0, 1]`` goes to
level ``rint(z * (n_levels - 1))`` for calibration; the merge interpolates ``g``
linearly between levels, so the full 16-bit precision is kept there.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError, StackError
from .merge import get_weight, weight_hat
from .stack import Stack

__all__ = [
    "ResponseCurves",
    "DEFAULT_LAMBDA",
    "DEFAULT_SAMPLES",
    "stack_codes",
    "check_usable",
    "sample_pixels",
    "solve_debevec",
    "isotonic_increasing",
    "calibrate_debevec",
    "calibrate_robertson",
    "plot_response",
]

#: Smoothness weight lambda of the Debevec system (the data rows have hat weights <= 1).
DEFAULT_LAMBDA = 30.0
#: Number of sampled pixel positions per channel for the Debevec system.
DEFAULT_SAMPLES = 256
_CHANNELS = "RGB"


@dataclass
class ResponseCurves:
    """Inverse camera response per channel.

    log_inverse : (n_levels, 3) float64, ``g = ln f^-1`` (natural log), ``g[n_levels // 2] = 0``.
    method : ``"debevec"``, ``"robertson"`` or ``"external"``.
    params : how it was obtained (lambda, samples, sampling, seed, iterations ...).
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
def _to_codes(arr: np.ndarray, n_levels: int) -> np.ndarray:
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
    return _to_codes(_images_of(stack_or_images), n_levels)


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
    bad = ", ".join(_CHANNELS[c] for c in range(3) if not usable[c])
    raise StackError(f"channel {bad} is black or clipped in every pixel of every image; cannot recover its response")


def _grid_positions(h: int, w: int, n: int, seed: int, border: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
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
        ys, xs = _grid_positions(h, w, n_samples, seed)
        return np.ascontiguousarray(_to_codes(arr[:, ys, xs, :], n_levels))
    if method == "histogram":
        codes = _to_codes(arr, n_levels)
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
def _level_weights(weights: Any, n_levels: int) -> np.ndarray:
    if weights is None:
        weights = weight_hat
    if callable(weights) or isinstance(weights, str):
        fn = get_weight(weights)
        return np.asarray(fn(np.linspace(0.0, 1.0, n_levels)), dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.size != n_levels:
        raise InputError(f"weights table has {w.size} entries, expected {n_levels}")
    return w


def solve_debevec(codes: np.ndarray, log_times: np.ndarray, lam: float = DEFAULT_LAMBDA,
                  weights: Any = None, n_levels: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares response recovery of Debevec & Malik (1997), Sec. 2.1 (their ``gsolve``).

    Minimises ``sum_ij [w(Z_ij) (g(Z_ij) - ln E_i - ln dt_j)]^2
    + sum_z [lam w(z) g''(z)]^2`` subject to ``g(mid) = 0`` (one equation of weight 1,
    ``mid = n_levels // 2``), for one channel. ``codes`` is (N_img, P), ``log_times``
    (N_img,), ``weights`` a name, a callable on [0, 1] (default hat) or an
    (n_levels,) table. Returns ``(g (n_levels,), ln E (P,))``.

    Solved exactly (same minimiser as the dense system) via the normal equations with
    the diagonal ``ln E`` block eliminated (Schur complement): an ``n_levels`` square
    system, fast for any number of samples. Samples with zero weight in every image
    get ``ln E = 0`` (their value is undetermined).
    """
    z = np.asarray(codes)
    if z.ndim != 2:
        raise InputError(f"codes must be (N_img, P), got {z.shape}")
    z = z.astype(np.int64)
    b = np.asarray(log_times, dtype=np.float64).reshape(-1)
    n_img, p = z.shape
    if b.size != n_img:
        raise InputError(f"{b.size} log times for {n_img} images")
    if z.size and (z.min() < 0 or z.max() >= n_levels):
        raise InputError(f"codes must lie in [0, {n_levels - 1}]")
    wl = _level_weights(weights, n_levels)
    w2 = wl[z] ** 2  # (N, P) squared data-row weights
    d = w2.sum(axis=0)  # diagonal of the ln E block
    # g-g block: data + constraint + smoothness
    a_gg = np.diag(np.bincount(z.ravel(), weights=w2.ravel(), minlength=n_levels))
    mid = n_levels // 2
    a_gg[mid, mid] += 1.0
    k = np.arange(1, n_levels - 1)
    s = (lam * wl[k]) ** 2
    stencil = np.array([1.0, -2.0, 1.0])
    for a in range(3):
        for c in range(3):
            a_gg[k - 1 + a, k - 1 + c] += s * stencil[a] * stencil[c]
    b_g = np.bincount(z.ravel(), weights=(w2 * b[:, None]).ravel(), minlength=n_levels)
    b_e = -(w2 * b[:, None]).sum(axis=0)
    # g-E coupling: M[z, p] = -sum_j w2[j, p] [z_jp = z]
    m = np.zeros((n_levels, p))
    np.add.at(m, (z, np.broadcast_to(np.arange(p), z.shape)), -w2)
    live = d > 0
    dinv = np.zeros(p)
    dinv[live] = 1.0 / d[live]
    schur = a_gg - (m * dinv) @ m.T
    rhs = b_g - m @ (dinv * b_e)
    try:
        g = np.linalg.solve(schur, rhs)
        if not np.all(np.isfinite(g)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        g = np.linalg.lstsq(schur, rhs, rcond=None)[0]
    log_e = np.zeros(p)
    log_e[live] = ((w2 * (g[z] - b[:, None])).sum(axis=0))[live] * dinv[live]
    return g, log_e


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


def _monotonic(g: np.ndarray) -> np.ndarray:
    """Make each column non-decreasing by isotonic regression, then re-anchor ``g(mid) = 0``."""
    out = np.empty_like(g)
    mid = g.shape[0] // 2
    for c in range(g.shape[1]):
        col = g[:, c] if np.all(np.diff(g[:, c]) >= 0) else isotonic_increasing(g[:, c])
        out[:, c] = col - col[mid]
    return out


def _as_stack(stack: Any) -> Stack:
    if not isinstance(stack, Stack):
        raise InputError(f"expected a Stack, got {type(stack).__name__}")
    return stack


def calibrate_debevec(stack: Stack, lam: float = DEFAULT_LAMBDA, n_samples: int = DEFAULT_SAMPLES,
                      sampling: str = "grid", seed: int = 0, weights: Any = "hat", n_levels: int = 256,
                      monotonic: bool = True) -> ResponseCurves:
    """Recover ``g = ln f^-1`` per channel with :func:`solve_debevec` (Debevec & Malik 1997).

    Samples by :func:`sample_pixels`; channels solved independently, each with
    ``g(mid) = 0`` (see the module docstring for what that implies for colour).
    With ``monotonic=True`` a non-monotonic least-squares solution is replaced by its
    isotonic (pool-adjacent-violators) least-squares fit, so ``g`` is non-decreasing;
    ``params["monotonic_fixed"]`` says per channel whether that was needed. If a
    grid sample misses every usable code of a channel, histogram samples are added.
    """
    stack = _as_stack(stack)
    if lam < 0 or not np.isfinite(lam):
        raise InputError(f"lambda must be a non-negative number, got {lam}")
    check_usable(stack, n_levels)
    samples = sample_pixels(stack, n_samples=n_samples, method=sampling, seed=seed, n_levels=n_levels)
    log_t = np.log(stack.times)
    g = np.empty((n_levels, 3))
    fixed = []
    for c in range(3):
        zc = samples[:, :, c]
        if not np.any((zc > 0) & (zc < n_levels - 1)):
            extra = sample_pixels(stack, n_samples=n_samples, method="histogram", n_levels=n_levels)[:, :, c]
            zc = np.concatenate([zc, extra], axis=1)
        g[:, c], _ = solve_debevec(zc, log_t, lam=lam, weights=weights, n_levels=n_levels)
        fixed.append(bool(np.any(np.diff(g[:, c]) < 0)))
    if monotonic:
        g = _monotonic(g)
    params = {"lambda": float(lam), "n_samples": int(n_samples), "sampling": sampling, "seed": int(seed),
              "weights": weights if isinstance(weights, str) else "custom", "monotonic_fixed": fixed}
    return ResponseCurves(log_inverse=g, method="debevec", params=params)


# --------------------------------------------------------------------------- Robertson
def calibrate_robertson(stack: Stack, n_iter: int = 30, tol: float = 1e-6, max_pixels: int = 40_000,
                        weight: Any = "gaussian", n_levels: int = 256, seed: int = 0) -> ResponseCurves:
    """Iterative response recovery of Robertson, Borman & Stevenson (1999; JEI 2003, Sec. 3).

    Alternates the maximum-likelihood radiance ``E_i = sum_j w_ij t_j I(z_ij) /
    sum_j w_ij t_j^2`` with ``I(m) = mean of t_j E_i over all (i, j) with z_ij = m``,
    normalising ``I(mid) = 1``; starts from the linear ``I(m) = m / mid``; stops after
    ``n_iter`` iterations or when the mean squared change of ``I`` drops below ``tol``.
    Uses at most ``max_pixels`` pixels (a regular grid). Levels never observed are
    interpolated in ``I``; the result is made non-decreasing in ``ln I`` like
    :func:`calibrate_debevec`.
    """
    stack = _as_stack(stack)
    check_usable(stack, n_levels)
    n_img, h, w_, _ = stack.images.shape
    ys, xs = _grid_positions(h, w_, min(max_pixels, h * w_), seed, border=0.0)
    z = _to_codes(stack.images[:, ys, xs, :], n_levels)  # (N, P, 3)
    wl = _level_weights(weight, n_levels)
    t = stack.times[:, None, None]
    wz = wl[z]
    wt = wz * t  # (N, P, 3)
    den = (wz * t * t).sum(axis=0)  # (P, 3), constant over iterations
    live = den > 0
    inv_den = np.where(live, 1.0 / np.where(live, den, 1.0), 0.0)
    flat = (z * 3 + np.arange(3)).ravel()  # level-major index into the (n_levels, 3) table
    live_obs = np.broadcast_to(live, z.shape).ravel().astype(np.float64)
    card = np.bincount(flat, weights=live_obs, minlength=3 * n_levels).reshape(n_levels, 3)
    seen = card > 0
    for c in range(3):
        if not np.any(seen[:, c]):
            raise StackError(f"channel {_CHANNELS[c]} has no usable pixel; cannot recover its response")
    mid = n_levels // 2
    inv = np.repeat((np.arange(n_levels, dtype=np.float64) / mid)[:, None], 3, axis=1)
    levels = np.arange(n_levels)
    iters = 0
    for iters in range(1, int(n_iter) + 1):
        e = (wt * inv.ravel()[flat].reshape(z.shape)).sum(axis=0) * inv_den  # (P, 3) ML radiance
        te = (t * e[None]).ravel() * live_obs
        tot = np.bincount(flat, weights=te, minlength=3 * n_levels).reshape(n_levels, 3)
        new = np.empty_like(inv)
        for c in range(3):
            sc = seen[:, c]
            new[:, c] = np.interp(levels, levels[sc], tot[sc, c] / card[sc, c])
            if new[mid, c] <= 0:
                raise StackError(f"channel {_CHANNELS[c]}: degenerate response (mid-grey maps to zero)")
            new[:, c] /= new[mid, c]
        change = float(np.mean((new - inv) ** 2))
        inv = new
        if change < tol:
            break
    positive = inv[inv > 0]
    floor = positive.min() * 0.5 if positive.size else 1e-6
    g = np.log(np.maximum(inv, floor))
    # Levels of zero weight (the clipped ends) carry no information in Robertson's update
    # (I(255) is the mean of t E over clipped pixels, i.e. anything above saturation): extend
    # g linearly from the two nearest weighted levels instead, like Debevec's smooth ends.
    nz = np.flatnonzero(wl > 0)
    if nz.size >= 2:
        lo, hi = int(nz[0]), int(nz[-1])
        if lo > 0:
            g[:lo] = g[lo] + (np.arange(lo) - lo)[:, None] * (g[lo + 1] - g[lo])
        if hi < n_levels - 1:
            g[hi + 1:] = g[hi] + (np.arange(hi + 1, n_levels) - hi)[:, None] * (g[hi] - g[hi - 1])
    g = _monotonic(g)
    return ResponseCurves(log_inverse=g, method="robertson",
                          params={"iterations": iters, "max_pixels": int(max_pixels),
                                  "weight": weight if isinstance(weight, str) else "custom"})


# --------------------------------------------------------------------------- plots
def plot_response(curves: ResponseCurves, path: str | os.PathLike, inputs=()) -> Path:
    """Plot ``g = ln f^-1`` per channel against the code level (PNG/PDF/SVG by suffix), atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .io import atomic_output

    g = curves.log_inverse
    fig = Figure(figsize=(5.5, 4.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(curves.n_levels)
    for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(x, g[:, c], color=colour, label=_CHANNELS[c])
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
