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

__all__ = ["GREY_BALANCE", "GREY_TOLERANCE", "GREY_MIN_BLOCKS", "GREY_MAX_GAIN", "grey_balance"]


#: Whether :func:`derender.hdr.stabilize.method.stabilize_aligned` grey-balances its matrices.
GREY_BALANCE = True

#: Largest spread of a block's mean codes (max - min over channels, in [0, 1] code units) for
#: the block to count as rendered neutral (8 levels, as the classic merges' balance,
#: :func:`derender.response.curves.neutral_offsets`).
GREY_TOLERANCE = 8.0 / 255.0

#: Fewest neutral blocks a frame needs to vote.
GREY_MIN_BLOCKS = 16

#: Largest plausible gain, either way (from 1 / GREY_MAX_GAIN to GREY_MAX_GAIN). The untied curves'
#: anchoring leaves casts of 1.2-1.3 (the iPhone 6 bracket: gains 0.78 / 1.01 and 0.83 / 1.12);
#: still brackets of the tuning families give 0.81-1.09. A gain beyond 1.5 says that the blocks
#: voting are not neutral surfaces of a consistent fit: on moving brackets (before this bound)
#: the votes reached 0.34 .. 14.8 (``dslr-lut``, ``stabilized-joint``), and the balance then
#: moved the ghost test's brightest-channel bounds (static-zone error 0.221 -> 0.397). Then the
#: output is left unbalanced (gains 1) and ``info["rejected"]`` says why.
GREY_MAX_GAIN = 1.5


def grey_balance(blocks: Blocks, curves: Sequence[Curve], matrices: np.ndarray, *, low: float = FIT_LOW,
                 high: float = FIT_HIGH, tolerance: float = GREY_TOLERANCE,
                 min_blocks: int = GREY_MIN_BLOCKS, max_gain: float = GREY_MAX_GAIN) -> tuple[np.ndarray, dict]:
    """The gains ``(g_R, 1, g_B)`` that make the frames' neutral blocks neutral in the output (module docstring).

    ``blocks``: the fitting blocks, codes (N, nb, k, 3) in [0, 1]; ``curves``: per-frame
    linearisations; ``matrices`` (N, 3, 3): ``H_j`` or ``K_j`` (a per-frame scale does not
    change a ratio). Returns ``(gains (3,), info)``; gains are ones when no frame has
    ``min_blocks`` neutral blocks, or when a gain would lie beyond ``max_gain`` either way
    (``info["rejected"]``; ``info["frames"]`` lists the voting frames and their ratios).
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
    info: dict = {"frames": used, "tolerance": float(tolerance)}
    if votes:
        r = np.median(np.asarray(votes), axis=0)
        if np.all(np.abs(np.log(r)) <= np.log(max_gain)):
            gains[0], gains[2] = r[0], r[1]
        else:
            info["rejected"] = (f"gains R {r[0]:.3g}, B {r[1]:.3g} beyond 1/{max_gain:g}..{max_gain:g}: the blocks "
                                "voting are not neutral surfaces of a consistent fit")
    info["gains"] = gains.tolist()
    return gains, info
