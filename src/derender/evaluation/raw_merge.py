"""RAW merges against the simulator's exact truth: frames, true noise, truths and scores.

A simulated bracket (:func:`derender.camera.simulate_bracket`) knows the noise-free mosaic
``X`` (normalised sensor units per second) and the sensor's noise (gain ``(white - black) /
full_well`` DN per electron; read noise ``read_noise`` DN plus the ADC's rounding, ``1/12``
DN^2). Two truths are scored against:

* ``truth_linear_srgb`` -- the scene itself at every pixel (what ``truth.exr`` holds); a RAW
  merge's error against it includes the demosaic's interpolation error, which no merge of the
  mosaic removes and no noise variance describes;
* :func:`demosaiced_truth` -- the same white balance, demosaic (Malvar) and colour matrix
  applied to the *true* mosaic: what a merge would give without noise, so the error against
  it is the merge's alone (the exact truth for the estimator and its variance).

:func:`raw_scores` reports the median and 90th percentile of the per-pixel relative error
``||r - g|| / ||g||`` (no fitting: the units are exact), over the pixels the merge measured
(mask 0), the median in the **darkest decade** (positive truth luminance within 10x of its
1st percentile) and in the **brightest unclipped decade** (within 10x below the 99th percentile of
the measured pixels), and the coverage of the central 50 % and 95 % intervals of the
variance, ``|r - g| <= z sigma`` per channel.

On a moving bracket (``motion=``) :func:`measured_pixels` gives, from the simulator's truth,
the reference's pixels that some frame measures: the reference, or a frame that sees there
the same scene (no object over the pixel's neighbourhood in it nor in the reference), with
every photosite of that neighbourhood unclipped. Elsewhere no merge has a measurement of the
reference's scene, only bounds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.core.types import RawFrame

__all__ = [
    "bracket_raw_frames",
    "true_noise",
    "demosaiced_truth",
    "raw_scores",
    "measured_pixels",
]


def bracket_raw_frames(bracket: Any) -> list[RawFrame]:
    """The bracket's mosaics as :class:`RawFrame` objects, as LibRaw reads its DNG files."""
    cam = bracket.camera
    return [RawFrame(mosaic=np.asarray(m), cfa_pattern="RGGB", black_level=np.full((2, 2), float(cam.black_level)),
                     white_level=float(cam.white_level), as_shot_wb=np.asarray(bracket.wb_true, dtype=np.float64),
                     xyz_to_camera=np.asarray(bracket.xyz_to_camera), exposure_time=float(t),
                     make=cam.make, model=cam.model)
            for m, t in zip(bracket.mosaics, bracket.times)]


def true_noise(camera: Any) -> tuple[float, float]:
    """The simulator's ``(gain DN/electron, read noise DN with the rounding's 1/12 DN^2)``."""
    gain = (camera.white_level - camera.black_level) / camera.full_well
    return float(gain), float(np.sqrt(camera.read_noise ** 2 + 1.0 / 12.0))


def demosaiced_truth(bracket: Any, result_info: dict) -> np.ndarray:
    """The merge's noise-free output: its white balance, demosaic and matrix (``result_info``) on the
    true mosaic (``bracket.camera_rgb_per_s`` sampled on the CFA; a lens falloff the simulator put
    on the sensor, :func:`derender.camera.luminance.radial_falloff`, is not in it: multiply it in
    first for such a bracket)."""
    from derender.camera.sensor import mosaic_signal
    from derender.raw.mosaic import cfa_channel_index, demosaic_bayer

    x = mosaic_signal(bracket.camera_rgb_per_s)
    pattern = result_info["cfa_pattern"]
    gains = np.asarray(result_info["wb_multipliers"], dtype=np.float64)[cfa_channel_index(x.shape, pattern)]
    cam = demosaic_bayer(x * gains, pattern, result_info.get("demosaic", "malvar2004")).astype(np.float64)
    m = np.asarray(result_info["output_matrix"], dtype=np.float64)
    return (cam.reshape(-1, 3) @ m.T).reshape(cam.shape)


