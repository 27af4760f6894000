"""Is a variance honest? Coverage of central intervals and standardised errors against the truth.

A method that reports a per-pixel variance ``s_i^2`` for its radiance ``r_i`` promises that
the error ``r_i - g_i`` behaves like a draw of ``N(0, s_i^2)``. The radiance is known only up
to a colour transform, so the result is first mapped onto the truth by the same trimmed 3x3
fit as the relative error of :func:`derender.evaluation.metrics.relative_errors` (``fit``:
``"matrix"``, ``"scale"`` or ``"none"``), and the variance is carried through that map,
``Var[(M r)_c] = sum_k M_ck^2 s_k^2`` (channels taken as independent, as every method of
derender reports them). Per pixel-channel

    z = ((M r)_c - g_c) / sqrt(Var[(M r)_c]),

and the central ``p`` interval covers the truth when ``|z| <= Phi^-1((1 + p) / 2)``. A
calibrated variance gives coverage ``p`` at every level and a median ``|z|`` of
``Phi^-1(0.75) = 0.674``; a variance too small by a factor ``c^2`` gives a median ``|z|``
``c`` times larger (the reliability diagram of the docs plots coverage against ``p``).

The errors of a merge are heavier-tailed than a Gaussian, most of all at edges (the largest
errors sit where the truth changes within a pixel). The share of pixel-channels with
``|z| > 3`` (0.0027 for a Gaussian) is reported over all of them and split into **edge**
pixels (the :data:`EDGE_SHARE` of pixels with the largest gradient of the truth's log
luminance, ``|grad ln(mean_c g + 1e-3 mean g)|``, central differences) and **flat** ones (the rest).

Pixel-channels whose variance is zero or not finite cannot be scored; they are counted
(``n_unscored``). With a merge mask (``derender merge --mask``), pixels over-exposed even in
the shortest frame are reported on their own: their value is a bound, not a measurement.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "chart_model",
    "COVERAGE_LEVELS",
    "EDGE_SHARE",
    "edge_pixels",
    "coverage_scores",
    "coverage_table",
    "uncertainty_experiment",
]

#: Central-interval probabilities reported by ``derender evaluate --variance``.
COVERAGE_LEVELS = (0.5, 0.8, 0.95, 0.99)


#: The share of pixels counted as edge pixels (largest log-luminance gradient of the truth).
EDGE_SHARE = 0.10


def edge_pixels(truth: np.ndarray, share: float = EDGE_SHARE) -> np.ndarray:
    """(H, W) bool: the ``share`` of pixels of ``truth`` (H, W, 3) with the largest gradient of
    ``ln(mean_c g + 1e-3 mean(g))`` (central differences; module docstring)."""
    g = np.asarray(truth, dtype=np.float64)
    lum = g.mean(axis=-1)
    lg = np.log(np.maximum(lum, 0.0) + 1e-3 * max(float(np.mean(lum)), 1e-30))
    if min(lg.shape) < 2:
        return np.zeros(lg.shape, dtype=bool)
    gy, gx = np.gradient(lg)
    grad = np.hypot(gx, gy)
    return grad >= np.quantile(grad, 1.0 - share)


def _half_widths(levels) -> np.ndarray:
    from scipy.stats import norm

    return norm.ppf(0.5 + 0.5 * np.asarray(levels, dtype=np.float64))


def coverage_scores(result: Any, variance: Any, truth: Any, fit: str = "matrix",
                    mask: np.ndarray | None = None, levels=COVERAGE_LEVELS) -> dict[str, Any]:
    """Coverage of the central ``levels`` intervals and the median ``|z|`` (module docstring).

    ``result``, ``variance``, ``truth``: (H, W, 3) arrays of one shape (linear radiance, its
    per-channel variance, the true radiance); ``mask`` (H, W) bool selects the pixels to
    score (all by default). Returns ``{"coverage": {p: share}, "coverage_rgb": {p: [R, G, B]},
    "median_abs_z", "tail3", "tail3_edge", "tail3_flat", "n", "n_unscored", "matrix", "fit"}``;
    shares are over scored pixel-channels (``tail3*``: the share with ``|z| > 3``, over all, edge
    and flat pixels, :func:`edge_pixels`)."""
    from derender.evaluation.metrics import relative_errors

    r = np.asarray(result, dtype=np.float64)
    v = np.asarray(variance, dtype=np.float64)
    g = np.asarray(truth, dtype=np.float64)
    if not (r.shape == v.shape == g.shape) or r.ndim != 3 or r.shape[-1] != 3:
        raise InputError(f"result {r.shape}, variance {v.shape} and truth {g.shape} must be (H, W, 3) images "
                         "of one size")
    m = np.asarray(relative_errors(r, g, fit=fit)["matrix"], dtype=np.float64)   # fitted on every pixel
    sel = np.ones(r.shape[:2], bool) if mask is None else np.asarray(mask, dtype=bool)
    if sel.shape != r.shape[:2]:
        raise InputError(f"mask shape {sel.shape} differs from image shape {r.shape[:2]}")
    edge = edge_pixels(g)[sel]
    rr, vv, gg = r[sel], v[sel], g[sel]
    mapped = rr @ m.T
    var_mapped = vv @ (m * m).T
    ok = np.isfinite(var_mapped) & (var_mapped > 0) & np.isfinite(mapped) & np.isfinite(gg)
    z = np.full(mapped.shape, np.nan)
    z[ok] = (mapped[ok] - gg[ok]) / np.sqrt(var_mapped[ok])
    az = np.abs(z)
    widths = _half_widths(levels)
    n = int(ok.sum())
    cov = {float(p): (float(np.sum(az[ok] <= w)) / n if n else float("nan")) for p, w in zip(levels, widths)}
    cov_rgb = {float(p): [float(np.sum(az[:, c][ok[:, c]] <= w)) / max(int(ok[:, c].sum()), 1) for c in range(3)]
               for p, w in zip(levels, widths)}
    def tail(rows: np.ndarray) -> float:
        o = ok[rows]
        return float(np.sum(az[rows][o] > 3.0)) / int(o.sum()) if o.any() else float("nan")

    return {"coverage": cov, "coverage_rgb": cov_rgb,
            "median_abs_z": float(np.median(az[ok])) if n else float("nan"),
            "tail3": tail(np.ones(edge.shape, dtype=bool)), "tail3_edge": tail(edge), "tail3_flat": tail(~edge),
            "n": n, "n_unscored": int(ok.size - n), "matrix": m.tolist(), "fit": fit}


def coverage_table(result: Any, variance: Any, truth: Any, fit: str = "matrix",
                   merge_mask: np.ndarray | None = None) -> dict[str, dict[str, Any]]:
    """:func:`coverage_scores` over all pixels, and with a merge mask (``HDRResult.mask``
    codes, or the 0/128/255 PNG of ``derender merge --mask``) split into pixels measured by
    some frame (``"measured"``) and pixels over-exposed in every frame (``"clipped"``), when
    the mask has both."""
    out = {"all": coverage_scores(result, variance, truth, fit=fit)}
    if merge_mask is not None:
        mm = np.asarray(merge_mask)
        clipped = (mm == 128) | (mm == 1)
        if clipped.any() and (~clipped).any():
            out["measured"] = coverage_scores(result, variance, truth, fit=fit, mask=~clipped)
            out["clipped"] = coverage_scores(result, variance, truth, fit=fit, mask=clipped)
    return out


def chart_model(camera: str = "nikon-d5100", n_train: int = 1200, seed: int = 0):
    """Paper 2's GP for ``camera``, calibrated on its simulated chart session (``camera`` style,
    fixed white balance: what ``derender chart-pairs`` + ``calibrate`` give a user), with the
    camera metadata ``calibrate`` stores; ``n_train`` pairs drawn with ``seed``."""
    from derender.camera.chart import chart_pairs
    from derender.derendering.base import fit_model, model_metadata

    pairs = chart_pairs(camera, seed=seed)
    rng = np.random.default_rng(seed)
    sel = rng.choice(pairs.jpeg.shape[0], size=min(n_train, pairs.jpeg.shape[0]), replace=False)
    model = fit_model("gp", pairs.jpeg[sel], pairs.raw[sel], seed=seed, n_train=n_train)
    model.metadata.update(model_metadata(pairs))
    return model


def uncertainty_experiment(families=("paper", "camera", "dslr-lut", "phone-local", "drift"), seeds=(0,),
                           size: tuple[int, int] = (192, 128), exposures: int = 7, camera: str = "nikon-d5100",
                           methods=None, n_train: int = 5000, progress=None) -> list[dict[str, Any]]:
    """``derender experiment uncertainty``: every method that gives a variance, on a bracket of
    every family, scored by :func:`coverage_table`. The de-rendering model is paper 2's GP
    calibrated once on the chart session of the same camera (``camera`` style, fixed white
    balance: what a user of ``derender chart-pairs`` + ``calibrate`` has). Methods without a
    variance are listed with ``gives_variance=False``. Rows: family, held_out, seed, method,
    the 50/80/95/99 % coverages, median abs(z) and the shares with ``|z| > 3`` (all, edge and flat
    pixels: ``tail3``, ``tail3_edge``, ``tail3_flat``) over all pixels, and over pixels measured by
    some frame (``measured_*``) when some are clipped in every frame."""
    from derender.camera import simulate_bracket
    from derender.camera.families import check_family
    from derender.core.types import Stack
    from derender.evaluation.families import TUNING_FAMILIES
    from derender.hdr.registry import METHODS, merge_seeded, method_spec

    methods = list(METHODS) if methods is None else list(methods)
    model = chart_model(camera, n_train)
    rows: list[dict[str, Any]] = []
    for family in families:
        check_family(family)
        for seed in seeds:
            if progress is not None:
                progress(f"{family} seed {seed}")
            b = simulate_bracket(camera, size=size, exposures=exposures, seed=int(seed), family=family)
            stack = Stack(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
            for m in methods:
                spec = method_spec(m)
                row: dict[str, Any] = {"family": family, "held_out": family not in TUNING_FAMILIES, "seed": int(seed),
                                       "method": m, "gives_variance": spec.gives_variance}
                if row["gives_variance"]:
                    opts = {"model": model} if spec.needs_model else {}
                    if spec.has_option("variance"):
                        opts["variance"] = True     # the classic and stabilised merges give it when asked
                    res = merge_seeded(stack, m, int(seed), opts)
                    table = coverage_table(res.radiance, res.variance, b.truth_linear_srgb, merge_mask=res.mask)
                    for part, d in table.items():
                        prefix = "" if part == "all" else f"{part}_"
                        for p, c in d["coverage"].items():
                            row[f"{prefix}cov{int(round(100 * p))}"] = c
                        row[f"{prefix}median_abs_z"] = d["median_abs_z"]
                        for t in ("tail3", "tail3_edge", "tail3_flat"):
                            row[f"{prefix}{t}"] = d[t]
                rows.append(row)
    return rows
