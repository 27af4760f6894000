"""The sensor's Poisson-Gaussian noise, estimated from the bracket itself (no calibration shots).

A photosite's value above black, ``d = y - black`` (DN), is gain times a Poisson count of
photo-electrons plus Gaussian read noise (and the ADC's rounding), so

    Var[d] = g * E[d] + sigma^2                                               (1)

with ``g`` in DN per electron and ``sigma^2`` (DN^2) the read noise plus the quantisation
1/12 (Healey & Kondepudy 1994; Foi et al. 2008). In a still bracket two frames ``j``, ``k``
(times ``t_j < t_k``) see the same radiance ``X`` (DN/s) at a photosite, so the
exposure-normalised difference ``r = d_k / t_k - d_j / t_j`` has mean 0 whatever the scene's
texture and

    Var[r] = g * X * (1/t_j + 1/t_k) + sigma^2 * (1/t_j^2 + 1/t_k^2)          (2)

-- a linear model in ``(g, sigma^2)``. :func:`estimate_noise` fits it by weighted least
squares on ``r^2`` over the photosites unsaturated in both frames of each adjacent pair
(a regular subsample of at most :data:`_MAX_SAMPLES` per pair; weights ``1 / Var[r]^2``, the
variance of ``r^2`` for Gaussian ``r``), ``X`` from the pooled Poisson estimate
``sum d / sum t``. Where something moves (or a pixel is hot) two frames do not see the same
``X`` and ``r^2`` holds the scene's change, which no noise model describes; those samples must
not enter the fit, and a least-squares start on every sample would be inflated by them (gain
9-17x the truth on the simulator's tripod brackets with moving objects, read noise 10-13x), so
that no clipping threshold drawn from it would ever leave them out. The fit therefore starts
robust (:func:`_robust_start`): per pair and per level of ``X`` (:data:`_START_BINS` quantile
bins) the median of ``r^2``, divided by the chi-square median ``0.4549`` (a Gaussian's
variance from its median square, unmoved while fewer than half of a bin's samples hold motion),
fitted to eq. (2) by weighted least squares; then :data:`_CLIP_ROUNDS` reweighted rounds on
the samples within :data:`_CLIP_SIGMA` sigma of the current model (frame pairs compared only
where their exposure-normalised samples agree), each round's result divided by the truncated
chi-square mean ``E[chi2_1 | chi2_1 < c^2]`` so that the clipped fit stays unbiased on
still photosites (the samples are tested against the noise model before they enter, as the
ghost-free reconstruction of Granados, Kim, Tompkin & Theobalt 2013, "Automatic noise modeling
for ghost-free HDR reconstruction", ACM TOG 32(6), tests pixels for consistency). This is the self-calibration of Granados et al. 2010 ("Optimal HDR
reconstruction with linear digital cameras", CVPR, Sec. 4) and Hanji, Zhong & Mantiuk 2020
("Noise-aware merging of high dynamic range image stacks without camera calibration", ECCV
workshops, Sec. 3-4), done on frame differences rather than on calibration frames.

A shaken bracket is fitted on the frame pairs whose relative shift is a whole even translation
(:func:`estimate_noise_shifted`): they compare the same scene point on the same colour with no
resampling, where a pair rounded to even shifts would hold the scene's gradient across the
residual photosite.

A single frame has no partner: :func:`estimate_noise` then uses the differences of the two
green photosites of every 2x2 Bayer block (``Var[d_G1 - d_G2] = 2 Var[d]`` where the scene
is smooth), with per-level medians (robust to edges, ``median(r^2) = 0.4549 Var[r]`` for
Gaussian ``r``): a cruder estimate, since texture adds to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "NoiseModel",
    "estimate_noise",
    "estimate_noise_pairs",
    "estimate_noise_single",
    "estimate_noise_frames",
    "estimate_noise_shifted",
]


@dataclass(frozen=True)
class NoiseModel:
    """Poisson-Gaussian sensor noise, eq. (1): ``Var[d] = gain * E[d] + read_variance`` (DN, DN^2).

    ``source``: ``"pairs"`` (estimated from frame pairs), ``"exact-pairs"`` (a shaken bracket's
    pairs whose relative shift is whole and even, :func:`estimate_noise_shifted`),
    ``"green-pairs"`` (one frame), ``"given"``. A bracket whose ISO varies has a model per ISO (eq. 3):
    ``frame_gain`` and ``frame_read_variance`` per frame (in the merge's exposure-sorted order),
    ``gain`` and ``read_variance`` those of the shortest exposure; ``isos`` the ISO per frame."""

    gain: float
    read_variance: float
    source: str = "given"
    samples: int = 0
    frame_gain: tuple | None = None
    frame_read_variance: tuple | None = None
    isos: tuple | None = None

    def per_frame(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``(gain, read variance)`` per frame, (n,) float64 each."""
        if self.frame_gain is not None:
            return np.asarray(self.frame_gain, np.float64), np.asarray(self.frame_read_variance, np.float64)
        return np.full(n, float(self.gain)), np.full(n, float(self.read_variance))

    def __post_init__(self) -> None:
        if not (np.isfinite(self.gain) and self.gain > 0 and np.isfinite(self.read_variance)
                and self.read_variance > 0):
            raise InputError(f"a noise model needs gain > 0 and read variance > 0, got gain {self.gain}, "
                             f"read variance {self.read_variance}")

    @property
    def read_noise(self) -> float:
        """sigma (DN), read noise and quantisation together."""
        return float(np.sqrt(self.read_variance))

    def variance(self, expected_dn: np.ndarray) -> np.ndarray:
        """Eq. (1) at the expected value above black (negative expectations count as 0)."""
        return self.gain * np.maximum(expected_dn, 0.0) + self.read_variance

    def as_dict(self) -> dict:
        """The model as JSON-ready numbers (per ISO too when it varies)."""
        out = {"gain_dn_per_electron": float(self.gain), "read_noise_dn": self.read_noise,
               "source": self.source, "samples": int(self.samples)}
        if self.frame_gain is not None and self.isos is not None:
            per = {}
            for iso, g, s2 in zip(self.isos, self.frame_gain, self.frame_read_variance):
                per[f"{iso:g}"] = {"gain_dn_per_electron": float(g), "read_noise_dn": float(np.sqrt(s2))}
            out["per_iso"] = per
        return out


#: At most about this many photosites per frame pair enter the fit (every k-th of the usable ones).
_MAX_SAMPLES = 1 << 18


#: Fraction of the saturation level above which samples do not enter the noise fit (the
#: clipped tail would shrink their variance).
_FIT_CEILING = 0.85


#: Quantile bins of the level ``X`` per frame pair in the robust start of the noise fit.
_START_BINS = 24

#: Samples a bin of the robust start needs.
_START_MIN = 16

#: The noise fit's rounds after the robust start keep the samples within this many sigma of the model.
_CLIP_SIGMA = 3.0

#: Reweighted, clipped rounds after the robust start.
_CLIP_ROUNDS = 5


def _truncated_chi2_mean(c: float) -> float:
    """``E[Z^2 | |Z| < c]`` for a standard normal ``Z``: ``1 - 2 c phi(c) / (2 Phi(c) - 1)``."""
    from math import erf, exp, pi, sqrt

    inside = erf(c / sqrt(2.0))
    return 1.0 - 2.0 * c * exp(-0.5 * c * c) / sqrt(2.0 * pi) / inside


#: ``E[r^2 | r^2 < (c sigma)^2] / sigma^2`` at ``c =`` :data:`_CLIP_SIGMA` (the clipped rounds divide by it).
_CLIP_MEAN = _truncated_chi2_mean(_CLIP_SIGMA)


def _robust_start(r2: np.ndarray, xs: np.ndarray, pair_of: np.ndarray, dg: np.ndarray,
                  ds: np.ndarray) -> np.ndarray | None:
    """The robust start of the noise fit (module docstring): per pair ``p`` and quantile bin of
    ``xs``, ``median(r2) / 0.4549`` fitted to ``E[r2] = sum_q g_q x dg[p, q] + s2_q ds[p, q]`` by
    weighted least squares (weights ``n / E^2``); ``params = (g_1..g_k, s2_1..s2_k)``, or None
    when the bins do not constrain them. The samples of a pair are contiguous in ``pair_of``."""
    k = dg.shape[1]
    vals, rows, counts = [], [], []
    bounds = np.flatnonzero(np.diff(pair_of)) + 1
    for chunk in np.split(np.arange(r2.size), bounds):
        if chunk.size < _START_MIN:
            continue
        p = int(pair_of[chunk[0]])
        order = chunk[np.argsort(xs[chunk], kind="stable")]
        nb = max(1, min(_START_BINS, order.size // _START_MIN))
        for part in np.array_split(order, nb):
            vals.append(float(np.median(r2[part])) / _CHI2_MEDIAN)
            rows.append(np.concatenate([float(np.mean(np.maximum(xs[part], 0.0))) * dg[p], ds[p]]))
            counts.append(part.size)
    if len(vals) < 2 * k:
        return None
    v, a, n = np.array(vals), np.array(rows), np.array(counts, np.float64)
    pred = np.maximum(v, 1e-12)
    params = None
    for _ in range(4):
        w = n / pred ** 2
        m = (a * w[:, None]).T @ a
        dia = np.sqrt(np.abs(np.diag(m)))
        if not np.all(np.isfinite(m)) or np.any(dia == 0) or np.linalg.cond(m / np.outer(dia, dia)) > _MAX_CONDITION:
            return None
        params = np.linalg.solve(m, (a * w[:, None]).T @ v)
        params[:k] = np.maximum(params[:k], 1e-6)
        params[k:] = np.maximum(params[k:], 1.0 / 12.0)
        pred = np.maximum(a @ params, 1e-12)
    return params


def _wls(r2: np.ndarray, xs: np.ndarray, pair_of: np.ndarray, dg: np.ndarray,
         ds: np.ndarray) -> tuple[float, float, int]:
    """Fit ``E[r2] = g x dg[p] + s2 ds[p]`` (one model; the robust start, then clipped reweighted
    rounds, module docstring); returns (g, s2, samples used)."""
    params = _robust_start(r2, xs, pair_of, dg, ds)
    if params is None:
        raise InputError("the bracket does not constrain the noise model (give gain and read noise)")
    g, s2 = float(params[0]), float(params[1])
    a, b = np.maximum(xs, 0.0) * dg[pair_of, 0], ds[pair_of, 0]
    keep = np.ones(r2.shape, bool)
    for _ in range(_CLIP_ROUNDS):
        pred = np.maximum(g * a + s2 * b, 1e-12)
        w = 1.0 / pred ** 2
        keep = r2 <= _CLIP_SIGMA ** 2 * pred
        aa, bb, rr, ww = a[keep], b[keep], r2[keep], w[keep]
        m = np.array([[np.sum(ww * aa * aa), np.sum(ww * aa * bb)], [np.sum(ww * aa * bb), np.sum(ww * bb * bb)]])
        v = np.array([np.sum(ww * aa * rr), np.sum(ww * bb * rr)])
        try:
            g, s2 = np.linalg.solve(m, v) / _CLIP_MEAN
        except np.linalg.LinAlgError:
            raise InputError("the bracket does not constrain the noise model (give gain and read noise)") from None
        g, s2 = float(max(g, 1e-6)), float(max(s2, 1.0 / 12.0))
    return g, s2, int(np.count_nonzero(keep))


def estimate_noise_pairs(d: list[np.ndarray], saturated: list[np.ndarray], ceilings: list[np.ndarray],
                         times: np.ndarray) -> NoiseModel:
    """Eq. (2) fitted on every adjacent pair of frames (``d``: DN above black, time-sorted)."""
    times = np.asarray(times, dtype=np.float64)
    num = np.zeros(d[0].shape, np.float64)
    den = np.zeros(d[0].shape, np.float64)
    for dj, sj, tj in zip(d, saturated, times):
        num += np.where(sj, 0.0, dj)
        den += np.where(sj, 0.0, tj)
    x = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    r2s, xss, pair_of, dg, ds = [], [], [], [], []
    for j in range(len(d) - 1):
        k = j + 1
        ok = ~saturated[j] & ~saturated[k] & (d[j] < _FIT_CEILING * ceilings[j]) \
            & (d[k] < _FIT_CEILING * ceilings[k]) & (den > 0)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            continue
        idx = idx[::max(1, idx.size // _MAX_SAMPLES)]         # a regular subsample: deterministic, ample
        r = d[k].ravel()[idx] / times[k] - d[j].ravel()[idx] / times[j]
        r2s.append(r * r)
        xss.append(x.ravel()[idx])
        pair_of.append(np.full(r.shape, len(dg), np.int64))
        dg.append([1.0 / times[j] + 1.0 / times[k]])
        ds.append([1.0 / times[j] ** 2 + 1.0 / times[k] ** 2])
    n = sum(len(r) for r in r2s)
    if n < 64:
        raise InputError(f"too few unsaturated photosites shared by adjacent frames ({n}) to estimate the "
                         "noise; give gain and read noise")
    g, s2, used = _wls(np.concatenate(r2s), np.concatenate(xss), np.concatenate(pair_of), np.array(dg),
                       np.array(ds))
    return NoiseModel(g, s2, "pairs", used)


#: median(r^2) / Var[r] for Gaussian r (chi-square with 1 degree of freedom).
_CHI2_MEDIAN = 0.454936423119572


def estimate_noise_single(d: np.ndarray, saturated: np.ndarray, ceiling: np.ndarray, pattern: str) -> NoiseModel:
    """One frame: the two greens of every 2x2 block (eq. (1) with ``Var[dG1 - dG2] = 2 Var[d]``),
    per-level robust (median) variances fitted by weighted least squares."""
    p = pattern.upper()
    greens = [i for i, c in enumerate(p) if c == "G"]
    h2, w2 = (d.shape[0] // 2) * 2, (d.shape[1] // 2) * 2
    pos = [(i // 2, i % 2) for i in greens]
    g1 = d[pos[0][0]:h2:2, pos[0][1]:w2:2]
    g2 = d[pos[1][0]:h2:2, pos[1][1]:w2:2]
    ok = ~saturated[pos[0][0]:h2:2, pos[0][1]:w2:2] & ~saturated[pos[1][0]:h2:2, pos[1][1]:w2:2]
    cap = _FIT_CEILING * float(np.min(ceiling))
    ok &= (g1 < cap) & (g2 < cap)
    if np.count_nonzero(ok) < 256:
        raise InputError("too few unsaturated green pairs to estimate the noise of a single frame; give gain "
                         "and read noise")
    r = (g1 - g2)[ok].astype(np.float64)
    lvl = np.maximum(0.5 * (g1 + g2)[ok].astype(np.float64), 0.0)
    edges = np.unique(np.quantile(lvl, np.linspace(0.0, 1.0, 41)))
    idx = np.clip(np.searchsorted(edges, lvl, side="right") - 1, 0, len(edges) - 2)
    vs, ls, ns = [], [], []
    for b in range(len(edges) - 1):
        sel = idx == b
        if np.count_nonzero(sel) < 32:
            continue
        vs.append(np.median(r[sel] ** 2) / _CHI2_MEDIAN / 2.0)
        ls.append(np.mean(lvl[sel]))
        ns.append(np.count_nonzero(sel))
    if len(vs) < 2:
        raise InputError("the frame's levels do not constrain the noise model; give gain and read noise")
    v, lv, nn = np.array(vs), np.array(ls), np.array(ns, np.float64)
    g, s2 = 1.0, 1.0
    for _ in range(3):
        w = nn / np.maximum(g * lv + s2, 1e-12) ** 2
        m = np.array([[np.sum(w * lv * lv), np.sum(w * lv)], [np.sum(w * lv), np.sum(w)]])
        g, s2 = np.linalg.solve(m, np.array([np.sum(w * lv * v), np.sum(w * v)]))
        g, s2 = float(max(g, 1e-6)), float(max(s2, 1.0 / 12.0))
    return NoiseModel(g, s2, "green-pairs", int(nn.sum()))


def estimate_noise(d: list[np.ndarray], saturated: list[np.ndarray], ceilings: list[np.ndarray],
                   times: np.ndarray, pattern: str) -> NoiseModel:
    """:func:`estimate_noise_pairs` for two frames or more, :func:`estimate_noise_single` for one."""
    if len(d) >= 2:
        return estimate_noise_pairs(d, saturated, ceilings, times)
    return estimate_noise_single(d[0], saturated[0], ceilings[0], pattern)


#: Condition number above which a per-ISO noise fit is taken as unconstrained (one model then).
_MAX_CONDITION = 1e10


def estimate_noise_frames(mosaics, black: np.ndarray, white: np.ndarray, exposures: np.ndarray,
                          isos: list | None = None) -> NoiseModel:
    """Eq. (2) fitted from the uint16 mosaics (compiled, :mod:`derender.raw.kernels`): the
    samples :func:`estimate_noise_pairs` takes, the same weighted least squares.

    ``mosaics``: a numba typed list of (H, W) uint16, exposure-sorted; ``black`` (N, 2, 2) and
    ``white`` (N,) per frame; ``exposures`` ``t S / N^2`` (relative). When ``isos`` vary, the
    gain and read variance are fitted per ISO (eq. 3), on every pair of frames (not only
    adjacent ones, so that each ISO meets the others):

        Var[r] = X (g_{S_j} / e_j + g_{S_k} / e_k) + s2_{S_j} / e_j^2 + s2_{S_k} / e_k^2     (3)

    (``g_S`` grows with the analogue gain of ISO ``S``, ``s2_S`` is that ISO's read noise); if
    the bracket does not constrain every ISO's pair of values (condition number above
    :data:`_MAX_CONDITION`), one model serves every frame."""
    from derender.raw.kernels import KERNEL_LOCK, grid_samples, wls_normal

    e = np.asarray(exposures, np.float64)
    n = len(e)
    levels = sorted({float(v) for v in isos}) if isos is not None and None not in isos else []
    grouped = len(levels) > 1
    if grouped:
        pairs = np.array([(j, k) for j in range(n) for k in range(j + 1, n)], np.int64)
    else:
        pairs = np.array([(j, j + 1) for j in range(n - 1)], np.int64)
    cap = _MAX_SAMPLES if not grouped else max(1 << 14, (4 * _MAX_SAMPLES) // len(pairs))
    h, w = mosaics[0].shape
    stride = max(1, (h * w) // (2 * cap))
    stride += 1 - stride % 2 if stride > 1 else 0          # odd: the grid meets every CFA phase
    m = (h * w + stride - 1) // stride
    r2g = np.empty((len(pairs), m))
    okg = np.empty((len(pairs), m), bool)
    xg = np.empty(m)
    with KERNEL_LOCK:
        grid_samples(mosaics, pairs, black, white, e, _FIT_CEILING, stride, r2g, xg, okg)
    r2s, xss, sizes = [], [], []
    for p in range(len(pairs)):
        idx = np.flatnonzero(okg[p])
        idx = idx[::max(1, idx.size // cap)]                 # a regular subsample: deterministic, ample
        r2s.append(r2g[p, idx])
        xss.append(xg[idx])
        sizes.append(idx.size)
    total = int(sum(sizes))
    if total < 64:
        raise InputError(f"too few unsaturated photosites shared by adjacent frames ({total}) to estimate the "
                         "noise; give gain and read noise")
    r2, xs = np.concatenate(r2s), np.concatenate(xss)
    pair_of = np.repeat(np.arange(len(pairs)), sizes)

    def fit(groups: np.ndarray, k: int):
        dg = np.zeros((len(pairs), k))
        ds = np.zeros((len(pairs), k))
        for p, (j, kk) in enumerate(pairs):
            for f in (j, kk):
                dg[p, groups[f]] += 1.0 / e[f]
                ds[p, groups[f]] += 1.0 / e[f] ** 2
        params = _robust_start(r2, xs, pair_of, dg, ds)
        if params is None:
            return None
        used = 0
        for _ in range(_CLIP_ROUNDS):
            with KERNEL_LOCK:
                m, v, used = wls_normal(r2, xs, pair_of, dg, ds, params, False, _CLIP_SIGMA ** 2)
            dia = np.sqrt(np.abs(np.diag(m)))
            if not np.all(np.isfinite(m)) or np.any(dia == 0) \
                    or np.linalg.cond(m / np.outer(dia, dia)) > _MAX_CONDITION:   # scale-free condition
                return None
            params = np.linalg.solve(m, v) / _CLIP_MEAN
            params[:k] = np.maximum(params[:k], 1e-6)
            params[k:] = np.maximum(params[k:], 1.0 / 12.0)
        return params, used

    if grouped:
        groups = np.array([levels.index(float(v)) for v in isos], np.int64)
        got = fit(groups, len(levels))
        if got is not None:
            params, used = got
            k = len(levels)
            fg = tuple(float(params[g]) for g in groups)
            fs = tuple(float(params[k + g]) for g in groups)
            return NoiseModel(fg[0], fs[0], "pairs-per-iso", used, fg, fs, tuple(float(v) for v in isos))
    got = fit(np.zeros(n, np.int64), 1)
    if got is None:
        raise InputError("the bracket does not constrain the noise model (give gain and read noise)")
    (g, s2), used = got
    return NoiseModel(float(g), float(s2), "pairs", used)


#: A photosite of a frame pair enters the shifted bracket's fit only where the mean of ``z^2``
#: (``z = r / sqrt(Var[r])``, eq. 2) over its :data:`_CONSISTENT_WINDOW` window stays below
#: this (noise alone: mean 1, standard deviation ``sqrt(2 / 25) = 0.28``).
_CONSISTENT_Z2 = 2.0

#: The window (photosites) of that consistency test.
_CONSISTENT_WINDOW = 5

#: :func:`estimate_noise_shifted` reads a frame pair this many rows at a time.
_STRIP_ROWS = 256

#: On a frame too large to read whole, :func:`estimate_noise_shifted` reads evenly spaced strips
#: of this many rows (every photosite of each), up to its budget of photosites per pair.
_SAMPLE_ROWS = 16


def _exact_pairs(shifts: np.ndarray, tolerance: float) -> list:
    """The frame pairs ``(j, k, o_j, o_k)`` whose relative shift is a whole even translation
    (within ``tolerance``): frame ``j`` read at ``p + o_j``, frame ``k`` at ``p + o_k``, the same
    scene point on the same CFA colour."""
    n = len(shifts)
    out = []
    for j in range(n):
        for k in range(j + 1, n):
            rel = shifts[k] - shifts[j]
            even = 2.0 * np.rint(rel / 2.0)
            if np.all(np.abs(rel - even) <= tolerance):
                oj = 2 * np.rint(shifts[j] / 2.0).astype(np.int64)
                out.append((j, k, oj, oj + even.astype(np.int64)))
    return out


def _strip_starts(hh: int, ww: int, budget: int) -> tuple[list, int]:
    """The first rows of the strips that :func:`estimate_noise_shifted` reads from an ``hh x ww``
    overlap, and the strips' height: the whole overlap in strips of :data:`_STRIP_ROWS` when it
    has at most ``budget`` photosites, else evenly spaced strips of :data:`_SAMPLE_ROWS` rows
    (every photosite of a strip read) up to about ``budget`` photosites."""
    if hh * ww <= budget:
        return list(range(0, hh, _STRIP_ROWS)), _STRIP_ROWS
    rows = _SAMPLE_ROWS
    n = max(1, min(hh // rows, -(-budget // (rows * ww))))
    return sorted({int(v) for v in np.linspace(0, hh - rows, n)}), rows


def estimate_noise_shifted(mosaics, black: np.ndarray, white: np.ndarray, exposures: np.ndarray,
                           shifts: np.ndarray, tolerance: float = 0.1) -> NoiseModel | None:
    """Eq. (2) on a shaken bracket, fitted only on the frame pairs that need no resampling.

    ``mosaics``: (H, W) arrays in exposure order, ``black`` (N, 2, 2), ``white`` (N,),
    ``exposures`` (N,), ``shifts`` (N, 2) photosites (the content of the reference at ``p`` is
    at ``p + shift`` in each frame). A pair whose relative shift is a whole even translation
    compares the same scene point on the same CFA colour, photosite for photosite, with no
    resampling and no residual misregistration -- any two frames, not only neighbours in
    exposure (a pair whose frames are shifted by an odd or fractional amount would compare
    neighbouring photosites, and the scene's gradient between them would enter ``r^2``: the gain
    1.27-2.12x the truth on the simulator's handheld brackets when such pairs, rounded to even
    shifts, were fitted on their smooth photosites). Moving things are left out twice: the
    photosites whose :data:`_CONSISTENT_WINDOW`-square mean of ``z^2`` under the current model
    exceeds :data:`_CONSISTENT_Z2` (frames far apart in time see objects moved far: their
    differences are spatially coherent, where noise is not; Granados et al. 2013's consistency
    test), and the fit's robust start and clipped rounds (:func:`estimate_noise`). ``X`` is the
    pair's own pooled estimate ``(d_j + d_k) / (e_j + e_k)``. A pair is read whole when it has
    at most ``max(2^15, 2^18 / pairs)`` photosites, else in evenly spaced strips of
    :data:`_SAMPLE_ROWS` rows up to that many (the fit's cost then does not grow with the frame:
    0.45-0.51 s at 1536x1024, measured). Returns None when no pair is exact or too few samples
    remain (the caller falls back)."""
    from scipy.ndimage import uniform_filter

    e = np.asarray(exposures, np.float64)
    s = np.asarray(shifts, np.float64)
    h, w = np.shape(mosaics[0])
    pairs = _exact_pairs(s, tolerance)
    if not pairs:
        return None
    budget = max(1 << 15, _MAX_SAMPLES // len(pairs))      # photosites read per pair at most

    def bounds(oj, ok):
        y0, y1 = max(0, -oj[0], -ok[0]), min(h, h - oj[0], h - ok[0])
        x0, x1 = max(0, -oj[1], -ok[1]), min(w, w - oj[1], w - ok[1])
        return y0, y1, x0, x1

    def strip(j, k, oj, ok, box, a, b):
        """``r``, ``X`` and where both frames are usable, on the overlap's rows ``a:b``."""
        y0, _, x0, x1 = box
        yy, xx = np.arange(y0 + a, y0 + b) & 1, np.arange(x0, x1) & 1
        out = []
        for f, o in ((j, oj), (k, ok)):
            y = np.asarray(mosaics[f][y0 + a + o[0]:y0 + b + o[0], x0 + o[1]:x1 + o[1]], np.float64)
            bl = black[f][yy[:, None], xx[None, :]]
            d = y - bl
            out.append((d, (y < white[f]) & (d < _FIT_CEILING * (white[f] - bl))))
        (dj, uj), (dk, uk) = out
        return dk / e[k] - dj / e[j], (dj + dk) / (e[j] + e[k]), uj & uk

    half = _CONSISTENT_WINDOW // 2

    def samples(model):
        r2s, xss, pof, dg, ds = [], [], [], [], []
        for j, k, oj, ok in pairs:
            box = bounds(oj, ok)
            hh, ww = box[1] - box[0], box[3] - box[2]
            if hh < _CONSISTENT_WINDOW or ww < _CONSISTENT_WINDOW:
                continue
            a_, b_ = 1.0 / e[j] + 1.0 / e[k], 1.0 / e[j] ** 2 + 1.0 / e[k] ** 2
            rr, xx = [], []
            starts, rows = _strip_starts(hh, ww, budget)
            for a in starts:
                b = min(hh, a + rows)
                lo, hi = max(0, a - half), min(hh, b + half)   # the window's halo
                r, x, usable = strip(j, k, oj, ok, box, lo, hi)
                if model is not None:
                    z2 = np.where(usable, r * r / (model[0] * np.maximum(x, 0.0) * a_ + model[1] * b_), 0.0)
                    num = uniform_filter(z2, _CONSISTENT_WINDOW, mode="nearest")
                    den = uniform_filter(usable.astype(np.float64), _CONSISTENT_WINDOW, mode="nearest")
                    usable = usable & (num <= _CONSISTENT_Z2 * np.maximum(den, 1e-12))
                inner = (slice(a - lo, b - lo), slice(None))
                keep = usable[inner].ravel()
                rr.append(r[inner].ravel()[keep])
                xx.append(x[inner].ravel()[keep])
            rr_, xx_ = np.concatenate(rr), np.concatenate(xx)
            if rr_.size == 0:
                continue
            r2s.append(rr_ * rr_)
            xss.append(xx_)
            pof.append(np.full(rr_.size, len(dg), np.int64))
            dg.append([a_])
            ds.append([b_])
        if sum(v.size for v in r2s) < 256:
            return None
        return np.concatenate(r2s), np.concatenate(xss), np.concatenate(pof), np.array(dg), np.array(ds)

    model = None
    used = 0
    for _ in range(3):
        got = samples(model)
        if got is None:
            return None
        try:
            g, s2, used = _wls(*got)
        except InputError:
            return None
        model = (g, s2)
    return NoiseModel(model[0], model[1], "exact-pairs", used)
