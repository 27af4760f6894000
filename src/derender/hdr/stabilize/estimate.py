"""Estimation for paper 1's stabiliser: reference choice, per-image exponents, curve models, 3x3 colour matrices.

See :mod:`derender.hdr.stabilize` for the method and its steps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709
from derender.core.errors import InputError, StackError
from derender.core.types import Stack

__all__ = [
    "make_blocks",
    "estimate_gammas_blocks",
    "screen_gamma_trend",
    "curve_model",
    "REF_LOW",
    "REF_HIGH",
    "REF_PIXELS",
    "FIT_LOW",
    "FIT_HIGH",
    "FIT_FLOOR",
    "exposure_fractions",
    "select_reference",
    "RIDGE",
    "Curve",
    "NARROW",
    "XATOL",
    "GammaEstimate",
    "estimate_gammas",
    "gamma_trend",
    "SCREEN_TREND",
    "power_law_plausible",
    "CURVE_CLIP",
    "CURVE_CLIP_RADIUS",
    "CURVE_SAMPLES",
    "unclipped_debevec",
    "fit_color_matrix",
    "color_matrices_to_reference",
    "joint_color_matrices",
    "reasonable_references",
]


#: Reference selection: a pixel is over-exposed when any channel is >= REF_HIGH and
#: under-exposed when any channel is <= REF_LOW (normalised codes; 0.02/0.98 = 5/250 of
#: 255, the zero points of the default trapezoid weight).
REF_LOW = 0.02


REF_HIGH = 0.98


#: Reference selection counts at most about this many pixels per frame (row subsample).
REF_PIXELS = 1 << 20


#: Fitting range for gammas and H_j: a pixel takes part only if all its channels lie in
#: (FIT_LOW, FIT_HIGH) in the brighter image of a pair and in (FIT_FLOOR, FIT_HIGH) in
#: the darker one. FIT_HIGH is well below 1 because sensors clip
#: *before* the colour matrix: a pixel with one saturated raw channel can render below
#: 255 in every channel, and such pixels break the 3x3 relation (eq. 9).
FIT_LOW = 0.12


FIT_HIGH = 0.85


#: The darker image of a pair is only required to exceed FIT_FLOOR (see :meth:`_Blocks.pair`).
FIT_FLOOR = 0.03


_W = LUMINANCE_WEIGHTS_REC709


# --------------------------------------------------------------------------- reference
def _check_images(images: Any) -> np.ndarray:
    arr = images.images if isinstance(images, Stack) else np.asarray(images)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"images must have shape (N, H, W, 3), got {arr.shape}")
    if arr.shape[0] < 2:
        raise StackError("an exposure stack needs at least two images")
    return arr


def exposure_fractions(images: Any, low: float = REF_LOW, high: float = REF_HIGH,
                       valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fractions of over-exposed (any channel ``>= high``) and under-exposed (any channel
    ``<= low``, and not over-exposed) pixels per image, each (N,), of float images in
    [0, 1] or of uint8 codes (read as ``k / 255``). ``valid`` (N, H, W)
    restricts the count (registration borders). Frames above :data:`REF_PIXELS` pixels are
    counted on every k-th row (fractions, not counts, are compared)."""
    arr = _check_images(images)
    n, h, w = arr.shape[:3]
    step = -(-h * w // REF_PIXELS)
    if step > 1:
        arr = arr[:, ::step]
        valid = None if valid is None else np.asarray(valid)[:, ::step]
    if arr.dtype == np.uint8:      # 8-bit codes k, read as k * float32(1/255): the same comparisons on k
        cv = np.arange(256, dtype=np.float32) * np.float32(1.0 / 255.0)
        high, low = int(np.argmax(cv >= high)) if (cv >= high).any() else 256, int(np.sum(cv <= low)) - 1
    over = np.empty(n)
    under = np.empty(n)
    for j in range(n):
        z = arr[j]
        # any channel >= high <=> brightest channel >= high (channel max/min without reduce over a size-3 axis)
        o = np.maximum(np.maximum(z[..., 0], z[..., 1]), z[..., 2]) >= high
        u = (np.minimum(np.minimum(z[..., 0], z[..., 1]), z[..., 2]) <= low) & ~o
        if valid is not None:
            v = np.asarray(valid[j], dtype=bool)
            cnt = max(int(v.sum()), 1)
            over[j], under[j] = (o & v).sum() / cnt, (u & v).sum() / cnt
        else:
            over[j], under[j] = o.mean(), u.mean()
    return over, under


def select_reference(images: Any, low: float = REF_LOW, high: float = REF_HIGH,
                     valid: np.ndarray | None = None) -> int:
    """Index of the best-exposed image (paper 1, Sec. 3.1): fewest over- plus under-exposed
    pixels (thresholds of :func:`exposure_fractions`); ties go to the image nearest the
    middle of the bracket."""
    over, under = exposure_fractions(images, low, high, valid)
    bad = over + under
    n = bad.size
    mid = (n - 1) / 2.0
    order = sorted(range(n), key=lambda j: (round(float(bad[j]), 12), abs(j - mid), j))
    return int(order[0])


# --------------------------------------------------------------------------- block data
def _block_view(img: np.ndarray, bs: int) -> np.ndarray:
    """(H, W, 3) -> (H//bs * W//bs, bs*bs, 3) blocks (crop to a multiple of bs)."""
    h, w = img.shape[0] // bs * bs, img.shape[1] // bs * bs
    b = img[:h, :w].reshape(h // bs, bs, w // bs, bs, 3).transpose(0, 2, 1, 3, 4)
    return b.reshape(-1, bs * bs, 3)


@dataclass
class _Blocks:
    """Pixel blocks used for fitting: codes (N, nb, bs*bs, 3), per-block min/max code (N, nb)
    and registration validity (N, nb)."""

    codes: np.ndarray
    bmin: np.ndarray
    bmax: np.ndarray
    valid: np.ndarray
    brightness: np.ndarray   # (N,) median code of each image (orders a pair by exposure)

    def pair(self, j: int, k: int, low: float, high: float, floor: float) -> np.ndarray:
        """Blocks usable for the pair (j, k): inside both registration masks, below ``high``
        in both images, above ``low`` in the brighter image and above ``floor`` in the
        darker one. Thresholding the darker image only at a low ``floor`` avoids a
        truncation bias: its noisy dark values are selected through the brighter image,
        whose noise is independent of them."""
        dark, bright = (j, k) if self.brightness[j] <= self.brightness[k] else (k, j)
        return (self.valid[j] & self.valid[k] & (self.bmax[j] < high) & (self.bmax[k] < high)
                & (self.bmin[bright] > low) & (self.bmin[dark] > floor))


def _pixels(images: Any, j: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """``images[j][ys, xs]`` of an array, or ``images.pixels(j, ys, xs)`` of a lazy stack
    (the streaming merge of :mod:`derender.fastmerge` keeps 8-bit frames and their shifts)."""
    if hasattr(images, "pixels"):
        return images.pixels(j, ys, xs)
    return np.asarray(images[j])[ys, xs]


def make_blocks(images: np.ndarray, valid: np.ndarray | None, block: int, max_blocks: int,
                 seed: int, times: np.ndarray | None = None) -> _Blocks:
    n, h, w, _ = images.shape
    bs = max(1, int(block))
    if h < bs or w < bs:
        raise InputError(f"images of {w}x{h} are smaller than the fitting block of {bs} px")
    nby, nbx = h // bs, w // bs
    nb = nby * nbx
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 5]))
    # leave out a 2-pixel frame (demosaicing borders of in-camera rendering): the kept blocks
    # are a rectangle of block rows / columns, numbered row-major (no per-block arrays: a
    # 24 MP frame has 6 M blocks)
    by0, by1 = -(-2 // bs), (h - 2) // bs - 1          # block rows with by*bs >= 2 and (by+1)*bs <= h-2
    bx0, bx1 = -(-2 // bs), (w - 2) // bs - 1
    if by1 < by0 or bx1 < bx0:
        by0, by1, bx0, bx1 = 0, nby - 1, 0, nbx - 1
    kx_n = bx1 - bx0 + 1
    n_inner = (by1 - by0 + 1) * kx_n
    if n_inner > max_blocks:        # rng.choice(keep, k) == keep[rng.choice(keep.size, k)]
        pick = rng.choice(n_inner, size=max_blocks, replace=False)
    else:
        pick = np.arange(n_inner)
    keep = np.sort((by0 + pick // kx_n) * nbx + bx0 + pick % kx_n)
    codes = np.empty((n, keep.size, bs * bs, 3), dtype=np.float64)
    vmask = np.ones((n, keep.size), dtype=bool)
    # pixel coordinates of the kept blocks only (no full-size copies): (nkeep, bs*bs), row-major in a block
    ky, kx = np.divmod(keep, nbx)
    oy, ox = np.divmod(np.arange(bs * bs), bs)
    ys = ky[:, None] * bs + oy[None, :]
    xs = kx[:, None] * bs + ox[None, :]
    for j in range(n):
        codes[j] = _pixels(images, j, ys, xs)
        if valid is not None:
            vmask[j] = _pixels(valid, j, ys, xs).all(axis=1)
    if times is not None:
        brightness = np.log(np.asarray(times, dtype=np.float64))
    else:
        brightness = np.array([float(np.median(codes[j][vmask[j]])) if vmask[j].any() else 0.0 for j in range(n)])
    return _Blocks(codes=codes, bmin=codes.min(axis=(2, 3)), bmax=codes.max(axis=(2, 3)), valid=vmask,
                   brightness=brightness)


# --------------------------------------------------------------------------- pair fits
#: Ridge on the off-diagonal entries of colour matrices, relative to the data's mean
#: eigenvalue: negligible for colourful overlaps, it keeps H_j near diagonal along colour
#: directions the overlapping pixels do not span (dim scenes, one illuminant).
RIDGE = 1e-2


_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))   # upper triangle of a 3x3


_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])                  # 3x3 -> its entry of the 6