def raw_scores(radiance: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
               variance: np.ndarray | None = None, border: int = 3) -> dict:
    """Relative errors (all, darkest decade, brightest unclipped decade) and coverages (module docstring);
    ``border`` pixels at the edges are left out (the demosaic reflects there)."""
    from derender.core.colorimetry import luminance

    sl = (slice(border, -border or None), slice(border, -border or None))
    r = np.asarray(radiance, dtype=np.float64)[sl]
    g = np.asarray(truth, dtype=np.float64)[sl]
    ok = np.ones(r.shape[:2], bool) if mask is None else (np.asarray(mask)[sl] == 0)
    n2 = np.sum(g * g, axis=-1)
    ok &= n2 > 0
    e = np.sqrt(np.sum((r - g) ** 2, axis=-1) / np.where(n2 > 0, n2, 1.0))
    lum = luminance(g)
    pos = ok & (lum > 0)
    lo = float(np.percentile(lum[pos], 1))
    hi = float(np.percentile(lum[pos], 99))
    dark = pos & (lum >= lo) & (lum <= 10 * lo)
    bright = pos & (lum >= hi / 10) & (lum <= hi)
    out = {"median": float(np.median(e[ok])), "p90": float(np.percentile(e[ok], 90)),
           "dark_decade": float(np.median(e[dark])), "bright_decade": float(np.median(e[bright])),
           "n": int(ok.sum())}
    if variance is not None:
        v = np.asarray(variance, dtype=np.float64)[sl][ok]
        d = np.abs(r[ok] - g[ok])
        good = v > 0
        z = d[good] / np.sqrt(v[good])
        out["coverage50"] = float(np.mean(z <= 0.6744897501960817))
        out["coverage95"] = float(np.mean(z <= 1.959963984540054))
    return out


def measured_pixels(bracket: Any, reach: int = 2, sigmas: float = 3.0) -> np.ndarray:
    """(H, W) bool, on the reference frame's grid of a moving bracket (``bracket.params["motion"]``,
    :mod:`derender.camera.motion`): the pixels ``p`` that some frame ``j`` measures. Frame ``j``
    measures ``p`` when

    * it is ghost-free there: ``j`` is the reference, or no object that moved between frame
      ``j`` and the reference covers the ``(2 reach + 1)^2`` pixels around ``p`` (the demosaic's
      support; each disc grown by 1 px, as :func:`derender.camera.motion.motion_zones`) in
      either, in scene coordinates, and ``p`` lies inside frame ``j`` (``p - shift_j``);
    * it is unclipped there: every channel of the noise-free signal over that neighbourhood,
      ``X t_j`` (``X`` = ``bracket.camera_rgb_per_s``, the reference's view, which a
      ghost-free frame shares; 1 = white), is below white by ``sigmas`` times its
      Poisson-Gaussian standard deviation.
    """
    from scipy.ndimage import maximum_filter

    mo = bracket.params["motion"]
    ref = int(mo["reference"])
    margin = int(mo["canvas_margin"])
    shifts = np.asarray(mo["shifts_dy_dx"], dtype=np.int64)
    paths = np.asarray(mo["object_paths_yx"], dtype=np.float64).reshape(-1, len(shifts), 2)
    r = float(mo["radius_px"]) + 1.0
    x = np.asarray(bracket.camera_rgb_per_s, dtype=np.float64)
    h, w = x.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    size = 2 * int(reach) + 1
    cam = bracket.camera
    sd_read = float(cam.read_noise) / float(cam.white_level - cam.black_level)

    def ghosts(j: int) -> np.ndarray:
        """Where an object that moved between frame j and the reference is in either (grown)."""
        out = np.zeros((h, w), bool)
        for path in paths:                         # canvas centres; reference pixel p is canvas p + margin
            if np.array_equal(path[j], path[ref]):
                continue
            for c in (path[j], path[ref]):
                out |= (yy + margin + 0.5 - c[0]) ** 2 + (xx + margin + 0.5 - c[1]) ** 2 <= r * r
        return maximum_filter(out, size=size, mode="nearest")

    peak = maximum_filter(x.max(axis=-1), size=size, mode="nearest")
    out = np.zeros((h, w), bool)
    for j, t in enumerate(np.asarray(bracket.times, dtype=np.float64)):
        level = peak * t
        unclipped = level + sigmas * np.sqrt(level / float(cam.full_well) + sd_read ** 2) < 1.0
        if j == ref:
            out |= unclipped
            continue
        dy, dx = shifts[j] - shifts[ref]
        inside = (yy - dy >= 0) & (yy - dy < h) & (xx - dx >= 0) & (xx - dx < w)
        out |= unclipped & inside & ~ghosts(j)
    return out
