"""Does a stack obey the constant-response assumption? (paper 1, Sec. 2, eq. 7 and Fig. 2)

Classic merging assumes one fixed response ``f`` per channel for the whole bracket, so
that for every exposure ``i`` and pixel ``p``
``ln(f^-1(J_i(p)) / dt_i) = g(J_i(p)) - ln dt_i = ln E(p)``: plotted against
``ln E`` all exposures should fall on one line of slope 1. When the camera changes
gain, gamma or white balance between exposures (paper 1, Sec. 2), the points spread.

:func:`diagnose_constant_response` computes, for sampled pixels, the pairs
``(x, y_i) = (ln E(p), g(J_i(p)) - ln dt_i)`` with ``ln E`` the Debevec merge
(eq. 6, with the weight below) of the same samples, and the spread figure

``rms = sqrt( sum w_i(p) (y_i(p) - x(p))^2 / sum w_i(p) ) / ln 2``  (in stops, log2),

the weighted RMS distance from the identity line over every exposure, sampled pixel
and channel; also per exposure, per channel, the weighted median of ``|y - x|``
(robust to the few wild points of noisy dark codes) and the weighted mean offset
``y - x`` per exposure and channel (a per-exposure gain or white-balance change
shows up there).

The weight ``w`` is, by default, a "well exposed" trapezoid on the code value
(:func:`~derender.engine.weights.weight_trapezoid` with ``low=0.1, high=0.9, ramp=0.1``):
like the colour-checker patches of the paper's Fig. 2, only codes between 10 % and
90 % of full scale count. Near-black codes would otherwise dominate: there ``g`` is
steep and poorly determined (film toe, black offset; e.g. Debevec's Memorial stack,
whose darkest codes are 13-20, scores 1.3 stops with the hat weight but 0.19 with
this one), which says nothing about the constant-response assumption.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from derender.core.errors import InputError
from derender.core.types import Stack
from derender.engine.weights import get_weight, weight_trapezoid
from derender.response.curves import ResponseCurves, check_usable, grid_positions
from derender.response.debevec1997 import calibrate_debevec

__all__ = [
    "DiagnoseResult",
    "diagnose_constant_response",
    "plot_diagnose",
]


_LN2 = float(np.log(2.0))


@dataclass
class DiagnoseResult:
    """Constant-response diagnosis of a stack (all spreads in stops = log2 units).

    Attributes
    ----------
    log_radiance : numpy.ndarray
        (P, 3) merged ``ln E`` of the sampled pixels (x axis).
    log_estimates : numpy.ndarray
        (N, P, 3) ``g(J_i) - ln dt_i`` per exposure (y axis).
    weights : numpy.ndarray
        (N, P, 3) weights used (0 where not well exposed).
    times : numpy.ndarray
        (N,) exposure times in seconds.
    rms_stops : float
        Overall weighted RMS distance from the identity line.
    median_stops : float
        Weighted median of the absolute distance (robust spread).
    rms_stops_per_exposure, rms_stops_per_channel : numpy.ndarray
        The RMS distance per exposure (N,) and per channel (3,).
    offset_stops : numpy.ndarray
        (N, 3) weighted mean of ``y - x`` per exposure and channel.
    curves : ResponseCurves
        The response curves the estimates were linearised with.
    """

    log_radiance: np.ndarray
    log_estimates: np.ndarray
    weights: np.ndarray
    times: np.ndarray
    rms_stops: float
    median_stops: float
    rms_stops_per_exposure: np.ndarray
    rms_stops_per_channel: np.ndarray
    offset_stops: np.ndarray
    curves: ResponseCurves
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """JSON-friendly numbers (finite floats and lists)."""
        return {
            "rms_stops": float(self.rms_stops),
            "median_stops": float(self.median_stops),
            "rms_stops_per_exposure": [float(v) for v in self.rms_stops_per_exposure],
            "rms_stops_per_channel": [float(v) for v in self.rms_stops_per_channel],
            "offset_stops": [[float(v) for v in row] for row in self.offset_stops],
            "times": [float(t) for t in self.times],
        }


def _wrms(d: np.ndarray, w: np.ndarray, axis) -> np.ndarray:
    sw = w.sum(axis=axis)
    return np.sqrt(np.divide((w * d * d).sum(axis=axis), sw, out=np.zeros_like(sw), where=sw > 0)) / _LN2


def _well_exposed(z: np.ndarray) -> np.ndarray:
    return weight_trapezoid(z, low=0.1, high=0.9, ramp=0.1)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    v, w = values.ravel(), weights.ravel()
    keep = w > 0
    if not keep.any():
        return 0.0
    v, w = v[keep], w[keep]
    order = np.argsort(v, kind="stable")
    cw = np.cumsum(w[order])
    return float(v[order][np.searchsorted(cw, 0.5 * cw[-1])])


def diagnose_constant_response(stack: Stack, curves: ResponseCurves | None = None, n_samples: int = 2000,
                               seed: int = 0, weight: Any = None) -> DiagnoseResult:
    """Spread of ``g(J_i) - ln dt_i`` around the merged ``ln E`` (see module docstring).

    ``curves`` defaults to :func:`~derender.response.calibrate_debevec` of the stack
    (the best single fixed response); samples are ``n_samples`` grid positions;
    ``weight`` (name or callable on [0, 1]) defaults to the well-exposed trapezoid
    of the module docstring and serves both the merge of ``x`` and the statistics.
    """
    if not isinstance(stack, Stack):
        raise InputError(f"expected a Stack, got {type(stack).__name__}")
    check_usable(stack)
    if curves is None:
        curves = calibrate_debevec(stack, seed=seed)
    n, h, w_, _ = stack.images.shape
    ys, xs = grid_positions(h, w_, n_samples, seed)
    vals = stack.images[:, ys, xs, :].astype(np.float32)  # (N, P, 3)
    y = curves.log_linearise(vals).astype(np.float64) - np.log(stack.times)[:, None, None]
    wts = np.asarray(get_weight(_well_exposed if weight is None else weight)(vals), dtype=np.float64)
    sw = wts.sum(axis=0)
    x = np.divide((wts * y).sum(axis=0), sw, out=np.zeros_like(sw), where=sw > 0)
    d = y - x[None]
    total = float(wts.sum())
    rms = float(np.sqrt((wts * d * d).sum() / total) / _LN2) if total > 0 else 0.0
    median = _weighted_median(np.abs(d), wts) / _LN2
    per_exp = _wrms(d, wts, axis=(1, 2))
    per_ch = _wrms(d, wts, axis=(0, 1))
    swe = wts.sum(axis=1)
    offset = np.divide((wts * d).sum(axis=1), swe, out=np.zeros_like(swe), where=swe > 0) / _LN2
    return DiagnoseResult(
        log_radiance=x, log_estimates=y, weights=wts, times=stack.times.copy(), rms_stops=rms,
        median_stops=median, rms_stops_per_exposure=per_exp, rms_stops_per_channel=per_ch, offset_stops=offset, curves=curves,
        info={"n_samples": int(len(ys)), "seed": int(seed)},
    )


def plot_diagnose(result: DiagnoseResult, path: str | os.PathLike, inputs=(), max_points: int = 20000) -> Path:
    """Paper 1 Fig. 2 style plot: ``g(J_i) - ln dt_i`` against merged ``ln E``, per channel, atomically."""
    from matplotlib import cm
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from derender.io.files import atomic_output

    n = result.log_estimates.shape[0]
    fig = Figure(figsize=(12, 4.2), dpi=110)
    FigureCanvasAgg(fig)
    colours = cm.viridis(np.linspace(0, 1, max(n, 2)))
    rng = np.random.default_rng(0)
    for c, name in enumerate("RGB"):
        ax = fig.add_subplot(1, 3, c + 1)
        xs_all, ys_all, cs_all = [], [], []
        for i in range(n):
            ok = result.weights[i, :, c] > 0
            xs_all.append(result.log_radiance[ok, c])
            ys_all.append(result.log_estimates[i, ok, c])
            cs_all.append(np.repeat(colours[i][None], ok.sum(), axis=0))
        xv = np.concatenate(xs_all) if xs_all else np.zeros(0)
        yv = np.concatenate(ys_all) if ys_all else np.zeros(0)
        cv = np.concatenate(cs_all) if cs_all else np.zeros((0, 4))
        if xv.size > max_points:
            keep = rng.choice(xv.size, max_points, replace=False)
            xv, yv, cv = xv[keep], yv[keep], cv[keep]
        ax.scatter(xv, yv, s=2, c=cv, linewidths=0)
        if xv.size:
            lo, hi = float(min(xv.min(), yv.min())), float(max(xv.max(), yv.max()))
            ax.plot([lo, hi], [lo, hi], "k--", lw=1, label="slope 1")
        ax.set_title(f"{name}: RMS {result.rms_stops_per_channel[c]:.3f} stops")
        ax.set_xlabel("merged ln E")
        ax.set_ylabel("g(J_i) - ln dt_i")
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"Constant-response check: RMS {result.rms_stops:.3f} stops, median {result.median_stops:.3f} "
                 f"over {n} exposures "
                 f"(colour = exposure, short to long)")
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".").lower() or "png")
    return path