def _wls_matrix(src: np.ndarray, dst: np.ndarray, wt: np.ndarray, ridge: float | None = None,
                prods: np.ndarray | None = None) -> np.ndarray:
    """Row-wise weighted least squares ``dst ~ src @ H.T`` with per-row-of-H sample weights
    wt (n, 3) and a ridge pulling off-diagonal entries to 0. ``prods`` (n, 6): the products
    ``src_k src_l`` (k <= l), when already computed."""
    lam = RIDGE if ridge is None else ridge
    if prods is None:
        prods = src[:, _IU[0]] * src[:, _IU[1]]
    ata = (wt.T @ prods)[:, _SYM]                # (row c, k, l): sum_n w_c s_k s_l
    atb = (wt * dst).T @ src                     # (row c, k): sum_n w_c d_c s_k
    scale = np.trace(ata, axis1=1, axis2=2) / 3.0 + 1e-300
    pen = np.full((3, 3), lam) * scale[:, None]
    pen[np.arange(3), np.arange(3)] = 1e-9 * scale
    ata[:, np.arange(3), np.arange(3)] += pen
    try:
        return np.linalg.solve(ata, atb[..., None])[..., 0]
    except np.linalg.LinAlgError:
        # colours spanning fewer than 3 directions without ridge (e.g. a grey frame, R = G = B,
        # with ridge=0): the minimum-norm least-squares map
        return np.einsum("cij,cj->ci", np.linalg.pinv(ata), atb)


