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

The disagreements see the *luminance* texture (Malvar's correction against the bilinear guess is
the own colour's Laplacian) but not the scene's *colour* texture in camera RGB, which adds its
own error (Malvar's green at a red photosite errs by about ``alpha L2[G - R]``, the colour
difference's distance-2 Laplacian). How much colour texture a scene has in camera RGB depends on
the camera: the simulator's scenes have 2.5-3.7x less of it (median ratio of colour to luminance Laplacian) through the sigma-sd-merrill's
overlapping sensitivities than through the nikon-d5100's (the same scenes; the matrix to sRGB
amplifies it back, singular values up to 11.9 against 2.3), and on the noise-free demosaic the
factor on eq. (1) (its weights below) that makes it cover 0.95 is 3.3-3.8 on the nikon-d5100
against 2.0-2.2 on the sigma-sd-merrill, but 2.3-2.5 against 2.1 once the scene's colour is
blurred (Gaussian, sigma 3 pixels) under its unchanged luminance texture (docs/results-raw.md; benchmarks/bench_raw_noise.py
``--colour-texture``). Weights fitted on the nikon-d5100 alone had absorbed its colour
error into eq. (1) and overstated the error on the sigma-sd-merrill, most where its matrix
amplifies. Where :data:`CHROMA_ESTIMATES` has a demosaic, a colour-texture term is added,

    Var_chroma[o] = k_c (M Pi_p P M^-1 L2[s])_o^2                                 (2)

with ``s`` a demosaic of the mosaic in the output space (Menon's for Malvar's output, its own
for Menon's), ``L2`` the distance-2 Laplacian (centre minus the mean of the four samples 2 away),
``M^-1`` back to white-balanced camera RGB, ``P = I - 11^T / 3`` the colour part (the mean over
the channels removed), ``Pi_p`` the photosite's own colour set to 0 (kept, not interpolated) and
``M`` the output matrix: a vector, so it reaches the output with its own per-pixel correlation
as eq. (1)'s disagreements do.

The weights were fitted on tuning brackets only -- nikon-d5100, ``outdoor`` and ``indoor``
scenes, seed 3, 256x192, 5 exposures -- by Nelder-Mead minimising the sum over camera RGB,
linear sRGB and XYZ of ``|coverage95 - 0.95| + |coverage50 - 0.50|`` against the scene; the
held-out brackets (the ``night`` scene, the sigma-sd-merrill camera, other seeds) are reported in
docs/results-raw.md. (Before eq. (2) the weights were fitted in camera RGB alone, by a grid.)
This is an empirical calibration, not an exact variance: it is measured
on the simulator's scenes and optics only (on the one real DNG, whose lens is softer, the
term is 17 % of a pixel's variance in median, against about 70 % on the simulator's scenes;
no truth there says whether it holds).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

__all__ = ["INTERPOLATION_ESTIMATES", "CHROMA_ESTIMATES", "chroma_phase_matrices", "VARIANCE_TERMS", "interpolation_variance",
           "chroma_texture"]

#: What a RAW merge's variance holds: ``"total"`` (noise and the demosaic's interpolation error,
#: eq. 1; what holds against the scene) or ``"noise"`` (the merge's noise only, exact against
#: the demosaiced true mosaic).
VARIANCE_TERMS = ("total", "noise")

#: Per demosaic of the output, the other demosaics of eq. (1) and their weights ``k`` (fitted on
#: the tuning brackets, module docstring).
INTERPOLATION_ESTIMATES = {
    "malvar2004": (("bilinear", 0.30), ("menon2007", 0.89)),
    "menon2007": (("bilinear", 0.26), ("malvar2004", 0.22)),
    "ahd": (("bilinear", 0.28), ("malvar2004", 0.28)),
    "bilinear": (("malvar2004", 0.96), ("menon2007", 0.85)),
}

#: Per demosaic of the output, the demosaic whose colour texture is eq. (2)'s ``s`` and its
#: weight ``k_c`` (fitted with :data:`INTERPOLATION_ESTIMATES` on the tuning brackets; AHD and
#: the bilinear demosaic have none: a refit with it did not raise AHD's held-out coverage).
CHROMA_ESTIMATES = {
    "malvar2004": ("menon2007", 0.78),
    "menon2007": ("menon2007", 0.39),
}


def chroma_phase_matrices(matrix: np.ndarray, pattern: str) -> np.ndarray:
    """Eq. (2)'s matrix ``M Pi_p P M^-1`` at each CFA phase ``p`` (``matrix`` ``M``: white-balanced
    camera RGB to the output; ``pattern``, e.g. ``"RGGB"``): the mean over the channels removed,
    the photosite's own colour set to 0, back through ``M``: (2, 2, 3, 3) float32, indexed by
    the row and column parity."""
    m = np.asarray(matrix, np.float64)
    back = (np.eye(3) - 1.0 / 3.0) @ np.linalg.inv(m)             # P M^-1
    lut = {"R": 0, "G": 1, "B": 2}
    p = pattern.upper()
    out = np.empty((2, 2, 3, 3), np.float32)
    for a in range(2):
        for b in range(2):
            keep = np.ones(3)
            keep[lut[p[2 * a + b]]] = 0.0
            out[a, b] = (m @ np.diag(keep) @ back).astype(np.float32)
    return out


def chroma_texture(image: np.ndarray, matrix: np.ndarray, pattern: str) -> np.ndarray:
    """Eq. (2)'s vector ``M Pi_p P M^-1 L2[s]`` of an (H, W, 3) image ``s`` in the output space
    (``matrix`` ``M``: white-balanced camera RGB to the output): the distance-2 Laplacian of
    every channel (borders mirrored), taken back to balanced camera RGB, its mean over the
    channels removed, the photosite's own colour (``pattern``, e.g. ``"RGGB"``) set to 0, and
    put through ``M`` again (:func:`chroma_phase_matrices`): (H, W, 3) float32. The merge adds
    it without this array, in :func:`derender.raw.kernels.interpolation_rows`."""
    s = np.asarray(image, np.float32)
    pad = np.pad(s, ((2, 2), (2, 2), (0, 0)), mode="reflect")
    h, w = s.shape[:2]
    lap = s - np.float32(0.25) * (pad[:h, 2:w + 2] + pad[4:h + 4, 2:w + 2] + pad[2:h + 2, :w] + pad[2:h + 2, 4:w + 4])
    phase = chroma_phase_matrices(matrix, pattern)
    out = np.empty_like(lap)
    for a in range(2):
        for b in range(2):
            out[a::2, b::2] = lap[a::2, b::2] @ phase[a, b].T
    return out


def interpolation_variance(radiance: np.ndarray, others: Mapping[str, np.ndarray], method: str,
                           matrix: np.ndarray | None = None, pattern: str | None = None) -> np.ndarray:
    """Eqs. (1)-(2): the interpolation-error variance of ``radiance`` (H, W, 3), demosaiced by
    ``method``, from ``others`` (the demosaics of :data:`INTERPOLATION_ESTIMATES` ``[method]``
    of the same mosaic, same white balance and matrix, by name) and, where
    :data:`CHROMA_ESTIMATES` has ``method`` and ``matrix`` (white-balanced camera RGB to the
    output) and ``pattern`` are given, the colour-texture term of eq. (2): (H, W, 3) float32, >= 0."""
    o = np.asarray(radiance, np.float32)
    total = np.zeros(o.shape, np.float32)
    for name, k in INTERPOLATION_ESTIMATES[method]:
        e = o - np.asarray(others[name], np.float32)
        total += np.float32(k) * e * e
    if method in CHROMA_ESTIMATES and matrix is not None and pattern is not None:
        name, k = CHROMA_ESTIMATES[method]
        c = chroma_texture(o if name == method else others[name], matrix, pattern)
        total += np.float32(k) * c * c
    return total
