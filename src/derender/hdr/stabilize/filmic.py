"""Tone curves that are not power laws: the ``response="auto"`` decision and a common Debevec & Malik curve.

Beyond paper 1, whose pipeline model (eq. 4) renders through a power law. Film and filmic
picture styles render through S-shaped curves; per-image gammas (:mod:`.exponents`) then
drift steadily with exposure time, because neighbouring exposures share different parts
of the curve, whose local log-log slope the pairwise search reports (:func:`gamma_trend`).
``response="auto"`` of :func:`derender.hdr.stabilize.method.stabilize` first runs a quick
search and sends clearly filmic brackets to the curve straight away
(:func:`screen_gamma_trend`, :data:`SCREEN_TREND`), otherwise it checks the full estimate
(:func:`power_law_plausible`). A rejected bracket gets one Debevec & Malik (1997) curve
per channel common to all images (:func:`curve_model`), fitted on samples away from
clipped pixels (:func:`unclipped_debevec`), with the per-image 3x3 matrices H_j of eq. 9-10
on top: ``L_j = G(J_j)`` takes the place of ``J_j ** gamma_j``.

Beyond paper 1 and Debevec & Malik (the default):
**exposures re-estimated** (:func:`_debevec_with_exposures`, :data:`CURVE_EXPOSURE_ROUNDS`,
``exposure_rounds=`` of :func:`derender.hdr.stabilize.method.merge_stabilized`; 0 turns it
off). Debevec & Malik fit ``g(Z_pj) = ln E_p + ln t_j`` with the EXIF times; a camera that
changes gain and white balance between frames (the ``auto`` pipelines) exposes frame j's
channel c by ``t_j k_jc`` instead, and the common curve bends to absorb the unknown
``ln k_jc`` (ripples of +-0.1 in ``ln`` with a period of one exposure step, measured
noise-free on the ``camera`` family). Each channel's fit therefore alternates (``R`` rounds)
with per-frame log-exposure offsets ``o_jc``:

    g, ln E = argmin sum_{p,j} [w(Z_pj) (g(Z_pj) - ln E_p - ln t_j - o_jc)]^2 + lambda^2 sum_z [w(z) g''(z)]^2
    o_jc    = sum_p w(Z_pj)^2 (g(Z_pj) - ln E_p - ln t_j) / (sum_p w(Z_pj)^2 + kappa)

then ``o_j`` loses its least-squares polynomial in ``ln t_j`` of degree
:data:`CURVE_OFFSET_DEGREE` (2: a common offset and a common exponent of ``g`` change no
residual and the times fix them; a smooth bend of the exposures in ``ln t`` trades against
the curve's shape: on Debevec's Memorial the free offsets form such a bend, +1.6 .. -1.1 ..
+0.5 across the 16 frames) and is clipped to +-:data:`CURVE_MAX_OFFSET`;
``kappa = CURVE_OFFSET_PRIOR * mean_j sum_p w^2`` (default 0). **Guard**: when an offset
reaches the bound the data do not determine it, and the times are taken as given (plain
Debevec & Malik, ``params["exposure_offsets_rejected"]``). The H_j on top still absorb what
the offsets leave.

Chosen on the tuning families ``paper`` and ``camera`` (``paper`` brackets take the power law
and do not change). Measured with ``benchmarks/families_measure.py --methods stabilized
stabilized-joint`` (outdoor + indoor, seeds 0-1), stabilized PSNR L / median relative error
of 4x4 means, without -> with (R = 3, degree 2, guard); oracle PSNR L in brackets:

    family (split)          without          with (default)    no guard         degree 1 + guard
    paper (tuning)          44.65 / 0.077    44.65 / 0.077     44.65            44.65      (43.81)
    camera (tuning)         42.68 / 0.159    43.54 / 0.144     43.54            43.49      (43.46)
    dslr-lut (held out)     43.53 / 0.158    43.90 / 0.147     44.40            43.95      (43.96)
    phone-local (held out)  43.67 / 0.210    43.91 / 0.214     43.91            43.96      (44.02)
    drift (held out)        43.74 / 0.168    44.11 / 0.157     44.11            44.09      (43.45)

(camera seeds 0-5, degree 1 without guard: 43.50 -> 44.15; degree 2: 44.08.) The guard
changes nothing on the tuning families; it rejects the offsets of ``derender demo``'s
bracket (camera rendering, auto pipeline, seed 0: stabilized L stays 48.84; without it
48.23, degree 1 48.28; at the demo's configuration over seeds 0-4 degree 1 without guard
moved the mean 47.83 -> 47.96, per seed -0.94 .. +1.26), some ``dslr-lut`` brackets whose
white-balance presets switch by more than the bound (44.40 -> 43.90, still at the oracle),
and Memorial (16 film frames; no truth: against ``memorial.hdr`` the brightest 0.1 % stay
at +0.48 in ``ln``, where the offsets moved them to +2.1 with degree 1, -0.8 with degree 2).
On the iPhone 6 bracket (degree 1, no guard) the median angle to the camera's own rendering
dropped 8.9 -> 5.2 degrees (Frobisher 3.8 either way).
**Per-frame exponents** (option ``exponent_rounds=`` of the stabilised merges, off by default,
:data:`CURVE_EXPONENT_ROUNDS`): the ``auto`` pipelines also change the display gamma per frame,
after the tone curve; :mod:`.frame_exponents` searches a relative exponent ``rho_j`` per frame
inside this alternation, the curve then fitted on the warped codes ``J_j ** rho_j`` (measured
table there).
**Code-stratified samples** (:data:`~derender.hdr.stabilize.curve_samples.CURVE_BIN_MIN` of
:mod:`.curve_samples`, off by default): samples added to the code
bins that the grid sees rarely; measured on the iPhone 6 bracket's sky (issue 36 item 6), they
narrow the spread over grid seeds but do not make the sky's colour independent of size and
alignment (docs/uncertainty.md).
Cost: the fit is linear in the log exposures, so one factorisation serves every round
(:func:`_debevec_affine`): measured 0.365 -> 0.405 s for the whole curve fit of 9 frames of
6 MP (the samples are a fixed 1024-point grid, so the cost does not grow with the frame size).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from derender.core.types import Stack
from derender.hdr.stabilize import curve_samples as cs
from derender.hdr.stabilize import frame_exponents as fe
from derender.hdr.stabilize.blocks import FIT_FLOOR, FIT_HIGH, FIT_LOW, Blocks
from derender.hdr.stabilize.curves import Curve
from derender.hdr.stabilize.exponents import relative_exponents

__all__ = ["gamma_trend", "SCREEN_TREND", "screen_gamma_trend", "power_law_plausible", "CURVE_TIE",
           "CURVE_TIE_CODES", "CURVE_SHAPE_TIE",
           "CURVE_EXPOSURE_ROUNDS", "CURVE_OFFSET_PRIOR", "CURVE_OFFSET_DEGREE",
           "CURVE_MAX_OFFSET", "CURVE_EXPONENT_ROUNDS", "unclipped_debevec", "curve_model"]


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
#: brackets (auto and fixed pipelines, simple style, 18 simulated) at most 0.13 in magnitude (0.12);
#: filmic camera style (18) 1.77 to 2.39 (1.35 to 1.76); Memorial 0.93-1.08 (0.76-0.89),
#: Frobisher 0.83 (0.75): the same decisions.
SCREEN_TREND = 0.6


#: Pair blocks and search rounds of the screening (the full search: 800 and 2).
SCREEN_BLOCKS, SCREEN_ROUNDS = 200, 1


def screen_gamma_trend(blocks: Blocks, times: Sequence[float], *, low: float = FIT_LOW, high: float = FIT_HIGH,
                       floor: float = FIT_FLOOR, max_gap: int = 2, prior_sd: float = 0.1, min_blocks: int = 12,
                       base: float = 2.2, bounds: tuple[float, float] = (1.0, 4.0)) -> float:
    """:func:`gamma_trend` of the relative exponents from a quick search (:data:`SCREEN_BLOCKS`
    blocks per pair, :data:`SCREEN_ROUNDS` round; the absolute level does not change a
    trend of log gammas), over the images the pairs connect; 0 with fewer than 3."""
    n = blocks.codes.shape[0]
    u, _, connected = relative_exponents(blocks, [base] * n, low=low, high=high, floor=floor, max_gap=max_gap,
                                         prior_sd=prior_sd, min_blocks=min_blocks,
                                         max_lr=float(np.log(bounds[1] / bounds[0])), max_pair_blocks=SCREEN_BLOCKS,
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



#: Rounds of per-frame exposure re-estimation in :func:`unclipped_debevec` (see
#: :func:`_debevec_with_exposures` and the module docstring; 0: Debevec & Malik with the EXIF
#: times as they are).
CURVE_EXPOSURE_ROUNDS = 3

#: Shrinkage of those offsets towards 0 (the EXIF times): a prior whose weight is this
#: fraction of a frame's mean total data weight.
CURVE_OFFSET_PRIOR = 0.0

#: Degree of the polynomial in ``ln t_j`` removed from the offsets (1: their mean and trend;
#: 2 also a smooth bend, which trades against the curve's shape; module docstring).
CURVE_OFFSET_DEGREE = 2

#: Largest per-frame, per-channel log-exposure offset :func:`_debevec_with_exposures` accepts;
#: :func:`unclipped_debevec` drops the offsets of a bracket where one reaches it (the guard).
CURVE_MAX_OFFSET = 0.5

#: Rounds of per-frame relative exponents ``rho_j`` searched with the curve in
#: :func:`unclipped_debevec` (:mod:`.frame_exponents`; 0: ``rho_j = 1``, one table for every frame).
CURVE_EXPONENT_ROUNDS = 0


def _debevec_affine(codes: np.ndarray, lam: float) -> tuple:
    """Debevec & Malik's system for one channel (:func:`~derender.response.solve_debevec`, hat
    weights, 256 levels, ``g(128) = 0``) solved for every log exposure vector at once: its
    solution is linear in the log exposures ``b`` (N,), ``g = G @ b``, and
    ``ln E_p = sum_j w_jp^2 (g(Z_jp) - b_j) / sum_j w_jp^2``. Returns ``(G (256, N), w2 (N, P),
    dinv (P,))``: one factorisation, however many times the exposures are re-estimated."""
    from derender.response.debevec1997 import debevec_system, solve_dense

    z = np.asarray(codes, dtype=np.int64)
    schur, m, w2, dinv = debevec_system(z, lam, "hat", 256)
    b_g = np.stack([np.bincount(z[j], weights=w2[j], minlength=256) for j in range(z.shape[0])], axis=1)  # (256, N)
    gm = solve_dense(schur, b_g + (m * dinv) @ w2.T)                # b_e = -w2.T b
    return gm, w2, dinv


def _debevec_with_exposures(codes: np.ndarray, log_t: np.ndarray, lam: float, rounds: int) -> tuple:
    """Debevec & Malik's ``g`` of one channel (``codes`` (N, P), hat weights, ``lam``) with the
    log exposures re-estimated ``rounds`` times as ``ln t_j + o_j`` (module docstring):
    ``o_j`` the weighted mean of ``g(Z_pj) - ln E_p - ln t_j`` over the samples (shrunk by
    :data:`CURVE_OFFSET_PRIOR`), its polynomial of degree :data:`CURVE_OFFSET_DEGREE` in
    ``ln t_j`` removed (the scale and the exponent of ``g``, which the times fix), clipped to
    +-:data:`CURVE_MAX_OFFSET`. Returns ``(g (256,), o (N,))``; ``rounds=0`` is plain
    Debevec & Malik (``o = 0``, :func:`~derender.response.solve_debevec`). The rounds reuse one
    solve of the system (:func:`_debevec_affine`)."""
    from derender.response.debevec1997 import solve_debevec

    off = np.zeros(log_t.size)
    if int(rounds) <= 0:
        g, _ = solve_debevec(codes, log_t, lam=lam, weights="hat", n_levels=256)
        return g, off
    z = np.asarray(codes, dtype=np.int64)
    tc = log_t - log_t.mean()
    # the offsets keep no component along 1, ln t (and (ln t)^2 with CURVE_OFFSET_DEGREE 2)
    span = np.stack([tc ** k for k in range(min(CURVE_OFFSET_DEGREE, log_t.size - 1) + 1)], axis=1)
    proj = span @ np.linalg.pinv(span)
    gm, w2, dinv = _debevec_affine(z, lam)
    ws = w2.sum(axis=1)
    kappa = CURVE_OFFSET_PRIOR * float(ws.mean())
    for _ in range(int(rounds)):
        b = log_t + off
        g = gm @ b
        gz = g[z]
        ln_e = (w2 * (gz - b[:, None])).sum(axis=0) * dinv
        res = gz - ln_e[None, :] - log_t[:, None]
        # minimiser of sum_p w^2 (res_p - o)^2 + kappa o^2
        new = (w2 * res).sum(axis=1) / np.maximum(ws + kappa, 1e-12)
        off = np.clip(new - proj @ new, -CURVE_MAX_OFFSET, CURVE_MAX_OFFSET)
    return gm @ (log_t + off), off


#: Codes ``(lo, hi)`` on which the channel tie (:data:`CURVE_TIE`) acts (None: every code): the
#: first differences ``(g_c - g_c')(z + 1) - (g_c - g_c')(z)`` for ``lo <= z < hi`` only, the
#: shoulders left free. Measured with the tie on (``docs/paper1.md``, neutral axis): 300 on codes
#: 0-160 keeps within 0.2 dB of the untied fit on ``camera`` and the demo's bracket but buys little
#: grey, so the tie stays off.
CURVE_TIE_CODES: tuple[int, int] | None = None


#: Weight ``kappa`` of the curve model's shape tie (:func:`_shape_penalty`, :func:`_solve_to_green`): green's
#: curve is the one its own samples give, and red's and blue's differences from it ``g_c - g_G`` get
#: ``kappa^2`` times the smoothness term each curve gets, on their second derivative in ``ln z`` (so a
#: constant, the white balance, and a multiple of ``ln z``, a different exponent per channel, cost
#: nothing). 0 (the default): independent channel curves, each anchored at ``g(128) = 0``. Why (issue 36
#: item 5): samples that do not follow the exposure (a thing that moves, residual misregistration of a
#: handheld bracket), and codes where a channel has no data (there its curve is the smoothness term's
#: extrapolation), bend each independent curve in its own way (a synthetic bracket with one tone curve for
#: every channel, ``tests/hdr/test_curve_shape_tie.py``: swing of ``ln R/G`` over the codes with data
#: 0.04-0.20 still, 0.20-0.26 with an unmasked moving patch). So on pingpong (3 frames, 2 stops, a person
#: moving) equal codes give R/G 0.90-1.20 across the codes (``--deghost``). Why green is held: a tie between
#: all three channels (the first form, measured in the previous session) moves green too, i.e. the
#: luminance (Rec. 709 weight 0.72), and cost the tuning family ``camera`` 43.53 -> 43.39 dB L (outdoor
#: -0.9 .. -1.3 dB); weighting that symmetric tie to give way where the data are many did not help (trials,
#: not kept, camera outdoor seeds 0 / 1, untied 44.00 / 43.28: weight ``1 / (1 + (q / 0.3)^2)``, ``q`` the
#: sparser channel's relative data density at the code, 42.74 / 42.31; only where samples are neutral
#: 42.69 / 42.36). Held to green (``benchmarks/families_measure.py --methods stabilized stabilized-joint``,
#: outdoor + indoor x seeds 0-1, PSNR L / median relative error of 4x4 means, stabilized; kappa 0 / 1):
#: tuning ``paper`` 44.64 / 0.077 unchanged (power law), ``camera`` 43.53 / 0.144 -> 43.47 / 0.144 (kappa
#: 0.3: 43.50; per bracket +0.33 .. -0.29), stabilized-joint 42.73 -> 42.68; held out ``dslr-lut`` 43.95 /
#: 0.141 -> 43.22 / 0.118 (kappa 0.3: 43.26 / 0.119; kappa 0.03 on outdoor seed 0 already 42.13 -> 41.83:
#: the LUTs' per-channel shapes are real, and weighting by data density does not keep them),
#: ``phone-local`` 43.85 / 0.214 -> 43.64 / 0.213, ``drift`` 44.08 -> 44.09. Pingpong (stabilized
#: ``--deghost``, ``reference_fidelity``) ``neutral_strict_p95`` 0.113 -> 0.039 (kappa 0.3: 0.038; debevec
#: 0.028). It recolours still real brackets, though (``derender merge ... --method stabilized`` against
#: ``-O shape_tie=1``, block chroma change median / p95, ``evaluation.consistency.compare_maps``; the
#: previews looked at full size): Memorial (``--reference 8``, film) 1.13 / 1.30, orange all over (the
#: symmetric form: p95 1.36, as orange); Frobisher 0.038 / 0.31, the window's blue sky turns yellow-white;
#: the sculpture garden 0.032 / 0.15; the iPhone (``--reference 3``) 0.092 / 0.34, the pink buildings
#: neutral; pingpong 0.047 / 0.13, the hill and the wall nearer grey. Film's dye layers, and the sky's
#: highlights, have channel curves whose shapes do differ, and the tie takes that away. So it is an
#: option, not the default: it meets the neutral line on pingpong at the price of the held-out
#: ``dslr-lut`` family's luminance (-0.7 dB) and of Memorial's and Frobisher's colours. On the iPhone sky
#: (issue 36 item 6) it does not settle the sky's colour (docs/uncertainty.md).
CURVE_SHAPE_TIE = 0.0


def _shape_penalty(n: int, lam: float, kappa: float) -> np.ndarray:
    """(n, n) ``P = sum_z (kappa lam w(z))^2 r_z r_z'`` with ``r_z . f`` the second derivative of ``f``
    in ``u = ln z`` at code ``z`` divided by ``z^2`` (three-point, non-uniform spacing: to leading
    order ``f(z+1) - 2 f(z) + f(z-1) + (f(z+1) - f(z-1)) / (2 z)``), ``w`` the hat weight, codes
    2 .. n-2. Applied to the difference between a channel's curve and green's
    (:func:`_solve_to_green`), it lets it be a constant plus a multiple of ``ln z`` and penalises any
    other shape as strongly as ``kappa^2`` times the curves' own smoothness
    (:func:`~derender.response.debevec1997.debevec_system`)."""
    z = np.arange(2, n - 1, dtype=np.float64)
    u = np.log(np.arange(1, n, dtype=np.float64))           # u[k] = ln(k + 1)
    um, u0, up = u[z.astype(int) - 2], u[z.astype(int) - 1], u[z.astype(int)]
    h1, h2 = u0 - um, up - u0
    rows = np.zeros((z.size, n))
    k = z.astype(int)
    scale = 2.0 / (h1 + h2) / z ** 2
    rows[np.arange(z.size), k - 1] = scale / h1
    rows[np.arange(z.size), k] = -scale * (1.0 / h1 + 1.0 / h2)
    rows[np.arange(z.size), k + 1] = scale / h2
    w = np.minimum(z, n - 1 - z) * float(kappa) * float(lam)
    rw = rows * w[:, None]
    return rw.T @ rw


def _solve_to_green(blocks: list, rhs: list, pen: np.ndarray) -> np.ndarray:
    """The three curves (768, k) with green's as Debevec & Malik fit it alone (``A_G g_G = r_G``) and
    red's and blue's tied to its shape: ``(A_c + pen) g_c = r_c + pen g_G``, the minimiser of channel
    c's own system plus ``(g_c - g_G)' pen (g_c - g_G)`` with ``g_G`` held (:data:`CURVE_SHAPE_TIE`)."""
    from scipy.linalg import solve

    gg = solve(np.asarray(blocks[1], dtype=np.float64), np.asarray(rhs[1], dtype=np.float64), assume_a="sym")
    out = []
    for c in range(3):
        if c == 1:
            out.append(gg)
        else:
            a = np.asarray(blocks[c], dtype=np.float64) + pen
            out.append(solve(a, np.asarray(rhs[c], dtype=np.float64) + pen @ gg, assume_a="sym"))
    return np.concatenate(out, axis=0)


def _solve_tied_codes(blocks: list, rhs: list, tie: float, codes: tuple[int, int]) -> np.ndarray:
    """The tied system of :func:`derender.response.curves.solve_tied` with the tie acting on the
    first differences between codes ``codes[0]`` and ``codes[1]`` only: the (768, 768) matrix
    ``blockdiag(A_c) + tie (3 I - J) kron (D' W D)`` solved directly. Returns (768, k)."""
    from scipy.linalg import solve

    n = blocks[0].shape[0]
    d = np.diff(np.eye(n), axis=0)
    w = np.zeros(n - 1)
    w[max(int(codes[0]), 0):min(int(codes[1]), n - 1)] = 1.0
    lap = d.T @ (w[:, None] * d) * float(tie)
    k3 = 3.0 * np.eye(3) - np.ones((3, 3))
    big = np.kron(k3, lap)
    for c in range(3):
        big[c * n:(c + 1) * n, c * n:(c + 1) * n] += np.asarray(blocks[c], dtype=np.float64)
    return solve(big, np.concatenate([np.asarray(r, dtype=np.float64) for r in rhs], axis=0), assume_a="sym")


def _debevec_tied_with_exposures(codes: np.ndarray, log_t: np.ndarray, lam: float, rounds: int,
                                 tie: float, shape_tie: float = 0.0) -> tuple:
    """:func:`_debevec_with_exposures` for the three channels at once, their curves tied
    (:func:`derender.response.curves.solve_tied`, weight ``tie``): ``codes`` (N, P, 3).
    The tied system is still linear in the per-channel log exposures, so one solve serves
    every round. Returns ``(g (256, 3), o (N, 3))``."""
    from derender.response.curves import solve_tied
    from derender.response.debevec1997 import debevec_system

    z = np.asarray(codes, dtype=np.int64)
    n = z.shape[0]
    blocks, rhs, w2s, dinvs = [], [], [], []
    for c in range(3):
        schur, m, w2, dinv = debevec_system(z[:, :, c], lam, "hat", 256)
        b_g = np.stack([np.bincount(z[j, :, c], weights=w2[j], minlength=256) for j in range(n)], axis=1)
        basis = np.zeros((256, 3 * n))       # channel c's right-hand side for every log exposure
        basis[:, c * n:(c + 1) * n] = b_g + (m * dinv) @ w2.T
        blocks.append(schur)
        rhs.append(basis)
        w2s.append(w2)
        dinvs.append(dinv)
    # (768, 3N): the three curves stacked by channel = gm @ (b_R, b_G, b_B)
    if shape_tie > 0:
        gm = _solve_to_green(blocks, rhs, _shape_penalty(256, lam, shape_tie))
    elif CURVE_TIE_CODES is None:
        gm = solve_tied(blocks, rhs, tie).transpose(1, 0, 2).reshape(768, 3 * n)
    else:
        gm = _solve_tied_codes(blocks, rhs, tie, CURVE_TIE_CODES)
    off = np.zeros((n, 3))
    tc = log_t - log_t.mean()
    span = np.stack([tc ** k for k in range(min(CURVE_OFFSET_DEGREE, log_t.size - 1) + 1)], axis=1)
    proj = span @ np.linalg.pinv(span)
    for _ in range(max(int(rounds), 0)):
        g = (gm @ (log_t[:, None] + off).T.ravel()).reshape(3, 256).T
        new = np.empty_like(off)
        for c in range(3):
            w2, dinv = w2s[c], dinvs[c]
            b = log_t + off[:, c]
            gz = g[z[:, :, c], c]
            ln_e = (w2 * (gz - b[:, None])).sum(axis=0) * dinv
            res = gz - ln_e[None, :] - log_t[:, None]
            ws = w2.sum(axis=1)
            kappa = CURVE_OFFSET_PRIOR * float(ws.mean())
            new[:, c] = (w2 * res).sum(axis=1) / np.maximum(ws + kappa, 1e-12)
        off = np.clip(new - proj @ new, -CURVE_MAX_OFFSET, CURVE_MAX_OFFSET)
    g = (gm @ (log_t[:, None] + off).T.ravel()).reshape(3, 256).T
    return g, off


#: Weight of the channel tie in the curve model's Debevec fit (:func:`unclipped_debevec`); the
#: classic merges tie their channels (:data:`derender.response.curves.DEFAULT_TIE`),
#: the curve model does not (0: independent channel curves, each anchored at ``g(128) = 0``).
#: Measured with a tie of 1000 (``derender experiment families``, outdoor + indoor x seeds 0-1;
#: PSNR L, stabilized / stabilized-joint): ``camera`` 43.54 / 42.79 -> 43.39 / 42.66 (tuning),
#: held out ``dslr-lut`` 43.90 / 43.33 -> 43.30 / 43.10, ``phone-local`` 43.91 / 43.30 -> 44.08 /
#: 43.56, ``drift`` 44.11 / 43.28 -> 44.23 / 43.15; on the demo's bracket (``camera`` style, auto
#: pipeline, 480x320, seed 0, codes) 49.23 / 47.09 -> 47.54 / 45.90 dB; every tie tried (30 to
#: 1e5) lowered ``camera``. What the tie would buy is neutral greys in the rendering: truly grey
#: pixels of ``camera`` 0.22 -> 0.10 largest deviation per decade, the iPhone's mid-frame greys
#: 0.21-0.29 -> 0.10-0.15. Against the exact radiance the tie loses on the tuning family, so it is
#: off (an option of :func:`unclipped_debevec`). The greys' constant cast is removed instead by
#: :mod:`derender.hdr.stabilize.grey_balance` (one gain per output channel; iPhone mid-frame greys
#: 0.21-0.29 -> 0.06-0.12); what varies with brightness stays (``docs/paper1.md``, neutral axis).
#: Remeasured with the grey balance: ``camera`` 43.49 -> 43.56 (per
#: bracket -1.25 .. +1.15), the demo's bracket 49.24 -> 47.54. The cost is not a channel-different
#: rendering: with one rendering for every frame the tie costs nothing on the demo's scene (49.00 /
#: 49.02); it comes from the per-frame tone changes (gamma times gain), which one common curve cannot
#: represent and each untied channel absorbs in its own way (``docs/paper1.md``).
CURVE_TIE = 0.0


def _misfit(codes: np.ndarray, log_t: np.ndarray, g: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(3,) weighted RMS of Debevec & Malik's data term per channel,
    ``sum_{p,j} w^2 (g(Z_pj) - ln E_p - ln t_j - o_jc)^2 / sum w^2`` (hat weights, ``ln E_p`` its
    weighted least-squares value), of curves ``g`` (256, 3) and offsets (N, 3) on ``codes`` (N, P, 3)."""
    z = np.asarray(codes, dtype=np.int64)
    w = np.minimum(z, 255 - z).astype(np.float64) + 0.0
    w2 = w ** 2
    out = np.empty(3)
    for c in range(3):
        b = log_t[:, None] + offsets[:, c][:, None]                     # (N, 1)
        gz = g[z[:, :, c], c]
        den = np.maximum(w2[:, :, c].sum(axis=0), 1e-12)
        ln_e = (w2[:, :, c] * (gz - b)).sum(axis=0) / den
        r = gz - ln_e[None, :] - b
        out[c] = np.sqrt((w2[:, :, c] * r ** 2).sum() / max(w2[:, :, c].sum(), 1e-12))
    return out


def unclipped_debevec(codes_at: Any, n: int, shape: tuple[int, int], times: np.ndarray, *, seed: int = 0,
                      high: float = cs.CURVE_CLIP, radius: int = cs.CURVE_CLIP_RADIUS,
                      exposure_rounds: int | None = None, tie: float | None = None, valid_at: Any = None,
                      exponent_rounds: int | None = None, exponents: Any = None,
                      shape_tie: float | None = None) -> Any:
    """Debevec & Malik (1997) curves (:func:`derender.response.solve_debevec`, hat weights,
    :data:`~derender.hdr.stabilize.curve_samples.CURVE_SAMPLES` grid samples, made non-decreasing) that leave out every sample whose
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

    ``shape_tie`` (default :data:`CURVE_SHAPE_TIE`): weight of the tie of red's and blue's shapes to green's
    (:func:`_shape_penalty`; ``params["shape_tie"]``).

    ``exposure_rounds`` (default :data:`CURVE_EXPOSURE_ROUNDS`): per-frame, per-channel
    log-exposure offsets re-estimated with the curve (:func:`_debevec_with_exposures`; in
    ``params["exposure_offsets"]``, (N, 3)); 0 is Debevec & Malik with the times as given.

    ``exponent_rounds`` (default :data:`CURVE_EXPONENT_ROUNDS`): per-frame relative exponents
    ``rho_j`` (the camera's per-frame display gamma) searched with the curve
    (:mod:`.frame_exponents`), the curve then fitted on the warped codes ``255 (Z / 255) ** rho_j``
    (``params["rho"]``; read them as ``Curve(rho_j, log_table=..., toe=params["toe"])``). ``exponents`` (N,): fixed
    ``rho_j`` instead (e.g. the simulator's true ``gamma_j / gamma_0``, an oracle).

    ``codes_at(j, ys, xs)``: (P, 3) integer codes of aligned image j at those pixels;
    ``valid_at(j, ys, xs)`` (optional): (P,) bool, False where image j does not take part
    (the engine's alignment borders and ghosts): that sample counts in no channel.
    Returns :class:`derender.response.ResponseCurves`, or None when some channel keeps no
    usable sample (then use :func:`derender.response.calibrate_debevec`).
    """
    from derender.response.curves import DEFAULT_LAMBDA, ResponseCurves, make_monotonic

    codes, clipped = cs.unclipped_samples(codes_at, n, shape, seed=seed, high=high, radius=radius, valid_at=valid_at)
    if not np.all(((codes > 0) & (codes < 255)).any(axis=(0, 1))):
        return None
    log_t = np.log(np.asarray(times, dtype=np.float64))
    # Debevec's lambda is set for 256 samples: scale it so that smoothness keeps its weight
    # against a data term that grows with the number of samples
    lam = DEFAULT_LAMBDA * float(np.sqrt(codes.shape[1] / 256.0))
    rounds = CURVE_EXPOSURE_ROUNDS if exposure_rounds is None else int(exposure_rounds)
    e_rounds = CURVE_EXPONENT_ROUNDS if exponent_rounds is None else int(exponent_rounds)
    tie = CURVE_TIE if tie is None else float(tie)
    shape = CURVE_SHAPE_TIE if shape_tie is None else float(shape_tie)
    curve = _CurveFit(codes, log_t, lam, tie, shape)
    rho = np.ones(n)
    curve.fit(rounds, rho)
    misfit_plain = curve.misfit().tolist()
    exp_rejected = False
    history: list = []
    if exponents is not None:
        rho = np.asarray(exponents, dtype=np.float64).reshape(n)
        curve.fit(rounds, rho)
    else:
        rho, exp_rejected = _fit_exponents(curve, rounds, e_rounds, history)
        misfit_fit = float(np.mean(curve.misfit()))
        if e_rounds > 0 and not exp_rejected and misfit_fit >= fe.EXPONENT_MISFIT_RATIO * float(np.mean(misfit_plain)):
            # the exponents do not lower Debevec's misfit: the alternation wandered off (the
            # frames change what neither the offsets nor the exponents model); keep rho = 1
            exp_rejected, rho = True, np.ones(n)
            curve.fit(rounds, rho)
    offsets = curve.offsets
    rejected = bool(rounds > 0 and np.max(np.abs(offsets)) >= CURVE_MAX_OFFSET * (1 - 1e-9))
    if rejected:
        # an offset at the bound is no gain or white-balance step of a camera: the data do not
        # determine it (Memorial's film frames), so the times are taken as given
        rho = np.ones(n)
        curve.fit(0, rho)
    params = {"lambda": lam, "n_samples": cs.CURVE_SAMPLES, "n_used": int(codes.shape[1]), "bin_min": cs.CURVE_BIN_MIN, "sampling": "grid", "seed": int(seed),
              "weights": "hat", "clip": float(high), "clip_radius": int(radius),
              "dropped": float(clipped.mean()), "exposure_rounds": rounds,
              "exposure_offsets": offsets.tolist(), "exposure_offsets_rejected": rejected, "tie": tie, "shape_tie": shape,
              "exponent_rounds": e_rounds, "rho": rho.tolist(), "rho_rejected": exp_rejected,
              "toe": fe.EXPONENT_TOE,
              "rho_history": history, "misfit_plain": misfit_plain, "misfit": curve.misfit().tolist()}
    return ResponseCurves(log_inverse=make_monotonic(curve.g), method="debevec-unclipped", params=params)



class _CurveFit:
    """Debevec's curves ``g`` (256, 3) and per-frame exposure offsets (N, 3) of fixed samples, refitted
    in place for given exponents ``rho`` (the codes warped to ``255 (Z / 255) ** rho_j``)."""

    def __init__(self, codes: np.ndarray, log_t: np.ndarray, lam: float, tie: float, shape_tie: float = 0.0):
        self.codes, self.log_t, self.lam, self.tie, self.shape_tie = codes, log_t, lam, tie, shape_tie
        self.g = np.empty((256, 3))
        self.offsets = np.zeros((codes.shape[0], 3))
        self.fitted = codes          # the (warped) codes of the last fit

    def fit(self, rounds: int, rho: np.ndarray) -> None:
        """Refit with ``rounds`` rounds of offsets on the codes warped by ``rho``."""
        codes = self.codes
        zc = codes if np.all(rho == 1.0) else np.where(
            codes > 0, np.clip(np.rint(fe.warp_codes(codes, rho)), 0, 255), 0).astype(np.int32)
        self.fitted = zc
        if self.tie > 0 or self.shape_tie > 0:
            self.g[:], self.offsets[:] = _debevec_tied_with_exposures(zc, self.log_t, self.lam, rounds, self.tie,
                                                                      self.shape_tie)
            return
        for c in range(3):
            self.g[:, c], self.offsets[:, c] = _debevec_with_exposures(zc[:, :, c], self.log_t, self.lam, rounds)

    def misfit(self) -> np.ndarray:
        """The last fit's misfit (:func:`_misfit`)."""
        return _misfit(self.fitted, self.log_t, self.g, self.offsets)


def _fit_exponents(curve: _CurveFit, rounds: int, e_rounds: int, history: list) -> tuple[np.ndarray, bool]:
    """Search the per-frame exponents with the curve (:mod:`.frame_exponents`: ``e_rounds`` alternations,
    then the profile refinement), the curve left fitted for them; ``(rho, rejected)`` (rho = 1 when
    an exponent reaches the bound). Each round's exponents are appended to ``history``."""
    codes, log_t, g, offsets = curve.codes, curve.log_t, curve.g, curve.offsets
    n = codes.shape[0]
    rho = np.ones(n)
    exp_rejected = False
    # EXPONENT_TIMES_GIVEN: the search alternates with the fit of the times as given
    # (no offsets to take up part of each exponent); the offsets come with the last fit
    search_rounds = 0 if (fe.EXPONENT_TIMES_GIVEN and e_rounds > 0) else rounds
    if search_rounds != rounds:
        curve.fit(search_rounds, rho)
    for _ in range(max(e_rounds, 0)):
        new, _gain = fe.search_exponents(codes, log_t, g, offsets, rho, free_offsets=search_rounds > 0)
        new = fe.gauge_exponents(new, log_t)
        history.append(new.tolist())
        if np.max(np.abs(np.log(new))) >= fe.EXPONENT_MAX:
            # an exponent at the bound: the data do not determine it; keep rho = 1
            exp_rejected, rho = True, np.ones(n)
            break
        rho = new
        curve.fit(search_rounds, rho)
    if search_rounds != rounds or exp_rejected:
        curve.fit(rounds, rho)
    if fe.EXPONENT_REFINE > 0 and e_rounds > 0:
        def cost_of(rh: np.ndarray) -> float:
            curve.fit(rounds, rh)
            return fe.profile_cost(codes, log_t, g, offsets, rh)
        start = rho if not exp_rejected else np.ones(n)
        c1 = cost_of(np.ones(n))
        cs = cost_of(start)
        if c1 < cs:
            start = np.ones(n)
        rho, _c0, c_end = fe.refine_exponents(cost_of, start, log_t, sweeps=fe.EXPONENT_REFINE)
        exp_rejected = bool(np.max(np.abs(np.log(rho))) >= fe.EXPONENT_MAX)
        if exp_rejected:
            rho = np.ones(n)
        history.append(rho.tolist())
        curve.fit(rounds, rho)
    return rho, exp_rejected


def curve_model(blocks: Blocks, images: np.ndarray, times: np.ndarray, low: float, high: float, floor: float,
                 *, max_gap: int = 2, prior_sd: float = 0.1, min_blocks: int = 12, rounds: int = 0,
                 seed: int = 0, calibrate: Any = None, exposure_rounds: int | None = None,
                 exponent_rounds: int | None = None, shape_tie: float | None = None) -> tuple[list, dict]:
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
    samples its frames). ``exposure_rounds``: per-frame exposure offsets re-estimated with
    ``G`` (:func:`unclipped_debevec`; default :data:`CURVE_EXPOSURE_ROUNDS`). ``exponent_rounds``:
    the ``rho_j`` searched inside that fit instead (:mod:`.frame_exponents`; default
    :data:`CURVE_EXPONENT_ROUNDS`), used when ``rounds=0``. ``shape_tie``: the tie on the
    channels' shapes (:func:`unclipped_debevec`; default :data:`CURVE_SHAPE_TIE`).
    """
    from derender.response.curves import to_codes
    from derender.response.debevec1997 import calibrate_debevec

    n = images.shape[0]
    rho = np.ones(n)
    pairs: list = []
    fitted: dict = {}

    def table_for(r: np.ndarray) -> np.ndarray:
        if calibrate is not None and np.all(r == 1.0):
            cur = calibrate()
            fitted["rho"] = cur.params.get("rho")
            fitted["toe"] = cur.params.get("toe")
            fitted["misfit"] = (cur.params.get("misfit_plain"), cur.params.get("misfit"))
            return cur.log_inverse
        if np.all(r == 1.0):
            cur = unclipped_debevec(lambda j, ys, xs: to_codes(np.asarray(images[j])[ys, xs], 256), n,
                                    images.shape[1:3], times, seed=seed, exposure_rounds=exposure_rounds,
                                    exponent_rounds=exponent_rounds, shape_tie=shape_tie)
            if cur is not None:
                fitted["rho"] = cur.params.get("rho")
                fitted["toe"] = cur.params.get("toe")
                fitted["misfit"] = (cur.params.get("misfit_plain"), cur.params.get("misfit"))
                return cur.log_inverse
        fitted["rho"] = None
        if np.all(r == 1.0) and images.min() >= 0.0 and images.max() <= 1.0:
            warped = images                 # no exponent warp: no full-size copy of the stack
        else:
            warped = np.clip(images, 0.0, 1.0) ** r[:, None, None, None].astype(np.float32)
        return calibrate_debevec(Stack(images=warped, times=times), seed=seed, tie=CURVE_TIE).log_inverse

    table = table_for(rho)
    if int(rounds) <= 0 and fitted.get("rho") is not None:
        rho = np.asarray(fitted["rho"], dtype=np.float64)     # searched with the curve (exponent_rounds)
    for _ in range(int(rounds)):
        bases = [Curve(rho[j], log_table=table) for j in range(n)]
        u, pairs, _ = relative_exponents(blocks, bases, low=low, high=high, floor=floor, max_gap=max_gap,
                                         prior_sd=prior_sd, min_blocks=min_blocks, max_lr=float(np.log(2.0)))
        rho = rho * np.exp(u)
        rho = rho / np.exp(np.mean(np.log(rho)))
        table = table_for(rho)
    # exponents searched inside unclipped_debevec: its table is on codes warped with the toe
    toe = float(fitted.get("toe") or 0.0) if int(rounds) <= 0 else 0.0
    curves = [Curve(rho[j], log_table=table, toe=toe) for j in range(n)]
    info = {"rho": rho.tolist(), "misfit": fitted.get("misfit"), "pairs": [{k: v for k, v in p.items() if k not in ("sel", "common")} for p in pairs]}
    return curves, info
