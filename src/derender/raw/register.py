"""Sub-photosite registration of RAW mosaics: a translation estimated on the CFA planes, each plane resampled.

A Bayer mosaic is four phase planes ``P_ab[i, k] = mosaic[2i + a, 2k + b]`` (``a, b`` in
{0, 1}), each a half-resolution image of one colour. When the content of the reference frame at
photosite ``p`` sits at ``p + s`` in frame ``j`` (a translation ``s = (dy, dx)`` in photosites,
the sign of :func:`derender.engine.motion.align.chain_transforms`), every plane of frame ``j``
is the same plane of the reference displaced by ``s / 2`` plane samples:

    P^j_ab(u + s / 2) = P^ref_ab(u)                                              (1)

whatever the colour -- no colour is mixed, so (1) holds at the sensor's full resolution.

**Estimation** (:func:`refine_shift`): Gauss-Newton (Lucas & Kanade 1981) on (1) for the
four planes together, exposure-normalised (``d / e``: DN above black per unit exposure), with
one shared ``s`` and a gain ``kappa`` (an exposure that is not exactly its nominal value):
minimise ``sum w (P^j(u + s/2) - kappa P^a(u))^2`` over the photosites well exposed in both
frames (above 8 read-noise sigma, below 85 % of the level), ``w = 1 / (x (1/e_a + 1/e_j))``
(the Poisson variance of the difference, ``x`` the reference's value) times Tukey's biweight of
the normalised residual (moving things, hot pixels); ``P^j(u + s/2)`` and its derivative
by the Keys (1981) cubic convolution (``a = -1/2``). The start is the caller's (the
engine's MTB on 2x2 blocks, whole blocks) improved to the best of the 3 x 3 whole-block
neighbours by the median weighted residual (MTB on blocks can miss by one block).

**Resampling** (:func:`resample_mosaic`): the reference's photosite ``p`` (colour ``c``)
takes frame ``j``'s colour ``c`` at ``p + s``: from the plane of colour ``c`` (either green
plane for green) whose samples lie nearest that point, by the Keys kernel, separable weights
``w_y w_x`` (constant over a plane, since ``s`` is). The value is ``sum w d`` and its variance
``sum w^2 Var[d]``: with the Poisson-Gaussian variance of the target's value, ``f * (g X e +
sigma^2)`` with ``f = (sum w_y^2)(sum w_x^2)`` per plane (:func:`plane_weights`; 1 for a
whole-photosite source, 0.41-0.64 at half a plane sample), which the merge takes as a per-frame,
per-phase variance factor (:func:`derender.raw.optimal.merge_compiled`). A sample whose support
is saturated everywhere is censored (set to the white level); a sample whose support is
partly saturated, or reaches outside the frame, takes no part (``valid`` False): a censored
observation says ``X e >= c``, which an interpolation of saturated and unsaturated samples
does not say (measured: censoring them at ``c`` biased the edges of clipped regions). Whole
even shifts are copies (no resampling: the CFA phase is kept), and a shift within
:data:`SNAP` photosites of a whole one is taken as whole, so a still or tripod bracket is
merged bit for bit as without registration.

The samples of neighbouring output photosites share sources, so the merged mosaic's noise is
correlated over a few photosites after resampling; the demosaic's variance treats photosites as
independent (docs/raw.md, "Motion on the mosaic", for what this does to the coverage).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "SNAP",
    "keys_weights",
    "snap_shift",
    "refine_shift",
    "resample_mosaic",
    "resample_rgb",
    "merge_shifted",
    "phase_scale",
    "shifted_box",
]

#: A shift component within this many photosites of a whole number is taken as whole.
SNAP = 0.1

#: Keys' cubic convolution parameter (Keys 1981: a = -1/2 reproduces quadratics).
_KEYS_A = -0.5

#: Gauss-Newton steps of :func:`refine_shift` at most (stops when a step is below 1e-4 plane samples).
_STEPS = 30

#: Tukey biweight constant, in robust sigmas of the normalised residual.
_TUKEY = 4.685

#: At most about this many samples per plane enter the estimate (every k-th row).
_MAX_SAMPLES = 1 << 18

#: Fewer common well-exposed samples than this: the pair's shift is not refined.
_MIN_SAMPLES = 512


def _keys(x: np.ndarray) -> np.ndarray:
    x = np.abs(x)
    a = _KEYS_A
    return np.where(x <= 1, (a + 2) * x ** 3 - (a + 3) * x ** 2 + 1,
                    np.where(x < 2, a * x ** 3 - 5 * a * x ** 2 + 8 * a * x - 4 * a, 0.0))


def _keys_d(x: np.ndarray) -> np.ndarray:
    s = np.sign(x)
    x = np.abs(x)
    a = _KEYS_A
    return s * np.where(x <= 1, 3 * (a + 2) * x ** 2 - 2 * (a + 3) * x,
                        np.where(x < 2, 3 * a * x ** 2 - 10 * a * x + 8 * a, 0.0))


def keys_weights(f: float, derivative: bool = False) -> np.ndarray:
    """The Keys cubic weights of the samples at offsets -1, 0, 1, 2 for a point ``f`` in [0, 1)
    past sample 0 (with ``derivative``: their derivatives in ``f``). ``f = 0`` gives (0, 1, 0, 0)."""
    t = float(f) - np.arange(-1, 3)
    if derivative:
        return _keys_d(t)
    w = _keys(t)
    if f == 0.0:
        w = np.array([0.0, 1.0, 0.0, 0.0])
    return w


def snap_shift(shift) -> tuple[float, float]:
    """The shift (dy, dx) with each component within :data:`SNAP` of a whole number made whole."""
    out = []
    for v in shift:
        r = float(np.rint(v))
        out.append(r if abs(float(v) - r) <= SNAP else float(v))
    return out[0], out[1]


@lru_cache(maxsize=64)
def _resampling_kernels(pattern: str, sy: float, sx: float) -> tuple:
    """Per output CFA phase ``(a, b)`` and colour ``c``: the linear filter ``C`` (correlation
    offsets ``(oy + u, ox + v)``) with ``out(p) = sum C[u, v] d(p + (oy + u, ox + v))``: Keys'
    weights over the 4 x 4 photosites around ``p + s`` of Malvar's estimate of colour ``c``
    there. Returns ``kernels[a][b][c] = (C, oy, ox)`` and the factors ``sum C^2`` (3, 2, 2)."""
    from derender.raw.optimal import linear_demosaic_kernels

    ker = linear_demosaic_kernels(pattern)                 # (2, 2, 3, 5, 5)
    iy, ix = math.floor(sy), math.floor(sx)
    wy, wx = keys_weights(sy - iy), keys_weights(sx - ix)
    out, factor = [[[None] * 3 for _ in range(2)] for _ in range(2)], np.ones((3, 2, 2))
    for a in range(2):
        for b in range(2):
            for c in range(3):
                acc = np.zeros((8, 8))                     # offsets iy - 3 .. iy + 4
                for ty in range(4):
                    for tx in range(4):
                        w = wy[ty] * wx[tx]
                        if w == 0.0:
                            continue
                        qy, qx = iy + ty - 1, ix + tx - 1      # the photosite p + (qy, qx)
                        acc[ty:ty + 5, tx:tx + 5] += w * ker[(a + qy) & 1, (b + qx) & 1, c]
                rows, cols = np.flatnonzero(np.any(acc != 0, axis=1)), np.flatnonzero(np.any(acc != 0, axis=0))
                sub = acc[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
                out[a][b][c] = (sub, iy - 3 + int(rows[0]), ix - 3 + int(cols[0]))
                factor[c, a, b] = float(np.sum(sub ** 2))
    return out, factor


#: Photosites mirrored beyond each edge (as the demosaic reflects, ``scipy.ndimage`` mode
#: ``reflect``), so that an unshifted frame's colours exist up to its border.
_PAD = 2


def _apply(d: np.ndarray, sat: np.ndarray, kernel: tuple, a: int, b: int, shape: tuple[int, int], shift):
    """One phase's filter (:func:`_resampling_kernels`) on ``d`` (padded by :data:`_PAD`) for the
    output photosites ``p = (2i + a, 2k + b)`` of a ``shape`` frame whose support lies inside
    and whose point ``p + shift`` lies inside the frame: ``(values, saturated taps, taps, (i0, i1, k0, k1))``."""
    ker, oy, ox = kernel
    h, w = shape
    hp, wp = d.shape
    oy, ox = oy + _PAD, ox + _PAD
    ny, nx = (h - a + 1) // 2, (w - b + 1) // 2
    kh, kw = ker.shape
    sy, sx = float(shift[0]), float(shift[1])
    i0 = max(0, math.ceil(-(a + oy) / 2), math.ceil(-(a + sy) / 2))
    i1 = min(ny, (hp - kh - a - oy) // 2 + 1, math.floor((h - 1 - a - sy) / 2) + 1)
    k0 = max(0, math.ceil(-(b + ox) / 2), math.ceil(-(b + sx) / 2))
    k1 = min(nx, (wp - kw - b - ox) // 2 + 1, math.floor((w - 1 - b - sx) / 2) + 1)
    if i1 <= i0 or k1 <= k0:
        return None
    vals = np.zeros((i1 - i0, k1 - k0))
    nsat = np.zeros((i1 - i0, k1 - k0))
    taps = 0
    for u in range(kh):
        for v in range(kw):
            c = ker[u, v]
            if c == 0.0:
                continue
            taps += 1
            r0, c0 = 2 * i0 + a + oy + u, 2 * k0 + b + ox + v
            sl = (slice(r0, r0 + 2 * (i1 - i0) - 1, 2), slice(c0, c0 + 2 * (k1 - k0) - 1, 2))
            vals += c * d[sl]
            nsat += sat[sl]
    return vals, nsat, taps, (i0, i1, k0, k1)


def _prepare(mosaic: np.ndarray, black, white: float):
    m = np.asarray(mosaic)
    h, w = m.shape
    black = np.broadcast_to(np.asarray(black, np.float64).reshape(-1)[0], (2, 2)) \
        if np.asarray(black).size == 1 else np.asarray(black, np.float64).reshape(2, 2)
    bl = np.tile(black, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    d = np.pad(np.asarray(m, np.float64) - bl, _PAD, mode="symmetric")
    sat = np.pad(np.asarray(m >= white, np.float64), _PAD, mode="symmetric")
    return m, black, d, sat


def resample_mosaic(mosaic: np.ndarray, shift, black: np.ndarray, white: float,
                    pattern: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``j``'s mosaic on the reference's photosites (module docstring, resampling):
    ``(codes, valid, factor)`` -- (H, W) float64 codes (the target phase's black level plus the
    resampled value above black; the white level where the support is saturated everywhere),
    (H, W) bool where the sample takes part, and the (2, 2) variance factor per phase."""
    m, black, d, sat = _prepare(mosaic, black, white)
    p = pattern.upper()
    lut = {"R": 0, "G": 1, "B": 2}
    kernels, factors = _resampling_kernels(p, float(shift[0]), float(shift[1]))
    codes = np.asarray(m, np.float64).copy()
    valid = np.zeros(m.shape, bool)
    factor = np.ones((2, 2))
    for a in range(2):
        for b in range(2):
            c = lut[p[2 * a + b]]
            factor[a, b] = factors[c, a, b]
            got = _apply(d, sat, kernels[a][b][c], a, b, m.shape, shift)
            if got is None:
                continue
            vals, nsat, taps, (i0, i1, k0, k1) = got
            sub = black[a, b] + vals
            full = nsat >= taps - 0.5
            sub[full] = float(white)                           # saturated everywhere: censored
            codes[a::2, b::2][i0:i1, k0:k1] = sub
            valid[a::2, b::2][i0:i1, k0:k1] = (nsat < 0.5) | full
    return codes, valid, factor


