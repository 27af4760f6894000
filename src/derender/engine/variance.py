"""The variance of the classic and stabilised merges: a noise model per frame, combined in the merge.

A table or matrix plan (:class:`~derender.engine.plans.TablePlan`,
:class:`~derender.engine.plans.MatrixPlan`) says what each code of frame ``j`` contributes,
``u_j(z)`` (log radiance ``g(z) - ln t_j`` in Debevec's log domain; ``f^-1(z) / t_j``, or
``M_j L_j(z)`` in the linear one), and with what weight ``w_j``. The merged value is the
weighted mean ``u = sum w_j u_j / sum w_j``. Its variance, per pixel and channel, is the sum of

* **noise** (independent between frames): shot and read noise of the sensor signal
  ``x = L(z) / L(255)`` (the frame's linear value relative to its white),
  ``Var x = SHOT x + READ^2``, through the frame's table;
* **quantisation** (independent): the 8-bit step through the inverse response,
  ``(dL/dz)^2 / 12`` (code units; derivative by central differences of the 256-entry table);
* **frame disagreement** (pipeline changes, curve errors that differ between frames): the
  weighted spread of the frames' own estimates around their mean,
  ``D = sum w_j (u_j - u)^2 / sum w_j``, as the variance of the mean
  ``D r / max(1 - r, R_FLOOR)`` with ``r = sum w_j^2 / (sum w_j)^2`` (1 / effective frames),
  and, for the part of it that is systematic (a pipeline change does not average out),
  ``D`` itself; or, robustly, ``R = sum w_j^2 (u_j - u)^2 / (sum w_j)^2`` (the
  heteroscedasticity-consistent, "sandwich", variance of a weighted mean: each frame's own
  deviation is its error, weighted as the frame is weighted; :data:`INFLATE_ROBUST`);
* **shared model error** (the response curve's shape, the colour matrices: the same in every
  frame, so it does not average out with their number): ``SHARED^2 r^2`` (relative); measured
  on the bracket when the method fits its curves there (:func:`measured_shared`: ``SHARED`` is
  :data:`SHARED_BOOTSTRAP` times the bootstrap spread of the bracket's curve over resampled
  calibration samples, and ``INFLATE`` scales with that spread squared);
* **edges** (errors every frame shares at a pixel because of where it lies: demosaicing, JPEG's
  chroma subsampling and sharpening move an edge by a fraction of a pixel): ``EDGE^2`` times
  the variance of the merged radiance over the pixel's 3x3 neighbourhood, per channel (within
  the engine's band of rows, its first and last rows repeated at the band's ends).

The independent terms combine as ``sum w_j^2 s_j^2 / (sum w_j)^2``; in the matrix merge frame
``j``'s channel ``c`` has ``s_jc^2 = sum_k M_jck^2 s_jk^2`` (channels mixed by ``M_j``). So

    Var u = INFLATE (V_noise + V_quant) + INFLATE_DIS V_dis + INFLATE_SYS D + INFLATE_ROBUST R   (u's own domain)
    Var r = [r^2 if log domain else 1] Var u + SHARED^2 r^2 + EDGE^2 Var_3x3(r)

Where no frame has weight (the saturation policy's bound from the shortest or longest frame)
the value is a bound, not a measurement: ``Var r = CENSORED r^2`` plus that frame's own noise
and quantisation. The constants were chosen on the tuning families (``paper``, ``camera``)
only (docs/uncertainty.md, "The classic and stabilised merges").

Why ``R`` for Debevec's merge (issue 36). ``INFLATE_SYS D`` does not shrink with the number of
frames, and ``D`` weighs a frame's squared deviation by its weight ``w_j``, not by ``w_j^2``:
a few frames of small weight that are far off (a film's toe or shoulder, codes 20-32 and
240-254 on Memorial, off by 0.2-0.8 in ln) dominate ``D`` while they move the weighted mean
little. Measured with Debevec's merge (``D`` after the black floor of
:mod:`derender.engine.weights`): the median ``sqrt D`` is 0.28 on Memorial (16 frames, 1 EV) and
0.18-0.46 on the tuning families' brackets (7 frames at 3 EV, 12 at 1 EV), but the median
``sqrt R`` is 0.058 on Memorial against 0.071-0.115 there: Memorial's frames disagree where
the merge does not listen to them. ``R`` shrinks as ``1 / frames`` when the deviations are
independent between frames, and keeps the 95 % coverage of the tuning families' 12-frame 1 EV
brackets (where ``c D`` was chosen on 7-frame brackets only). The engine's compiled
kernels (:mod:`derender.engine.variance_kernels`) accumulate ``sum w``, ``sum w u``,
``sum w u^2``, ``sum w^2`` and ``sum w^2 s^2`` in the same pass as the radiance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["VarianceModel", "add_edge_term", "EDGE", "METHOD_CONSTANTS", "method_constants", "SHARED_BOOTSTRAP",
           "CURVE_SD_TUNING", "measured_shared", "variance_tables", "matrix_variance_tables", "SOURCES", "source_shares",
           "SHOT", "READ", "SHARED", "scale_relative_variance", "INFLATE", "INFLATE_DIS", "INFLATE_SYS", "INFLATE_ROBUST",
           "CENSORED", "R_FLOOR", "SOURCE_STRIDE", "VAR_CAP"]

#: Shot noise of the sensor signal relative to white: ``Var x = SHOT x`` (a 24 000 e- full well
#: times ~2.4 for white balance and colour-matrix gains).
SHOT = 1e-4
#: Read noise relative to white (sd).
READ = 3e-4
#: Relative sd of the errors every frame shares (curve shape, colour matrices); tuned on
#: ``paper`` and ``camera``.
SHARED = 0.03
#: Factor on the independent terms (noise, quantisation); tuned on ``paper`` and ``camera``.
INFLATE = 1.0
#: Factor on the disagreement term; tuned on ``paper`` and ``camera``.
INFLATE_DIS = 1.0
#: Factor (sd) on the 3x3 local variance of the radiance; tuned on ``paper`` and ``camera``.
EDGE = 1.0
#: Factor on the systematic disagreement ``D``; tuned on ``paper`` and ``camera``.
INFLATE_SYS = 0.0
#: Factor on the robust (sandwich) variance of the weighted mean ``R``; tuned on ``paper`` and ``camera``.
INFLATE_ROBUST = 0.0
#: Relative variance of a bound (a pixel no frame measures).
CENSORED = 1.0
#: Smallest ``1 - r`` in the disagreement term (bounds it at ``D r / R_FLOOR``).
R_FLOOR = 0.25
#: Every SOURCE_STRIDE-th row is split by source for ``info["variance_sources"]``.
SOURCE_STRIDE = 16
#: The sources, in the order of the kernels' ``parts`` planes.
SOURCES = ("noise", "quantisation", "disagreement", "shared", "edges")

_BIG = 1e12

#: ``(INFLATE, INFLATE_DIS, SHARED, EDGE, INFLATE_SYS, INFLATE_ROBUST)`` per method, chosen on the tuning families ``paper`` and
#: ``camera`` only (docs/uncertainty.md); a method not listed takes the module's defaults.
#: Grid search minimising ``(cov50 - 0.5)^2 + 4 (cov95 - 0.95)^2`` over the pixel-channels of 6
#: brackets (``paper``, ``camera`` x seeds 0-2, 192x128, 7 exposures, nikon-d5100), INFLATE >= 1;
#: the stabilised merges then re-chosen (same brackets, pixels measured by some frame) for the line
#: "95 % coverage >= 0.90 on each tuning family, 50 % within 0.40-0.60": a random search of 500
#: and a local grid over all five, penalty ``100 sum max(0, 0.90 - cov95)^2`` + the 50 % excess
#: first (docs/uncertainty.md).
METHOD_CONSTANTS: dict[str, tuple[float, float, float, float, float, float]] = {
    "debevec": (1.0, 0.0, 0.07, 1.0, 0.0, 1.0),
    "robertson": (16.0, 0.0, 0.07, 1.0, 0.05, 0.0),
    "stabilized": (96.0, 0.0, 0.09, 0.3, 0.0, 0.0),
    "stabilized-joint": (32.0, 0.0, 0.0, 0.47, 8.0, 0.0),
}


#: The curve terms measured on the bracket (issue 36), for the methods listed, when the method fits
#: its curves on the bracket: the ``shared`` term's relative sd is this factor times the bracket's
#: bootstrap curve spread ``s`` (:func:`derender.response.debevec1997.bracket_curve_sd`: the sd of
#: the Debevec curve over refits on resampled calibration samples), instead of the prior ``SHARED``
#: of :data:`METHOD_CONSTANTS`; and the noise factor ``INFLATE`` (which, above 1, stands for per-code
#: curve errors of the noise model's shape) is scaled by ``(s / CURVE_SD_TUNING)^2``, at least 1.
#: Chosen on the tuning families only (``paper``, ``camera`` x seeds 0-2, where ``s`` is
#: 0.026-0.029 with Debevec's grid samples, 0.026-0.038 with Robertson's clusters, so both give
#: back about the priors there) by the objective of :data:`METHOD_CONSTANTS` (debevec, robertson)
#: and, for the stabilised merge, its line "95 % coverage >= 0.90 on each tuning family"
#: (docs/uncertainty.md, "What the bracket can measure").
SHARED_BOOTSTRAP: dict[str, float] = {"debevec": 3.0, "robertson": 2.0, "stabilized": 3.5}

#: The bootstrap curve spread of the tuning brackets (mean over ``paper``, ``camera`` x seeds 0-2,
#: 192x128, 7 exposures, nikon-d5100: 0.0261-0.0294), the spread at which :data:`METHOD_CONSTANTS`'
#: ``INFLATE`` applies as chosen.
CURVE_SD_TUNING = 0.0274


def measured_shared(model: "VarianceModel", method: str, spread: float) -> "VarianceModel":
    """``model`` with its curve terms measured on the bracket's curve ``spread`` (for the methods
    of :data:`SHARED_BOOTSTRAP`; others unchanged): ``shared = SHARED_BOOTSTRAP[method] spread``,
    ``inflate = max(1, inflate (spread / CURVE_SD_TUNING)^2)``; ``curve_sd = spread``."""
    if method in SHARED_BOOTSTRAP and np.isfinite(spread) and spread >= 0:
        model.shared = float(SHARED_BOOTSTRAP[method] * spread)
        model.inflate = float(max(INFLATE, model.inflate * (spread / CURVE_SD_TUNING) ** 2))
        model.curve_sd = float(spread)
    return model


def method_constants(method: str | None) -> dict:
    """The :class:`VarianceModel` constants of ``method`` (:data:`METHOD_CONSTANTS`)."""
    a, b, s, e, c, d = METHOD_CONSTANTS.get(method or "", (INFLATE, INFLATE_DIS, SHARED, EDGE, INFLATE_SYS,
                                                          INFLATE_ROBUST))
    return {"inflate": a, "inflate_dis": b, "shared": s, "edge": e, "inflate_sys": c, "inflate_robust": d}


@dataclass
class VarianceModel:
    """What the engine needs to give a table or matrix plan's variance.

    ``noise``, ``quant`` (N, 256, 3) float32: the variance of ``u_j(z)`` from sensor noise and
    quantisation, in the plan's value domain (log domain: relative variance; linear: the
    square of the value tables' units, before any matrix); the constants as the module's
    (``shared`` measured on the bracket by :func:`measured_shared`, ``curve_sd`` then the spread
    it was measured from)."""

    noise: np.ndarray
    quant: np.ndarray
    inflate: float = INFLATE
    inflate_dis: float = INFLATE_DIS
    shared: float = SHARED
    edge: float = EDGE
    inflate_sys: float = INFLATE_SYS
    inflate_robust: float = INFLATE_ROBUST
    censored: float = CENSORED
    r_floor: float = R_FLOOR
    #: The bracket's bootstrap curve spread the ``shared`` term was measured from
    #: (:func:`measured_shared`), or None (the method's prior).
    curve_sd: float | None = None

    def constants(self) -> np.ndarray:
        """``[inflate, inflate_dis, shared^2, censored, r_floor, inflate_sys, inflate_robust]`` float64, as the
        kernels take them."""
        return np.array([self.inflate, self.inflate_dis, self.shared ** 2, self.censored, self.r_floor,
                         self.inflate_sys, self.inflate_robust], dtype=np.float64)


def _noise_quant_linear(lin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise and quantisation variance (N, 256, 3) of linear tables ``lin`` (N, 256, 3), in their units."""
    lin = np.maximum(np.asarray(lin, dtype=np.float64), 0.0)
    white = np.maximum(lin[:, -1:, :], 1e-30)
    x = np.clip(lin / white, 0.0, 1.0)
    noise = (SHOT * x + READ ** 2) * white ** 2
    d = np.gradient(lin, axis=1)
    quant = d * d / 12.0
    return noise, quant


