"""Paper 1, Algorithm 1 step 3.2 as the stabilised merges run it: the colour model of a bracket
whose linearisations are known, i.e. the per-frame 3x3 matrices and what is done to them after
the fit.

``mode="reference"``: ``H_j`` maps image ``j``'s linear values onto the reference's, exposure ratio
included (eq. 9-10, :func:`~derender.hdr.stabilize.colour_matrices.colour_matrices_to_reference`);
``mode="joint"``: ``K_j`` maps ``L_j / t_j`` into the bracket's average rendering
(:func:`~derender.hdr.stabilize.colour_matrices.joint_colour_matrices`, beyond the paper). Then,
beyond the paper: when the frames' exposures follow their times, each matrix's luminance scale is
set from the times (:func:`anchor_to_times`), and the grey balance multiplies every matrix by one
gain per output channel, ``D M_j`` (:mod:`.grey_balance`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709 as _W
from derender.hdr.stabilize import grey_balance as gb
from derender.hdr.stabilize.colour_matrices import colour_matrices_to_reference, joint_colour_matrices

__all__ = ["fit_colour_model", "anchor_to_times"]


def fit_colour_model(blocks: Any, curves: list, ge: Any, times: np.ndarray, ref: int, mode: str, *, low: float,
                     high: float, floor: float, path: str, seed: int, ransac_iter: int,
                     info: dict) -> tuple[np.ndarray, list]:
    """The matrices of :func:`~derender.hdr.stabilize.method.stabilize_aligned`: ``H_j`` to frame
    ``ref`` (``mode="reference"``) or the joint ``K_j`` (``mode="joint"``) from the sampled
    ``blocks`` through the linearisations ``curves``, anchored to the ``times`` when the gamma
    estimate ``ge`` found that the exposures follow them, grey-balanced when
    :data:`~derender.hdr.stabilize.grey_balance.GREY_BALANCE` is on. ``info`` (the
    stabilisation's) receives ``"colour_model"``, ``"gamma_level"`` and ``"grey_balance"``.
    Returns ``(matrices (N, 3, 3), how)``, ``how`` per frame how its matrix was obtained."""
    n = np.asarray(times).shape[0]
    if mode == "reference":
        info["colour_model"] = {}
        mats, how = colour_matrices_to_reference(blocks, curves, ref, low=low, high=high, floor=floor,
                                                path=path, seed=seed, n_iter=ransac_iter, times=times,
                                                info=info["colour_model"])
    else:
        info["colour_model"] = {}
        mats = joint_colour_matrices(blocks, curves, times, low=low, high=high, floor=floor, seed=seed,
                                    n_iter=ransac_iter, info=info["colour_model"])
        how = ["joint"] * n
    if "follows_times" in ge.info:
        info["gamma_level"] = {k: ge.info[k] for k in ("level_gain", "follows_times", "time_residuals")}
    if ge.info.get("follows_times") and ge.method == "times":
        mats = anchor_to_times(mats, times, ref if mode == "reference" else None)
        info["gamma_level"]["anchored_to_times"] = True
    if gb.GREY_BALANCE:
        gains, info["grey_balance"] = gb.grey_balance(blocks, curves, mats, low=low, high=high)
        mats = np.asarray(mats, dtype=np.float64) * gains[None, :, None]      # D M_j
    return mats, how


def anchor_to_times(mats: np.ndarray, times: np.ndarray, reference: int | None) -> np.ndarray:
    """The matrices rescaled so that their luminance gain on white follows the exposure times:
    ``lum(H_j 1) = t_ref / t_j`` (``reference`` given, :func:`colour_matrices_to_reference`), or
    ``lum(K_j 1)`` equal for every frame, their mean (``reference=None``,
    :func:`joint_colour_matrices`). Colour (each matrix's shape) is kept, only its scale changes.

    Used when the bracket's exposures follow its times (``GammaEstimate.info["follows_times"]``,
    :func:`~derender.hdr.stabilize.exponents.estimate_gammas_blocks`: one rendering, the gammas'
    level set from the times): the fitted scale of a frame far from the reference is then worse
    than the times' (on a pure gamma-2.2 camera at 2 EV, the shortest frames' fits, 8-10 stops from
    the reference through blocks at codes near 11, carry 0.935-0.941 of the time ratio: the
    convexity of ``J^gamma`` lifts the mean of noisy dark codes)."""
    m = np.array(mats, dtype=np.float64, copy=True)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    lum = np.einsum("c,jcd->j", _W, m)          # lum(M_j 1)
    if not np.all(np.isfinite(lum)) or np.any(lum <= 0):
        return m
    target = t[reference] / t if reference is not None else np.full(t.shape, float(np.mean(lum)))
    return m * (target / lum)[:, None, None]
