"""The 3x3 map between two linearised images and its code-domain misfit (paper 1, eq. 9).

Two images of one scene, linearised (:mod:`derender.hdr.stabilize.curves`), are related by a 3x3 matrix:
``L_k = H L_j`` with ``H = A_k A_j^-1`` (eq. 9; exposure ratio and gain absorbed in H).
:func:`fit_pair` fits H by row-wise weighted least squares in the linear domain, with
weights (:func:`pair_weights`) that make the linear residual approximate the residual in
code units of image k, equal code noise in both images propagated through the map, two
reweighting passes; a ridge (:data:`RIDGE`) pulls off-diagonal entries to 0 along colour
directions the data do not span. :func:`pair_cost` is the symmetric code-domain misfit of
the best map (both directions): the objective of the blind exponent searches
(:mod:`.exponents`; :func:`pair_costs_power` evaluates it for many pairs with power-law
curves in one batch). The RANSAC fit of the stabilised matrices H_j builds on
:func:`fit_pair` (:mod:`.colour_matrices`).
"""

from __future__ import annotations

import numpy as np

from derender.hdr.stabilize.curves import Curve, as_curve

__all__ = ["RIDGE", "predict_codes", "pair_weights", "fit_pair", "effective_codes", "pair_cost", "pair_residuals",
           "pair_costs_power"]


#: Ridge on the off-diagonal entries of colour matrices, relative to the data's mean
#: eigenvalue: negligible for colourful overlaps, it keeps H_j near diagonal along colour
#: directions the overlapping pixels do not span (dim scenes, one illuminant).
RIDGE = 1e-2


_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))   # upper triangle of a 3x3


_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])                  # 3x3 -> its entry of the 6


def _wls_matrix(src: np.ndarray, dst: np.ndarray, wt: np.ndarray, ridge: float | None = None,
                prods: np.ndarray | None = None, diagonal: bool = False) -> np.ndarray:
    """Row-wise weighted least squares ``dst ~ src @ H.T`` with per-row-of-H sample weights
    wt (n, 3) and a ridge pulling off-diagonal entries to 0. ``prods`` (n, 6): the products
    ``src_k src_l`` (k <= l), when already computed. ``diagonal``: H restricted to a diagonal
    (one gain per channel, ``h_c = sum w_c s_c d_c / sum w_c s_c^2``)."""
    if diagonal:
        num = np.sum(wt * dst * src, axis=0)
        den = np.sum(wt * src * src, axis=0)
        return np.diag(num / np.maximum(den, 1e-300))
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


def predict_codes(h: np.ndarray, lin_src: np.ndarray, curve_dst: "float | Curve") -> np.ndarray:
    """Codes of the destination image predicted from linear source values through ``h`` (eq. 9)."""
    return as_curve(curve_dst).code(np.maximum(lin_src @ h.T, 1e-12))


