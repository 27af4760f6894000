"""Every HDR method on every camera-pipeline family, beside the oracle and OpenCV.

``derender experiment families`` simulates brackets through each pipeline family of
:mod:`derender.camera.families` (scene kinds x seeds), merges the *same* 8-bit codes with

* each derender method (``debevec``, ``robertson``, ``stabilized``, ``stabilized-joint``),
* OpenCV's peers on the same codes (``opencv-debevec``: ``CalibrateDebevec`` +
  ``MergeDebevec``; ``opencv-robertson``: ``CalibrateRobertson`` + ``MergeRobertson``, OpenCV
  defaults, BGR in and out),
* the oracle that inverts each frame's true pipeline (:func:`derender.evaluation.oracle.oracle_merge_bracket`):
  ``oracle`` with the engine's trapezoid weights, ``oracle-q`` with them divided by each
  code's quantisation variance through the true inverse,

and scores each against the simulator's exact radiance with
:func:`derender.evaluation.metrics.hdr_scores`: PSNR R/G/B/L after one least-squares scale
per plane (paper 1's protocol), the median and 90th percentile of the per-pixel relative
error ``||M r - g|| / ||g||`` after a 3x3 ``M`` fitted with weights ``1/||g||^2`` (every pixel
counts alike), and log-luminance PSNR; once over all pixels and once over the *smooth* pixels
(:func:`smooth_mask`: away from edges, texture and the border), where the camera's
demosaicing and chroma noise reduction, which no merge can undo, leave the truth intact.
Over all pixels these spatial filters dominate: at 192x128 a few dozen pixels on the lamp's
rim set PSNR L, and colour fringes at edges set the relative error, for every method alike.
Rows per (family, method) are means over the brackets, plus the mean difference to
``debevec`` (``dL``) and the ratio of the median relative error to the oracle's.

Tuning and reporting are kept apart (DESIGN.md, "Truth and hold-outs"): the methods'
defaults were chosen on the ``paper`` and ``camera`` families
(:data:`TUNING_FAMILIES`); every other family is a hold-out, and the table says which.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "TUNING_FAMILIES",
    "FAMILY_METHODS",
    "PEERS",
    "MIN_SMOOTH_PIXELS",
    "opencv_merge",
    "smooth_mask",
    "family_comparison",
    "summarise_families",
]

#: Families the methods' defaults were chosen on; all others are held out of tuning.
TUNING_FAMILIES = ("paper", "camera")

#: derender's model-free HDR methods compared on every family.
FAMILY_METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint")

#: Fewest smooth pixels (:func:`smooth_mask`) for the smooth scores; below, they are NaN.
MIN_SMOOTH_PIXELS = 16

#: OpenCV's HDR merges run on the same codes (names as in the tables).
PEERS = ("opencv-debevec", "opencv-robertson")


def opencv_merge(codes: np.ndarray, times: Sequence[float], which: str = "debevec") -> np.ndarray:
    """OpenCV's calibrate + merge (defaults) of an (N, H, W, 3) uint8 RGB stack; radiance RGB float32.

    ``which`` is ``"debevec"`` or ``"robertson"``. OpenCV works in BGR; the result is turned
    back to RGB, and non-finite or negative values (which OpenCV can return for pixels
    no frame exposes) are set to 0, as our merges never produce them.
    """
    from derender.core.memory import import_cv2

    cv2 = import_cv2()
    imgs = [np.ascontiguousarray(c[..., ::-1]) for c in np.asarray(codes, dtype=np.uint8)]
    t = np.asarray(times, dtype=np.float32)
    if which == "debevec":
        resp = cv2.createCalibrateDebevec().process(imgs, t)
        hdr = cv2.createMergeDebevec().process(imgs, t, resp)
    elif which == "robertson":
        resp = cv2.createCalibrateRobertson().process(imgs, t)
        hdr = cv2.createMergeRobertson().process(imgs, t, resp)
    else:
        raise InputError(f"unknown OpenCV merge {which!r}: use 'debevec' or 'robertson'")
    rgb = np.asarray(hdr, dtype=np.float32)[..., ::-1]
    return np.maximum(np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0), 0.0)


def smooth_mask(truth: np.ndarray, sigma: float = 1.5, tol: float = 0.02, border: int = 4) -> np.ndarray:
    """(H, W) bool: pixels whose truth differs from its Gaussian blur (``sigma`` px) by at most
    ``tol`` (relative), at least ``border`` pixels from the image edge: where the in-camera
    demosaicing and chroma denoising (spatial filters of a few pixels) keep the truth."""
    from derender.core.memory import import_cv2

    cv2 = import_cv2()
    g = np.asarray(truth, dtype=np.float64)
    k = int(6 * sigma) | 1
    blurred = cv2.GaussianBlur(g, (k, k), sigma, borderType=cv2.BORDER_REFLECT)
    m = np.linalg.norm(blurred - g, axis=-1) <= tol * np.linalg.norm(g, axis=-1)
    if border > 0:
        m[:border] = m[-border:] = False
        m[:, :border] = m[:, -border:] = False
    return m


def family_comparison(families: Sequence[str] | None = None, *, kinds: Sequence[str] = ("outdoor", "indoor"),
                      seeds: Sequence[int] = (0, 1), size: tuple[int, int] = (192, 128), exposures: int = 7,
                      camera: str = "nikon-d5100", methods: Sequence[str] = FAMILY_METHODS,
                      peers: Sequence[str] = PEERS, oracle: bool = True,
                      progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Score every method (and the peers and the oracle) on brackets of every family.

    Returns one row per (family, bracket, method) with the keys of
    :func:`~derender.evaluation.metrics.hdr_scores` plus ``family``, ``scene``, ``method``,
    ``held_out`` (the family is not one of :data:`TUNING_FAMILIES`), and the scores on the
    :func:`smooth_mask` pixels (``L_smooth``, ``rel_median_smooth``, ``rel_p90_smooth``); see
    :func:`summarise_families` for the per-family means.
    """
    from derender.camera import simulate_bracket
    from derender.camera.families import FAMILIES, check_family
    from derender.core.types import Stack
    from derender.evaluation.metrics import hdr_scores
    from derender.evaluation.oracle import oracle_merge_bracket
    from derender.hdr.registry import merge_seeded

    families = list(FAMILIES) if families is None else [check_family(f) for f in families]
    for p in peers:
        if p not in PEERS:
            raise InputError(f"unknown peer {p!r}: choose from {', '.join(PEERS)}")
    rows: list[dict[str, Any]] = []
    for family in families:
        for kind in kinds:
            for seed in seeds:
                b = simulate_bracket(camera, kind=kind, size=size, exposures=exposures, seed=int(seed), family=family)
                truth = b.truth_linear_srgb
                stack = Stack(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
                smooth = smooth_mask(truth)
                results: dict[str, np.ndarray] = {}
                if oracle:
                    results["oracle"] = oracle_merge_bracket(b).radiance
                    results["oracle-q"] = oracle_merge_bracket(b, quantisation_weights=True).radiance
                for m in methods:
                    results[m] = merge_seeded(stack, m, int(seed)).radiance
                for p in peers:
                    results[p] = opencv_merge(b.jpeg_codes, b.times, p.split("-", 1)[1])
                for m, rad in results.items():
                    sc = hdr_scores(np.asarray(rad), truth)
                    nan = float("nan")
                    sm = (hdr_scores(np.asarray(rad), truth, mask=smooth) if smooth.sum() >= MIN_SMOOTH_PIXELS
                          else {"L": nan, "rel_median": nan, "rel_p90": nan})
                    rows.append({"family": family, "scene": f"{kind}-{seed}", "method": m,
                                 "held_out": family not in TUNING_FAMILIES, **sc,
                                 "L_smooth": sm["L"], "rel_median_smooth": sm["rel_median"],
                                 "rel_p90_smooth": sm["rel_p90"], "smooth_fraction": float(smooth.mean())})
                if progress is not None:
                    line = "  ".join(f"{r['method']} {r['L']:.2f}" for r in rows[-len(results):])
                    progress(f"{family} {kind}-{seed}: PSNR L {line}")
    return rows


def _mean(values: list[float]) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def summarise_families(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (family, method): means over the brackets of PSNR R/G/B/L, relative error median
    and p90, log-luminance PSNR (all pixels), PSNR L and relative error on the smooth pixels;
    ``dL`` = mean PSNR L minus ``debevec``'s on the same brackets; ``rel_to_oracle`` = mean
    median relative error over the oracle's. Means skip NaN (a bracket with too few smooth pixels)."""
    keys = ("R", "G", "B", "L", "rel_median", "rel_p90", "log_psnr_L", "L_smooth", "rel_median_smooth",
            "rel_p90_smooth")
    out: list[dict[str, Any]] = []
    families = list(dict.fromkeys(r["family"] for r in rows))
    for fam in families:
        fr = [r for r in rows if r["family"] == fam]
        methods = list(dict.fromkeys(r["method"] for r in fr))
        means = {m: {k: _mean([r[k] for r in fr if r["method"] == m]) for k in keys} for m in methods}
        for m in methods:
            row = {"family": fam, "held_out": "yes" if fr[0]["held_out"] else "no (tuned)", "method": m,
                   "brackets": sum(r["method"] == m for r in fr), **means[m]}
            row["dL"] = means[m]["L"] - means["debevec"]["L"] if "debevec" in means else float("nan")
            row["rel_to_oracle"] = (means[m]["rel_median"] / means["oracle"]["rel_median"]
                                    if "oracle" in means else float("nan"))
            out.append(row)
    return out