def variance_tables(values: np.ndarray, domain: str, method: str | None = None) -> VarianceModel:
    """The :class:`VarianceModel` of a table plan's ``values`` (N, 256, 3) (``domain`` ``"log"``:
    ``g(z) - ln t_j``; ``"linear"``: ``f^-1(z) / t_j``)."""
    v = np.asarray(values, dtype=np.float64)
    if domain == "log":
        lin = np.exp(np.minimum(v, 80.0))
        noise, quant = _noise_quant_linear(lin)
        l2 = np.maximum(lin * lin, 1e-300)
        noise, quant = noise / l2, quant / l2           # variance of the log (relative variance)
    else:
        noise, quant = _noise_quant_linear(v)
    return VarianceModel(noise=_f32(noise), quant=_f32(quant), **method_constants(method))


def matrix_variance_tables(values: np.ndarray, method: str | None = None) -> VarianceModel:
    """The :class:`VarianceModel` of a matrix plan's linearisation tables (N, 256, 3) (before the matrices)."""
    noise, quant = _noise_quant_linear(values)
    return VarianceModel(noise=_f32(noise), quant=_f32(quant), **method_constants(method))


def _f32(a: np.ndarray) -> np.ndarray:
    a = np.nan_to_num(np.asarray(a, dtype=np.float64), nan=_BIG, posinf=_BIG, neginf=0.0)
    return np.ascontiguousarray(np.clip(a, 0.0, _BIG), dtype=np.float32)