def pair_weights(j_src: np.ndarray, j_dst: np.ndarray, c_src: "float | Curve",
                 c_dst: "float | Curve", least_squares: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Code-domain residual weights v (equal code noise in both images, propagated through
    the map) and the linear-domain least-squares weights ``v * (dJ/dL)^2`` of the
    destination (None unless ``least_squares``). ``j_dst`` should be noise-free (a
    prediction): weights computed from noisy observations bias the fit.

    For a (nearly) diagonal map ``L_d = a L_s`` the code slope ``dJ_d / dJ_s`` is
    ``(d ln L_s / dJ_s) / (d ln L_d / dJ_d)`` (:meth:`Curve.log_slope`), so v needs no
    linear values; only the least-squares weights need ``L_d``."""
    cs, cd = as_curve(c_src), as_curve(c_dst)
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
    # floored log slopes (:meth:`Curve.noise_log_slope`): a flat segment of a fitted response
    # table claims a noise-free linear value, and its blocks took weights up to 2e8 times the
    # median (the sculpture garden's Debevec curve is flat over codes 185-208 and 241-255 in R,
    # 172-199 and 225-255 in G: its pair (1/320 s, 1/160 s) came out with a diagonal map of
    # 0.79 / 0.77 / 1.89 where the exposure ratio is 2, residual 53 codes)
    dlog_dst = cd.noise_log_slope(j_dst)
    slope = cs.noise_log_slope(j_src) / dlog_dst
    v = 1.0 / (1.0 + slope * slope)
    if not least_squares:
        return v, None
    djdl_dst = 1.0 / np.maximum(cd.lin(np.maximum(j_dst, 1e-6)) * dlog_dst, 1e-300)
    return v, v * djdl_dst * djdl_dst


def fit_pair(jj: np.ndarray, jk: np.ndarray, gj: "float | Curve", gk: "float | Curve", iters: int = 2,
             ridge: float | None = None, diagonal: bool = False) -> tuple[np.ndarray, float]:
    """H (k <- j) on effective codes jj, jk (n, 3) and its weighted mean squared code residual.

    Weighted least squares in the linear domain approximating the code-domain error; the
    weights come from the current prediction (first pass: the observation). ``diagonal``:
    H restricted to one gain per channel."""
    cj, ck = as_curve(gj), as_curve(gk)
    lj, lk = cj.lin(jj), ck.lin(jk)
    prods = lj[:, _IU[0]] * lj[:, _IU[1]]
    lo = 0.5 * jk.min(axis=0)
    pred = jk
    for _ in range(iters):
        v, wl = pair_weights(jj, pred, cj, ck)
        h = _wls_matrix(lj, lk, wl, ridge, prods, diagonal)
        raw = predict_codes(h, lj, ck)
        pred = np.clip(raw, lo, 1.0)
    r = raw - jk
    return h, float(np.sum(v * r * r) / np.sum(v))


def effective_codes(p: np.ndarray, curve: "float | Curve") -> np.ndarray:
    """Block means in the linear domain, back in code units."""
    c = as_curve(curve)
    return c.code(np.mean(c.lin(p), axis=1))


def pair_cost(pj: np.ndarray, pk: np.ndarray, gj: float, gk: float, sel: np.ndarray | None = None,
              jj: np.ndarray | None = None) -> float:
    """Symmetric code-domain misfit of the best 3x3 linear map between two linearised images
    (``jj``: image j's effective codes, if already computed)."""
    jj = effective_codes(pj, gj) if jj is None else jj
    jk = effective_codes(pk, gk)
    if sel is not None:
        jj, jk = jj[sel], jk[sel]
    _, c1 = fit_pair(jj, jk, gj, gk, ridge=0.0)
    _, c2 = fit_pair(jk, jj, gk, gj, ridge=0.0)
    return c1 + c2


def pair_residuals(pj: np.ndarray, pk: np.ndarray, gj: float, gk: float, sel: np.ndarray | None) -> np.ndarray:
    """Per-block max code residual of both directions, with maps fitted on ``sel``."""
    jj, jk = effective_codes(pj, gj), effective_codes(pk, gk)
    s = slice(None) if sel is None else sel
    h1, _ = fit_pair(jj[s], jk[s], gj, gk, ridge=0.0)
    h2, _ = fit_pair(jk[s], jj[s], gk, gj, ridge=0.0)
    r1 = np.abs(predict_codes(h1, as_curve(gj).lin(jj), gk) - jk).max(axis=1)
    r2 = np.abs(predict_codes(h2, as_curve(gk).lin(jk), gj) - jj).max(axis=1)
    return np.maximum(r1, r2)


def pair_costs_power(reqs: list) -> list[float]:
    """:func:`pair_cost` of several pairs with power-law curves at once: ``reqs`` holds
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
    """Batched :func:`fit_pair` (``ridge=0``) of power-law curves: codes (P, n, 3), gammas
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
        # power-law weights (:func:`pair_weights`)
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
