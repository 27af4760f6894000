"""The demosaic's interpolation error as a variance term, estimated from the merged mosaic itself.

The merge's noise variance (:mod:`derender.raw.optimal`) is exact for the demosaiced *true*
mosaic, but a user compares the output with the scene, and two of every pixel's three colours
are interpolated from its neighbours: where the scene has texture that guess is wrong by more
than the noise (against the scene the noise-only sigma's 95 % interval covers 0.55-0.64 of
the pixel-channels with Malvar's demosaic on the simulator's brackets, docs/results-raw.md). No statistic of one
merged mosaic gives that error without a model of the scene, but demosaics that interpolate
differently disagree where interpolation is hard, and by about as much as they err there.
The term added to the variance of output ``o`` (demosaic ``m``) at every pixel and channel is

    Var_interp[o] = sum_a k_{m,a} (o - o_a)^2                                   (1)

over two other demosaics ``a`` of the same merged, white-balanced mosaic put through the same
matrix (:data:`INTERPOLATION_ESTIMATES`): the bilinear demosaic, whose error at an edge is
large and in its direction, and one edge-directed or gradient-corrected demosaic, whose
disagreement with ``o`` marks the pixels where even a good guess is uncertain. Per pixel
(not smoothed): the interpolation error is heavy-tailed within a neighbourhood, so a local
scale, even the true error's 3x3 mean square, covers 0.61 at 50 % when scaled to cover 0.95
(measured); the per-pixel disagreements follow the error closely enough to hold both
intervals. At a photosite's own colour every demosaic keeps the sample, so the term is 0 there.
The disagreement also holds the two demosaics' different response to the noise (a share of the
noise variance counted twice in flat regions); the weights ``k`` are fitted with it.

The weights were fitted on tuning brackets only -- nikon-d5100, ``outdoor`` and ``indoor``
scenes, seed 3, 256x192, 5 exposures, camera RGB, the white-balanced demosaic of every output
space (refitted after that change: the weights fitted on the unbalanced camera-RGB demosaic
covered the tuning brackets 0.932-0.938 at 95 % once the demosaic saw the balanced mosaic) --
by a grid search (step 0.04) minimising the sum of
``|coverage95 - 0.95| + |coverage50 - 0.50|`` against the scene; the held-out brackets (the
``night`` scene, the sigma-sd-merrill camera, other seeds) are reported in
docs/results-raw.md. This is an empirical calibration, not an exact variance: it is measured
on the simulator's scenes and optics only (on the one real DNG, whose lens is softer, the
term is 17 % of a pixel's variance in median, against about 70 % on the simulator's scenes;
no truth there says whether it holds).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

__all__ = ["INTERPOLATION_ESTIMATES", "VARIANCE_TERMS", "interpolation_variance"]

#: What a RAW merge's variance holds: ``"total"`` (noise and the demosaic's interpolation error,
#: eq. 1; what holds against the scene) or ``"noise"`` (the merge's noise only, exact against
#: the demosaiced true mosaic).
VARIANCE_TERMS = ("total", "noise")

#: Per demosaic of the output, the other demosaics of eq. (1) and their weights ``k`` (fitted on
#: the tuning brackets, module docstring).
INTERPOLATION_ESTIMATES = {
    "malvar2004": (("bilinear", 0.68), ("menon2007", 1.08)),
    "menon2007": (("bilinear", 0.32), ("malvar2004", 0.52)),
    "ahd": (("bilinear", 0.28), ("malvar2004", 0.28)),
    "bilinear": (("malvar2004", 0.96), ("menon2007", 0.85)),
}


def interpolation_variance(radiance: np.ndarray, others: Mapping[str, np.ndarray], method: str) -> np.ndarray:
    """Eq. (1): the interpolation-error variance of ``radiance`` (H, W, 3), demosaiced by
    ``method``, from ``others`` (the demosaics of :data:`INTERPOLATION_ESTIMATES` ``[method]``
    of the same mosaic, same white balance and matrix, by name): (H, W, 3) float32, >= 0."""
    o = np.asarray(radiance, np.float32)
    total = np.zeros(o.shape, np.float32)
    for name, k in INTERPOLATION_ESTIMATES[method]:
        e = o - np.asarray(others[name], np.float32)
        total += np.float32(k) * e * e
    return total
