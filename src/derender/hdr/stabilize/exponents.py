"""Per-image display gammas ``gamma_j`` (paper 1, Sec. 3.1, Algorithm 1 step 3.1; eq. 4, 8).

Undoing image j's gamma, ``L_j = J_j ** gamma_j``, must make every pair of images related
by a 3x3 matrix (eq. 9). Following Vazquez-Corral & Bertalmio's blind gamma estimation
(2015; paper 1's ref. [24]), the ratio ``gamma_k / gamma_j`` of two overlapping images is
the one for which their linearised images are best related by such a matrix: a bounded
1-D search (:mod:`.solvers`) on the symmetric code-domain misfit of :mod:`.pair_fit`, the
worst blocks trimmed between rounds, with a standard error from the cost curvature. The
pairwise log ratios are combined by weighted least squares over the pair graph
(:func:`relative_exponents`). A common factor on all gammas hardly changes pairwise
linearity; :func:`estimate_gammas` sets it from the exposure times (the fitted maps'
luminance gains must grow like ``t_j``) or, without times, by the smallest total misfit.
Each pair's gain is first read at the pair's own mean colour, ``lum(H_jk m_j) / lum(m_j)``;
when every frame's exposure then follows its time within :data:`TIME_FOLLOW` (one rendering,
no hidden gain: issue 36) that level is kept and the matrices' scale is later taken from the
times (:func:`derender.hdr.stabilize.colour_model.anchor_to_times`); otherwise the gain is read on
white, ``lum(H_jk 1)`` (brackets whose frames draw their own gain and white balance).
:mod:`.filmic` uses the relative exponents to tell power-law brackets from filmic ones.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709
from derender.core.errors import InputError
from derender.engine.motion.reference_frame import check_images
from derender.hdr.stabilize.blocks import FIT_FLOOR, FIT_HIGH, FIT_LOW, Blocks, make_blocks
from derender.hdr.stabilize.curves import Curve, as_curve
from derender.hdr.stabilize.pair_fit import effective_codes, fit_pair, pair_cost, pair_costs_power, pair_residuals
from derender.hdr.stabilize.solvers import bounded_minimizer, drive, find_root, minimize_bounded

__all__ = ["NARROW", "XATOL", "TIME_FOLLOW", "relative_exponents", "GammaEstimate", "estimate_gammas", "estimate_gammas_blocks"]


_W = LUMINANCE_WEIGHTS_REC709


def _robust_inliers(r: np.ndarray, floor: float) -> np.ndarray:
    med = float(np.median(r))
    mad = 1.4826 * float(np.median(np.abs(r - med)))
    return r <= max(med + 3.0 * mad, floor)


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
    jj = effective_codes(pj, base)
    return drive(_pair_log_ratio_steps(pj, pk, base, max_log_ratio, rounds, bk),
                 lambda req: pair_cost(pj, pk, base, bk * np.exp(req[0]), req[1], jj))


def _pair_log_ratio_steps(pj: np.ndarray, pk: np.ndarray, base: "float | Curve", max_log_ratio: float,
                          rounds: int, bk: "float | Curve") -> Any:
    """Coroutine of :func:`_pair_log_ratio`: yields cost requests ``(log ratio, sel)`` (the
    cost is :func:`pair_cost` of image k's curve ``bk * exp(log ratio)`` on the blocks
    ``sel``, None for all), receives their values, returns (log factor, se, inlier mask)."""
    def search(lo: float, hi: float, sel: np.ndarray | None) -> Any:
        steps = bounded_minimizer(lo, hi, XATOL)
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
        r = pair_residuals(pj, pk, base, bk * np.exp(x), sel)
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
    :func:`pair_costs_power` call. Same results as one search at a time."""
    steps, jjs, pending, out = [], [], {}, [None] * len(items)
    for i, (pj, pk, bj, bk) in enumerate(items):
        steps.append(_pair_log_ratio_steps(pj, pk, bj, max_lr, rounds, bk))
        jjs.append(effective_codes(pj, bj))
        try:
            pending[i] = next(steps[i])
        except StopIteration as stop:           # pragma: no cover - a search always evaluates
            out[i] = stop.value
    while pending:
        keys = list(pending)
        if batched:
            costs = pair_costs_power([(items[i][0], items[i][1], jjs[i], as_curve(items[i][2]),
                                        as_curve(items[i][3]) * np.exp(pending[i][0]), pending[i][1])
                                       for i in keys])
        else:
            costs = [pair_cost(items[i][0], items[i][1], items[i][2], items[i][3] * np.exp(pending[i][0]),
                               pending[i][1], jjs[i]) for i in keys]
        for i, c in zip(keys, costs):
            try:
                pending[i] = steps[i].send(c)
            except StopIteration as stop:
                out[i] = stop.value
                del pending[i]
    return out


