"""Grey balance of the stabilised merges (the neutral axis): pixels the frames render grey come out grey.

Beyond paper 1. A camera renders neutral surfaces with equal codes. The curve model
(:mod:`.filmic`) fits one Debevec & Malik curve per channel, each anchored at
``g_c(128) = 0``, which declares the code ``(128, 128, 128)`` neutral and leaves the colour
balance of every other grey to the shape of three independently fitted curves (on the
real iPhone 6 bracket the untied curves' ``G_R / G_G`` swings between 0.99 and 1.22 from
code to code, and the merged greys came out R/G x1.2-1.3). The stabilised images
``I'_j = H_j L_j`` (eq. 10) are then all in the reference's (or, joint, the average)
rendering, so the *output's* colour balance is a gauge the fit does not determine.

:func:`grey_balance` fixes that gauge with the data: over the fitting blocks
(:mod:`.blocks`) that a frame renders near-neutral (block-mean codes within
:data:`GREY_TOLERANCE` of each other, every pixel's codes in (:data:`~.blocks.FIT_LOW`,
:data:`~.blocks.FIT_HIGH`), inside the registration mask), the stabilised linear values
``v = M_j L_j(z)`` (block means of the linearised codes, ``M_j`` the frame's matrix) give
per frame the medians ``r_jc = median(v_G / v_c)``; the gains are

    D = diag(median_j r_jR, 1, median_j r_jB)

over the frames with at least :data:`GREY_MIN_BLOCKS` such blocks (each frame one vote:
the frames of an auto-white-balance bracket disagree about grey), and every matrix
becomes ``D M_j``. A constant per-channel gain of the output changes no 3x3-mapped score
(:mod:`derender.evaluation.metrics` fits a 3x3 matrix to the truth, which absorbs ``D``),
so it costs nothing against the exact radiance; it moves the greys. What it cannot do is
remove a tint that varies with brightness (curves of different shape); that is the
channel tie's job (:data:`.filmic.CURVE_TIE`), measured in ``docs/paper1.md``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from derender.hdr.stabilize.blocks import FIT_HIGH, FIT_LOW, Blocks
from derender.hdr.stabilize.curves import Curve

__all__ = ["GREY_BALANCE", "GREY_TOLERANCE", "GREY_MIN_BLOCKS", "grey_balance"]


#: Whether :func:`derender.hdr.stabilize.method.stabilize_aligned` grey-balances its matrices.
GREY_BALANCE = True

#: Largest spread of a block's mean codes (max - min over channels, in [0, 1] code units) for
#: the block to count as rendered neutral (8 levels, as the classic merges' balance,
#: :func:`derender.response.curves.neutral_offsets`).
GREY_TOLERANCE = 8.0 / 255.0

#: Fewest neutral blocks a frame needs to vote.
GREY_MIN_BLOCKS = 16


def grey_balance(blocks: Blocks, curves: Sequence[Curve], matrices: np.ndarray, *, low: float = FIT_LOW,
                 high: float = FIT_HIGH, tolerance: float = GREY_TOLERANCE,
                 min_blocks: int = GREY_MIN_BLOCKS) -> tuple[np.ndarray, dict]:
    """The gains ``(g_R, 1, g_B)`` that make the frames' neutral blocks neutral in the output (module docstring).

    ``blocks``: the fitting blocks, codes (N, nb, k, 3) in [0, 1]; ``curves``: per-frame
    linearisations; ``matrices`` (N, 3, 3): ``H_j`` or ``K_j`` (a per-frame scale does not
    change a ratio). Returns ``(gains (3,), info)``; gains are ones when no frame has
    ``min_blocks`` neutral blocks (``info["frames"]`` lists the voting frames and their ratios).
    """
    codes = np.asarray(blocks.codes, dtype=np.float64)
    n = codes.shape[0]
    mean = codes.mean(axis=2)                                            # (N, nb, 3)
    grey = (mean.max(axis=-1) - mean.min(axis=-1)) <= tolerance
    grey &= (blocks.bmin > low) & (blocks.bmax < high) & np.asarray(blocks.valid, dtype=bool)
    votes, used = [], []
    for j in range(n):
        sel = np.flatnonzero(grey[j])
        if sel.size < int(min_blocks):
            continue
        lin = np.asarray(curves[j].lin(codes[j, sel]), dtype=np.float64).mean(axis=1)   # (m, 3)
        v = lin @ np.asarray(matrices[j], dtype=np.float64).T
        ok = (v > 0).all(axis=-1)
        if int(ok.sum()) < int(min_blocks):
            continue
        v = v[ok]
        votes.append([float(np.median(v[:, 1] / v[:, 0])), float(np.median(v[:, 1] / v[:, 2]))])
        used.append({"frame": j, "blocks": int(ok.sum()), "r_over_g": 1.0 / votes[-1][0],
                     "b_over_g": 1.0 / votes[-1][1]})
    gains = np.ones(3)
    if votes:
        r = np.median(np.asarray(votes), axis=0)
        gains[0], gains[2] = r[0], r[1]
    return gains, {"gains": gains.tolist(), "frames": used, "tolerance": float(tolerance)}
