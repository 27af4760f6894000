"""Censored fill: where ghost removal left only clipped frames, fill log radiance from the measured clipped scene around.

Beyond both papers. Where the reference frame is clipped, only the shorter frames can measure
the scene; where the moving thing stands in all of them (the sky beside the ping-pong player's
head: the short frame still shows the head there), ghost removal rightly leaves them out, and
every frame that remains is clipped. The merge then knows only a lower bound per channel,
``L_c >= B_c`` (the clipped frames' bound, which the merge returns: the reference's clip
value), and returned that bound as if it were measured: a flat band along the moving thing's
outline, below the radiance around it.

The **region** ``R_c`` (per channel ``c``) is where no kept frame (``valid``: taking part in
the merge after ghost removal) has a code below :data:`CENSOR_CODE` and some frame rejected
as a ghost does (it would have measured the pixel, had it not shown the moving thing there).
Its **data** ``D_c`` are the pixels of the same kind that the bracket does measure: the
reference is clipped (code >= :data:`CENSOR_CODE`) and a kept frame is not, so the merge's
value there is a measurement of what the reference's clip hides; a datum more than
:data:`DATA_TOL` below the region's bound (carried out from ``R_c`` by the same interpolation)
cannot be such a measurement and is left out. Pixels the reference measures
below its clip (darker texture, or the occluder itself: the head) are not data: they say
nothing about how far above the clip the hidden scene lies.

Per channel the log radiance on ``R_c`` is the pull-push interpolation of the data (Gortler et
al. 1996, *The Lumigraph*, Sec. 3.4: normalised convolution on a Gaussian pyramid, a smooth
membrane-like fill that reads the nearest data first). With ``N_0 = m u``, ``W_0 = m`` (``u``
the merge's log radiance, ``m`` the indicator of ``D_c``), push: ``N_{l+1} = down(N_l)``,
``W_{l+1} = down(W_l)`` for :data:`PYRAMID_LEVELS` levels (the data are read at most about
``2^levels`` pixels away); pull, from the top:

    a_l = min(1, W_l / W_FULL),    v_l = a_l N_l / W_l + (1 - a_l) up(v_{l+1})

(:data:`W_FULL`), and a pixel whose pyramid saw no data keeps its value. A pixel with some
channels measured (by a kept frame) takes the fill's colour anchored on them: ``v_c`` plus the
mean, over its measured channels ``k``, of ``u_k - v_k`` (lifting a censored channel alone
would change the hue: red rims on the sculpture garden's sunlit facade). Then the bound holds:
``v_c <- max(v_c, ln B_c)``, and only the censored channels of ``R`` are written; every pixel
and channel a kept frame measures keeps the merge's value.

The variance says that the value is not measured: in log, per channel,

    sigma_c^2 = max((v_c - ln B_c)^2, s_c^2)

where ``s_c^2`` is the data's relative variance (``Var / L^2``), pulled and pushed the same way
(the fill is never more certain than what it reads); the radiance variance is the
log-normal's ``L^2 (exp(sigma^2) - 1)``, never below the merge's own.

A still bracket has no ghosts, so no frame is rejected and nothing is filled: a lamp clipped in
every frame keeps its plain-merge value (issue 36, "lamps are kept"). The motion run calls the
fill after the consensus correction (:mod:`derender.engine.motion.consensus`), for every method.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["CENSOR_CODE", "DATA_TOL", "PYRAMID_LEVELS", "W_FULL", "hidden_views", "pull_push", "censored_fill"]

#: A code at or above this is clipped for the fill: a lower bound on the radiance, not a
#: measurement (many cameras saturate somewhere in 250-254; the ping-pong reference's sky
#: stands at 250-253).
CENSOR_CODE = 250

#: A datum (the reference clipped, a kept frame measuring) whose log radiance lies more than this
#: below the censored region's bound (carried out from the region by the same pull-push) is
#: left out: the clipped scene is at least at the bound, so such a value is a moving thing's
#: edge that ghost removal kept, or a misregistered one. Measured: the ping-pong band against
#: the clipped hill within 20 px (stabilized, translation) 0.88 without this rule, 1.07 at 0.1,
#: 1.04 at 0.3; on the simulator's hidden regions (tuning families, ``tests/engine``) 0.3 gives
#: a median ``|ln error|`` of 0.156 against 0.149 without the rule and 0.177 at 0.1.
DATA_TOL = 0.3

#: Levels of the pull-push pyramid: the fill reads data at most about ``2^levels`` pixels away.
PYRAMID_LEVELS = 8

#: A pyramid cell whose data weight (the Gaussian-weighted fraction of data pixels) reaches this
#: is read on its own; below it, blended with the coarser level.
W_FULL = 0.25


def hidden_views(frames: np.ndarray, rejected: np.ndarray) -> np.ndarray | None:
    """``(H, W, 3)`` bool: where, per channel, some frame rejected as a ghost has a code below
    :data:`CENSOR_CODE` (it would measure the scene there). ``frames`` (N, H, W, 3) uint8,
    ``rejected`` (N, H, W) bool. None when no rejected frame measures anything."""
    out = None
    for j in range(frames.shape[0]):
        if not rejected[j].any():
            continue
        seen = (frames[j] < CENSOR_CODE) & rejected[j][..., None]
        out = seen if out is None else np.logical_or(out, seen, out=out)
    return out if out is not None and out.any() else None


def _kept_measured(frames: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """``(H, W, 3)`` bool: some kept frame has a code below :data:`CENSOR_CODE` in that channel."""
    out = np.zeros(frames.shape[1:], dtype=bool)
    for j in range(frames.shape[0]):
        m = frames[j] < CENSOR_CODE
        if valid is not None:
            m &= valid[j][..., None] != 0
        out |= m
    return out


def pull_push(values: np.ndarray, weights: np.ndarray, levels: int = PYRAMID_LEVELS) -> tuple[np.ndarray, np.ndarray]:
    """The pull-push interpolation (module docstring) of ``values`` (H, W, C) float32 where
    ``weights`` (H, W, C) float32 (0 or 1) marks the data: ``(v, covered)``, ``v`` everywhere, and
    ``covered`` (H, W, C) the weight the data had in ``v`` (0 where no level saw data).

    Examples
    --------
    >>> import numpy as np
    >>> v = np.zeros((32, 32, 1), np.float32); w = np.zeros_like(v)
    >>> v[:, :8] = 1.0; w[:, :8] = 1.0          # data on the left only
    >>> out, cov = pull_push(v, w)
    >>> bool(np.allclose(out[:, 20:], 1.0, atol=1e-5)), bool((cov > 0.99).all())
    (True, True)
    """
    import cv2

    num = [np.ascontiguousarray(values * weights, dtype=np.float32)]
    wts = [np.ascontiguousarray(weights, dtype=np.float32)]
    for _ in range(levels):
        h, w = wts[-1].shape[:2]
        if min(h, w) < 2:
            break
        num.append(cv2.pyrDown(num[-1]).reshape(((h + 1) // 2, (w + 1) // 2, -1)))
        wts.append(cv2.pyrDown(wts[-1]).reshape(((h + 1) // 2, (w + 1) // 2, -1)))
    v = cov = None
    for nl, wl in zip(reversed(num), reversed(wts)):
        with np.errstate(divide="ignore", invalid="ignore"):
            own = np.where(wl > 0, nl / np.maximum(wl, 1e-30), 0.0).astype(np.float32)
        a = np.minimum(1.0, wl / W_FULL).astype(np.float32)
        if v is None:
            a = (wl > 0).astype(np.float32)
            v, cov = own, a
            continue
        size = (wl.shape[1], wl.shape[0])
        up_v = cv2.pyrUp(v, dstsize=size).reshape(wl.shape)
        up_c = cv2.pyrUp(cov, dstsize=size).reshape(wl.shape)
        # the coarser level's value where it had data (its weight divided out of the pyramid's blur)
        with np.errstate(divide="ignore", invalid="ignore"):
            up_v = np.where(up_c > 1e-6, up_v / np.maximum(up_c, 1e-30), 0.0).astype(np.float32)
        v = a * own + (1 - a) * up_v
        cov = a + (1 - a) * np.clip(up_c, 0.0, 1.0)
        v = (v * cov).astype(np.float32)          # carried with its coverage (divided out on the way down)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(cov > 1e-6, v / np.maximum(cov, 1e-30), 0.0).astype(np.float32)
    return v, cov


def censored_fill(radiance: np.ndarray, variance: np.ndarray | None, frames: np.ndarray, valid: np.ndarray | None,
                  hidden: np.ndarray | None, ref: int) -> dict[str, Any] | None:
    """Fill, **in place**, the censored pixels of ``radiance`` (H, W, 3) float32 (and raise their
    ``variance``, if given) as the module docstring says. ``frames`` (N, H, W, 3) uint8 as merged,
    ``valid`` (N, H, W) uint8 the planes the merge read (None: every frame kept), ``hidden`` from
    :func:`hidden_views`, ``ref`` the reference frame. Returns a summary (pixels in the region,
    pixels filled, the median log lift over the bound of the filled channels) or None when there
    is nothing to fill."""
    if hidden is None:
        return None
    kept = _kept_measured(frames, valid)
    censored = hidden & ~kept          # (H, W, 3)
    region = censored.any(axis=-1)
    n_region = int(np.count_nonzero(region))
    if n_region == 0:
        return None
    data = (frames[ref] >= CENSOR_CODE) & kept           # the reference's clip, measured by a kept frame
    del kept
    logr = np.log(np.maximum(radiance, np.float32(1e-30)))
    # a datum below the region's bound by more than DATA_TOL is not the clipped scene (a moving
    # thing's blurred edge the test kept): the bound is carried out from the region the same way
    bound_near, _ = pull_push(logr, censored.astype(np.float32))
    data &= logr >= bound_near - np.float32(DATA_TOL)
    del bound_near
    fill, cov = pull_push(logr, data.astype(np.float32))
    ys, xs = np.nonzero(region)
    cens = censored[ys, xs] & (cov[ys, xs] > 0.5)       # the fill read data within the pyramid's reach
    bound = logr[ys, xs].astype(np.float64)
    f = fill[ys, xs].astype(np.float64)
    # a pixel with some channels measured: the fill's colour anchored on them (their mean log
    # offset from the fill), so that lifting the censored channels alone does not change its hue
    meas = ~censored[ys, xs]
    n_meas = meas.sum(axis=-1)
    delta = np.where(n_meas > 0, np.where(meas, bound - f, 0.0).sum(axis=-1) / np.maximum(n_meas, 1), 0.0)
    u = np.where(cens, np.maximum(f + delta[:, None], bound), bound)
    lift = u - bound
    info: dict[str, Any] = {"region_pixels": n_region, "filled_pixels": int(np.count_nonzero(cens.any(axis=-1))),
                            "censor_code": CENSOR_CODE,
                            "median_lift": round(float(np.median(lift[cens])), 4) if cens.any() else 0.0}
    radiance[ys, xs] = np.where(cens, np.exp(u), radiance[ys, xs]).astype(np.float32)
    if variance is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(data, variance / np.maximum(radiance, np.float32(1e-30)) ** 2, 0.0).astype(np.float32)
        s2, _ = pull_push(np.minimum(rel, np.float32(1e6)), data.astype(np.float32))
        sig2 = np.maximum(lift * lift, s2[ys, xs].astype(np.float64))
        val = np.exp(u)
        var = np.minimum(val * val * np.expm1(np.minimum(sig2, 50.0)), np.finfo(np.float32).max / 4)
        old = variance[ys, xs].astype(np.float64)
        variance[ys, xs] = np.where(cens, np.maximum(var, old), old).astype(np.float32)
    return info
