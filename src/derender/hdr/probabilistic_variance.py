"""The probabilistic merge's variance with the model's error kept shared (paper 2, Sec. 3.1, eq. 3).

Eq. 3 multiplies the exposures' Gaussians as if each frame's de-rendering error were
independent: the product's log variance ``1 / sum_i p_i`` shrinks like ``1 / N`` when N
frames see a pixel. Measured before this module (``derender experiment uncertainty``,
192x128, 7 exposures): 95 % coverage 0.38-0.42 on the tuning families, 0.19-0.38 held out.
Each frame i gives a log estimate ``y_i`` (its log raw median scaled to the target exposure)
with log variance ``s2_i = s2m_i + s2n_i``:

* ``s2m_i``, the **model** part: the GP's predictive variance of the colour (delta method,
  plus ``floor``). The same scene colour is de-rendered by the same fitted curve in every
  frame (a neighbouring code of the same curve), so this error is *shared*: it is counted as
  fully correlated across frames and combined with the merge's own weights, ``(sum_i w_i
  sm_i)^2`` with ``sm_i = sqrt(s2m_i)``, which is a weighted mean of standard deviations and
  does not shrink with N.
* ``s2n_i``, the **noise** part: the pixel's own code noise through the curve (``code_noise``
  of :mod:`derender.hdr.probabilistic`), independent between frames: ``sum_i w_i^2 s2n_i``.
* **Pipeline change**: white balance, gain or tone that change between frames are outside the
  model; they move each frame's estimate by its own amount, so the frames disagree by more
  than their variances say. The weighted spread ``sum_i w_i (y_i - m)^2`` of the estimates
  around the merged mean ``m`` measures that disagreement per pixel (0 for one frame).

With the weights unchanged (``w_i = p_i / P``, ``p_i = 1 / s2_i`` joint over the measured
channels, so the radiance is eq. 3's, byte for byte) the merged log variance is

    V = sum_i w_i^2 s2n_i + k_model (sum_i w_i sm_i)^2 + k_pipe sum_i w_i (y_i - m)^2,

at least eq. 3's ``1 / P``; censored channels truncate ``V`` at the bound as eq. 3's variance
is truncated, and the output variance is the log-normal ``(m, V)``'s about the radiance
output (its variance plus the squared difference of the two means), carried through the
camera -> linear sRGB matrix by its squares. ``k_model`` and ``k_pipe`` (:data:`K_MODEL`,
:data:`K_PIPE`) were chosen on the tuning families (``paper``, ``camera``) only; the figures
are in ``docs/uncertainty.md``. ``info["variance_sources"]`` gives the median share of each
term in ``V`` over the measured pixel-channels.
"""

from __future__ import annotations

import numpy as np

from derender.hdr.lognormal import MAX_LOG, truncate_below_log

__all__ = ["K_MODEL", "K_PIPE", "K_SPATIAL", "add_spatial", "model_sd", "fill_model_sd", "shared_log_moments"]

#: Inflation of the shared model term (tuning families; docs/uncertainty.md).
K_MODEL = 1.0
#: Weight of the frames' spread, the pipeline-change term (tuning families; docs/uncertainty.md).
K_PIPE = 0.01
#: Weight of the spatial-mixing term (tuning families; docs/uncertainty.md).
K_SPATIAL = 0.3


def model_sd(model, colours: np.ndarray, floor: float, clip_code: int, censor: bool, per_channel: bool = True
             ) -> np.ndarray:
    """``sqrt(mean_c s2m_c)`` over each uint8 colour's (M, 3) measured channels (0 where all are
    censored): the model part of the log variance, NumPy (any model with ``predict_log``)."""
    eps = float(getattr(model, "eps", 0.0))
    mu, s2 = model.predict_log(colours)
    mu = np.clip(np.nan_to_num(np.asarray(mu, dtype=np.float64), nan=0.0), -MAX_LOG, MAX_LOG)
    s2 = np.clip(np.nan_to_num(np.asarray(s2, dtype=np.float64), nan=1e6), 1e-12, 1e6)
    e = np.exp(mu)
    r = np.maximum(e - eps, 1e-30)
    s2m = np.minimum(s2 * (e / r) ** 2, 1e6) + floor
    clipped = (colours >= clip_code) if censor else np.zeros(colours.shape, bool)
    if not per_channel:
        clipped = np.repeat(np.any(clipped, axis=-1, keepdims=True), 3, axis=-1)
    n_ok = np.sum(~clipped, axis=-1)
    tot = np.sum(np.where(clipped, 0.0, s2m), axis=-1)
    return np.where(n_ok > 0, np.sqrt(tot / np.maximum(n_ok, 1)), 0.0)


