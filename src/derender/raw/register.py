"""Sub-photosite registration of RAW mosaics: translations to a fraction of a photosite, colours resampled.

A translation ``s = (dy, dx)`` (photosites; the sign of
:func:`derender.engine.motion.align.chain_transforms`: the reference's content at photosite ``p``
sits at ``p + s`` in frame ``j``) moves the scene against the colour filter array: where ``s`` is
odd or fractional, frame ``j`` has no sample of the reference's colour at ``p + s``.

**Estimation** (:func:`refine_shift`), at the sensor's full resolution. Each frame's sliding 2x2
window sum of ``d / (e k)`` (``d`` DN above black, ``e`` the exposure, ``k`` per CFA phase the
reference's median level: :func:`phase_scale`) holds one photosite of every colour whatever the
window's phase, so it has no CFA pattern and can be shifted by any amount. Gauss-Newton (Lucas &
Kanade 1981) minimises

    sum_p w(p) rho(B_j(p + s) - kappa B_a(p))                                    (1)

over ``s`` and a gain ``kappa`` (an exposure not exactly its nominal value), ``B_j(p + s)`` and
its derivatives by Keys' (1981) cubic convolution (``a = -1/2``), over the windows well exposed
in both frames (every photosite unsaturated and below 85 % of its level, the sum above 10
read-noise sigma), ``w = 1 / (B (1/e_a + 1/e_j) + ...)`` the Poisson part of the difference's
variance and ``rho`` Tukey's biweight (moving things). It starts from the best of the 5 x 5
whole shifts around the caller's (the engine's MTB on 2x2 blocks: whole blocks, and it can miss by
one), by the median weighted residual; a refinement that does not lower that median (frames
stops apart with few common samples) is not taken. :func:`derender.hdr.raw.raw_motion` refines
each frame against its neighbour towards the reference and chains the shifts, as the engine does.

**Resampling** (:func:`resample_rgb`): frame ``j``'s colour ``c`` at ``p + s`` is Malvar, He &
Cutler's (2004) demosaic of frame ``j`` for colour ``c`` at the 4 x 4 photosites around ``p + s``
(on the mosaic white-balanced as :func:`derender.raw.optimal.raw_merge`'s demosaic sees it, the
colour unbalanced again: a tap of colour ``c'`` weighs ``w_c' / w_c``), weighted by Keys: one linear filter ``C`` of about 8 x 8 photosites per output CFA phase and
colour (constant over the frame, since ``s`` is), borders mirrored within each CFA phase
(:func:`derender.raw.register_kernels.mirror_cfa`: a mirrored photosite keeps its colour; the
mosaic's own mirror, as the demosaic has it, put a border row's other colours in, and a frame's
border rows shifted into the reference's frame carried that error: 11-13x the still twin's on
seed 0's two last rows). Away from the border, at a whole shift it is the demosaic of frame ``j``
at ``p + s`` exactly. Its noise variance is
``sum_q C[q]^2 Var[d(q)]``: :func:`variance_factors` gives it over the variance of a photosite of
colour ``c``, each photosite's variance taken proportional to its colour's level (shot noise),
and the merge multiplies the noise model by it per frame, phase and colour
(:func:`derender.raw.optimal.merge_compiled`). A colour whose support is saturated everywhere is
censored (at the level); one whose support is partly saturated takes no part (an interpolation
of saturated and unsaturated samples is neither a measurement nor a bound at ``c``); one whose
point ``p + s`` lies outside frame ``j`` takes no part.

**Merging in colour** (:func:`merge_shifted`): each colour is merged on its own, by the censored
maximum likelihood of :mod:`derender.raw.optimal`, over every frame's resampled colour (the
reference's too: its own colour exact, the two others its demosaic), and the three are the
output: no second demosaic. A frame resampled onto the reference's mosaic and then demosaiced
again stacks two interpolations: on handheld brackets that left the static zone 1.45x the still
bracket's error (measured, docs/results-raw.md). The colours of one frame share photosites, so
their noise is correlated: :func:`colour_correlation` gives it per phase, and the output
matrix's variance uses it (averaged over the frames: the merge's weights are not followed).

Whole even shifts need none of this: :func:`derender.hdr.raw.raw_motion` shifts those mosaics
(the CFA phase kept) and merges on the mosaic, and a shift within :data:`SNAP` of a whole number
is taken as whole, so a still or tripod bracket is merged bit for bit as without registration.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit

from derender.raw.colour_ghost_test import colour_ghosts
from derender.raw.register_kernels import PAD, box_image, colour_variance, filter_phase

__all__ = [
    "SNAP",
    "keys_weights",
    "snap_shift",
    "refine_shift",
    "resample_mosaic",
    "resample_rgb",
    "merge_shifted",
    "raw_merge_shifted",
    "colour_correlation",
    "variance_factors",
    "phase_scale",
]

#: A shift component within this many photosites of a whole number is taken as whole.
SNAP = 0.1

#: Keys' cubic convolution parameter (Keys 1981: a = -1/2 reproduces quadratics).
_KEYS_A = -0.5

#: Gauss-Newton steps of :func:`refine_shift` at most (stops when a step is below 1e-4 plane samples).
_STEPS = 30

#: Tukey biweight constant, in robust sigmas of the normalised residual.
_TUKEY = 4.685

#: At most about this many 2x2 windows enter the estimate (a regular grid, every k-th row and column).
_MAX_SAMPLES = 1 << 16

#: Fewer common well-exposed samples than this: the pair's shift is refined to whole photosites
#: only (on simulated tripod brackets, 389-702 samples gave fractions of 0.17-0.22 photosite
#: where the truth was whole, 3-6 standard errors of the fit away).
_MIN_FRACTION_SAMPLES = 1000

#: Fewer common well-exposed samples than this: the pair's shift is not refined.
_MIN_SAMPLES = 64


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
def _resampling_kernels(pattern: str, sy: float, sx: float, wb: tuple = (1.0, 1.0, 1.0)) -> tuple:
    """Per output CFA phase ``(a, b)`` and colour ``c``: the linear filter ``C`` (correlation
    offsets ``(oy + u, ox + v)``) with ``out(p) = sum C[u, v] d(p + (oy + u, ox + v))``: Keys'
    weights over the 4 x 4 photosites around ``p + s`` of Malvar's estimate of colour ``c``
    there, on the mosaic balanced by ``wb`` (R, G, B) and unbalanced again (each tap of colour
    ``c'`` times ``wb[c'] / wb[c]``). Returns ``kernels[a][b][c] = (C, oy, ox)`` and the factors
    ``sum C^2`` (3, 2, 2)."""
    from derender.raw.optimal import linear_demosaic_kernels

    ker = linear_demosaic_kernels(pattern)                 # (2, 2, 3, 5, 5)
    lut = {"R": 0, "G": 1, "B": 2}
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
                oy, ox = iy - 3 + int(rows[0]), ix - 3 + int(cols[0])
                if tuple(wb) != (1.0, 1.0, 1.0):
                    uy = (a + oy + np.arange(sub.shape[0])) & 1
                    ux = (b + ox + np.arange(sub.shape[1])) & 1
                    col = np.array([[lut[pattern[2 * i + k]] for k in ux] for i in uy])
                    sub = sub * (np.asarray(wb, np.float64)[col] / float(wb[c]))
                out[a][b][c] = (sub, oy, ox)
                factor[c, a, b] = float(np.sum(sub ** 2))
    return out, factor


#: Photosites mirrored beyond each edge (within each CFA phase,
#: :func:`derender.raw.register_kernels.mirror_cfa`), so that a frame's colours exist up to its border.
_PAD = PAD


def _apply(m: np.ndarray, black: np.ndarray, white: float, kernel: tuple, a: int, b: int, shift):
    """One phase's filter (:func:`_resampling_kernels`) on the mosaic ``m`` (values above
    ``black`` (2, 2), mirrored by :data:`_PAD` beyond its edges) for the output photosites
    ``p = (2i + a, 2k + b)`` whose support lies inside the padded frame and whose point
    ``p + shift`` lies inside the frame: ``(values, saturated taps, taps, (i0, i1, k0, k1))``
    (:func:`derender.raw.register_kernels.filter_phase`)."""
    ker, oy, ox = kernel
    h, w = m.shape
    hp, wp = h + 2 * _PAD, w + 2 * _PAD
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
    vals = np.empty((i1 - i0, k1 - k0))
    nsat = np.empty((i1 - i0, k1 - k0))
    filter_phase(m, black, float(white), np.ascontiguousarray(ker, np.float64), 2 * i0 + a + oy,
                 2 * k0 + b + ox, vals, nsat)
    return vals, nsat, int(np.count_nonzero(ker)), (i0, i1, k0, k1)


def _wb_key(wb) -> tuple:
    """``wb`` (R, G, B, or None: ones) as the kernels' cache key, relative to green."""
    if wb is None:
        return (1.0, 1.0, 1.0)
    m = np.asarray(wb, np.float64).reshape(3)
    return tuple(float(v) for v in m / m[1])