def relative_exponents(blocks: Blocks, bases: list, *, low: float, high: float, floor: float, max_gap: int,
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
    # once (:func:`pair_costs_power`; one pair at a time was Python-overhead bound: the
    # screening of the 24 MP bracket took 0.32 s, now 0.10-0.14 s)
    powers = all(as_curve(b).table is None for b in bases)
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

    Attributes
    ----------
    gammas : numpy.ndarray
        (N,) display gammas (:attr:`exponents` gives ``1 / gammas``).
    method : str
        ``"times"`` (relative gammas blind, absolute level from the exposure times) or
        ``"blind"`` (no times: absolute level from the 3x3 fit alone).
    pairs : list
        dicts ``{j, k, blocks, inliers, log_ratio, se}`` used.
    scale : float
        the common factor kappa applied to the relative gammas.
    unconnected : list
        images without enough overlap with any other (gamma = median of others).
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


def _pair_matrices(blocks: Blocks, pairs: list, gammas: np.ndarray) -> list[np.ndarray]:
    out = []
    for p in pairs:
        j, k = p["j"], p["k"]
        common = p["common"]
        pj, pk = blocks.codes[j][common], blocks.codes[k][common]
        sel = p["sel"]
        jj, jk = effective_codes(pj, gammas[j])[sel], effective_codes(pk, gammas[k])[sel]
        h, _ = fit_pair(jj, jk, gammas[j], gammas[k], ridge=0.0)
        out.append(h)
    return out


def _pair_gains(blocks: Blocks, pairs: list, gammas: np.ndarray, at: str) -> list[float]:
    """Luminance gain of each pair's fitted map ``H_jk`` (:func:`_pair_matrices`): on white,
    ``lum(H_jk 1)`` (``at="white"``, paper 1's level), or at the mean linear colour ``m_j`` of
    the pair's own inlier blocks, ``lum(H_jk m_j) / lum(m_j)`` (``at="data"``: no extrapolation of
    the 3x3 fit beyond the colours the pair sees; pairs that see only the lamps and the window
    read white at 0.951-0.999 of the time ratio's exponent on a pure gamma-2.2 camera, at their
    own colour 0.994-1.006)."""
    out = []
    for p, h in zip(pairs, _pair_matrices(blocks, pairs, gammas)):
        if at == "white":
            out.append(float(_W @ h @ np.ones(3)))
            continue
        j = p["j"]
        jj = effective_codes(blocks.codes[j][p["common"]], gammas[j])[p["sel"]]
        m = as_curve(gammas[j]).lin(jj).mean(axis=0)
        lm = float(_W @ m)
        out.append(float(_W @ h @ m) / lm if lm > 0 else float("nan"))
    return out


def _per_image_log_scales(pairs: list, gains: list[float], n: int) -> np.ndarray:
    """Least-squares per-image log exposure scales ``a`` with ``a_k - a_j = log(g_jk)``, ``g_jk``
    each pair's luminance gain (:func:`_pair_gains`), weights ``sqrt`` of its inlier count."""
    rows, rhs, wts = [], [], []
    for p, g in zip(pairs, gains):
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


#: The exposures follow the times (:func:`estimate_gammas_blocks`) when, at the level set from the pairs'
#: gains at their own colours, every connected frame's log exposure scale lies within ``TIME_FOLLOW``
#: of ``log t_j`` (after one common offset). Measured largest residual: at most 0.017 on the 48
#: pure gamma-2.2 brackets of issue 36's grid (4 cameras, 1 / 1.5 / 2 EV, 2 scenes, 2 whites); 0.18,
#: 0.097 and 0.094 on the ``paper`` family's 9-frame brackets, seeds 0-2, whose frames draw a hidden
#: gain each (``docs/results-luminance.md``). Real cameras' shutter times that miss their nominal
#: values by more than this keep paper 1's level.
TIME_FOLLOW = 0.03


def _level_from_times(blocks: Blocks, pairs: list, rel: np.ndarray, tarr: np.ndarray, connected: np.ndarray,
                      lo_k: float, hi_k: float) -> tuple[float, dict]:
    """The common factor ``kappa`` on the relative gammas ``rel`` for which the per-image log scales
    (:func:`_per_image_log_scales`) grow like ``log t_j`` (slope 1), and what it found.

    The pairs' gains are first read at their own colours (``at="data"``, :func:`_pair_gains`). When
    every frame's log scale then lies within :data:`TIME_FOLLOW` of its log time (the exposures
    follow the times: one rendering, no hidden gain), that level is kept and ``follows_times`` is
    True; otherwise the level is paper 1's, the gains read on white (``at="white"``: frames with
    hidden gains and white balances, where the data-colour level was measured worse, the ``paper``
    family). Returns (kappa, {"level_gain", "follows_times", "time_residuals"})."""
    n = rel.shape[0]
    logt = np.log(tarr)
    lt = logt[connected] - logt[connected].mean()
    denom = float(lt @ lt)
    if denom <= 0:
        return 1.0, {}

    def residuals(kap: float, at: str) -> np.ndarray:
        a_s = _per_image_log_scales(pairs, _pair_gains(blocks, pairs, rel * kap, at), n)
        return a_s[connected] - a_s[connected].mean()

    def solve(at: str) -> float:
        def slope_err(kap: float) -> float:
            return float(residuals(kap, at) @ lt) / denom - 1.0

        f_lo, f_hi = slope_err(lo_k), slope_err(hi_k)
        if f_lo * f_hi < 0:
            return find_root(slope_err, lo_k, hi_k, xtol=1e-5)
        return minimize_bounded(lambda k_: abs(slope_err(k_)), lo_k, hi_k)

    kappa = solve("data")
    res = residuals(kappa, "data") - lt
    follows = bool(np.max(np.abs(res - res.mean())) <= TIME_FOLLOW)
    if not follows:
        kappa = solve("white")
    return kappa, {"level_gain": "data" if follows else "white", "follows_times": follows,
                   "time_residuals": [float(v) for v in res - res.mean()]}


def estimate_gammas(images: Any, *, times: Sequence[float] | None = None, valid: np.ndarray | None = None,
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
       A pair's gain is read at the mean colour of its own blocks; when every frame's log scale
       then lies within :data:`TIME_FOLLOW` of its log time, that level stands
       (``info["follows_times"]``), else the gains are read on white, ``lum(H_jk 1)``, paper 1's
       level (the 3x3 fit extrapolated beyond the pair's colours: on a pure gamma-2.2 camera the
       pairs that see only lamps and a window read 0.951-0.999 of the time ratio's exponent
       there and set every gamma 0.7 % high; on frames with hidden gains the white reading was
       measured better, ``docs/results-luminance.md``).
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
    arr = check_images(images)
    n = arr.shape[0]
    tarr = None if times is None else np.asarray(times, dtype=np.float64).reshape(-1)
    if tarr is not None and tarr.size != n:
        raise InputError(f"{tarr.size} exposure time(s) for {n} image(s)")
    blocks = make_blocks(arr, valid, block, max_blocks, seed, tarr)
    return estimate_gammas_blocks(blocks, tarr, low=low, high=high, floor=floor, max_gap=max_gap,
                                  prior_sd=prior_sd, min_blocks=min_blocks, base=base, bounds=bounds,
                                  info={"block": block, "max_blocks": max_blocks})


def estimate_gammas_blocks(blocks: Blocks, tarr: np.ndarray | None, *, low: float, high: float, floor: float,
                           max_gap: int, prior_sd: float, min_blocks: int, base: float,
                           bounds: tuple[float, float], info: dict) -> GammaEstimate:
    """:func:`estimate_gammas` on blocks already gathered (:func:`make_blocks`); ``tarr`` the
    exposure times or None (blind absolute level), ``info`` merged into the result's."""
    n = blocks.codes.shape[0]
    t0 = time.perf_counter()
    max_lr = float(np.log(bounds[1] / bounds[0]))
    u, pairs, connected = relative_exponents(blocks, [base] * n, low=low, high=high, floor=floor, max_gap=max_gap,
                                             prior_sd=prior_sd, min_blocks=min_blocks, max_lr=max_lr)
    rel = base * np.exp(u)
    lo_k = bounds[0] / rel.min()
    hi_k = bounds[1] / rel.max()
    method = "times" if tarr is not None else "blind"
    kappa = 1.0
    extra: dict = {}
    if pairs and hi_k > lo_k:
        if tarr is not None:
            kappa, extra = _level_from_times(blocks, pairs, rel, tarr, connected, lo_k, hi_k)
        else:
            def total_cost(kap: float) -> float:
                g = rel * kap
                tot = 0.0
                for p in pairs:
                    j, k = p["j"], p["k"]
                    common = p["common"]
                    tot += p["inliers"] * pair_cost(blocks.codes[j][common], blocks.codes[k][common],
                                                    g[j], g[k], p["sel"])
                return tot

            kappa = minimize_bounded(total_cost, lo_k, hi_k, 1e-4)
    gammas = np.clip(rel * kappa, bounds[0], bounds[1])
    public_pairs = [{k_: v for k_, v in p.items() if k_ not in ("sel", "common")} for p in pairs]
    return GammaEstimate(gammas=gammas, method=method, pairs=public_pairs, scale=kappa,
                         unconnected=[int(j) for j in np.flatnonzero(~connected)],
                         info=dict(info, low=low, high=high, floor=floor, seconds=time.perf_counter() - t0,
                                   n_blocks=int(blocks.codes.shape[1]), **extra))