class Curve:
    """Per-image linearisation ``L = G(J ** rho)`` (per channel), with ``G`` either the power
    law ``u ** gamma`` (paper 1's model, eq. 4) or a common response table (natural log of
    ``G`` on equally spaced code levels, per channel, e.g. Debevec & Malik's ``g``).

    Multiplying a curve by a number scales ``rho`` (for a power law: the gamma), which is
    how the pairwise searches vary one image's exponent.
    """

    def __init__(self, rho: float = 1.0, gamma: float | None = None, log_table: np.ndarray | None = None):
        if (gamma is None) == (log_table is None):
            raise ValueError("a Curve needs exactly one of gamma and log_table")
        self.rho = float(rho)
        self.gamma = None if gamma is None else float(gamma)
        self.table = None
        if log_table is not None:
            t = np.asarray(log_table, dtype=np.float64)
            if t.ndim == 1:
                t = np.repeat(t[:, None], 3, axis=1)
            # strictly increasing (invertible), finite
            t = np.maximum.accumulate(t, axis=0) + 1e-7 * np.arange(t.shape[0])[:, None]
            self.table = t
            self._levels = np.arange(t.shape[0], dtype=np.float64)
            self._dt = np.diff(t, axis=0)

    def __mul__(self, r: float) -> "Curve":
        r = float(r)
        if self.table is None:
            return Curve(1.0, gamma=self.gamma * self.rho * r)
        c = Curve.__new__(Curve)
        c.rho, c.gamma, c.table, c._levels, c._dt = self.rho * r, None, self.table, self._levels, self._dt
        return c

    __rmul__ = __mul__

    @property
    def effective_gamma(self) -> float:
        """Display gamma of a power curve; for a table, the log-log slope of ``G`` between
        codes 0.2 and 0.8 (the gamma of the power law through those points)."""
        if self.table is None:
            return self.gamma * self.rho
        n = self.table.shape[0] - 1
        lo, hi = int(round(0.2 * n)), int(round(0.8 * n))
        slope = (self.table[hi] - self.table[lo]) / (np.log(hi / n) - np.log(lo / n))
        return float(np.mean(slope) * self.rho)

    def lin(self, j: np.ndarray) -> np.ndarray:
        """Linear values (same shape as ``j``, float64)."""
        u = np.clip(np.asarray(j, dtype=np.float64), 0.0, 1.0)
        if self.table is None:
            return u ** (self.gamma * self.rho)
        x, i0 = self._segments(u)
        ch = np.arange(3)
        return np.exp(self.table[i0, ch] + (x - i0) * self._dt[i0, ch])

    def _segments(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Table position ``x = u ** rho * (levels - 1)`` of codes ``u`` in [0, 1] and its segment."""
        n = self.table.shape[0] - 1
        x = (u if self.rho == 1.0 else u ** self.rho) * n
        return x, np.minimum(x.astype(np.int64), n - 1)

    def code(self, lin: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`lin` (values below/above the table's range clamp to 0/1)."""
        lv = np.maximum(np.asarray(lin, dtype=np.float64), 1e-300)
        if self.table is None:
            return lv ** (1.0 / (self.gamma * self.rho))
        lg = np.log(lv)
        out = np.empty_like(lg)
        n = self.table.shape[0] - 1
        for c in range(3):
            out[..., c] = np.interp(lg[..., c], self.table[:, c], self._levels) / n
        return np.clip(out, 0.0, 1.0) ** (1.0 / self.rho)

    def dlin(self, j: np.ndarray) -> np.ndarray:
        """Derivative ``dL/dJ`` (float64, positive)."""
        u = np.clip(np.asarray(j, dtype=np.float64), 1e-6, 1.0)
        if self.table is None:
            g = self.gamma * self.rho
            return g * u ** (g - 1.0)
        return np.maximum(self.lin(u) * self.log_slope(u), 1e-300)

    def log_slope(self, j: np.ndarray) -> np.ndarray:
        """``d ln L / dJ`` (float64, positive; codes below 1e-6 count as 1e-6): ``gamma / J``
        for a power law, ``dG * (levels - 1) * rho * J ** (rho - 1)`` (``dG`` the table
        segment's log step) for a table. Needs no exponential."""
        u = np.clip(np.asarray(j, dtype=np.float64), 1e-6, 1.0)
        if self.table is None:
            return (self.gamma * self.rho) / u
        _, i0 = self._segments(u)
        n = self.table.shape[0] - 1
        tail = n * self.rho if self.rho == 1.0 else (n * self.rho) * u ** (self.rho - 1.0)
        return self._dt[i0, np.arange(3)] * tail


def _as_curve(g: "float | Curve") -> Curve:
    return g if isinstance(g, Curve) else Curve(1.0, gamma=float(g))


def _predict_codes(h: np.ndarray, lin_src: np.ndarray, curve_dst: "float | Curve") -> np.ndarray:
    return _as_curve(curve_dst).code(np.maximum(lin_src @ h.T, 1e-12))


def _pair_weights(j_src: np.ndarray, j_dst: np.ndarray, c_src: "float | Curve",
                  c_dst: "float | Curve", least_squares: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Code-domain residual weights v (equal code noise in both images, propagated through
    the map) and the linear-domain least-squares weights ``v * (dJ/dL)^2`` of the
    destination (None unless ``least_squares``). ``j_dst`` should be noise-free (a
    prediction): weights computed from noisy observations bias the fit.

    For a (nearly) diagonal map ``L_d = a L_s`` the code slope ``dJ_d / dJ_s`` is
    ``(d ln L_s / dJ_s) / (d ln L_d / dJ_d)`` (:meth:`Curve.log_slope`), so v needs no
    linear values; only the least-squares weights need ``L_d``."""
    cs, cd = _as_curve(c_src), _as_curve(c_dst)
    if cs.table is None and cd.table is None:
        # power laws (eq. 4): d ln L / dJ = g / J, so the slope is (g_s / g_d) J_d / J_s
        gs, gd = cs.gamma * cs.rho, cd.gamma * cd.rho
        js, jd = np.clip(j_src, 1e-6, 1.0), np.clip(j_dst, 1e-6, 1.0)
        slope = (gs / gd) * (jd / js)
        v = 1.0 / (1.0 + slope * slope)
        if not least_squares:
            return v, None
        djdl_dst = jd / (gd * jd ** gd)
        return v, v * djdl_dst * djdl_dst
    dlog_dst = cd.log_slope(j_dst)
    slope = cs.log_slope(j_src) / dlog_dst
    v = 1.0 / (1.0 + slope * slope)
    if not least_squares:
        return v, None
    djdl_dst = 1.0 / np.maximum(cd.lin(np.maximum(j_dst, 1e-6)) * dlog_dst, 1e-300)
    return v, v * djdl_dst * djdl_dst


def _fit_pair(jj: np.ndarray, jk: np.ndarray, gj: "float | Curve", gk: "float | Curve", iters: int = 2,
              ridge: float | None = None) -> tuple[np.ndarray, float]:
    """H (k <- j) on effective codes jj, jk (n, 3) and its weighted mean squared code residual.

    Weighted least squares in the linear domain approximating the code-domain error; the
    weights come from the current prediction (first pass: the observation)."""
    cj, ck = _as_curve(gj), _as_curve(gk)
    lj, lk = cj.lin(jj), ck.lin(jk)
    prods = lj[:, _IU[0]] * lj[:, _IU[1]]
    lo = 0.5 * jk.min(axis=0)
    pred = jk
    for _ in range(iters):
        v, wl = _pair_weights(jj, pred, cj, ck)
        h = _wls_matrix(lj, lk, wl, ridge, prods)
        raw = _predict_codes(h, lj, ck)
        pred = np.clip(raw, lo, 1.0)
    r = raw - jk
    return h, float(np.sum(v * r * r) / np.sum(v))


def _effective_codes(p: np.ndarray, curve: "float | Curve") -> np.ndarray:
    """Block means in the linear domain, back in code units."""
    c = _as_curve(curve)
    return c.code(np.mean(c.lin(p), axis=1))


def _pair_cost(pj: np.ndarray, pk: np.ndarray, gj: float, gk: float, sel: np.ndarray | None = None,
               jj: np.ndarray | None = None) -> float:
    """Symmetric code-domain misfit of the best 3x3 linear map between two linearised images
    (``jj``: image j's effective codes, if already computed)."""
    jj = _effective_codes(pj, gj) if jj is None else jj
    jk = _effective_codes(pk, gk)
    if sel is not None:
        jj, jk = jj[sel], jk[sel]
    _, c1 = _fit_pair(jj, jk, gj, gk, ridge=0.0)
    _, c2 = _fit_pair(jk, jj, gk, gj, ridge=0.0)
    return c1 + c2


def _pair_residuals(pj: np.ndarray, pk: np.ndarray, gj: float, gk: float, sel: np.ndarray | None) -> np.ndarray:
    """Per-block max code residual of both directions, with maps fitted on ``sel``."""
    jj, jk = _effective_codes(pj, gj), _effective_codes(pk, gk)
    s = slice(None) if sel is None else sel
    h1, _ = _fit_pair(jj[s], jk[s], gj, gk, ridge=0.0)
    h2, _ = _fit_pair(jk[s], jj[s], gk, gj, ridge=0.0)
    r1 = np.abs(_predict_codes(h1, _as_curve(gj).lin(jj), gk) - jk).max(axis=1)
    r2 = np.abs(_predict_codes(h2, _as_curve(gk).lin(jk), gj) - jj).max(axis=1)
    return np.maximum(r1, r2)


def _robust_inliers(r: np.ndarray, floor: float) -> np.ndarray:
    med = float(np.median(r))
    mad = 1.4826 * float(np.median(np.abs(r - med)))
    return r <= max(med + 3.0 * mad, floor)


def _minimize_bounded(f: Callable[[float], float], lo: float, hi: float, xatol: float = 1e-5,
                      maxiter: int = 500) -> float:
    """Minimiser of ``f`` on [lo, hi] by Brent's method: golden-section steps, parabolic
    steps where the last three points allow (Brent 1973, ch. 5; Forsythe, Malcolm & Moler
    1977, ``fmin``), stopping when the bracket is within ``xatol / 3`` (plus a relative
    ``sqrt(eps)``) of the best point. The same steps as scipy's
    ``minimize_scalar(method="bounded")`` (tested: same points, same evaluations), without
    importing scipy.optimize (0.4 s here). The steps are :func:`_bounded_minimizer`'s."""
    return _drive(_bounded_minimizer(lo, hi, xatol, maxiter), f)


def _drive(steps: Any, f: Callable[[Any], float]) -> Any:
    """Run a coroutine that yields evaluation requests and receives ``f(request)``; its return value."""
    try:
        req = next(steps)
        while True:
            req = steps.send(f(req))
    except StopIteration as stop:
        return stop.value


def _bounded_minimizer(lo: float, hi: float, xatol: float = 1e-5, maxiter: int = 500) -> Any:
    """Coroutine of :func:`_minimize_bounded`: yields each point to evaluate, receives its
    value, returns the minimiser (lets several searches run in lock-step with their
    evaluations batched, :func:`_relative_exponents`)."""
    sqrt_eps = float(np.sqrt(2.2e-16))
    golden = 0.5 * (3.0 - float(np.sqrt(5.0)))
    a, b = float(lo), float(hi)
    x = w = v = a + golden * (b - a)
    fx = fw = fv = yield x
    d = e = 0.0
    n = 1
    m = 0.5 * (a + b)
    tol1 = sqrt_eps * abs(x) + xatol / 3.0
    while abs(x - m) > 2.0 * tol1 - 0.5 * (b - a) and n < maxiter:
        parabolic = False
        if abs(e) > tol1:                       # parabola through x, w, v
            r = (x - w) * (fx - fv)
            q = (x - v) * (fx - fw)
            p = (x - v) * q - (x - w) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            e_prev, e = e, d
            if abs(p) < abs(0.5 * q * e_prev) and q * (a - x) < p < q * (b - x):
                d = p / q
                u = x + d
                if (u - a) < 2.0 * tol1 or (b - u) < 2.0 * tol1:
                    d = tol1 if m >= x else -tol1
                parabolic = True
        if not parabolic:                       # golden section into the larger part
            e = (a - x) if x >= m else (b - x)
            d = golden * e
        u = x + (1.0 if d >= 0 else -1.0) * max(abs(d), tol1)
        fu = yield u
        n += 1
        if fu <= fx:
            if u >= x:
                a = x
            else:
                b = x
            v, fv, w, fw, x, fx = w, fw, x, fx, u, fu
        else:
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, fv, w, fw = w, fw, u, fu
            elif fu <= fv or v == x or v == w:
                v, fv = u, fu
        m = 0.5 * (a + b)
        tol1 = sqrt_eps * abs(x) + xatol / 3.0
    return x


def _find_root(f: Callable[[float], float], a: float, b: float, xtol: float = 1e-12, maxiter: int = 100) -> float:
    """Root of ``f`` in [a, b] (``f(a)``, ``f(b)`` of opposite signs) by Brent's method:
    inverse quadratic or secant steps kept inside the bisection bracket (Brent 1973, ch. 4;
    Forsythe, Malcolm & Moler 1977, ``zeroin``); within ``xtol`` (plus 4 eps relative)."""
    a, b = float(a), float(b)
    fa, fb = f(a), f(b)
    if fa == 0.0:
        return a
    if fb == 0.0:
        return b
    if (fa > 0) == (fb > 0):
        raise ValueError("the root is not bracketed")
    c, fc = a, fa
    d = e = b - a
    for _ in range(maxiter):
        if (fb > 0) == (fc > 0):                # keep the root between b and c
            c, fc = a, fa
            d = e = b - a
        if abs(fc) < abs(fb):                   # b is the best estimate
            a, b, c = b, c, b
            fa, fb, fc = fb, fc, fb
        tol = 4.0 * 2.2e-16 * abs(b) + 0.5 * xtol
        mid = 0.5 * (c - b)
        if abs(mid) <= tol or fb == 0.0:
            return b
        if abs(e) >= tol and abs(fa) > abs(fb):
            s = fb / fa
            if a == c:                          # secant
                p, q = 2.0 * mid * s, 1.0 - s
            else:                               # inverse quadratic interpolation
                q, r = fa / fc, fb / fc
                p = s * (2.0 * mid * q * (q - r) - (b - a) * (r - 1.0))
                q = (q - 1.0) * (r - 1.0) * (s - 1.0)
            if p > 0:
                q = -q
            else:
                p = -p
            if 2.0 * p < min(3.0 * mid * q - abs(tol * q), abs(e * q)):
                e, d = d, p / q
            else:
                d = e = mid
        else:
            d = e = mid
        a, fa = b, fb
        b += d if abs(d) > tol else (tol if mid > 0 else -tol)
        fb = f(b)
    return b


#: Half-width (log units) of the refined exponent search after trimming (:func:`_pair_log_ratio`).
NARROW = 0.1


#: Tolerance of the exponent searches (log units; 1e-3 is 0.1 % of a gamma).
XATOL = 1e-3


def _pair_log_ratio(pj: np.ndarray, pk: np.ndarray, base: "float | Curve", max_log_ratio: float,
                    rounds: int = 2, base_k: "float | Curve | None" = None) -> tuple[float, float, np.ndarray]:
    """``log`` of the factor on image k's exponent (relative to ``base_k``, default ``base``)
    that makes the two linearised images best related by a 3x3 linear map (Vazquez-Corral
    & Bertalmio 2015), by a bounded 1-D search with the worst blocks trimmed between
    rounds. Returns (log factor, standard error from the cost curvature, inlier mask)."""
    bk = base if base_k is None else base_k
    jj = _effective_codes(pj, base)
    return _drive(_pair_log_ratio_steps(pj, pk, base, max_log_ratio, rounds, bk),
                  lambda req: _pair_cost(pj, pk, base, bk * np.exp(req[0]), req[1], jj))


def _pair_log_ratio_steps(pj: np.ndarray, pk: np.ndarray, base: "float | Curve", max_log_ratio: float,
                          rounds: int, bk: "float | Curve") -> Any:
    """Coroutine of :func:`_pair_log_ratio`: yields cost requests ``(log ratio, sel)`` (the
    cost is :func:`_pair_cost` of image k's curve ``bk * exp(log ratio)`` on the blocks
    ``sel``, None for all), receives their values, returns (log factor, se, inlier mask)."""
    def search(lo: float, hi: float, sel: np.ndarray | None) -> Any:
        steps = _bounded_minimizer(lo, hi, XATOL)
        try:
            u = next(steps)
            while True:
                u = steps.send((yield (u, sel)))
        except StopIteration as stop:
            return stop.value

    sel = None
    x = 0.0
    for rnd in range(rounds):
        lo, hi = -max_log_ratio, max_log_ratio
        if rnd > 0:
            # trimming moves the optimum little: search near the previous one (full range
            # again if it lands on the narrowed bound)
            lo, hi = max(lo, x - NARROW), min(hi, x + NARROW)
        x = yield from search(lo, hi, sel)
        if rnd > 0 and min(x - lo, hi - x) < 1e-3 and (lo, hi) != (-max_log_ratio, max_log_ratio):
            x = yield from search(-max_log_ratio, max_log_ratio, sel)
        r = _pair_residuals(pj, pk, base, bk * np.exp(x), sel)
        sel = _robust_inliers(r, 2.0 / 255.0)
    n = int(sel.sum())
    step = 0.01
    c0 = yield (x, sel)
    cp = yield (x + step, sel)
    cm = yield (x - step, sel)
    curv = (cp + cm - 2.0 * c0) / (step * step)
    if curv <= 0 or n < 4:
        se = 1.0
    else:
        se = float(np.sqrt(2.0 * c0 / (n * curv)))
    return x, max(se, 1e-4), sel


def _run_pair_searches(items: list, max_lr: float, rounds: int, batched: bool) -> list:
    """:func:`_pair_log_ratio` of every ``(pj, pk, base_j, base_k)``, the searches advanced
    together; with ``batched`` (power-law bases) each step's costs come from one
    :func:`_pair_costs_power` call. Same results as one search at a time."""
    steps, jjs, pending, out = [], [], {}, [None] * len(items)
    for i, (pj, pk, bj, bk) in enumerate(items):
        steps.append(_pair_log_ratio_steps(pj, pk, bj, max_lr, rounds, bk))
        jjs.append(_effective_codes(pj, bj))
        try:
            pending[i] = next(steps[i])
        except StopIteration as stop:           # pragma: no cover - a search always evaluates
            out[i] = stop.value
    while pending:
        keys = list(pending)
        if batched:
            costs = _pair_costs_power([(items[i][0], items[i][1], jjs[i], _as_curve(items[i][2]),
                                        _as_curve(items[i][3]) * np.exp(pending[i][0]), pending[i][1])
                                       for i in keys])
        else:
            costs = [_pair_cost(items[i][0], items[i][1], items[i][2], items[i][3] * np.exp(pending[i][0]),
                                pending[i][1], jjs[i]) for i in keys]
        for i, c in zip(keys, costs):
            try:
                pending[i] = steps[i].send(c)
            except StopIteration as stop:
                out[i] = stop.value
                del pending[i]
    return out


def _pair_costs_power(reqs: list) -> list[float]:
    """:func:`_pair_cost` of several pairs with power-law curves at once: ``reqs`` holds
    ``(pj, pk, jj, curve_j, curve_k, sel)``; the pairs are padded to a common block count
    (padding carries zero weight) and fitted with batched 3x3 solves. Equal to the one-pair
    cost to rounding (test)."""
    p = len(reqs)
    m = max(r[0].shape[0] for r in reqs)
    px = reqs[0][1].shape[1]
    pk = np.zeros((p, m, px, 3))
    jj = np.full((p, m, 3), 0.5)
    valid = np.zeros((p, m), dtype=bool)
    gj = np.empty((p, 1, 1))
    gk = np.empty((p, 1, 1))
    for i, (pj_i, pk_i, jj_i, cj, ck, sel) in enumerate(reqs):
        nb = pk_i.shape[0]
        pk[i, :nb] = pk_i
        pk[i, nb:] = 0.5
        jj[i, :nb] = jj_i
        valid[i, :nb] = True if sel is None else sel
        gj[i] = cj.gamma * cj.rho
        gk[i] = ck.gamma * ck.rho
    # image k's effective codes (block means in its linear domain, back in code units)
    lin_k = np.clip(pk, 0.0, 1.0) ** gk[..., None]
    jk = np.maximum(np.mean(lin_k, axis=2), 1e-300) ** (1.0 / gk)
    return list(_fit_pair_power(jj, jk, gj, gk, valid) + _fit_pair_power(jk, jj, gk, gj, valid))


def _fit_pair_power(js: np.ndarray, jd: np.ndarray, gs: np.ndarray, gd: np.ndarray, valid: np.ndarray,
                    iters: int = 2) -> np.ndarray:
    """Batched :func:`_fit_pair` (``ridge=0``) of power-law curves: codes (P, n, 3), gammas
    (P, 1, 1), rows outside ``valid`` (P, n) weightless. Returns the (P,) weighted mean
    squared code residuals."""
    ls = np.clip(js, 0.0, 1.0) ** gs
    ld = np.clip(jd, 0.0, 1.0) ** gd
    w_rows = valid[..., None].astype(np.float64)
    prods = ls[..., _IU[0]] * ls[..., _IU[1]]                              # (P, n, 6)
    lo = 0.5 * np.where(valid[..., None], jd, np.inf).min(axis=1, keepdims=True)
    pred = jd
    eye = np.arange(3)
    for _ in range(iters):
        # power-law weights (:func:`_pair_weights`)
        jsc, jdc = np.clip(js, 1e-6, 1.0), np.clip(pred, 1e-6, 1.0)
        slope = (gs / gd) * (jdc / jsc)
        v = 1.0 / (1.0 + slope * slope)
        djdl = jdc / (gd * jdc ** gd)
        wl = v * djdl * djdl * w_rows
        # row-wise weighted least squares (:func:`_wls_matrix`, ridge 0)
        wt = wl.transpose(0, 2, 1)
        ata = np.matmul(wt, prods)[:, :, _SYM]                              # (P, 3, 3, 3)
        atb = np.matmul(wt * ld.transpose(0, 2, 1), ls)                     # (P, 3, 3)
        scale = np.trace(ata, axis1=2, axis2=3) / 3.0 + 1e-300
        ata[:, eye, eye, eye] += 1e-9 * scale                              # H's diagonal entry of row c
        try:
            h = np.linalg.solve(ata, atb[..., None])[..., 0]                # (P, 3, 3): row c of H
        except np.linalg.LinAlgError:
            h = np.einsum("pcij,pcj->pci", np.linalg.pinv(ata), atb)
        raw = np.maximum(np.matmul(ls, h.transpose(0, 2, 1)), 1e-12) ** (1.0 / gd)
        pred = np.clip(raw, lo, 1.0)
    r = raw - jd
    v = v * w_rows
    return np.sum(v * r * r, axis=(1, 2)) / np.sum(v, axis=(1, 2))


def _relative_exponents(blocks: _Blocks, bases: list, low: float, high: float, floor: float, max_gap: int,
                        prior_sd: float, min_blocks: int, max_lr: float,
                        max_pair_blocks: int = 800, rounds: int = 2) -> tuple[np.ndarray, list, np.ndarray]:
    """Per-image log exponent corrections ``u`` (mean 0 over connected images) from the
    pairwise searches (pairs k - j <= max_gap), combined by weighted least squares over
    the pair graph with a prior ``u_j - mean(u) ~ N(0, prior_sd^2)``."""
    n = blocks.codes.shape[0]
    todo = []
    for j in range(n):
        for k in range(j + 1, min(n, j + 1 + max_gap)):
            common = blocks.pair(j, k, low, high, floor)
            nb = int(common.sum())
            if nb < min_blocks:
                continue
            idx = np.flatnonzero(common)
            if idx.size > max_pair_blocks:      # evenly thinned, deterministic
                idx = idx[np.linspace(0, idx.size - 1, max_pair_blocks).astype(int)]
            common = np.zeros_like(common)
            common[idx] = True
            todo.append((j, k, nb, blocks.codes[j][idx], blocks.codes[k][idx], common))
    # every pair's search runs in lock-step; power-law costs are evaluated for all pairs at
    # once (:func:`_pair_costs_power`; one pair at a time was Python-overhead bound: the
    # screening of the 24 MP bracket took 0.32 s, now 0.10-0.14 s)
    powers = all(_as_curve(b).table is None for b in bases)
    found = _run_pair_searches([(pj, pk, bases[j], bases[k]) for j, k, _, pj, pk, _ in todo], max_lr, rounds,
                               batched=powers)
    pairs = []
    for (j, k, nb, _, _, common), (lr, se, sel) in zip(todo, found):
        pairs.append({"j": j, "k": k, "blocks": nb, "inliers": int(sel.sum()), "log_ratio": lr,
                      "se": se, "sel": sel, "common": common})
    connected = np.zeros(n, dtype=bool)
    rows, rhs, wts = [], [], []
    for p in pairs:
        r = np.zeros(n)
        r[p["k"]], r[p["j"]] = 1.0, -1.0
        rows.append(r)
        rhs.append(p["log_ratio"])
        wts.append(1.0 / p["se"])
        connected[p["j"]] = connected[p["k"]] = True
    for j in range(n):            # prior: log exponents spread around their mean by ~prior_sd
        r = np.full(n, -1.0 / n)
        r[j] += 1.0
        rows.append(r)
        rhs.append(0.0)
        wts.append(1.0 / prior_sd)
    rows.append(np.ones(n))       # gauge
    rhs.append(0.0)
    wts.append(1.0)
    a = np.asarray(rows) * np.asarray(wts)[:, None]
    u = np.linalg.lstsq(a, np.asarray(rhs) * np.asarray(wts), rcond=None)[0]
    if connected.any():
        u[connected] -= np.mean(u[connected])
        u[~connected] = float(np.median(u[connected]))
    else:
        u[:] = 0.0
    return u, pairs, connected


@dataclass
class GammaEstimate:
    """Per-image display gammas (encoding exponent ``1 / gamma``) and how they were found.

    gammas : (N,) display gammas. exponents : (N,) ``1 / gammas``.
    method : ``"times"`` (relative gammas blind, absolute level from the exposure times) or
        ``"blind"`` (no times: absolute level from the 3x3 fit alone).
    pairs : list of dicts ``{j, k, blocks, inliers, log_ratio, se}`` used.
    scale : the common factor kappa applied to the relative gammas.
    unconnected : images without enough overlap with any other (gamma = median of others).
    """

    gammas: np.ndarray
    method: str
    pairs: list = field(default_factory=list)
    scale: float = 1.0
    unconnected: list = field(default_factory=list)
    info: dict = field(default_factory=dict)

    @property
    def exponents(self) -> np.ndarray:
        return 1.0 / self.gammas


def _pair_matrices(blocks: _Blocks, pairs: list, gammas: np.ndarray) -> list[np.ndarray]:
    out = []
    for p in pairs:
        j, k = p["j"], p["k"]
        common = p["common"]
        pj, pk = blocks.codes[j][common], blocks.codes[k][common]
        sel = p["sel"]
        jj, jk = _effective_codes(pj, gammas[j])[sel], _effective_codes(pk, gammas[k])[sel]
        h, _ = _fit_pair(jj, jk, gammas[j], gammas[k], ridge=0.0)
        out.append(h)
    return out


def _per_image_log_scales(pairs: list, mats: list[np.ndarray], n: int) -> np.ndarray:
    """Least-squares per-image log exposure scales ``a`` with ``a_k - a_j = log(lum(H_jk 1))``."""
    rows, rhs, wts = [], [], []
    for p, h in zip(pairs, mats):
        g = float(_W @ h @ np.ones(3))
        if not np.isfinite(g) or g <= 0:
            continue
        r = np.zeros(n)
        r[p["k"]], r[p["j"]] = 1.0, -1.0
        rows.append(r)
        rhs.append(np.log(g))
        wts.append(np.sqrt(p["inliers"]))
    rows.append(np.ones(n))          # gauge: sum a = 0
    rhs.append(0.0)
    wts.append(1.0)
    a = np.asarray(rows) * np.asarray(wts)[:, None]
    b = np.asarray(rhs) * np.asarray(wts)
    return np.linalg.lstsq(a, b, rcond=None)[0]


def estimate_gammas(images: Any, times: Sequence[float] | None = None, valid: np.ndarray | None = None,
                    block: int = 2, low: float = FIT_LOW, high: float = FIT_HIGH, floor: float = FIT_FLOOR,
                    max_blocks: int = 20000, max_gap: int = 2, prior_sd: float = 0.1,
                    min_blocks: int = 12, base: float = 2.2, bounds: tuple[float, float] = (1.0, 4.0),
                    seed: int = 0) -> GammaEstimate:
    """Estimate the display gamma ``gamma_j`` of every image of a bracket (issue item 3).

    Estimator:

    1. Fitting data: blocks of ``block x block`` pixels (a random subset of at most
       ``max_blocks``, seeded) whose pixels all lie in (``low``, ``high``) in an image and
       inside its registration mask. Linearised values are averaged per block, which
       removes most sensor noise (errors in both images bias a pixel-wise fit) while
       keeping the linear relation exact.
    2. Relative gammas, blind (Vazquez-Corral & Bertalmio 2015): for every pair (j, k)
       sharing at least ``min_blocks`` usable blocks, the ratio ``gamma_k / gamma_j`` is
       the one for which the linearised images are best related by a 3x3 matrix
       (symmetric code-domain misfit, weighted for the noise of both images, worst blocks
       trimmed). Pairwise log ratios (with standard errors from the cost curvature) are
       combined by weighted least squares over the pair graph.
    3. Absolute level: a common factor on all gammas hardly changes pairwise linearity
       (``J2 = r^(1/gamma) J1`` for any gamma when only the exposure changes). With times
       (``method="times"``): the factor for which the luminance gain of the fitted maps
       grows like the exposure time, i.e. the slope of the per-image log scale
       against ``log t_j`` is 1 (per-image gain changes average out across the bracket).
       Without times (``method="blind"``): the factor minimising the total pairwise misfit
       (the 3x3 structure is exact only at the true level when the images' colour
       matrices differ).

    Failure modes: pairs whose overlap covers a narrow range of intensities or few
    colours (extreme exposures) give poor ratios (they get large standard errors);
    images overlapping no other image keep the median gamma (listed in ``unconnected``);
    gains that change *systematically* with exposure time bias the absolute level (a
    gain trend g ~ t^e multiplies all gammas by ~1/(1+e)); tone curves that are not
    power laws (picture styles, S-curves) give only an effective gamma; the blind
    absolute level is weak when all images share one colour rendering.
    """
    arr = _check_images(images)
    n = arr.shape[0]
    tarr = None if times is None else np.asarray(times, dtype=np.float64).reshape(-1)
    if tarr is not None and tarr.size != n:
        raise InputError(f"{tarr.size} exposure time(s) for {n} image(s)")
    blocks = make_blocks(arr, valid, block, max_blocks, seed, tarr)
    return estimate_gammas_blocks(blocks, tarr, low=low, high=high, floor=floor, max_gap=max_gap,
                                   prior_sd=prior_sd, min_blocks=min_blocks, base=base, bounds=bounds,
                                   info={"block": block, "max_blocks": max_blocks})


def estimate_gammas_blocks(blocks: _Blocks, tarr: np.ndarray | None, low: float, high: float, floor: float,
                            max_gap: int, prior_sd: float, min_blocks: int, base: float,
                            bounds: tuple[float, float], info: dict) -> GammaEstimate:
    n = blocks.codes.shape[0]
    t0 = time.perf_counter()
    max_lr = float(np.log(bounds[1] / bounds[0]))
    u, pairs, connected = _relative_exponents(blocks, [base] * n, low, high, floor, max_gap, prior_sd,
                                              min_blocks, max_lr)
    rel = base * np.exp(u)
    lo_k = bounds[0] / rel.min()
    hi_k = bounds[1] / rel.max()
    method = "times" if tarr is not None else "blind"
    kappa = 1.0
    if pairs and hi_k > lo_k:
        if tarr is not None:
            logt = np.log(tarr)
            lt = logt[connected] - logt[connected].mean()
            denom = float(lt @ lt)

            def slope_err(kap: float) -> float:
                g = rel * kap
                a_s = _per_image_log_scales(pairs, _pair_matrices(blocks, pairs, g), n)
                a_c = a_s[connected] - a_s[connected].mean()
                return float(a_c @ lt) / denom - 1.0

            if denom > 0:
                f_lo, f_hi = slope_err(lo_k), slope_err(hi_k)
                if f_lo * f_hi < 0:
                    kappa = _find_root(slope_err, lo_k, hi_k, xtol=1e-5)
                else:
                    kappa = _minimize_bounded(lambda k_: abs(slope_err(k_)), lo_k, hi_k)
        else:
            def total_cost(kap: float) -> float:
                g = rel * kap
                tot = 0.0
                for p in pairs:
                    j, k = p["j"], p["k"]
                    common = p["common"]
                    tot += p["inliers"] * _pair_cost(blocks.codes[j][common], blocks.codes[k][common],
                                                     g[j], g[k], p["sel"])
                return tot

            kappa = _minimize_bounded(total_cost, lo_k, hi_k, 1e-4)
    gammas = np.clip(rel * kappa, bounds[0], bounds[1])
    public_pairs = [{k_: v for k_, v in p.items() if k_ not in ("sel", "common")} for p in pairs]
    return GammaEstimate(gammas=gammas, method=method, pairs=public_pairs, scale=kappa,
                         unconnected=[int(j) for j in np.flatnonzero(~connected)],
                         info=dict(info, low=low, high=high, floor=floor, seconds=time.perf_counter() - t0,
                                   n_blocks=int(blocks.codes.shape[1])))


def gamma_trend(gammas: Sequence[float], times: Sequence[float]) -> float:
    """Change of ``log gamma_j`` across the bracket explained by a straight line in
    ``log t_j`` (least-squares slope times the log-time range)."""
    lg = np.log(np.asarray(gammas, dtype=np.float64))
    tau = np.log(np.asarray(times, dtype=np.float64))
    tc = tau - tau.mean()
    den = float(tc @ tc)
    if den <= 0:
        return 0.0
    return float((tc @ (lg - lg.mean())) / den * (tau.max() - tau.min()))


#: Screening of ``response="auto"`` (:func:`screen_gamma_trend`): a bracket whose quick
#: relative-exponent trend exceeds this goes straight to the curve model. Twice
#: :func:`power_law_plausible`'s ``max_trend``. Measured quick (full) trends: power-law
#: brackets (auto and fixed pipelines, simple style, 18 simulated) |0.13| at most (|0.12|);
#: filmic camera style (18) 1.77 to 2.39 (1.35 to 1.76); Memorial 0.93-1.08 (0.76-0.89),
#: Frobisher 0.83 (0.75): the same decisions.
SCREEN_TREND = 0.6


#: Pair blocks and search rounds of the screening (the full search: 800 and 2).
SCREEN_BLOCKS, SCREEN_ROUNDS = 200, 1


def screen_gamma_trend(blocks: "_Blocks", times: Sequence[float], low: float = FIT_LOW, high: float = FIT_HIGH,
                       floor: float = FIT_FLOOR, max_gap: int = 2, prior_sd: float = 0.1, min_blocks: int = 12,
                       base: float = 2.2, bounds: tuple[float, float] = (1.0, 4.0)) -> float:
    """:func:`gamma_trend` of the relative exponents from a quick search (:data:`SCREEN_BLOCKS`
    blocks per pair, :data:`SCREEN_ROUNDS` round; the absolute level does not change a
    trend of log gammas), over the images the pairs connect; 0 with fewer than 3."""
    n = blocks.codes.shape[0]
    u, _, connected = _relative_exponents(blocks, [base] * n, low, high, floor, max_gap, prior_sd, min_blocks,
                                          float(np.log(bounds[1] / bounds[0])), max_pair_blocks=SCREEN_BLOCKS,
                                          rounds=SCREEN_ROUNDS)
    if int(connected.sum()) < 3:
        return 0.0
    t = np.asarray(times, dtype=np.float64)
    return gamma_trend(base * np.exp(u[connected]), t[connected])


def power_law_plausible(gammas: Sequence[float], times: Sequence[float], max_trend: float = 0.3,
                        bounds: tuple[float, float] = (1.0, 4.0)) -> bool:
    """False when per-image gammas look like the signature of a fixed tone curve that is
    not a power law: they drift steadily with exposure time (``|gamma_trend| > max_trend``,
    i.e. more than ~35 % across the bracket: each pair of neighbours sees a different part
    of an S-shaped curve, whose local log-log slope the pairwise search reports), or some
    gamma sits on the search bound. Measured: auto-pipeline power-law brackets (random
    gamma per image) trend by at most 0.12; filmic brackets by 1.3-1.8; Debevec's Memorial
    stack by ~0.8."""
    g = np.asarray(gammas, dtype=np.float64)
    if np.any(g <= bounds[0] * 1.001) or np.any(g >= bounds[1] * 0.999):
        return False
    return abs(gamma_trend(g, times)) <= max_trend


#: Response fit of the curve model (:func:`unclipped_debevec`): a sample (pixel, image) is left
#: out when any channel of it or of a pixel within CURVE_CLIP_RADIUS reaches CURVE_CLIP.
CURVE_CLIP = REF_HIGH


CURVE_CLIP_RADIUS = 1


#: Grid samples of that fit (the Schur-complement solver costs little per sample; lambda
#: grows with sqrt(samples / 256)). With Debevec's 256 the camera-style gain over debevec
#: swung by up to 2.6 dB per scene with the sampling seed; measured with ``derender
#: experiment fusion-gain --styles camera`` (9 scenes, seeds 0-2 / 3-5): 256 samples
#: +1.76 / +1.97 dB L, 1024 +2.19 / +2.36.
CURVE_SAMPLES = 1024


def unclipped_debevec(codes_at: Any, n: int, shape: tuple[int, int], times: np.ndarray, seed: int = 0,
                      high: float = CURVE_CLIP, radius: int = CURVE_CLIP_RADIUS) -> Any:
    """Debevec & Malik (1997) curves (:func:`derender.response.solve_debevec`, hat weights,
    :data:`CURVE_SAMPLES` grid samples, made non-decreasing) that leave out every sample whose
    pixel has a clipped neighbour: sample (p, j) counts in no channel when some channel of
    image j reaches ``high`` within ``radius`` pixels (Chebyshev) of p.

    Why: sensors clip *before* the colour matrix (see :data:`FIT_HIGH`). Once one raw
    channel saturates, the pixel's other channels stop following the exposure while they
    still render below white, and in-camera demosaicing and chroma filtering spread that
    into the neighbours. Debevec's per-channel fit reads those codes as the top of the
    curve and bends its shoulder (measured on the simulator's filmic style, noise-free,
    fixed rendering: up to +0.4 to +2.4 in ``ln`` at codes 245-250; with the samples left
    out +-0.2). The shoulder is what linearises a highlight that only the shortest exposure
    sees unclipped. The rendered channel that does clip is (nearly) always at white: the
    colour matrix has negative off-diagonals, so a saturated raw channel renders above 1.

    ``codes_at(j, ys, xs)``: (P, 3) integer codes of aligned image j at those pixels.
    Returns :class:`derender.response.ResponseCurves`, or None when some channel keeps no
    usable sample (then use :func:`derender.response.calibrate_debevec`).
    """
    from derender.response.curves import DEFAULT_LAMBDA, ResponseCurves, grid_positions, make_monotonic
    from derender.response.debevec1997 import solve_debevec

    h, w = int(shape[0]), int(shape[1])
    ys, xs = grid_positions(h, w, CURVE_SAMPLES, seed)
    top = int(np.ceil(high * 255 - 1e-9))
    codes = np.stack([np.asarray(codes_at(j, ys, xs)) for j in range(n)]).astype(np.int32)   # (N, P, 3)
    clipped = np.zeros(codes.shape[:2], dtype=bool)
    r = int(radius)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            yy, xx = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
            for j in range(n):
                clipped[j] |= np.asarray(codes_at(j, yy, xx)).max(axis=-1) >= top
    codes[clipped] = 0                       # hat weight 0: the sample drops out of every channel
    if not np.all(((codes > 0) & (codes < 255)).any(axis=(0, 1))):
        return None
    log_t = np.log(np.asarray(times, dtype=np.float64))
    # Debevec's lambda is set for 256 samples: scale it so that smoothness keeps its weight
    # against a data term that grows with the number of samples
    lam = DEFAULT_LAMBDA * float(np.sqrt(codes.shape[1] / 256.0))
    g = np.empty((256, 3))
    for c in range(3):
        g[:, c], _ = solve_debevec(codes[:, :, c], log_t, lam=lam, weights="hat", n_levels=256)
    params = {"lambda": lam, "n_samples": CURVE_SAMPLES, "sampling": "grid", "seed": int(seed),
              "weights": "hat", "clip": float(high), "clip_radius": r,
              "dropped": float(clipped.mean())}
    return ResponseCurves(log_inverse=make_monotonic(g), method="debevec-unclipped", params=params)


def curve_model(blocks: _Blocks, images: np.ndarray, times: np.ndarray, low: float, high: float, floor: float,
                 max_gap: int = 2, prior_sd: float = 0.1, min_blocks: int = 12, rounds: int = 0,
                 seed: int = 0, calibrate: Any = None) -> tuple[list, dict]:
    """Response model ``L_j = G(J_j ** rho_j)``: one response table ``G`` per channel common to
    the bracket (Debevec & Malik 1997, on the exponent-warped codes) and a relative
    exponent ``rho_j`` (geometric mean 1) per image from the pairwise 3x3-linearity
    searches, alternated ``rounds`` times before ``G`` is refitted.

    Default ``rounds=0``: ``rho_j = 1``, i.e. a common non-parametric response with the
    per-image colour matrices H_j on top. Measured on the simulator's filmic "camera"
    style, the exponent search is biased by the S-curve (the local log-log slope of ``G``
    differs between the dark and bright parts that neighbouring exposures share: rho
    trends by +-0.2 across the bracket) and lowers PSNR; on true power laws use
    ``response="power"``. ``G`` comes from :func:`unclipped_debevec` (samples next to a
    clipped pixel left out; plain :func:`~derender.response.calibrate_debevec` if that
    leaves a channel without data, or for warped codes). ``calibrate()`` (optional) returns
    the curves of the unwarped ``images`` without reading them (the streaming path
    samples its frames).
    """
    from derender.response.curves import to_codes
    from derender.response.debevec1997 import calibrate_debevec

    n = images.shape[0]
    rho = np.ones(n)
    pairs: list = []

    def table_for(r: np.ndarray) -> np.ndarray:
        if calibrate is not None and np.all(r == 1.0):
            return calibrate().log_inverse
        if np.all(r == 1.0):
            cur = unclipped_debevec(lambda j, ys, xs: to_codes(np.asarray(images[j])[ys, xs], 256), n,
                                    images.shape[1:3], times, seed)
            if cur is not None:
                return cur.log_inverse
        if np.all(r == 1.0) and images.min() >= 0.0 and images.max() <= 1.0:
            warped = images                 # no exponent warp: no full-size copy of the stack
        else:
            warped = np.clip(images, 0.0, 1.0) ** r[:, None, None, None].astype(np.float32)
        return calibrate_debevec(Stack(images=warped, times=times), seed=seed).log_inverse

    table = table_for(rho)
    for _ in range(int(rounds)):
        bases = [Curve(rho[j], log_table=table) for j in range(n)]
        u, pairs, _ = _relative_exponents(blocks, bases, low, high, floor, max_gap, prior_sd, min_blocks,
                                          max_lr=float(np.log(2.0)))
        rho = rho * np.exp(u)
        rho = rho / np.exp(np.mean(np.log(rho)))
        table = table_for(rho)
    curves = [Curve(rho[j], log_table=table) for j in range(n)]
    info = {"rho": rho.tolist(), "pairs": [{k: v for k, v in p.items() if k not in ("sel", "common")} for p in pairs]}
    return curves, info


# --------------------------------------------------------------------------- colour matrices
def fit_color_matrix(src_codes: np.ndarray, dst_codes: np.ndarray, gamma_src: "float | Curve",
                     gamma_dst: "float | Curve",
                     n_iter: int = 100, sample: int = 4, threshold: float | None = None,
                     seed: int = 0, ridge: float | None = None,
                     max_score: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """H with ``dst_codes ** gamma_dst ~ H @ src_codes ** gamma_src`` (paper 1, eq. 9), by
    weighted least squares inside a seeded RANSAC. ``gamma_*`` are display gammas or
    :class:`Curve` linearisations.

    ``src_codes``, ``dst_codes``: (n, 3) corresponding rendered values in [0, 1] (pixels or
    block means) already restricted to well-exposed ones. Hypotheses are fitted to
    ``sample`` random correspondences; a correspondence is an inlier when its largest
    channel residual in destination code units, divided by its noise scale (errors of
    both images propagated through the map), is below ``threshold`` (default: 3 robust
    standard deviations of the all-data fit, at least 2/255). The best hypothesis' inliers
    are refitted by weighted least squares (code-domain error, 2 reweighting passes) with
    the off-diagonal ridge ``ridge`` (default :data:`RIDGE`; 0 for plain least squares).
    Hypotheses are ranked on at most ``max_score`` evenly spread correspondences (their
    inlier count only orders them); the winner's inliers are found on all.
    Returns ``(H, inlier_mask)``.
    """
    src = np.asarray(src_codes, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst_codes, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape:
        raise InputError(f"correspondences differ in shape: {src.shape} vs {dst.shape}")
    n = src.shape[0]
    if n < max(sample, 3):
        raise StackError(f"only {n} well-exposed correspondences between two images; cannot fit a 3x3 colour matrix")
    c_src, c_dst = _as_curve(gamma_src), _as_curve(gamma_dst)
    ls, ld = c_src.lin(src), c_dst.lin(dst)

    def norm_resid(h: np.ndarray) -> np.ndarray:
        pred = _predict_codes(h, ls, gamma_dst)
        v, _ = _pair_weights(src, np.clip(pred, 1e-3, 1.0), gamma_src, gamma_dst, least_squares=False)
        return (np.abs(pred - dst) * np.sqrt(v)).max(axis=1)

    h_all, _ = _fit_pair(src, dst, gamma_src, gamma_dst, ridge=ridge)
    r_all = norm_resid(h_all)
    if threshold is None:
        med = float(np.median(r_all))
        threshold = max(med + 3.0 * 1.4826 * float(np.median(np.abs(r_all - med))), 2.0 / 255.0)
    best = r_all <= threshold
    # hypotheses are scored on at most `max_score` evenly spread correspondences (preemptive
    # RANSAC: the count only ranks hypotheses); the winner's inliers are taken on all of them
    sub = np.arange(n) if n <= max_score else np.linspace(0, n - 1, int(max_score)).astype(np.int64)
    best_cnt, best_h = int(best[sub].sum()), None
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
    # all hypotheses at once: least squares on `sample` distinct random correspondences each
    idx = np.array([np.sort(rng.choice(n, size=sample, replace=False)) for _ in range(int(n_iter))],
                   dtype=np.int64).reshape(-1, sample)
    a = ls[idx]                                            # (iters, sample, 3)
    ata = np.einsum("isk,isl->ikl", a, a)
    atb = np.einsum("isk,isl->ikl", a, ld[idx])
    det = np.linalg.det(ata)
    ok = np.isfinite(det) & (np.abs(det) > 1e-12 * np.einsum("ikk->i", ata) ** 3)
    if ok.any():
        hyp = np.transpose(np.linalg.solve(ata[ok], atb[ok]), (0, 2, 1))     # (m, 3, 3)
        ls_s, src_s, dst_s = ls[sub], src[sub], dst[sub]
        for start in range(0, hyp.shape[0], 64):
            hh = hyp[start:start + 64]
            pred = c_dst.code(np.maximum(np.matmul(ls_s, hh.transpose(0, 2, 1)), 1e-12))
            v, _ = _pair_weights(src_s[None], np.clip(pred, 1e-3, 1.0), gamma_src, gamma_dst,
                                 least_squares=False)
            inl = (np.abs(pred - dst_s[None]) * np.sqrt(v)).max(axis=2) <= threshold
            cnt = inl.sum(axis=1)
            m = int(np.argmax(cnt))
            if cnt[m] > best_cnt:
                best_cnt, best_h = int(cnt[m]), hh[m]
    if best_h is not None:
        best = norm_resid(best_h) <= threshold
    if best.sum() < 3:
        best = np.ones(n, dtype=bool)
    h, _ = _fit_pair(src[best], dst[best], gamma_src, gamma_dst, ridge=ridge)
    inl = norm_resid(h) <= threshold
    if inl.sum() >= max(3, best.sum() // 2):
        h, _ = _fit_pair(src[inl], dst[inl], gamma_src, gamma_dst, ridge=ridge)
        best = inl
    return h, best


def _neighbour_matrix(blocks: _Blocks, j: int, a: int, gammas, low: float, high: float, floor: float,
                      n_iter: int, seed: int) -> np.ndarray | None:
    """H (a <- j) fitted on the blocks images j and a share, or None when fewer than 8 blocks
    (too few to pin down 9 entries against noise) or the fit is implausible."""
    jj, ja = _pair_effective(blocks, j, a, gammas, low, high, floor)
    if jj.shape[0] < 8:
        return None
    h, _ = fit_color_matrix(jj, ja, gammas[j], gammas[a], n_iter=n_iter, seed=seed + 101 * j + a)
    return h if _plausible_matrix(h) else None


def _plausible_matrix(h: np.ndarray) -> bool:
    """A colour matrix between two renderings of one scene: positive luminance gain of
    white and a dominant positive diagonal (each diagonal entry above the sum of the
    absolute off-diagonals of its row, up to a factor 2)."""
    if not np.all(np.isfinite(h)):
        return False
    if float(_W @ h @ np.ones(3)) <= 0:
        return False
    d = np.diag(h)
    off = np.abs(h).sum(axis=1) - np.abs(d)
    return bool(np.all(d > 0) and np.all(2.0 * d > off))


def _pair_effective(blocks: _Blocks, j: int, k: int, gammas: np.ndarray, low: float, high: float,
                    floor: float) -> tuple[np.ndarray, np.ndarray]:
    common = blocks.pair(j, k, low, high, floor)
    return (_effective_codes(blocks.codes[j][common], gammas[j]),
            _effective_codes(blocks.codes[k][common], gammas[k]))


def _pair_graph(blocks: _Blocks, gammas: np.ndarray, n: int, low: float, high: float, floor: float,
                min_blocks: int, max_gap: int, seed: int, n_iter: int) -> dict:
    """RANSAC-fitted maps for pairs (j, k), k - j <= max_gap: {(j, k): (H_k<-j, jj_in, jk_in)}."""
    out = {}
    for j in range(n):
        for k in range(j + 1, min(n, j + 1 + max_gap)):
            jj, jk = _pair_effective(blocks, j, k, gammas, low, high, floor)
            if jj.shape[0] < min_blocks:
                continue
            h, inl = fit_color_matrix(jj, jk, gammas[j], gammas[k], n_iter=n_iter, seed=seed + 31 * j + k)
            out[(j, k)] = (h, jj[inl], jk[inl])
    return out


def color_matrices_to_reference(blocks: _Blocks, gammas: Sequence, reference: int, low: float = FIT_LOW,
                                high: float = FIT_HIGH, floor: float = FIT_FLOOR, min_blocks: int = 12,
                                path: str = "auto", seed: int = 0, n_iter: int = 100,
                                times: np.ndarray | None = None) -> tuple[np.ndarray, list]:
    """H_j (N, 3, 3) mapping image j's linear values onto the reference's (paper 1, eq. 9-10).

    ``path="direct"`` fits every (I_j, I_ref) pair as the paper does; ``"chain"`` fits
    neighbouring pairs and composes them towards the reference; ``"auto"`` (default)
    fits directly when the pair shares at least ``4 * min_blocks`` usable blocks and at
    least half as many as image j shares with its neighbour towards the reference, and
    the fitted matrix is plausible (:func:`_plausible_matrix`); otherwise it chains
    (distant exposures share only a few noisy pixels with the reference). The exposure
    ratio (and any gain change) is absorbed in H_j. An image that shares nothing usable
    with its neighbour gets the neighbour's matrix times ``t_neighbour / t_j``
    ("assumed"). ``gammas``: display gammas or :class:`Curve` objects. Returns (H, how)
    with ``how[j]`` in {"reference", "direct", "chain", "assumed"}.
    """
    n = blocks.codes.shape[0]
    eye = np.eye(3)
    mats = np.repeat(eye[None], n, axis=0)
    how = ["reference"] * n
    order = list(range(reference - 1, -1, -1)) + list(range(reference + 1, n))
    for j in order:
        a = j + 1 if j < reference else j - 1           # neighbour towards the reference
        if path in ("direct", "auto"):
            jj, jr = _pair_effective(blocks, j, reference, gammas, low, high, floor)
            if path == "direct":
                need = min_blocks
            else:
                need = max(4 * min_blocks, int(0.5 * blocks.pair(j, a, low, high, floor).sum()))
            if jj.shape[0] >= need:
                h, _ = fit_color_matrix(jj, jr, gammas[j], gammas[reference], n_iter=n_iter,
                                        seed=seed + 101 * j + reference)
                if path == "direct" or _plausible_matrix(h):
                    mats[j] = h
                    how[j] = "direct"
                    continue
            elif path == "direct":
                raise StackError(f"image {j} shares only {jj.shape[0]} usable blocks with the reference "
                                 f"{reference}; use path='chain'")
        elif path != "chain":
            raise InputError(f"path must be 'auto', 'direct' or 'chain', got {path!r}")
        h = _neighbour_matrix(blocks, j, a, gammas, low, high, floor, n_iter, seed)
        if h is None:
            # nothing well exposed in common (exposure step too large, frame nearly black or
            # white): assume the neighbour's rendering, scaled by the exposure ratio
            h = np.eye(3) * (times[a] / times[j]) if times is not None else np.eye(3)
            how[j] = "assumed"
        else:
            how[j] = "chain"
        mats[j] = mats[a] @ h
    return mats, how


def joint_color_matrices(blocks: _Blocks, gammas: np.ndarray, times: np.ndarray, low: float = FIT_LOW,
                         high: float = FIT_HIGH, floor: float = FIT_FLOOR, min_blocks: int = 12,
                         max_gap: int = 2, seed: int = 0, n_iter: int = 100) -> np.ndarray:
    """Reference-free colour matrices: K_j (N, 3, 3) such that ``K_j L_j / t_j`` agree on every
    overlapping pair (beyond paper 1; its Fig. 5 limitation).

    Minimises ``sum_pairs sum_blocks w ||K_j l_j / t_j - K_k l_k / t_k||^2`` over the RANSAC
    inliers of every pair (k - j <= ``max_gap``) subject to ``mean_j K_j = I``: the common
    space is the bracket's average rendering (if ``L_j = t_j B_j E`` then
    ``K_j = (mean_i B_i^-1)^-1 B_j^-1``), independent of any reference. Weights ``w`` make
    the residual relative (noise of both images, in code units, propagated). Times only
    set the gauge; wrong times are absorbed into K_j. Each output row of the K_j is an
    equality-constrained least-squares problem (KKT system). The fit covers the longest
    run of neighbouring images that share pixels; images outside it (nearly black or
    white frames) are chained to their neighbour afterwards, or assumed to share its
    rendering when nothing is usable in common.
    """
    n = blocks.codes.shape[0]
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    graph = _pair_graph(blocks, gammas, n, low, high, floor, min_blocks, max_gap, seed, n_iter)
    # the joint fit runs over the largest connected run of images; the others are attached
    # afterwards to their nearest fitted neighbour (see the end)
    adj = np.zeros(n - 1, dtype=bool)
    for (j, k) in graph:
        adj[j:k] = True
    runs, start = [], 0
    for i in range(n - 1):
        if not adj[i]:
            runs.append((start, i))
            start = i + 1
    runs.append((start, n - 1))
    lo_i, hi_i = max(runs, key=lambda r: (r[1] - r[0], -abs((r[0] + r[1]) / 2 - (n - 1) / 2)))
    mats = np.empty((n, 3, 3))
    # only images that share pixels with another take part: a frame skipped by a pair
    # across it (e.g. an all-white middle frame) has no data, and the constraint
    # mean K_j = I would put the whole rendering on it
    paired = {i for key in graph for i in key}
    members = [i for i in range(lo_i, hi_i + 1) if i in paired]
    if len(members) < 2:        # no neighbours share pixels: all renderings assumed alike
        mats[:] = np.eye(3)
        return mats
    lo_i, hi_i = members[0], members[-1]
    graph = {key: val for key, val in graph.items() if lo_i <= key[0] and key[1] <= hi_i}
    sub = {j: i for i, j in enumerate(members)}
    m = 3 * len(members)
    normal = [np.zeros((m, m)) for _ in range(3)]
    for (j, k), (_, jj, jk) in graph.items():
        cj, ck = _as_curve(gammas[j]), _as_curve(gammas[k])
        mj = cj.lin(jj) / t[j]
        mk = ck.lin(jk) / t[k]
        # relative noise of each linear value, (dL/dJ) sigma / L with equal code noise sigma
        rel = cj.log_slope(jj) ** 2 + ck.log_slope(jk) ** 2
        scale2 = np.maximum(mj * mk, 1e-300)       # ~ E^2 in either image's rendering
        for c in range(3):
            w = 1.0 / (scale2[:, c] * rel[:, c])
            a = np.zeros((mj.shape[0], m))
            a[:, 3 * sub[j]:3 * sub[j] + 3] = mj
            a[:, 3 * sub[k]:3 * sub[k] + 3] = -mk
            normal[c] += (a * w[:, None]).T @ a
    nm = len(members)
    cons = np.zeros((3, m))
    for i in range(nm):
        cons[:, 3 * i:3 * i + 3] = np.eye(3) / nm
    for c in range(3):
        kkt = np.zeros((m + 3, m + 3))
        scale = np.trace(normal[c]) / m
        kkt[:m, :m] = normal[c] / scale
        off = np.ones(m)
        off[c::3] = 0.0                        # ridge on off-diagonal entries (see RIDGE)
        kkt[:m, :m] += np.diag(RIDGE * off)
        kkt[:m, m:] = cons.T
        kkt[m:, :m] = cons
        rhs = np.zeros(m + 3)
        rhs[m + c] = 1.0
        sol = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
        mats[members, c, :] = sol[:m].reshape(nm, 3)
    # images outside the fit (outside the run, or without pixels in common): chained to the
    # nearest fitted image, nearest first (or assumed alike)
    done = set(members)
    rest = [j for j in range(n) if j not in done]
    while rest:
        j = min(rest, key=lambda i: (min(abs(i - d) for d in done), i))
        a = min(done, key=lambda d: (abs(d - j), d))
        rest.remove(j)
        done.add(j)
        h = _neighbour_matrix(blocks, j, a, gammas, low, high, floor, n_iter, seed)
        mats[j] = mats[a] @ (h * (t[j] / t[a]) if h is not None else np.eye(3))
    return mats


def reasonable_references(images: Any, max_bad: float = 0.5) -> list[int]:
    """Images usable as reference: at most ``max_bad`` of their pixels over- or
    under-exposed (:func:`exposure_fractions`), always including the best-exposed one."""
    over, under = exposure_fractions(images)
    refs = [int(j) for j in np.flatnonzero(over + under <= max_bad)]
    best = select_reference(images)
    return sorted(set(refs) | {best})