def _prepare(mosaic: np.ndarray, black):
    m = np.ascontiguousarray(mosaic)
    black = np.broadcast_to(np.asarray(black, np.float64).reshape(-1)[0], (2, 2)).copy() \
        if np.asarray(black).size == 1 else np.ascontiguousarray(np.asarray(black, np.float64).reshape(2, 2))
    return m, black


def resample_mosaic(mosaic: np.ndarray, shift, black: np.ndarray, white: float,
                    pattern: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``j``'s mosaic on the reference's photosites: at each photosite the reference's colour
    of :func:`resample_rgb` (for ghost removal's test per photosite, and a merge on the mosaic):
    ``(codes, valid, factor)`` -- (H, W) float64 codes (the target phase's black level plus the
    resampled value above black; the white level where the support is saturated everywhere),
    (H, W) bool where the sample takes part, and the (2, 2) variance factor per phase."""
    m, black = _prepare(mosaic, black)
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
            got = _apply(m, black, white, kernels[a][b][c], a, b, shift)
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
                 pattern: str, channels: tuple[int, ...] = (0, 1, 2),
                 wb=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``j``'s colours ``channels`` (0, 1, 2: R, G, B) at the reference's photosites
    (module docstring, merging in colour): ``(values, state, factor)`` -- (C, H, W) float64 DN
    above black, (C, H, W) uint8 state (0: takes no part, 1: a measurement, 2: censored, its
    support saturated everywhere) and the (3, 2, 2) variance factor per colour and output phase.
    ``wb`` (R, G, B; None: ones): the balance Malvar's demosaic sees the mosaic in (as
    :func:`derender.raw.optimal.raw_merge`'s); the values stay unbalanced."""
    m, black = _prepare(mosaic, black)
    kernels, factors = _resampling_kernels(pattern.upper(), float(shift[0]), float(shift[1]), _wb_key(wb))
    h, w = m.shape
    values = np.zeros((len(channels), h, w))
    state = np.zeros((len(channels), h, w), np.uint8)
    for a in range(2):
        for b in range(2):
            for k, c in enumerate(channels):
                got = _apply(m, black, white, kernels[a][b][c], a, b, shift)
                if got is None:
                    continue
                vals, nsat, taps, (i0, i1, k0, k1) = got
                full = nsat >= taps - 0.5
                values[k, a::2, b::2][i0:i1, k0:k1] = vals
                state[k, a::2, b::2][i0:i1, k0:k1] = np.where(full, 2, np.where(nsat < 0.5, 1, 0))
    return values, state, factors


def variance_factors(pattern: str, shift, colour_level: np.ndarray, wb=None) -> np.ndarray:
    """(3, 2, 2): per colour and output phase, the variance of a resampled colour (:func:`resample_rgb`)
    over the variance of a photosite of that colour, ``sum C[q]^2 V(q) / V_c``, each photosite's
    variance taken as its colour's ``colour_level`` (R, G, B: a typical variance, ``g L e +
    sigma^2`` at the colour's typical level ``L`` in the frame); ``wb`` as :func:`resample_rgb`'s."""
    p = pattern.upper()
    lut = {"R": 0, "G": 1, "B": 2}
    kernels, _ = _resampling_kernels(p, float(shift[0]), float(shift[1]), _wb_key(wb))
    lv = np.asarray(colour_level, np.float64)
    out = np.ones((3, 2, 2))
    for a in range(2):
        for b in range(2):
            for c in range(3):
                ker, oy, ox = kernels[a][b][c]
                uy = (a + oy + np.arange(ker.shape[0])) & 1
                ux = (b + ox + np.arange(ker.shape[1])) & 1
                col = np.array([[lut[p[2 * i + k]] for k in ux] for i in uy])
                out[c, a, b] = float(np.sum(ker ** 2 * lv[col]) / lv[c])
    return out


def merge_shifted(mosaics: list, shifts: np.ndarray, black: np.ndarray, white: np.ndarray, exposures: np.ndarray,
                  noise, pattern: str, *, valid: np.ndarray | None = None, censored: bool = True,
                  untested: np.ndarray | None = None, reference: int | None = None,
                  threshold: float = 4.0, wb=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The censored ML merge (:func:`derender.raw.optimal.merge_compiled`) done per colour on
    the frames' colours at the reference's photosites (:func:`resample_rgb`, each frame at its
    ``shift``; module docstring, merging in colour). ``mosaics`` (N, H, W) exposure-sorted,
    ``black`` (N, 2, 2), ``white`` (N,), ``exposures`` (N,), ``valid`` (N, H, W) where each
    frame may take part (ghost removal; None: everywhere); ``untested`` (N, H, W) where ghost
    removal could not test a frame (:func:`colour_ghosts`: tested here colour by colour against
    frame ``reference``'s, ``threshold`` on the 5x5 mean of ``z^2``); ``wb`` the balance the
    resampling's demosaic sees the mosaic in (:func:`resample_rgb`). Returns camera RGB (H, W, 3) in
    units of the white level per second, its variance (H, W, 3), the (H, W) mask (bright where
    a colour has every frame saturated) and the colours' correlation per CFA phase (2, 2, 3, 3),
    the frames' :func:`colour_correlation` averaged (the merge's weights are not followed)."""
    from numba.typed import List

    from derender.raw.optimal import interleave, merge_compiled

    n = len(mosaics)
    h, w = np.asarray(mosaics[0]).shape
    ceil = np.array([float(white[j]) - float(np.mean(black[j])) for j in range(n)])
    span = float(ceil[int(np.argmax(white))])
    x_out = np.empty((h, w, 3), np.float32)
    v_out = np.empty((h, w, 3), np.float32)
    mask = np.zeros((h, w), np.uint8)
    rho = np.zeros((2, 2, 3, 3))
    for j in range(n):
        rho += colour_correlation(pattern, shifts[j], wb) / n
    # each colour's typical level per unit exposure (median of the unshifted frame, else the
    # middle one), and in each frame its typical variance g L e + sigma^2 per colour
    k = next((j for j in range(n) if tuple(shifts[j]) == (0.0, 0.0)), n // 2)
    mk = np.asarray(mosaics[k], np.float64)
    lut = {"R": 0, "G": 1, "B": 2}
    parts: list = [[], [], []]
    for a in range(2):
        for b in range(2):
            d = mk[a::2, b::2] - black[k][a, b]
            good = (mk[a::2, b::2] < white[k]) & (d > 0)
            parts[lut[pattern.upper()[2 * a + b]]].append(d[good] / float(exposures[k]))
    level = np.array([float(np.median(np.concatenate(q))) if sum(x.size for x in q) else 0.0 for q in parts])
    g_f, s2_f = noise.per_frame(n)
    weighted = [variance_factors(pattern, shifts[j], g_f[j] * level * float(exposures[j]) + s2_f[j], wb)
                for j in range(n)]
    for c in range(3):
        codes, ok, factors, loose = [], np.empty((n, h, w), bool), np.empty((n, 2, 2)), []
        measured = np.empty((n, h, w), bool)
        states = []
        for j in range(n):
            vals, state, f = resample_rgb(mosaics[j], shifts[j], black[j], white[j], pattern, (c,), wb)
            vals, state = vals[0], state[0]
            vals[state == 2] = ceil[j]                          # censored: at the level
            codes.append(np.ascontiguousarray(vals))
            states.append(state)
            ok[j] = state != 0
            if valid is not None:
                ok[j] &= np.asarray(valid[j], bool)
            factors[j] = weighted[j][c]
            if tuple(shifts[j]) == (0.0, 0.0):
                loose.append((j, state == 0))
        if untested is not None and reference is not None:
            r = int(reference)
            for j in range(n):
                if j != r and np.any(untested[j]):
                    ok[j] &= ~colour_ghosts(codes[j], states[j], codes[r], states[r],
                                            exposures=(exposures[j], exposures[r]), gain=(g_f[j], g_f[r]),
                                            read_variance=(s2_f[j], s2_f[r]), factors=(factors[j], factors[r]),
                                            ceiling=(ceil[j], ceil[r]), where=np.asarray(untested[j], bool),
                                            threshold=threshold)
        for j in range(n):
            measured[j] = ok[j] & (states[j] == 1)
        # an unshifted frame's colour whose support is partly saturated (biased low) stands in
        # only where no other frame measures the colour at all (ghost removal kept the reference
        # alone, or the others kept are censored: censored samples alone bound it from below only)
        for j, part in loose:
            ok[j] |= part & ~np.any(np.delete(measured, j, axis=0), axis=0)
        x, var, m = merge_compiled(List(codes), np.zeros((n, 2, 2)), ceil, exposures, noise, censored=censored,
                                   scale=1.0 / span, valid=ok, variance_factor=factors)
        x_out[..., c] = interleave(x, (h, w))
        v_out[..., c] = interleave(var, (h, w))
        mask = np.maximum(mask, m)
    return x_out, v_out, mask, rho


def colour_correlation(pattern: str, shift, wb=None) -> np.ndarray:
    """(2, 2, 3, 3): per output CFA phase, the correlation of a frame's three resampled colours
    (:func:`resample_rgb`, ``wb`` as its) for photosites of equal variance: ``sum C_c C_c' /
    sqrt(sum C_c^2 sum C_c'^2)`` over the filters' common photosites."""
    kernels, _ = _resampling_kernels(pattern.upper(), float(shift[0]), float(shift[1]), _wb_key(wb))
    out = np.ones((2, 2, 3, 3))
    for a in range(2):
        for b in range(2):
            full = []
            y0 = min(kernels[a][b][c][1] for c in range(3))
            x0 = min(kernels[a][b][c][2] for c in range(3))
            for c in range(3):
                ker, oy, ox = kernels[a][b][c]
                canvas = np.zeros((16, 16))
                canvas[oy - y0:oy - y0 + ker.shape[0], ox - x0:ox - x0 + ker.shape[1]] = ker
                full.append(canvas.ravel())
            f = np.array(full)
            cov = f @ f.T
            d = np.sqrt(np.diag(cov))
            out[a, b] = cov / np.outer(d, d)
    return out


def _box_image(mosaic: np.ndarray, e: float, black: np.ndarray, white: float, scale: np.ndarray,
               read_sd: float) -> tuple[np.ndarray, np.ndarray]:
    """The sliding 2x2 sum of the exposure-normalised mosaic, each photosite divided by its CFA
    phase's ``scale``: ``(y, ok)``, (H - 1, W - 1), every window one photosite of each phase
    (so no CFA pattern is left in it), ``ok`` where its four photosites are unsaturated, below
    85 % of the level, and the window sum above 10 read-noise sigma."""
    m = np.ascontiguousarray(mosaic)
    h, w = m.shape
    y = np.empty((h - 1, w - 1))
    ok = np.empty((h - 1, w - 1), np.bool_)
    box_image(m, float(e), np.ascontiguousarray(black, np.float64).reshape(2, 2), float(white),
              np.ascontiguousarray(scale, np.float64).reshape(2, 2), float(read_sd), y, ok)
    return y, ok


@njit(cache=True, nogil=True)
def _keys_grid(img, ok, ri, ci, iy, ix, wy, wx, dwy, dwx, need_y, need_x, derivative, val, gy, gx,
               usable):  # pragma: no cover - compiled
    """Keys' 4 x 4 interpolation of ``img`` at ``(ri[r] + iy + fy, ci[c] + ix + fx)`` (the
    weights ``wy``, ``wx`` of the fractions given; their derivatives ``dwy``, ``dwx``): values and
    derivatives on the grid, ``usable`` where every needed tap is inside and ``ok``."""
    h, w = img.shape
    for r in range(ri.shape[0]):
        for c in range(ci.shape[0]):
            good = True
            v = 0.0
            dy = 0.0
            dx = 0.0
            for m in range(4):
                y = ri[r] + iy + m - 1
                inside_y = 0 <= y < h
                if need_y[m] and not inside_y:
                    good = False
                    break
                if not inside_y:
                    continue
                for n in range(4):
                    x = ci[c] + ix + n - 1
                    inside_x = 0 <= x < w
                    if need_x[n] and (not inside_x or not ok[y, x]):
                        if need_y[m]:
                            good = False
                            break
                    if not inside_x:
                        continue
                    q = img[y, x]
                    v += wy[m] * wx[n] * q
                    if derivative:
                        dy += dwy[m] * wx[n] * q
                        dx += wy[m] * dwx[n] * q
                if not good:
                    break
            usable[r, c] = good
            val[r, c] = v
            gy[r, c] = dy
            gx[r, c] = dx


def _gauss_newton(sample, va: np.ndarray, wa: np.ndarray, best: np.ndarray) -> tuple:
    """Robust (Tukey-weighted) Gauss-Newton steps of the shift and a gain ``kappa`` from ``best``:
    ``sample(s, True)`` gives frame b's values, their derivatives and where usable at ``p + s``;
    ``va`` the reference's values, ``wa`` their inverse variances. Returns ``(s, kappa,
    standard errors of s, samples, steps done)``; it stops on a step below 1e-4 photosite, on
    too few samples, or 3 photosites away from ``best``."""
    s, kappa = best.copy(), 1.0
    se = np.zeros(2)
    scale_z = None
    n = done = 0
    for steps in range(1, _STEPS + 1):
        val, gy, gx, sel = sample(s, True)
        n = int(sel.sum())
        if n < _MIN_SAMPLES:
            break
        done += 1
        r = val[sel] - kappa * va[sel]
        z = r * np.sqrt(wa[sel])
        if scale_z is None or steps <= 3:
            scale_z = 1.4826 * float(np.median(np.abs(z))) + 1e-30
        zz = z / (_TUKEY * scale_z)
        wt = wa[sel] * np.where(np.abs(zz) < 1, (1 - zz ** 2) ** 2, 0.0)
        jac = np.stack([gy[sel], gx[sel], -va[sel]], axis=1)
        jtj = jac.T @ (jac * wt[:, None])
        try:
            step = -np.linalg.solve(jtj, jac.T @ (wt * r))
            cov = np.linalg.inv(jtj) * float(np.sum(wt * r * r)) / max(n - 3, 1)
        except np.linalg.LinAlgError:
            break
        se = np.sqrt(np.maximum(np.diag(cov)[:2], 0.0))
        s = s + step[:2]
        kappa = kappa + step[2]
        if np.max(np.abs(step[:2])) < 1e-4 or np.max(np.abs(s - best)) > 3.0:
            break
    return s, kappa, se, n, done


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
    scale = phase_scale(ref_mosaic, ba, float(white[0]), e_a)
    ya, oka = _box_image(ref_mosaic, e_a, ba, float(white[0]), scale, read_sd)
    yb, okb = _box_image(mosaic, e_b, bb, float(white[1]), scale, read_sd)
    hp, wp = ya.shape
    k = max(1, math.ceil(math.sqrt(hp * wp / _MAX_SAMPLES)))     # a regular grid of windows
    ri, ci = np.arange(0, hp, k), np.arange(0, wp, k)
    va, oka = ya[np.ix_(ri, ci)], oka[np.ix_(ri, ci)]
    # the Poisson part of the difference's variance (a constant gain drops out of the estimate)
    wa = 1.0 / (np.maximum(va, 0.0) * (1.0 / e_a + 1.0 / e_b) + 16.0 * read_sd ** 2 * (1 / e_a ** 2 + 1 / e_b ** 2))
    info = {"start": [int(start[0]), int(start[1])], "refined": False, "samples": 0, "steps": 0, "gain": 1.0}

    def sample(s: np.ndarray, derivative: bool):
        """Frame b's box image at p + s on the grid: values, d/dy, d/dx (None without
        ``derivative``), where usable (every tap inside, well exposed, and the reference's too)."""
        iy, ix = math.floor(s[0]), math.floor(s[1])
        fy, fx = s[0] - iy, s[1] - ix
        wy, wx = keys_weights(fy), keys_weights(fx)
        dwy, dwx = keys_weights(fy, True), keys_weights(fx, True)
        if derivative:
            need_y, need_x = (wy != 0) | (dwy != 0), (wx != 0) | (dwx != 0)
        else:
            need_y, need_x = wy != 0, wx != 0
        val = np.empty(va.shape)
        gy = np.empty(va.shape)
        gx = np.empty(va.shape)
        usable = np.empty(va.shape, np.bool_)
        _keys_grid(yb, okb, ri, ci, iy, ix, wy, wx, dwy, dwx, need_y, need_x, bool(derivative), val, gy, gx, usable)
        usable &= oka
        return val, (gy if derivative else None), (gx if derivative else None), usable

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
    s, kappa, se, n, done = _gauss_newton(sample, va, wa, best)
    if not done or not np.all(np.isfinite(s)) or np.max(np.abs(s - best)) > 3.0:
        return best, {**info, "samples": n, "steps": done}
    # a refinement that does not lower the median residual of the best whole shift is not taken
    # (few common samples: frames stops apart)
    # each component indistinguishable from a whole number (within 3 standard errors of the
    # estimate) is taken as whole
    s = np.where(np.abs(s - np.rint(s)) <= 3.0 * se, np.rint(s), s)
    if n < _MIN_FRACTION_SAMPLES:      # too few to trust a fraction (biased by 0.2 photosite, measured)
        s = np.rint(s)
    c_final, _ = cost(s)
    whole = np.rint(s)
    c_whole, _ = cost(whole) if np.any(whole != s) else (np.inf, 0)
    if c_whole < min(c_final, best_cost):
        best, best_cost = whole, c_whole
    if not c_final < best_cost:
        return best, {**info, "samples": n, "steps": done, "kept_whole": True}
    return s, {**info, "refined": True, "samples": int(n), "steps": done, "gain": float(kappa),
               "standard_error": [round(float(v), 4) for v in se]}




def phase_scale(mosaic: np.ndarray, black: np.ndarray, white: float, exposure: float) -> np.ndarray:
    """(2, 2): each CFA phase's median value above black per unit exposure over its unsaturated
    positive photosites, over their mean: weights that make a 2x2 window's sum treat the colours
    alike (:func:`derender.raw.window_ghost_test.shifted_box`, :func:`refine_shift`)."""
    m = np.asarray(mosaic, np.float64)
    bl = np.asarray(black, np.float64).reshape(2, 2)
    scale = np.ones((2, 2))
    for a in range(2):
        for b in range(2):
            d = m[a::2, b::2] - bl[a, b]
            good = (m[a::2, b::2] < float(white)) & (d > 0)
            scale[a, b] = max(float(np.median(d[good])) / exposure, 1e-30) if good.any() else 1.0
    return scale / scale.mean()


def raw_merge_shifted(frames, shifts, noise, *, valid=None, output_space: str = "linear_srgb", wb=None,
                      variance: bool = True, clip_negative: bool = True, censored: bool = True,
                      untested=None, reference: int | None = None, threshold: float = 4.0):
    """:func:`derender.raw.optimal.raw_merge` for frames at ``shifts`` (per frame as given,
    (dy, dx) photosites: the reference's content at ``p`` sits at ``p + s`` in the frame):
    every frame's colours at the reference's photosites merged per colour
    (:func:`merge_shifted`), then white balance (``wb``, else the as-shot multipliers of the
    middle frame of the time-sorted stack) and the output matrix; the variance through them with
    the colours' correlation per CFA phase (:func:`colour_correlation`). ``noise`` the
    :class:`~derender.raw.noise.NoiseModel`; ``valid`` per frame as given, where it may take
    part (ghost removal); ``untested`` per frame as given, where ghost removal could not test it,
    to be tested colour by colour against frame ``reference`` (as given) with ``threshold``
    (:func:`colour_ghosts`). Returns an :class:`~derender.core.types.HDRResult` as ``raw_merge``,
    its ``info`` in the same terms: the resampling's Malvar demosaic sees the mosaic balanced
    as raw_merge's does (``wb_multipliers``, :func:`derender.raw.optimal.white_balances`: Malvar's
    colour-difference terms assume balanced colours; the reference frame's demosaic on its
    unbalanced mosaic had a 5-13 % larger median error in every zone of handheld seeds 0, 4 and 7,
    measured, docs/results-raw.md), the balance the output keeps ``output_wb_multipliers`` and
    ``output_matrix`` the matrix after the demosaic of the balanced mosaic (raw_merge's)."""
    from derender.core.errors import InputError
    from derender.core.types import HDRResult
    from derender.raw.mosaic import MASK_RADIUS, sorted_raw_frames, spread_mask
    from derender.raw.optimal import compiled_frames, output_matrix, white_balances

    given = list(frames)
    if len(shifts) != len(given) or (valid is not None and len(valid) != len(given)):
        raise InputError(f"shifts and valid need one entry per frame ({len(given)})")
    frames, times = sorted_raw_frames(given)
    index = {id(f): j for j, f in enumerate(given)}
    order = [index[id(f)] for f in frames]
    shift_arr = np.array([[float(shifts[j][0]), float(shifts[j][1])] for j in order])
    valid_stack = None if valid is None else np.stack([np.asarray(valid[j], bool) for j in order])
    untested_stack = None if untested is None else np.stack([np.asarray(untested[j], bool) for j in order])
    ref_sorted = None if reference is None else order.index(int(reference))
    pattern = frames[0].cfa_pattern.upper()
    _, black, white = compiled_frames(frames)
    mosaics = [np.asarray(f.mosaic) for f in frames]
    ref = frames[len(frames) // 2]
    # the balance the resampling's demosaic sees the mosaic in and the one the output keeps, as
    # raw_merge's (white_balances: the output's ones in camera_rgb and for a file that states
    # none); the resampled colours stay unbalanced, so nothing is divided out
    demosaic_wb, mult = white_balances(ref, output_space, wb, mosaic=np.asarray(ref.mosaic), pattern=pattern)
    rgb, var, mmask, rho = merge_shifted(mosaics, shift_arr, black, white, times, noise, pattern, valid=valid_stack,
                                         censored=censored, untested=untested_stack, reference=ref_sorted,
                                         threshold=threshold, wb=demosaic_wb)
    mat = output_matrix(ref, output_space)
    full = mat * mult[None, :]
    h, w = mmask.shape
    out = (rgb.reshape(-1, 3).astype(np.float64) @ full.T).reshape(h, w, 3)
    var_out = None
    if variance:
        # Var[o] = sum_cc' F_oc F_oc' rho_cc' sigma_c sigma_c', rho of the photosite's phase
        sd = np.sqrt(np.maximum(var.astype(np.float64), 0.0))
        var_out = np.empty((h, w, 3), np.float32)
        q = np.empty((2, 2, 3, 3, 3))
        for a in range(2):
            for b in range(2):
                q[a, b] = np.einsum("oc,cd,od->ocd", full, rho[a, b], full)
        colour_variance(sd, q, var_out)
    out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    if clip_negative:
        out = np.maximum(out, 0.0)
    span = white - black.mean(axis=(1, 2))
    info = {"colour_space": output_space, "exposure_times": times.tolist(), "demosaic": "malvar2004",
            "cfa_pattern": pattern, "noise": noise.as_dict(), "censored": bool(censored),
            "units": "white level per second", "white_minus_black_dn": float(span[int(np.argmax(white))]),
            "mosaic_mask": mmask, "n_frames": len(frames), "wb_multipliers": np.asarray(demosaic_wb).tolist(),
            "output_wb_multipliers": mult.tolist(), "output_matrix": (full / np.asarray(demosaic_wb)[None, :]).tolist(),
            "merged": "per colour, frames resampled at the reference's photosites"}
    return HDRResult(radiance=np.ascontiguousarray(out, dtype=np.float32),
                     mask=spread_mask(mmask, MASK_RADIUS["malvar2004"]), variance=var_out, info=info)