def fill_model_sd(model, colours: np.ndarray, planes: np.ndarray, floor: float, clip_code: int, censor: bool,
                  colour_major: bool, compiled: tuple | None, *, threads: int | None = 1) -> np.ndarray:
    """The model's log sd per colour into the probabilistic merge's planes: column 7 of the
    colour-major (M, 8) table (compiled :func:`~derender.engine.gaussian_kernels.model_sd_rows`
    on the GP's interpolation table, in ``threads`` threads), or two more rows ``[sm; vn]`` of
    the (9, M) planes (returned as (11, M))."""
    from derender.core.memory import thread_count

    m = colours.shape[0]
    if colour_major:
        from derender.engine.gaussian_kernels import model_sd_rows

        tab_mu, tab_lv, lut_lo, lut_w = compiled
        eps = float(getattr(model, "eps", 0.0))
        nthreads = max(1, min(thread_count(threads), -(-m // (1 << 16))))
        cuts = [m * i // nthreads for i in range(nthreads + 1)]

        def one(i: int) -> None:
            model_sd_rows(colours, cuts[i], cuts[i + 1], tab_lv, tab_mu, lut_lo, lut_w, eps, float(floor),
                          int(clip_code), bool(censor), True, MAX_LOG, planes)

        if nthreads > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(nthreads, thread_name_prefix="derender-modelsd") as ex:
                list(ex.map(one, range(nthreads)))
        else:
            one(0)
        return planes
    sm = np.empty(m, dtype=np.float64)
    chunk = 1 << 18
    for s in range(0, m, chunk):
        sm[s:s + chunk] = model_sd(model, colours[s:s + chunk], floor, clip_code, censor)
    pj = planes[3:6].max(axis=0)        # the joint precision (0 where every channel is censored)
    with np.errstate(divide="ignore"):
        vn = np.where(pj > 0, np.maximum(1.0 / np.where(pj > 0, pj, 1.0) - sm * sm, 0.0), 0.0)
    return np.ascontiguousarray(np.concatenate([planes, sm[None], vn[None]]))


def add_spatial(radiance: np.ndarray, variance: np.ndarray, terms: np.ndarray, hist: np.ndarray,
                k_spatial: float, floor_share: float) -> None:
    """Add the spatial-mixing term ``k_spatial L_c^2 sqrt(D_c)`` to a block's float32 output
    (rows, W, 3) in place (NumPy :func:`~derender.engine.gaussian_kernels.gaussian_variance_band`):
    ``D_c`` the mean squared difference of ``log(L_c + floor_share mean_c L)`` to the four
    neighbours within the block; ``terms`` (rows, W, 3, 3) the log-space model / noise /
    pipeline terms, whose shares with the spatial one are counted in ``hist`` (rows, 4, NBINS)."""
    rad = radiance.astype(np.float64)
    lf = np.log((rad + floor_share * rad.sum(axis=-1, keepdims=True) / 3.0).astype(np.float32) + np.float32(1e-30))
    lf = lf.astype(np.float64)
    d2 = np.zeros(lf.shape)
    nd = np.zeros(lf.shape)
    for ax in (0, 1):
        n = lf.shape[ax]
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[ax], b[ax] = slice(1, n), slice(0, n - 1)
        a, b = tuple(a), tuple(b)
        d = (lf[a] - lf[b]) ** 2
        d2[a] += d
        d2[b] += d
        nd[a] += 1
        nd[b] += 1
    rs = k_spatial * np.sqrt(d2 / np.maximum(nd, 1))
    big = np.finfo(np.float32).max / 4
    vo = variance.astype(np.float64)
    pos = (rs > 0) & (rad > 0)
    vo = np.where(pos, np.minimum(vo + rs * rad * rad, big), vo)
    variance[...] = vo.astype(np.float32)
    t3 = terms.sum(axis=-1)
    has = (t3 > 0) & (rad > 0)
    has[1::4] = has[2::4] = has[3::4] = False       # shares on the kernel's 1-in-4 grid (bands start at
    has[:, 1::4] = has[:, 2::4] = has[:, 3::4] = False   # multiples of 4 rows)
    nb = hist.shape[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(has, vo / np.where(has, rad * rad, 1.0), 0.0)
        sh_s = np.where(has & (rel > 0), np.minimum(rs / np.where(rel > 0, rel, 1.0), 1.0), 0.0)
        shares = [terms[..., q] / np.where(has, t3, 1.0) * (1.0 - sh_s) for q in range(3)] + [sh_s]
    rows = np.broadcast_to(np.arange(rad.shape[0]).reshape(-1, 1, 1), rad.shape)[has]
    for q, sh in enumerate(shares):
        np.add.at(hist[:, q, :], (rows, np.minimum((sh[has] * nb).astype(np.int64), nb - 1)), 1)


def shared_log_moments(prec, acc, bound, extra, *, censor: bool, k_model: float, k_pipe: float,
                       max_log: float, max_v: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-RGB mean (eq. 3's, as :func:`~derender.hdr.probabilistic.log_product_moments`) and
    the shared-error variance (module docstring) (..., 3) from the log-space sums (3, ...) and
    ``extra = (sum p y^2, sum p sm, sum p^2 vn, sum p vn)``, and the model / noise / pipeline terms of ``V``
    (rows, W, 3, 3) for :func:`add_spatial` (NumPy
    :func:`~derender.engine.gaussian_kernels.gaussian_variance_band`)."""
    sq, shm, noi, nw = extra[:4]
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = prec > 0
        v = np.where(ok, 1.0 / prec, np.inf)
        m = np.where(ok, acc * v, 0.0)
        vm = k_model * np.where(ok, shm * v, 0.0) ** 2
        vn = np.where(ok, noi * v * v, 0.0)
        vp = k_pipe * np.where(ok, np.maximum(sq * v - m * m - (nw * v - noi * v * v), 0.0), 0.0)
        terms = np.stack([vm, vn, vp], axis=-1)          # (3, rows, W, 3)
        vv = vm + vn + vp
        vv = np.where(ok, np.maximum(vv, v), np.inf)
    mv = m
    if censor:
        m, v = truncate_below_log(m, v, bound)
        mv, vv = truncate_below_log(mv, vv, bound)
    m, mv = np.clip(m, -max_log, max_log), np.clip(mv, -max_log, max_log)
    v, vv = np.clip(v, 0.0, max_v), np.clip(vv, 0.0, max_v)
    with np.errstate(over="ignore", invalid="ignore"):
        mean0 = np.exp(m + 0.5 * v)
        ev = np.exp(mv + 0.5 * vv)
        var0 = np.expm1(vv) * ev * ev + (ev - mean0) ** 2
    return np.moveaxis(mean0, 0, -1), np.moveaxis(var0, 0, -1), np.moveaxis(terms, 0, 2)