def add_edge_term(radiance: np.ndarray, var: np.ndarray, parts: np.ndarray, edge: float, y0: int, y1: int,
                  row0: int) -> None:
    """Add ``edge^2`` times the 3x3 local variance of ``radiance`` (3, rows, W) float32 (rows
    ``y0:y1`` of the image, at ``y - row0``) to ``var`` (same layout), and write it as the
    ``"edges"`` source of the sampled rows of ``parts``. OpenCV's float32 box filters: the
    engine itself uses :func:`derender.engine.variance_kernels.variance_finish_rows` (float64
    3x3 sums, one compiled pass), since running float32 sums over tall bands carry a
    highlight's rounding down its column into the dark pixels below it."""
    if edge <= 0 or y1 <= y0:
        return
    from derender.core.memory import import_cv2

    cv2 = import_cv2()
    e2 = np.float32(edge * edge)
    a, b = y0 - row0, y1 - row0
    rows = [y for y in range(y0, y1) if y % SOURCE_STRIDE == 0]
    for c in range(3):
        r = np.ascontiguousarray(radiance[c, a:b])
        mu = cv2.boxFilter(r, -1, (3, 3), borderType=cv2.BORDER_REPLICATE)
        m2 = cv2.boxFilter(cv2.multiply(r, r), -1, (3, 3), borderType=cv2.BORDER_REPLICATE)
        lv = cv2.subtract(m2, cv2.multiply(mu, mu))
        np.maximum(lv, 0.0, out=lv)
        lv *= e2
        np.minimum(lv, np.float32(_F32_QUARTER), out=lv)
        v = var[c, a:b]
        v += lv
        np.minimum(v, np.float32(_F32_QUARTER), out=v)
        for y in rows:
            parts[4, y // SOURCE_STRIDE, :, c] = lv[y - y0]


_F32_QUARTER = float(np.finfo(np.float32).max) / 4.0
#: The largest variance written (a quarter of float32's largest value).
VAR_CAP = _F32_QUARTER


def scale_relative_variance(radiance: np.ndarray, var: np.ndarray, parts: np.ndarray, c: int, y0: int) -> None:
    """Channel ``c``'s relative variance ``var`` (rows, W) float32 of image rows ``y0:``, as the
    log-domain kernel writes it, times ``radiance^2`` (same rows, after the exponential), capped
    at ``f32max / 4``; the sampled rows' kernel sources in ``parts`` likewise."""
    from derender.core.memory import import_cv2

    cv2 = import_cv2()
    r2 = cv2.multiply(radiance, radiance)
    cv2.multiply(var, r2, dst=var)
    if not cv2.checkRange(var)[0]:     # r^2 beyond float32 (radiance near exp(88)): the cap
        np.nan_to_num(var, copy=False, nan=_F32_QUARTER, posinf=_F32_QUARTER)
    np.minimum(var, np.float32(_F32_QUARTER), out=var)
    for y in range(y0 + (-y0) % SOURCE_STRIDE, y0 + var.shape[0], SOURCE_STRIDE):
        p = parts[:4, y // SOURCE_STRIDE, :, c]
        p *= r2[y - y0]
        np.nan_to_num(p, copy=False, nan=_F32_QUARTER, posinf=_F32_QUARTER)
        np.minimum(p, np.float32(_F32_QUARTER), out=p)


def source_shares(parts: np.ndarray) -> dict[str, float]:
    """Median share of each source (:data:`SOURCES`) of the variance over the sampled
    pixel-channels ``parts`` (4, ...) with a positive total (``info["variance_sources"]``).
    The shares are one source at a time (float64 total, its reciprocal once): no (5, n) float64
    copy (24 MP: 0.3 s instead of 0.5 s CPU)."""
    p = np.asarray(parts).reshape(len(SOURCES), -1)
    tot = p.sum(axis=0, dtype=np.float64)
    ok = np.isfinite(tot) & (tot > 0)
    if not ok.any():
        return {s: 0.0 for s in SOURCES}
    inv = 1.0 / tot[ok]
    return {s: float(np.median(p[k][ok] * inv)) for k, s in enumerate(SOURCES)}


def new_parts(h: int, w: int) -> np.ndarray:
    """The kernels' ``parts`` planes (5, rows, W, 3) float32 for every :data:`SOURCE_STRIDE`-th row."""
    return np.zeros((len(SOURCES), -(-int(h) // SOURCE_STRIDE), int(w), 3), dtype=np.float32)
