"""Response recovery of Robertson, Borman & Stevenson (2003), "Estimation-theoretic approach to dynamic range enhancement using multiple exposures", made robust.

Robertson et al. alternate the ML radiance ``E_i = sum_j w_ij t_j I(Z_ij) / sum_j w_ij
t_j^2`` and the response ``I(m) = mean of t_j E_i over the observations with code m``.
Taken literally (as OpenCV's ``CalibrateRobertson`` does) this is ill-posed on 8-bit
camera JPEGs: nothing ties neighbouring codes together, so the curve comes out as a
staircase (isotonic repairs of a noisy ``I(m)``: 100+ flat steps on simulator brackets,
visible contour rings on a 3-frame bracket), and the ``t_j^2`` weights let the longest
frame's near-clipped codes decide every pixel (-12 to -15 dB PSNR L against Debevec on
simulator brackets). What is computed here:

1. **Leave-one-out radiance.** Observation ``(i, j)`` is compared with ``E_i`` estimated
   from the *other* frames; with its own frame included, a code whose weight dominates
   confirms whatever ``I(m)`` it had (a self-consistent flat step).
2. **Update in the log domain.** ``g(m) = ln I(m)`` is the mean of ``ln(t_j E_i)`` over the
   observations of code ``m`` (a geometric mean: ``E_i`` from a frame stops away has
   multiplicative errors, whose arithmetic mean is biased upwards).
3. **Monotone and smooth.** Each iteration projects ``g`` onto the curves rising by at
   least :data:`MIN_STEP` per code (weighted pool-adjacent-violators), then applies a
   Whittaker smoother (``lambda`` :data:`ROBERTSON_LAMBDA` on the second difference), which
   also fills codes that no pixel hits and extends the curve past the clipped ends; then the
   projection again: ``g`` is strictly increasing, without flat steps. Each code's update is
   weighted by its inverse variance, ``n(z) / var(z)`` (the number of its observations over
   the spread of their log updates, kept within :data:`VARIANCE_FLOOR` and
   :data:`VARIANCE_CAP` times the median spread: :func:`_update_variance`), not by the base
   weight times ``n(z)``, which left the top and bottom quarters of the curve to the
   smoother's extrapolation (the Gaussian base weight is 0.08 at code 224, 0.03 at 240).
   Measured on ``paper`` / ``camera`` (24 brackets each, see point 5; Debevec 43.34 / 42.48 dB
   PSNR L): 42.94 / 42.75 with ``base * n`` and lambda 30; with ``n / var``: 43.12 / 43.11
   (lambda 30), 43.12 / 43.07 (100), 43.13 / 42.96 (300), and with the cap 4 and lambda 100
   (this) 43.09 / 42.98 (cap 2: 43.05 / 42.92). Lambda 30 leaves a wiggle in the R curve of
   the simulator's outdoor camera-style bracket (steepest step 4.1x the median between codes
   30 and 225; 3.8x at 100). Without the cap the dark end, where the log updates spread
   widely, is left to the smoother: on a synthetic bracket with a known response (the test
   suite's) the error at code 25 grows from 0.02 to 0.10 at lambda 100.
4. **Started from Debevec & Malik's least squares** on a subset of the pixels
   (:func:`_start_curve`): from a linear or gamma start the iteration needs hundreds of
   rounds on a 3-frame bracket; from this start 30 suffice.
5. **Weights consistent with the curve.** A constant noise on the codes gives ``I(z)``
   the variance ``sigma^2 (I(z) g'(z))^2``, so Robertson's ML estimate weights each frame's
   ``I(z_j) / t_j`` by ``w(z_j) / g'(z_j)^2`` (:func:`noise_weights`; ``w`` the Gaussian-like
   weight, zero at black and clipped codes) in the merge
   (:func:`derender.hdr.classic.merge_robertson`).
   The calibration's leave-one-out ``E_i`` is something else: the weighted *geometric* mean
   of the other frames' estimates ``exp(g(z_ik)) / t_k`` with the base weight ``w`` alone.
   Its error is dominated by how the other frames' pipelines differ (auto pipelines draw a
   gamma in 1.8-2.6, a gain and a white balance per frame: at one code, single frames' mean
   updates differ by up to 2 in ``ln`` on ``paper`` / ``camera`` brackets), a multiplicative
   error, not by code noise; and ``w / g'^2`` hands ``E_i`` to the one frame whose code is
   brightest, so that the curve inherits that frame's pipeline. Measured on the ``paper`` /
   ``camera`` families (outdoor + indoor x seeds 0-11, 192x128, 7 exposures, PSNR L;
   Debevec 43.34 / 42.48 dB): ``w / g'^2``, linear (before) 42.09 / 42.88; ``w / g'`` 42.48 /
   42.82; ``w`` 43.08 / 42.74; ``w``, log domain (this) 42.94 / 42.75; the hat, log domain
   42.93 / 42.58. With ``w`` or the hat averaged linearly the curve gets a wiggle where the
   frames' mix changes with the code (R of the simulator's outdoor camera-style bracket,
   128x96: steepest step 4.9-5.1x the median between codes 30 and 225, a near-flat run at
   codes 72-80); the log-domain mean does not (3.5x; ``w / g'^2`` linear 3.7x). (These
   figures with point 3's former ``base * n`` data weights and lambda 30.)
6. **Colour balance.** The per-channel curves are offset so that neutral colours stay
   neutral (:func:`derender.response.curves.balance_channels`): ``g_G(128) = 0``, R and B
   shifted so that near-neutral, well-exposed sampled pixels come out grey; with tied curves
   (point 7) along the grey axis (equal codes give equal radiance).
7. **Channels tied**. The three Whittaker smoothers of point 3 (and the Debevec
   start of point 4) are solved as one system with ``tie * sum_z [Delta (g_c - g_c')(z)]^2``
   (:func:`derender.response.curves.solve_tied`, default
   :data:`~derender.response.curves.DEFAULT_TIE`): the curves keep their own offsets but share
   their shape unless the data insist, so greys that a frame renders with equal codes stay grey
   at every level. Independent curves bent apart where a channel has few samples (the ends of
   the range): PSNR L on the families (outdoor + indoor, seeds 0-1, 192x128, 7 exposures)
   ``paper`` 42.61 -> 42.65, ``camera`` 43.06 -> 43.64 dB (tuning); held out ``dslr-lut``
   40.13 -> 42.47, ``phone-local`` 41.14 -> 41.61, ``drift`` 43.32 -> 43.10.
8. **Bounds are not data** (``censor=True``, the default; :func:`calibration_bounds`). With the
   frames in order of exposure, a channel's observations of a pixel are bounds (its exposure is
   *at least* what the code says), left out of ``E_i`` and of the update, from the first frame
   where the channel is stuck below the top code
   (:func:`~derender.response.debevec1997.censored_observations`), where it is at or above its
   white code (:func:`~derender.response.debevec1997.white_codes`, which the merge then gives no
   weight, as Debevec's does), or where the pixel is on the rim of a clipped region (a neighbour
   +-2 pixels away clipped while it is not, :func:`robertson_clusters`; Debevec's
   :func:`~derender.response.curves.uniform_samples` drops such samples: demosaicing and JPEG mix
   the clipped neighbour in). Those observations are few (at 2 EV, 2-15 % of a code's) but
   each is off by 0.5-2.5 in ``ln``, upwards at the top codes: the mean update followed them,
   and the 2-stop step left its shape to them, so the curve rippled with the period of the step
   (luminance family, fixed gamma-2.2 rendering, Canon EOS 5D Mark III, 2 EV, scene 1: 1.07 at
   code 96, 1.12-1.16 at 160-192, 1.24 at 224 of the true gamma relative to code 128; every
   decade after the grey card's spot 0.93-0.98). Measured on that bracket, spot-scaled median
   abs error: 3.85 % before; stuck codes censored 3.73 %; with the white codes and the rims
   (this) 1.78 %. Making a pixel's three channels bounds once one is stuck, clipped or on a rim
   (the simulator clips its sensor channels before the 3x3 matrix, which bends the others'
   codes: green 118, 127, 160, 243 in frames 4x apart next to a red channel at 234, 250, 255)
   gave 0.8 % there, but recoloured the iPhone bracket's sky (block B/G 3.70 -> 4.37; per
   channel 3.42) and worsened Memorial's round trip (weighted median / p95 3.07 / 10.8 -> 3.97 /
   14.6 codes; per channel 3.27 / 13.5): not kept. A per-code median instead of the mean (no
   censoring) gave 0.73 % but bent the curves of the auto-pipeline ``camera`` family, whose
   frames disagree by design (PSNR L, outdoor seeds 0-2: 43.75 -> 38.71 dB): not kept.

Measured (simulator, 8 brackets outdoor/indoor x simple/camera x seeds 0-1, 192x128, 7
exposures, PSNR L vs truth): literal Robertson 27.1 dB (OpenCV's 27.0), this one 42.4 dB,
Debevec 42.4 dB (per bracket -2.4 to +2.5 dB from Debevec). Real brackets: no flat step
between codes 30 and 225 (literal: 101-124 of 196 on Frobisher, up to 58 on the iPhone).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.core.errors import StackError
from derender.core.types import Stack
from derender.response.curves import (
    CHANNELS,
    CLUSTER_REACH,
    DEFAULT_LAMBDA,
    DEFAULT_TIE,
    ResponseCurves,
    as_stack,
    balance_channels,
    check_usable,
    grid_positions,
    isotonic_weighted,
    level_weights,
    make_monotonic,
    smooth_log_curve,
    solve_tied,
    to_codes,
)

__all__ = [
    "calibrate_robertson",
    "robertson_positions",
    "robertson_clusters",
    "robertson_from_samples",
    "calibration_bounds",
    "noise_weights",
    "ROBERTSON_LAMBDA",
    "RIM_CODES",
]


# --------------------------------------------------------------------------- Robertson
def calibrate_robertson(stack: Stack, *, n_iter: int = 30, tol: float = 1e-6, max_pixels: int = 40_000,
                        weight: Any = "gaussian", n_levels: int = 256, seed: int = 0,
                        lam: float | None = None, balance: bool = True, tie: float | None = None,
                        censor: bool = True) -> ResponseCurves:
    """Iterative response recovery of Robertson, Borman & Stevenson (1999; JEI 2003, Sec. 3), made robust.

    Alternates the leave-one-out ML radiance with the log-domain update of ``g = ln I``,
    each followed by the monotone projection and smoothing of the module docstring; starts
    from a gamma-2.2 curve; stops after ``n_iter`` iterations or when ``g`` changes by less
    than ``tol`` (max over usable codes). ``g_G(mid) = 0``; with ``balance`` (default) R
    and B are offset so that neutral colours stay neutral, else ``g_c(mid) = 0`` per
    channel. Uses at most ``max_pixels`` pixels (a regular grid). ``lam`` is the smoothing
    weight. ``tie``: the channel tie of :func:`derender.response.curves.solve_tied` in the start
    and in every smoothing step (default :data:`~derender.response.curves.DEFAULT_TIE`; 0: the
    channels independent). ``censor``: observations that stopped following the exposure are
    bounds, not data (:func:`calibration_bounds`; module docstring, point 8). The result is
    strictly increasing.

    Parameters
    ----------
    stack : Stack
        The bracket (8- or 16-bit images and their exposure times).
    n_iter : int
        Iterations at most.
    tol : float
        Stop when ``g`` changes by less than this (natural log units).
    max_pixels : int
        Pixels used at most (a regular grid).
    weight : str or callable
        The base weight of the ML merge (a name of :data:`derender.engine.weights.WEIGHTS`).
    n_levels : int
        Code levels of the curves (256 for 8-bit images).
    seed : int
        Seed of the sampling.
    lam : float, optional
        Smoothing weight (default :data:`ROBERTSON_LAMBDA`).
    balance : bool
        Offset R and B so that neutral colours stay neutral.
    tie : float, optional
        Channel tie of the smoothing (default
        :data:`~derender.response.curves.DEFAULT_TIE`).
    censor : bool
        Leave the observations that stopped following the exposure out of the calibration
        (:func:`calibration_bounds`); False: every observation is data (the former calibration).

    Returns
    -------
    ResponseCurves
        ``log_inverse`` (n_levels, 3) ``g = ln f^-1``, strictly increasing, with
        ``g_G(mid) = 0``; ``params`` records the iterations and settings (with ``censor``, the
        channels' ``white_codes``, which the merge gives no weight).

    Raises
    ------
    InputError
        A stack too small or too poorly exposed to calibrate from, or bad settings.

    Examples
    --------
    A gamma-2.2 camera: the recovered ``g`` rises by 2.2 natural-log units per unit of
    ``ln z``, as ``g = 2.2 ln z + c`` does:

    >>> import numpy as np
    >>> import derender
    >>> radiance = np.geomspace(0.01, 1.0, 16 * 16).reshape(16, 16, 1).repeat(3, axis=2)   # 100:1
    >>> times = np.array([0.25, 1.0, 4.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> stack = derender.Stack((codes / 255).astype(np.float32), times)
    >>> curves = derender.calibrate_robertson(stack, n_iter=5)
    >>> g = curves.log_inverse[:, 1]
    >>> curves.log_inverse.shape, curves.method, bool(np.all(np.diff(g) > 0))
    ((256, 3), 'robertson', True)
    >>> round(float((g[255] - g[128]) / np.log(255 / 128)), 1)
    2.2
    """
    stack = as_stack(stack)
    check_usable(stack, n_levels)
    n_img, h, w_, _ = stack.images.shape
    ys, xs = robertson_positions(h, w_, max_pixels, seed)
    z, rim = robertson_clusters(to_codes(stack.images[:, ys, xs, :], n_levels), n_levels)  # (N, P, 3), (N, P)
    return robertson_from_samples(z, stack.times, n_iter=n_iter, tol=tol, max_pixels=max_pixels, weight=weight,
                                  n_levels=n_levels, lam=ROBERTSON_LAMBDA if lam is None else lam,
                                  balance=balance, tie=tie, censor=censor, rim=rim)


#: Positions per calibration pixel in :func:`robertson_positions`: the pixel and its 8 neighbours.
CLUSTER = 9


def robertson_positions(h: int, w: int, max_pixels: int = 40_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The positions :func:`calibrate_robertson` reads: at most ``max_pixels`` pixels on a regular
    grid (no border), each as a cluster of :data:`CLUSTER` positions, the pixel (5th) and its 8
    neighbours at ``+-``:data:`~derender.response.curves.CLUSTER_REACH` pixels (clipped
    to the image), for :func:`robertson_clusters`."""
    ys, xs = grid_positions(h, w, min(int(max_pixels), h * w), seed, border=0.0)
    d = np.array([-CLUSTER_REACH, 0, CLUSTER_REACH])
    dy, dx = np.meshgrid(d, d, indexing="ij")
    yy = np.clip(ys[:, None] + dy.ravel()[None, :], 0, h - 1)
    xx = np.clip(xs[:, None] + dx.ravel()[None, :], 0, w - 1)
    return yy.ravel(), xx.ravel()


#: A pixel is on the rim of a clipped region in a frame when one of its neighbours has a channel
#: within this many codes of the top code (250 and above for 8-bit codes, as
#: :func:`~derender.response.curves.uniform_samples` counts clipped) and its own channels are all below that.
RIM_CODES = 5


def robertson_clusters(codes: np.ndarray, n_levels: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """The calibration pixels' codes and where they are on a rim, from the codes at
    :func:`robertson_positions` (``codes`` (N, 9 P, 3)): ``(z, rim)``, ``z`` (N, P, 3) int64 the
    pixels' own codes and ``rim`` (N, P) bool, True in the frames where one of the pixel's
    neighbours is clipped (a channel at ``n_levels - 1 -`` :data:`RIM_CODES` or above) while the
    pixel's channels are all below that."""
    c = np.asarray(codes)
    n_img, p9, _ = c.shape
    c = c.reshape(n_img, p9 // CLUSTER, CLUSTER, 3)
    mid = CLUSTER // 2
    z = c[:, :, mid, :].astype(np.int64)
    top = c.max(axis=3)                                       # (N, P, 9) brightest channel per position
    clip = n_levels - 1 - RIM_CODES
    around = np.delete(top, mid, axis=2).max(axis=2)
    rim = (around >= clip) & (top[:, :, mid] < clip)
    return z, rim


#: Smoothness weight of the per-iteration Whittaker smoothing of ``g`` (data weights normalised to mean 1).
ROBERTSON_LAMBDA = 100.0
#: Smallest step of ``g`` between neighbouring codes (natural log): strictly increasing, no flat steps.
MIN_STEP = 1e-3
#: Code noise (levels) of the weights' noise model: ``g'`` is the secant over +- this many codes.
NOISE_CODES = 6
#: Floor of ``g'`` in the weights, relative to its median over the well-weighted codes (base weight > 1/2).
RELATIVE_SLOPE_FLOOR = 0.5
#: Absolute floor of the log slope ``g'`` (per code) in the noise model of the weights.
MIN_LOG_SLOPE = 4e-3


def noise_weights(g: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(n_levels, 3) weights of the ML merge: ``base(z) / g'(z)^2``, normalised to a peak of 1 per channel.

    Robertson's estimator ``E = sum_j w_j t_j I(z_j) / sum_j w_j t_j^2`` is maximum
    likelihood when ``w_j`` is the inverse variance of ``I(z_j)``. With a constant noise
    ``sigma`` on the codes (read noise, quantisation), ``var I(z) = sigma^2 I'(z)^2 =
    sigma^2 (I(z) g'(z))^2``; since ``I(z_j) ~ t_j E`` this makes every frame's estimate
    ``I(z_j) / t_j`` count with ``1 / (E^2 g'(z_j)^2)``, and the common ``E^2`` cancels.
    ``base`` (the Gaussian-like weight, 0 at black and clipped codes) tapers the ends.

    ``g'`` is the secant over +- :data:`NOISE_CODES` codes (the code noise of a JPEG spans
    several levels, and a one-code slope of a wiggly real curve, e.g. the iPhone's, swings
    the weights 100-fold between neighbouring codes: seams in smooth skies), floored at
    :data:`RELATIVE_SLOPE_FLOOR` times its median over the well-weighted codes and at
    :data:`MIN_LOG_SLOPE`.
    """
    n = g.shape[0]
    hi = np.minimum(np.arange(n) + NOISE_CODES, n - 1)
    lo = np.maximum(np.arange(n) - NOISE_CODES, 0)
    s = (g[hi] - g[lo]) / (hi - lo)[:, None]
    core = base > 0.5
    if core.any():
        s = np.maximum(s, RELATIVE_SLOPE_FLOOR * np.median(s[core], axis=0))
    s = np.maximum(s, MIN_LOG_SLOPE)
    w = base[:, None] / (s * s)
    peak = w.max(axis=0)
    return w / np.where(peak > 0, peak, 1.0)


#: Pixels of the Debevec least-squares solve that starts the iteration.
START_SAMPLES = 1000


def _start_curve(z: np.ndarray, times: np.ndarray, n_levels: int, tie: float = 0.0,
                 keep: np.ndarray | None = None) -> np.ndarray:
    """Starting curve: Debevec & Malik's least squares on up to :data:`START_SAMPLES` of the pixels.

    Robertson's iteration converges slowly from a linear or gamma start when frames are
    stops apart (hundreds of iterations on a 3-frame bracket: each iteration propagates
    the curve by one frame ratio); from this start 30 iterations suffice.
    """
    from derender.response.debevec1997 import solve_debevec_tied

    p = z.shape[1]
    idx = np.linspace(0, p - 1, min(p, START_SAMPLES)).astype(np.int64)
    log_t = np.log(times)
    g = solve_debevec_tied([z[:, idx, c] for c in range(3)], log_t, lam=DEFAULT_LAMBDA, weights="hat",
                           n_levels=n_levels, tie=tie, keep=None if keep is None else [keep[:, idx, c] for c in range(3)])
    return make_monotonic(g)


#: Floor of a code's update variance in the smoother's data weights, relative to its median over the codes.
VARIANCE_FLOOR = 0.1
#: Cap of a code's update variance in the smoother's data weights, relative to the same median.
VARIANCE_CAP = 4.0


def _update_variance(y: np.ndarray, sq: np.ndarray, cnt: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Per code, the variance of the log updates ``ln(t_j E_i)`` around their mean ``y``, from
    their sum of squares ``sq`` and count ``cnt``; floored at :data:`VARIANCE_FLOOR` times the
    median over the ``ok`` codes with two or more updates, which also stands in for the others."""
    var = np.full(y.shape, np.nan)
    two = ok & (cnt > 1)
    var[two] = sq[two] / cnt[two] - y[two] ** 2
    med = float(np.median(var[two])) if two.any() else 1.0
    med = med if med > 0 else 1.0
    return np.where(two, np.clip(var, VARIANCE_FLOOR * med, VARIANCE_CAP * med), med)


def calibration_bounds(z: np.ndarray, times: np.ndarray, rim: np.ndarray | None = None,
                       n_levels: int = 256) -> tuple[np.ndarray, list[int]]:
    """Which observations of the calibration pixels are data: ``(keep, white)``, ``keep`` (N, P, 3)
    bool (True = data) and ``white`` the channels' white codes.

    ``z`` (N, P, 3) codes of P pixels in N frames with exposure ``times``; ``rim`` (N, P) the
    frames where the pixel is beside a clipped one (:func:`robertson_clusters`; None: nowhere).
    With the frames in order of exposure, a channel's observation and every longer frame's of that
    channel are bounds (the exposure is *at least* what the code says) from the first frame where

    * the channel has stopped following the exposure
      (:func:`~derender.response.debevec1997.censored_observations`: an upper-half code that
      does not rise by more than one code in the next longer frame),
    * or the channel is at or above its white code
      (:func:`~derender.response.debevec1997.white_codes` of those censored observations; the
      top code when none is found),
    * or the pixel is on a rim (``rim``).

    Per channel: making a pixel's other channels bounds too once one is clipped (a camera clips
    its sensor channels before the 3x3 matrix) served the simulator's fixed pipeline as well, but
    recoloured the iPhone bracket's sky (block B/G 3.70 -> 4.37; per channel 3.42) and took data
    from Memorial's film frames (module docstring, point 8).
    """
    from derender.response.debevec1997 import censored_observations, white_codes

    z = np.asarray(z, dtype=np.int64)
    log_t = np.log(np.asarray(times, dtype=np.float64))
    per = [z[:, :, c] for c in range(3)]
    stuck = [censored_observations(zc, log_t, n_levels) for zc in per]
    white = white_codes(per, stuck, log_t, n_levels)
    bad = ~np.stack(stuck, axis=-1) | (z >= np.asarray(white))
    if rim is not None:
        bad |= np.asarray(rim, dtype=bool)[:, :, None]
    order = np.argsort(log_t, kind="stable")
    spread = np.logical_or.accumulate(bad[order], axis=0)
    keep = np.empty_like(spread)
    keep[order] = ~spread
    return keep, white


def _monotone_updates(tot: np.ndarray, sq: np.ndarray, cnt: np.ndarray, base: np.ndarray,
                      g: np.ndarray) -> tuple[list, list, list]:
    """Robertson's update per channel from the per-code sums of the leave-one-out log estimates
    (``tot``, their squares ``sq``, counts ``cnt``; (n_levels, 3)): the mean per code, its
    precision ``q`` (normalised to mean 1) and its monotone projection; ``(monos, qs, live)``,
    ``live[c]`` False where no frame overlaps another (a single exposure: the start ``g`` kept)."""
    n_levels = g.shape[0]
    monos, qs, live = [], [], []
    for c in range(3):
        ok = (cnt[:, c] > 0) & (base > 0)
        live.append(bool(ok.any()))
        if not ok.any():
            monos.append(g[:, c].copy())
            qs.append(np.zeros(n_levels))
            continue
        y = np.zeros(n_levels)
        y[ok] = tot[ok, c] / cnt[ok, c]
        q = np.where(ok, cnt[:, c] / _update_variance(y, sq[:, c], cnt[:, c], ok), 0.0)
        q /= q[ok].mean()
        monos.append(np.where(ok, isotonic_weighted(y, q, MIN_STEP), 0.0))  # monotone projection, then smooth
        qs.append(q)
    return monos, qs, live


def robertson_from_samples(z: np.ndarray, times: np.ndarray, *, n_iter: int = 30, tol: float = 1e-6,
                           max_pixels: int = 40_000, weight: Any = "gaussian", n_levels: int = 256,
                           lam: float = ROBERTSON_LAMBDA, balance: bool = True,
                           tie: float | None = None, censor: bool = True,
                           rim: np.ndarray | None = None) -> ResponseCurves:
    """:func:`calibrate_robertson` on sampled codes ``z`` (N, P, 3) int of a bracket with ``times`` (s);
    ``rim`` (N, P) bool: where each pixel is beside a clipped one (:func:`robertson_clusters`), read
    with ``censor``."""
    times = np.asarray(times, dtype=np.float64)
    z = np.asarray(z).astype(np.int64)
    base = level_weights(weight, n_levels)
    log_t = np.log(times)[:, None, None]
    flat = (z * 3 + np.arange(3)).ravel()  # level-major index into the (n_levels, 3) table
    card = np.bincount(flat, minlength=3 * n_levels).reshape(n_levels, 3).astype(np.float64)
    for c in range(3):
        if not np.any((card[:, c] > 0) & (base > 0)):
            raise StackError(f"channel {CHANNELS[c]} has no usable pixel; cannot recover its response")
    mid = n_levels // 2
    tie = DEFAULT_TIE if tie is None else float(tie)
    keep, white = calibration_bounds(z, times, rim, n_levels) if censor else (None, None)
    if keep is not None:
        keep = np.broadcast_to(keep if keep.ndim == 3 else keep[:, :, None], z.shape)
    g = _start_curve(z, times, n_levels, tie, keep)
    d2 = np.diff(np.eye(n_levels), n=2, axis=0)
    smooth2 = float(lam) * (d2.T @ d2)
    # the other frames count with the base weight w (not the merge's w / g'^2) and their
    # estimates average in the log domain: see the module docstring, point 5
    wz = base[z]  # (N, P, 3)
    if keep is not None:
        wz = wz * keep    # bounds are neither in E_i nor updated
    den = wz.sum(axis=0)[None] - wz
    live_obs = den > 1e-6 * base.max()
    if keep is not None:
        live_obs &= keep
    live_obs = live_obs.ravel()
    den = np.where(den > 0, den, 1.0)
    iters = 0
    for iters in range(1, int(n_iter) + 1):
        x = g.ravel()[flat].reshape(z.shape) - log_t  # ln of each frame's radiance estimate
        wx = wz * x
        # leave-one-out radiance: observation (i, j) is compared with E_i of the *other* frames
        # (with its own frame in E_i, a code whose weight dominates would confirm any I(m));
        # Robertson's update I(m) = mean of t_j E_i over the observations of code m, taken in the
        # log domain (geometric mean: a leave-one-out E_i from a frame stops away has
        # multiplicative errors, and their arithmetic mean is biased upwards at dark codes)
        te = (log_t + (wx.sum(axis=0)[None] - wx) / den).ravel()
        fl = flat[live_obs]
        tot = np.bincount(fl, weights=te[live_obs], minlength=3 * n_levels).reshape(n_levels, 3)
        sq = np.bincount(fl, weights=te[live_obs] ** 2, minlength=3 * n_levels).reshape(n_levels, 3)
        cnt = np.bincount(fl, minlength=3 * n_levels).reshape(n_levels, 3).astype(np.float64)
        new = np.empty_like(g)
        monos, qs, live = _monotone_updates(tot, sq, cnt, base, g)
        if tie > 0 and all(live):
            # the three Whittaker smoothers in one system, tied: see solve_tied
            cols = solve_tied([np.diag(q + 1e-12) + smooth2 for q in qs], [q * m for q, m in zip(qs, monos)], tie)
        else:
            cols = np.stack([smooth_log_curve(m, q, lam) if lv else m for m, q, lv in zip(monos, qs, live)], axis=1)
        for c in range(3):
            if not live[c]:
                new[:, c] = g[:, c]
                continue
            col = isotonic_weighted(cols[:, c], np.ones(n_levels), MIN_STEP)
            new[:, c] = col - col[mid]
        change = float(np.max(np.abs(new - g)[base > 0]))
        g = new
        if change < tol:
            break
    params = {"iterations": iters, "max_pixels": int(max_pixels), "lambda": float(lam),
              "weight": weight if isinstance(weight, str) else "custom", "calibration_weights": "base, log domain",
              "merge_weights": "base / g'^2", "tie": tie, "censor": bool(censor)}
    if keep is not None:
        params["censored"] = int((~keep).sum())
        params["white_codes"] = [int(v) for v in white]
    if balance:
        g, info = balance_channels(g, z, mode="grey-axis" if tie > 0 else "neutral")
        params.update(info)
    return ResponseCurves(log_inverse=g, method="robertson", params=params)