def resample_rgb(mosaic: np.ndarray, shift, black: np.ndarray, white: float,
                 pattern: str, channels: tuple[int, ...] = (0, 1, 2)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``j``'s colours ``channels`` (0, 1, 2: R, G, B) at the reference's photosites
    (module docstring, merging in colour): ``(values, state, factor)`` -- (C, H, W) float64 DN
    above black, (C, H, W) uint8 state (0: takes no part, 1: a measurement, 2: censored, its
    support saturated everywhere) and the (3, 2, 2) variance factor per colour and output phase."""
    m, black, d, sat = _prepare(mosaic, black, white)
    kernels, factors = _resampling_kernels(pattern.upper(), float(shift[0]), float(shift[1]))
    h, w = m.shape
    values = np.zeros((len(channels), h, w))
    state = np.zeros((len(channels), h, w), np.uint8)
    for a in range(2):
        for b in range(2):
            for k, c in enumerate(channels):
                got = _apply(d, sat, kernels[a][b][c], a, b, m.shape, shift)
                if got is None:
                    continue
                vals, nsat, taps, (i0, i1, k0, k1) = got
                full = nsat >= taps - 0.5
                values[k, a::2, b::2][i0:i1, k0:k1] = vals
                state[k, a::2, b::2][i0:i1, k0:k1] = np.where(full, 2, np.where(nsat < 0.5, 1, 0))
    return values, state, factors


def merge_shifted(mosaics: list, shifts: np.ndarray, black: np.ndarray, white: np.ndarray, exposures: np.ndarray,
                  noise, pattern: str, valid: np.ndarray | None = None,
                  censored: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The censored ML merge (:func:`derender.raw.optimal.merge_compiled`) done per colour on
    the frames' colours at the reference's photosites (:func:`resample_rgb`, each frame at its
    ``shift``; module docstring, merging in colour). ``mosaics`` (N, H, W) exposure-sorted,
    ``black`` (N, 2, 2), ``white`` (N,), ``exposures`` (N,), ``valid`` (N, H, W) where each
    frame may take part (ghost removal; None: everywhere). Returns camera RGB (H, W, 3) in
    units of the white level per second, its variance (H, W, 3) (colours taken as
    independent) and the (H, W) mask (bright where a colour has every frame saturated)."""
    from numba.typed import List

    from derender.raw.optimal import interleave, merge_compiled

    n = len(mosaics)
    h, w = np.asarray(mosaics[0]).shape
    ceil = np.array([float(white[j]) - float(np.mean(black[j])) for j in range(n)])
    span = float(ceil[int(np.argmax(white))])
    x_out = np.empty((h, w, 3), np.float32)
    v_out = np.empty((h, w, 3), np.float32)
    mask = np.zeros((h, w), np.uint8)
    for c in range(3):
        codes, ok, factors = [], np.empty((n, h, w), bool), np.empty((n, 2, 2))
        for j in range(n):
            vals, state, f = resample_rgb(mosaics[j], shifts[j], black[j], white[j], pattern, (c,))
            vals, state = vals[0], state[0]
            vals[state == 2] = ceil[j]                          # censored: at the level
            codes.append(np.ascontiguousarray(vals))
            ok[j] = state != 0
            if valid is not None:
                ok[j] &= np.asarray(valid[j], bool)
            factors[j] = f[c]
        x, var, m = merge_compiled(List(codes), np.zeros((n, 2, 2)), ceil, exposures, noise, censored=censored,
                                   scale=1.0 / span, valid=ok, variance_factor=factors)
        x_out[..., c] = interleave(x, (h, w))
        v_out[..., c] = interleave(var, (h, w))
        mask = np.maximum(mask, m)
    return x_out, v_out, mask


def _taps(w: np.ndarray) -> np.ndarray:
    return np.flatnonzero(w != 0.0)


def _convolve(plane: np.ndarray, off: tuple[int, int], wy: np.ndarray, wx: np.ndarray,
              shape: tuple[int, int]) -> tuple[np.ndarray, tuple[slice, slice]]:
    """``out[i, k] = sum_mn wy[m] wx[n] plane[i + oy + m - 1, k + ox + n - 1]`` over the output
    samples whose taps (the non-zero weights) lie inside ``plane``: ``(values, (rows, cols))``,
    the values on that sub-rectangle of an output of ``shape``."""
    ty, tx = _taps(wy), _taps(wx)
    oy, ox = off
    hs, ws = plane.shape
    i0 = max(0, -(oy + ty[0] - 1))
    i1 = min(shape[0], hs - (oy + ty[-1] - 1))
    k0 = max(0, -(ox + tx[0] - 1))
    k1 = min(shape[1], ws - (ox + tx[-1] - 1))
    if i1 <= i0 or k1 <= k0:
        return np.zeros((0, 0)), (slice(0, 0), slice(0, 0))
    rows = np.zeros((i1 - i0, plane.shape[1]))
    for m in ty:
        r = i0 + oy + m - 1
        rows += wy[m] * plane[r:r + (i1 - i0)]
    out = np.zeros((i1 - i0, k1 - k0))
    for n in tx:
        c = k0 + ox + n - 1
        out += wx[n] * rows[:, c:c + (k1 - k0)]
    return out, (slice(i0, i1), slice(k0, k1))


def _box_image(mosaic: np.ndarray, e: float, black: np.ndarray, white: float, scale: np.ndarray,
               read_sd: float) -> tuple[np.ndarray, np.ndarray]:
    """The sliding 2x2 sum of the exposure-normalised mosaic, each photosite divided by its CFA
    phase's ``scale``: ``(y, ok)``, (H - 1, W - 1), every window one photosite of each phase
    (so no CFA pattern is left in it), ``ok`` where its four photosites are unsaturated, below
    85 % of the level, and the window sum above 10 read-noise sigma."""
    m = np.asarray(mosaic, np.float64)
    h, w = m.shape
    bl = np.tile(black, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    sc = np.tile(scale, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    d = m - bl
    bad = (m >= white) | (d >= 0.85 * (white - bl))
    q = d / (e * sc)
    y = q[:-1, :-1] + q[1:, :-1] + q[:-1, 1:] + q[1:, 1:]
    dsum = d[:-1, :-1] + d[1:, :-1] + d[:-1, 1:] + d[1:, 1:]
    nbad = bad[:-1, :-1] | bad[1:, :-1] | bad[:-1, 1:] | bad[1:, 1:]
    return y, ~nbad & (dsum > 10.0 * read_sd)


def refine_shift(ref_mosaic: np.ndarray, mosaic: np.ndarray, start, exposures: tuple[float, float],
                 black: tuple[np.ndarray, np.ndarray], white: tuple[float, float],
                 read_sd: float = 2.0) -> tuple[np.ndarray, dict]:
    """The translation (dy, dx), photosites, that carries ``ref_mosaic``'s content onto
    ``mosaic``'s (module docstring, estimation), from ``start`` (whole photosites: the
    2x2-block MTB's); ``exposures`` ``(e_ref, e)`` relative, ``black`` (2, 2) and ``white`` per
    frame, ``read_sd`` the read noise (DN). Returns the shift (float64, (2,)) and what was done
    (``samples``, ``steps``, ``start``, ``gain``; ``refined`` False when too few samples were
    common to both frames: the shift is then ``start``)."""
    e_a, e_b = float(exposures[0]), float(exposures[1])
    ba = np.asarray(black[0], np.float64).reshape(2, 2)
    bb = np.asarray(black[1], np.float64).reshape(2, 2)
    # one scale per CFA phase (the reference's median exposure-normalised value), so that a
    # window's sum weighs the colours alike whatever its phase
    scale = np.ones((2, 2))
    ra = np.asarray(ref_mosaic, np.float64)
    for a in range(2):
        for b in range(2):
            d = ra[a::2, b::2] - ba[a, b]
            good = (ra[a::2, b::2] < float(white[0])) & (d > 0)
            scale[a, b] = max(float(np.median(d[good])) / e_a, 1e-30) if good.any() else 1.0
    scale /= scale.mean()
    ya, oka = _box_image(ref_mosaic, e_a, ba, float(white[0]), scale, read_sd)
    yb, okb = _box_image(mosaic, e_b, bb, float(white[1]), scale, read_sd)
    okb = okb.astype(np.float64)
    hp, wp = ya.shape
    stride = max(1, (hp * wp) // _MAX_SAMPLES)
    rows = slice(0, hp, stride)
    va, oka = ya[rows], oka[rows]
    # the Poisson part of the difference's variance (a constant gain drops out of the estimate)
    wa = 1.0 / (np.maximum(va, 0.0) * (1.0 / e_a + 1.0 / e_b) + 16.0 * read_sd ** 2 * (1 / e_a ** 2 + 1 / e_b ** 2))
    info = {"start": [int(start[0]), int(start[1])], "refined": False, "samples": 0, "steps": 0, "gain": 1.0}
    full = (hp, wp)

    def sample(s: np.ndarray, derivative: bool):
        """Frame b's box image at p + s on the sampled rows: values, d/dy, d/dx, where usable."""
        iy, ix = math.floor(s[0]), math.floor(s[1])
        fy, fx = s[0] - iy, s[1] - ix
        wy, wx = keys_weights(fy), keys_weights(fx)
        val = np.full(full, np.nan)
        v, (rs, cs) = _convolve(yb, (iy, ix), wy, wx, full)
        val[rs, cs] = v
        okv = np.zeros(full)
        o, (rs2, cs2) = _convolve(okb, (iy, ix), (wy != 0).astype(float), (wx != 0).astype(float), full)
        okv[rs2, cs2] = o
        ntap = float(np.count_nonzero(wy) * np.count_nonzero(wx))
        usable = (okv >= ntap - 0.5)[rows] & np.isfinite(val[rows]) & oka
        if not derivative:
            return val[rows], None, None, usable
        gy = np.full(full, np.nan)
        gx = np.full(full, np.nan)
        wy4, wx4 = _keys(fy - np.arange(-1, 3)), _keys(fx - np.arange(-1, 3))
        g, (r3, c3) = _convolve(yb, (iy, ix), keys_weights(fy, True), wx4, full)
        gy[r3, c3] = g
        g, (r3, c3) = _convolve(yb, (iy, ix), wy4, keys_weights(fx, True), full)
        gx[r3, c3] = g
        usable &= np.isfinite(gy[rows]) & np.isfinite(gx[rows])
        return val[rows], gy[rows], gx[rows], usable

    def cost(s: np.ndarray) -> tuple[float, int]:
        val, _, _, sel = sample(s, False)
        n = int(sel.sum())
        if n < _MIN_SAMPLES:
            return np.inf, n
        return float(np.median(np.abs(val[sel] - va[sel]) * np.sqrt(wa[sel]))), n

    s0 = np.array([float(start[0]), float(start[1])])
    best, best_cost, n_best = s0, np.inf, 0
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            cand = s0 + np.array([dy, dx], float)
            c, n = cost(cand)
            if c < best_cost:
                best, best_cost, n_best = cand, c, n
    if not np.isfinite(best_cost):
        return s0, {**info, "samples": n_best}
    s, kappa = best.copy(), 1.0
    scale_z = None
    steps = n = 0
    for steps in range(1, _STEPS + 1):
        val, gy, gx, sel = sample(s, True)
        n = int(sel.sum())
        if n < _MIN_SAMPLES:
            break
        r = val[sel] - kappa * va[sel]
        z = r * np.sqrt(wa[sel])
        if scale_z is None or steps <= 3:
            scale_z = 1.4826 * float(np.median(np.abs(z))) + 1e-30
        zz = z / (_TUKEY * scale_z)
        wt = wa[sel] * np.where(np.abs(zz) < 1, (1 - zz ** 2) ** 2, 0.0)
        jac = np.stack([gy[sel], gx[sel], -va[sel]], axis=1)
        try:
            step = -np.linalg.solve(jac.T @ (jac * wt[:, None]), jac.T @ (wt * r))
        except np.linalg.LinAlgError:
            break
        s = s + step[:2]
        kappa = kappa + step[2]
        if np.max(np.abs(step[:2])) < 1e-4 or np.max(np.abs(s - best)) > 3.0:
            break
    if not np.all(np.isfinite(s)) or np.max(np.abs(s - best)) > 3.0:
        return best, {**info, "samples": n, "steps": steps}
    return s, {**info, "refined": True, "samples": int(n), "steps": steps, "gain": float(kappa)}


def _check_pattern(pattern: str) -> None:
    p = pattern.upper()
    if len(p) != 4 or sorted(p) != ["B", "G", "G", "R"]:
        raise InputError(f"unsupported CFA pattern {pattern!r}; expected a Bayer pattern such as 'RGGB'")


def phase_scale(mosaic: np.ndarray, black: np.ndarray, white: float, exposure: float) -> np.ndarray:
    """(2, 2): each CFA phase's median value above black per unit exposure over its unsaturated
    positive photosites, over their mean: weights that make a 2x2 window's sum treat the colours
    alike (:func:`shifted_box`, :func:`refine_shift`)."""
    m = np.asarray(mosaic, np.float64)
    bl = np.asarray(black, np.float64).reshape(2, 2)
    scale = np.ones((2, 2))
    for a in range(2):
        for b in range(2):
            d = m[a::2, b::2] - bl[a, b]
            good = (m[a::2, b::2] < float(white)) & (d > 0)
            scale[a, b] = max(float(np.median(d[good])) / exposure, 1e-30) if good.any() else 1.0
    return scale / scale.mean()


def shifted_box(values: np.ndarray, saturated: np.ndarray, shift, scale: np.ndarray) -> tuple:
    """The sliding 2x2 sum of ``values / scale`` (per CFA phase; (H, W) per photosite) at the
    reference's photosites ``p + shift`` (window ``[p + s, p + s + 1]``, Keys between whole
    shifts): ``(box, saturated, inside, factor)`` -- (H, W) float64, (H, W) bool (a saturated
    photosite in the support), (H, W) bool (the support inside the frame) and ``sum w^2``."""
    v = np.asarray(values, np.float64)
    h, w = v.shape
    sc = np.tile(scale, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    q = np.pad(v / sc, ((0, 1), (0, 1)), mode="edge")
    st = np.pad(np.asarray(saturated, np.float64), ((0, 1), (0, 1)), mode="edge")
    box = q[:-1, :-1] + q[1:, :-1] + q[:-1, 1:] + q[1:, 1:]
    sbox = st[:-1, :-1] + st[1:, :-1] + st[:-1, 1:] + st[1:, 1:]
    iy, ix = math.floor(float(shift[0])), math.floor(float(shift[1]))
    wy, wx = keys_weights(float(shift[0]) - iy), keys_weights(float(shift[1]) - ix)
    out = np.zeros((h, w))
    sat = np.ones((h, w), bool)
    inside = np.zeros((h, w), bool)
    vals, (rs, cs) = _convolve(box, (iy, ix), wy, wx, (h, w))
    out[rs, cs] = vals
    ns, (rs2, cs2) = _convolve(sbox, (iy, ix), (wy != 0).astype(float), (wx != 0).astype(float), (h, w))
    sat[rs2, cs2] = ns > 0.5
    inside[rs, cs] = True
    return out, sat, inside, float(np.sum(wy ** 2) * np.sum(wx ** 2))
