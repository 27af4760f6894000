"""Probabilistic colour de-rendering: p(raw camera colour | 8-bit rendered colour).

Implements paper 2 (``papers/probabilistic-color-derendering.txt``), Sec. 2.2 and 4.1:

* :class:`LocalGPModel` (``"gp"``) -- the *offline local Gaussian process* of Sec. 4:
  k-means (k = 10) on the rendered inputs ``y = code / 255``, one GP per cluster and
  output channel (eq. 1, ``x^c = z^c(y) + eps``), squared-exponential kernel with
  automatic relevance determination (one length-scale per input channel) plus white
  noise, hyper-parameters by maximum marginal likelihood (L-BFGS-B on the exact
  log marginal likelihood and its gradient, Rasmussen & Williams eq. 5.8/5.9). A test
  colour uses the GP of its nearest cluster centre (eq. 2 with D_N(y) = that cluster).
* :class:`PolynomialModel` (``"poly"``) -- the deterministic baseline of Chakrabarti et
  al.: forward model ``y_c = f_c((C x)_c)`` (3x3 linear map, then per-channel monotone
  polynomial curves, here Bernstein polynomials in the sRGB-encoded ``(C x)_c``, fitted
  jointly with a robust loss), inverted numerically (monotone look-up table per channel,
  then C^-1).
* :class:`RBFModel` (``"rbf"``) -- Lin-style radial-basis-function regression from the
  rendered colour to the (log) raw colour: a smoothing thin-plate spline with a linear
  tail (the same linear system as ``scipy.interpolate.RBFInterpolator``).

Output space. Raw values span several decades, so the GP and RBF model the *log* raw
colour ``t = log(max(raw, 0) + eps)`` with ``eps = eps_rel * raw_white`` (``raw_white``
= median raw maximum of bright, unclipped training colours; eps_rel = 1e-4 puts eps
below one 8-bit code step). Rendering errors are multiplicative (quantisation of a
gamma-encoded code is a relative error), so a Gaussian is a far better noise model for
``t`` than for ``raw``, and predictions are scale-equivariant in the raw units. The
Gaussian over ``t`` is returned as the moments of the implied log-normal in raw space:
``mean = exp(mu + s2/2) - eps``, ``var = (exp(s2) - 1) exp(2 mu + s2)``, where ``s2``
includes the noise variance (predictive distribution of an observation). The
log-space Gaussian itself is available from :meth:`LocalGPModel.predict_log`
(``exp(mu) - eps`` is the predictive median).

Two departures from the paper's plain local GP, both to keep the variance calibrated
where the rendering is one-to-many (paper 2, Sec. 2.1 and Fig. 2): colours with a
clipped (255) channel are clustered separately from unclipped ones (optionally one group
per clip pattern), and each GP has an input-dependent noise variance (most-likely heteroscedastic GP, Kersting et al.
2007), bounded at prediction by its range over the training colours. The whole predictive
variance of ``t`` is also capped at the variance of ``t`` over the training colours (a
cluster extrapolating with a huge signal variance otherwise reported log-variances of 40+).

Where the error comes from (measured on the simulated S90 chart, MAP point): 75 % of the
GP's squared relative error is colours with a channel at 255 (18 % of the colours,
relative RMSE 0.48) and 15 % near-black codes (max code <= 6, 5 %, 0.40). On the clipped
colours the GP matches a leave-one-out look-up of the best point per code over all
49,280 pairs (0.47-0.49): that error is the rendering's, not the model's. The ``floor``
row of ``derender experiment derender-table`` (:func:`code_floor_errors`) is the bound no
function of the code can beat on the test colours.

Speed path. :meth:`DerenderModel.predict` computes one prediction per *distinct*
colour (24-bit packed codes; a 2^24 bincount for large images) and gathers. For the
GP and RBF the per-colour prediction is a trilinear interpolation of a table of the
latent ``(mu, log s2)``, evaluated exactly on a rectilinear grid of codes (denser where
the log curve bends, see :func:`table_nodes`; exact at the grid nodes) and expanded
once to every (G, B) code pair, so a colour costs one interpolation along R.
``exact=True`` evaluates the GP/RBF itself (slow; for evaluation). The table is built
at fit time and stored in the model file.

Model files are ``.npz`` (never pickled) with ``format="derender-model"``,
``format_version=2``, ``method``, ``p_*`` parameter arrays and ``metadata_json``.
"""

from __future__ import annotations

import json
import os
import time
import zipfile
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from derender.core.errors import InputError, ModelFileError

__all__ = [
    "model_camera_to_srgb",
    "MODEL_FORMAT",
    "MODEL_FORMAT_VERSION",
    "table_nodes",
    "DerenderModel",
    "finite32",
    "load_model",
    "LocalGPModel",
    "PolynomialModel",
    "RBFModel",
    "MODEL_TYPES",
    "model_metadata",
    "fit_model",
    "relative_rmse",
    "rmse",
    "median_relative_error",
    "code_floor_errors",
    "interval_coverage",
]


def model_camera_to_srgb(model) -> np.ndarray | None:
    """``A = camera_to_srgb @ diag(wb)`` from the model's metadata, or None when absent."""
    meta = getattr(model, "metadata", {}) or {}
    m = meta.get("camera_to_srgb")
    wb = meta.get("wb")
    if m is None or wb is None:
        return None
    m = np.asarray(m, dtype=np.float64).reshape(3, 3)
    wb = np.asarray(wb, dtype=np.float64).reshape(3)
    return m * wb[None, :]


MODEL_FORMAT = "derender-model"


MODEL_FORMAT_VERSION = 2   # 2: GP inputs may be warped (p_input_warp), clip-pattern cluster groups


_MAX_LOG_VAR = 60.0          # cap on the latent log-space variance (keeps moments finite in float32)


_MAX_LOG_MEAN = 80.0         # cap on |latent log mean|


_BINCOUNT_THRESHOLD = 1 << 20  # above this many pixels, find distinct codes by a 2^24 bincount


# ============================================================================ validation
def _check_pairs(jpeg, raw) -> tuple[np.ndarray, np.ndarray]:
    """Validate training pairs: jpeg (N,3) codes in [0,255], raw (N,3) finite floats."""
    try:
        j = np.asarray(jpeg)
        r = np.asarray(raw)
    except Exception as exc:  # pragma: no cover - exotic inputs
        raise InputError(f"training pairs are not arrays: {exc}") from None
    if j.ndim != 2 or j.shape[1] != 3:
        raise InputError(f"jpeg colours must have shape (N, 3), got {j.shape}")
    if r.ndim != 2 or r.shape[1] != 3:
        raise InputError(f"raw colours must have shape (N, 3), got {r.shape}")
    if j.shape[0] != r.shape[0]:
        raise InputError(f"jpeg and raw have different numbers of colours ({j.shape[0]} vs {r.shape[0]})")
    if j.dtype.kind not in "uif" or r.dtype.kind not in "uif":
        raise InputError("jpeg and raw colours must be numeric arrays")
    jf = j.astype(np.float64)
    rf = r.astype(np.float64)
    if not np.all(np.isfinite(jf)):
        raise InputError("jpeg colours contain NaN or inf")
    if not np.all(np.isfinite(rf)):
        raise InputError("raw colours contain NaN or inf")
    if jf.size and (jf.min() < 0 or jf.max() > 255):
        raise InputError(f"jpeg colours must be 8-bit codes in [0, 255], got range "
                         f"[{jf.min():g}, {jf.max():g}]")
    if j.dtype.kind == "f" and jf.size > 30 and jf.max() <= 1.0 and jf.max() > 0:
        raise InputError("jpeg colours look like floats in [0, 1]; pass 8-bit codes 0..255 (value * 255)")
    if jf.shape[0] < 20:
        raise InputError(f"need at least 20 training pairs, got {jf.shape[0]}")
    if not np.any(rf > 0):
        raise InputError("raw colours are all <= 0")
    return jf, rf


def _as_colour_array(x) -> tuple[np.ndarray, bool]:
    """Validate predict input; return (flat (P,3) array, is_codes) -- uint8 codes or float64 in [0,1]."""
    a = np.asarray(x)
    if a.ndim == 0 or a.shape[-1] != 3:
        if a.ndim >= 1 and a.shape[-1] == 4:
            raise InputError("image has 4 channels (alpha?); pass RGB only, e.g. image[..., :3]")
        raise InputError(f"colours must have a last axis of length 3 (RGB), got shape {a.shape}")
    if a.dtype == np.bool_ or a.dtype.kind not in "uif":
        raise InputError(f"colours must be uint8 codes or floats in [0, 1], got dtype {a.dtype}")
    flat = a.reshape(-1, 3)
    if a.dtype == np.uint8:
        return flat, True
    if a.dtype.kind in "ui":
        if a.dtype.itemsize == 2:
            raise InputError(f"{a.dtype} (16-bit) input is not supported: the model is for 8-bit rendered "
                             "colours; pass uint8 codes or floats code/255 in [0, 1]")
        if flat.size and (flat.min() < 0 or flat.max() > 255):
            raise InputError("integer colours must be 8-bit codes in [0, 255]")
        return flat.astype(np.uint8), True
    f = flat.astype(np.float64)
    if not np.all(np.isfinite(f)):
        raise InputError("colours contain NaN or inf")
    if f.size and (f.min() < -1e-6 or f.max() > 1 + 1e-6):
        raise InputError(f"float colours must be in [0, 1] (code / 255), got range [{f.min():g}, {f.max():g}]")
    f = np.clip(f, 0.0, 1.0)
    codes = np.rint(f * 255.0)
    if np.all(np.abs(f * 255.0 - codes) < 1e-3):
        return codes.astype(np.uint8), True
    return f, False


def _distinct_codes(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct rows of uint8 (P,3) codes: (sorted packed 24-bit codes (M,), inverse index (P,))."""
    packed = codes[:, 0].astype(np.int32)
    packed <<= 8
    packed |= codes[:, 1]
    packed <<= 8
    packed |= codes[:, 2]
    if packed.shape[0] > _BINCOUNT_THRESHOLD:
        present = np.bincount(packed, minlength=1 << 24)
        uniq = np.flatnonzero(present).astype(np.int32)
        lut = np.zeros(1 << 24, dtype=np.int32)
        lut[uniq] = np.arange(uniq.shape[0], dtype=np.int32)
        return uniq, np.take(lut, packed)
    uniq, inv = np.unique(packed, return_inverse=True)
    return uniq.astype(np.int32), inv.reshape(-1).astype(np.int32)


def _unpack(packed: np.ndarray) -> np.ndarray:
    """Packed 24-bit codes -> (M,3) int32 codes."""
    return np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.int32)


# ============================================================================ helpers
def _srgb_decode(v: np.ndarray) -> np.ndarray:
    """Inverse sRGB OETF in float64 (IEC 61966-2-1)."""
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _raw_white(jf: np.ndarray, rf: np.ndarray) -> float:
    """Typical raw value of bright, unclipped colours (sets the scale of eps)."""
    mx = jf.max(axis=1)
    sel = (mx >= 200) & (mx <= 250)
    rmax = rf.max(axis=1)
    if np.count_nonzero(sel) >= 5:
        w = float(np.median(rmax[sel]))
    else:
        unclipped = mx < 255
        w = float(np.percentile(rmax[unclipped], 99)) if np.count_nonzero(unclipped) >= 5 else float(rmax.max())
    if not np.isfinite(w) or w <= 0:
        w = float(np.max(np.abs(rf)))
    return max(w, 1e-30)


def _log_training_targets(model, jf: np.ndarray, rf: np.ndarray):
    """Shared by the log-space models: seeded subsample to ``model.n_train`` pairs, set
    ``model.raw_white`` and ``model.eps``; returns (rng, jf, rf, inputs code/255, log targets)."""
    rng = np.random.default_rng(model.seed)
    if jf.shape[0] > model.n_train:
        sel = np.sort(rng.choice(jf.shape[0], model.n_train, replace=False))
        jf, rf = jf[sel], rf[sel]
    model.raw_white = _raw_white(jf, rf)
    model.eps = model.eps_rel * model.raw_white
    return rng, jf, rf, jf / 255.0, np.log(np.maximum(rf, 0.0) + model.eps)


def _lognormal_moments(mu: np.ndarray, s2: np.ndarray, eps: float,
                       median: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Raw-space (centre, spread) of raw = exp(t) - eps with t ~ N(mu, s2), float64.

    ``median=False``: mean ``exp(mu + s2/2) - eps`` and variance ``(exp(s2) - 1) exp(2 mu + s2)``.
    ``median=True``: median ``exp(mu) - eps`` and the mean squared deviation about it,
    ``exp(2 mu) ((exp(s2) - 1) exp(s2) + (exp(s2/2) - 1)^2)``.
    """
    s2 = np.clip(s2, 0.0, _MAX_LOG_VAR)
    big = np.finfo(np.float32).max / 4
    with np.errstate(over="ignore"):
        if not median:
            e = np.exp(np.minimum(np.maximum(mu, -_MAX_LOG_MEAN) + 0.5 * s2, 40.0))
            return np.minimum(e - eps, big), np.minimum(np.expm1(s2) * (e * e), big)
        e = np.exp(np.minimum(np.maximum(mu, -_MAX_LOG_MEAN), 40.0))
        h = np.exp(0.5 * s2)
        return np.minimum(e - eps, big), np.minimum((np.expm1(s2) * h * h + (h - 1.0) ** 2) * (e * e), big)


def _lognormal_moments_inplace(mu: np.ndarray, logvar: np.ndarray, eps: float,
                               median: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Same as :func:`_lognormal_moments` from (mu, log s2), float32, reusing the input buffers."""
    big = np.float32(np.finfo(np.float32).max / 4)
    np.minimum(logvar, np.float32(np.log(_MAX_LOG_VAR)), out=logvar)
    s2 = np.exp(logvar, out=logvar)
    var = np.multiply(s2, np.float32(0.5))
    with np.errstate(over="ignore"):
        if median:
            h = np.exp(var, out=var)                 # exp(s2/2)
            g = np.expm1(s2, out=s2)
            g *= h
            g *= h
            h -= np.float32(1.0)
            h *= h
            h += g                                   # (exp(s2)-1) exp(s2) + (exp(s2/2)-1)^2
        else:
            mu += var
            np.expm1(s2, out=var)
        np.minimum(mu, np.float32(40.0), out=mu)
        e = np.exp(mu, out=mu)
        var *= e
        var *= e
    np.minimum(var, big, out=var)
    e -= np.float32(eps)
    np.minimum(e, big, out=e)
    return e, var


def table_nodes(n: int = 40, offset: float = 3e-3) -> np.ndarray:
    """Per-axis integer code nodes of the prediction table (float64, sorted, 0 and 255 included).

    Nodes are uniform in ``log(srgb_decode(code/255) + offset)`` (so the log-raw mean is
    close to linear between nodes), plus every code in 0..3 and 250..255 where clipping
    makes the de-rendering curve bend sharply.
    """
    if n < 8:
        raise InputError("table size must be at least 8 nodes per axis")
    codes = np.arange(256.0)
    w = np.log(_srgb_decode(codes / 255.0) + offset)
    targets = np.linspace(w[0], w[-1], n - 10)
    nodes = np.interp(targets, w, codes)
    nodes = np.unique(np.concatenate([np.rint(nodes), [0, 1, 2, 3, 250, 251, 252, 253, 254, 255]]))
    return nodes.astype(np.float64)


class _Table:
    """Trilinear interpolation of latent values tabulated on a rectilinear grid of codes.

    For 8-bit codes the table is first interpolated (once, lazily) along the G and B axes
    to every code, giving a float32 (n, 256, 256, C) array; a colour then needs a single
    linear interpolation along R -- the same trilinear interpolant, evaluated in O(1)
    gathers per colour.
    """

    def __init__(self, nodes: np.ndarray, values: np.ndarray):
        self.nodes = np.asarray(nodes, dtype=np.float64)
        self.values = np.ascontiguousarray(values, dtype=np.float64)  # (n, n, n, C)
        n = self.nodes.shape[0]
        self.flat = self.values.reshape(n * n * n, -1)
        self._lut_lo, self._lut_w = self._locate(np.arange(256.0))
        self._gb: list[np.ndarray] | None = None

    def _locate(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.nodes.shape[0]
        i = np.clip(np.searchsorted(self.nodes, codes, side="right") - 1, 0, n - 2)
        x0, x1 = self.nodes[i], self.nodes[i + 1]
        w = np.clip((codes - x0) / (x1 - x0), 0.0, 1.0)
        return i.astype(np.intp), w

    def _gb_tables(self) -> list[np.ndarray]:
        if self._gb is None:
            # float32 throughout, one 3-value block at a time: the (n, 256, 256, 3) tables are
            # ~30 MB each, and float64 temporaries of the full width cost seconds on first use
            lo = self._lut_lo
            w = self._lut_w.astype(np.float32)
            vb = self.values[:, :, lo]                                  # along B: (n, n, 256, C)
            vb += (self.values[:, :, lo + 1] - vb) * self._lut_w[:, None]
            vb = vb.astype(np.float32)
            wg = w[None, :, None, None]
            tabs = []
            for k in range(0, vb.shape[-1], 3):
                part = np.ascontiguousarray(vb[..., k:k + 3])
                out = part[:, lo]                                      # along G: (n, 256, 256, 3)
                hi = part[:, lo + 1]
                hi -= out
                hi *= wg
                out += hi
                tabs.append(out.reshape(-1, 3))
            self._gb = tabs
        return self._gb

    def at_codes(self, codes: np.ndarray) -> list[np.ndarray]:
        """Interpolate at integer (M,3) codes: list of contiguous float32 (M,3) blocks (3 values each)."""
        tabs = self._gb_tables()
        c = codes if codes.dtype.kind in "iu" else codes.astype(np.intp)
        i = self._lut_lo[c[:, 0]]
        w = self._lut_w[c[:, 0]].astype(np.float32)[:, None]
        j = i * 65536 + c[:, 1].astype(np.intp) * 256 + c[:, 2]
        j1 = j + 65536
        out = []
        for tab in tabs:
            v0 = np.take(tab, j, axis=0)
            v1 = np.take(tab, j1, axis=0)
            v1 -= v0
            v1 *= w
            v1 += v0
            out.append(v1)
        return out

    def at_float(self, codes: np.ndarray) -> np.ndarray:
        """Interpolate at real-valued (M,3) codes in [0, 255]; float64 (M, C)."""
        n = self.nodes.shape[0]
        lo, w = self._locate(codes)
        base = lo[:, 0] * (n * n) + lo[:, 1] * n + lo[:, 2]
        out = np.zeros((codes.shape[0], self.flat.shape[1]))
        for dr in (0, 1):
            wr = w[:, 0] if dr else 1.0 - w[:, 0]
            for dg in (0, 1):
                wg = wr * (w[:, 1] if dg else 1.0 - w[:, 1])
                for db in (0, 1):
                    wb = wg * (w[:, 2] if db else 1.0 - w[:, 2])
                    out += wb[:, None] * self.flat[base + (dr * n * n + dg * n + db)]
        return out


# ============================================================================ base class
class DerenderModel:
    """Common interface: ``fit(jpeg, raw)``, ``predict(colours) -> (mean, var)``, ``save``, ``load``.

    ``jpeg``: (N,3) 8-bit codes; ``raw``: (N,3) linear camera RGB (white balance fixed,
    relative units). ``predict`` takes uint8 codes (..., 3) or floats code/255 in [0, 1]
    and returns float32 ``mean`` and ``variance`` of the raw colour, shape (..., 3).
    """

    method: ClassVar[str] = ""
    _param_names: ClassVar[tuple[str, ...]] = ()

    def __init__(self, seed: int = 0, metadata: dict | None = None):
        self.seed = int(seed)
        self.metadata: dict[str, Any] = dict(metadata or {})
        self.fitted = False

    # ------------------------------------------------------------------ to implement
    def _fit(self, jf: np.ndarray, rf: np.ndarray) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _predict_codes(self, codes: np.ndarray, integer: bool, exact: bool,
                       median: bool) -> tuple[np.ndarray, np.ndarray]:
        """(M,3) codes (integer if ``integer``, else real in [0,255]) -> raw-space (centre, spread).

        Float32 results must be finite (they are used as is); float64 results are sanitised.
        """
        raise NotImplementedError  # pragma: no cover

    def _get_params(self) -> dict[str, np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _set_params(self, p: dict[str, np.ndarray]) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # ------------------------------------------------------------------ public API
    def fit(self, jpeg, raw) -> "DerenderModel":
        """Learn the model from pairs ``jpeg`` (N,3) codes and ``raw`` (N,3) linear camera RGB."""
        jf, rf = _check_pairs(jpeg, raw)
        t0 = time.perf_counter()
        self._fit(jf, rf)
        self.fitted = True
        self.metadata.setdefault("training", {})
        self.metadata["training"].update({"n_pairs": int(jf.shape[0]), "seed": self.seed,
                                          "fit_seconds": round(time.perf_counter() - t0, 3)})
        return self

    def predict(self, colours, exact: bool = False, point: str = "mean") -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance (float32, shape ``colours.shape``) of the raw colour given rendered colours.

        Accepts uint8 codes (any leading shape, e.g. an (H, W, 3) image) or floats in
        [0, 1] meaning code/255. Each distinct colour is predicted once. ``exact=True``
        skips the interpolation table (slow). ``point="median"`` returns the predictive
        median and the mean squared deviation about it instead of mean and variance (a
        better point estimate under relative error when the distribution is wide, e.g.
        for clipped colours); ``point="map"`` returns the mode of the predictive
        distribution (the MAP estimate paper 2 Sec. 4.1 names; for the GP's log-normal
        ``exp(mu - s2) - eps``) and the mean squared deviation about it. Deterministic
        models ignore ``point``.
        """
        if point not in ("mean", "median", "map"):
            raise InputError(f"point must be 'mean', 'median' or 'map', got {point!r}")
        median = point == "median"
        if not self.fitted:
            raise InputError(f"{type(self).__name__} is not fitted; call fit() or load a model file")
        if point == "map" and hasattr(self, "predict_log"):
            return self._predict_map(colours, exact)
        shape = np.shape(colours)
        flat, is_codes = _as_colour_array(colours)
        if flat.shape[0] == 0:
            z = np.zeros(shape, dtype=np.float32)
            return z, z.copy()
        if is_codes:
            uniq, inv = _distinct_codes(flat)
            m, v = self._predict_codes(_unpack(uniq), True, exact, median)
            if m.dtype != np.float32 or v.dtype != np.float32:   # the float32 table path is finite by design
                m, v = finite32(m, v)
            mean, var = np.take(m, inv, axis=0), np.take(v, inv, axis=0)
        else:
            mean = np.empty(flat.shape, dtype=np.float32)
            var = np.empty(flat.shape, dtype=np.float32)
            step = 1 << 18
            for s in range(0, flat.shape[0], step):
                m, v = self._predict_codes(flat[s:s + step] * 255.0, False, exact, median)
                mean[s:s + step], var[s:s + step] = finite32(m, v)
        return mean.reshape(shape), var.reshape(shape)

    __call__ = predict

    def _predict_map(self, colours, exact: bool) -> tuple[np.ndarray, np.ndarray]:
        """Mode ``exp(mu - s2) - eps`` of the log-normal predictive and E[(x - mode)^2]."""
        mu, s2 = self.predict_log(colours, exact=exact)
        s2 = np.clip(np.asarray(s2, dtype=np.float64), 0.0, _MAX_LOG_VAR)
        mu = np.clip(np.asarray(mu, dtype=np.float64), -_MAX_LOG_MEAN, _MAX_LOG_MEAN)
        with np.errstate(over="ignore"):
            mode = np.exp(mu - s2)
            mean = np.exp(mu + 0.5 * s2)
            var = np.expm1(s2) * np.exp(2 * mu + s2) + (mean - mode) ** 2
        return finite32(mode - self.eps, var)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model to a versioned ``.npz`` file (no pickle); returns the path."""
        from derender.io.files import atomic_output

        if not self.fitted:
            raise InputError("cannot save an unfitted model")
        arrays: dict[str, np.ndarray] = {
            "format": np.array(MODEL_FORMAT),
            "format_version": np.array(MODEL_FORMAT_VERSION, dtype=np.int64),
            "method": np.array(self.method),
            "seed": np.array(self.seed, dtype=np.int64),
            "metadata_json": np.array(json.dumps(self.metadata, default=_json_default, sort_keys=True)),
        }
        for k, v in self._get_params().items():
            arrays["p_" + k] = np.asarray(v)
        path = Path(path)
        with atomic_output(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "DerenderModel":
        """Read a model file written by :meth:`save` (raises ModelFileError if unusable)."""
        model = load_model(path)
        if cls is not DerenderModel and not isinstance(model, cls):
            raise ModelFileError(f"{path}: holds a '{model.method}' model, not '{cls.method}'")
        return model

    def __repr__(self) -> str:
        state = "fitted" if self.fitted else "unfitted"
        return f"{type(self).__name__}({state}, seed={self.seed})"


def finite32(m: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 copies with NaN/inf replaced (mean: 0 / +-max; variance: max)."""
    big = np.finfo(np.float32).max
    m = np.nan_to_num(m.astype(np.float32, copy=False), nan=0.0, posinf=big, neginf=-big)
    v = np.nan_to_num(v.astype(np.float32, copy=False), nan=big, posinf=big, neginf=0.0)
    return m, np.maximum(v, 0.0)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def load_model(path: str | os.PathLike) -> DerenderModel:
    """Load any de-rendering model file; corrupt, foreign or mismatched files raise ModelFileError."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"model file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
        raise ModelFileError(f"{path}: not a readable .npz model file ({type(exc).__name__}: {exc})") from None
    if "format" not in data or str(data["format"]) != MODEL_FORMAT:
        raise ModelFileError(f"{path}: not a derender model file (no format='{MODEL_FORMAT}' entry)")
    try:
        version = int(data["format_version"])
    except (KeyError, TypeError, ValueError):
        raise ModelFileError(f"{path}: model file has no valid format_version") from None
    if version != MODEL_FORMAT_VERSION:
        raise ModelFileError(f"{path}: model file format version {version} is not supported "
                             f"(this derender reads version {MODEL_FORMAT_VERSION})")
    method = str(data.get("method", ""))
    if method not in MODEL_TYPES:
        raise ModelFileError(f"{path}: unknown model method '{method}' (known: {', '.join(MODEL_TYPES)})")
    cls = MODEL_TYPES[method]
    try:
        metadata = json.loads(str(data.get("metadata_json", "{}")))
        model = cls(seed=int(data.get("seed", 0)), metadata=metadata)
        params = {k[2:]: v for k, v in data.items() if k.startswith("p_")}
        missing = [k for k in cls._param_names if k not in params]
        if missing:
            raise ModelFileError(f"model file lacks parameters {missing}")
        model._set_params(params)
    except ModelFileError as exc:
        raise ModelFileError(f"{path}: {exc}") from None
    except Exception as exc:
        raise ModelFileError(f"{path}: inconsistent model parameters ({type(exc).__name__}: {exc})") from None
    model.fitted = True
    return model


# ============================================================================ local GP
_ELL_MIN = 0.004                        # smallest SE length-scale (in GP input units)


_LOG_CHI2_MEAN = -1.2703628454614782   # E[log chi^2_1] = digamma(1/2) + log 2


_LOG_CHI2_VAR = np.pi ** 2 / 2          # Var[log chi^2_1] = trigamma(1/2)


def _sq_dists(X: np.ndarray) -> list[np.ndarray]:
    return [np.ascontiguousarray((X[:, None, d] - X[None, :, d]) ** 2) for d in range(X.shape[1])]


def _se_kernel(A: np.ndarray, B: np.ndarray, log_ell: np.ndarray, log_sf: float) -> np.ndarray:
    """Squared-exponential ARD kernel sf^2 exp(-0.5 sum_d (a_d - b_d)^2 / l_d^2)."""
    s = np.exp(-np.asarray(log_ell))
    a, b = A * s, B * s
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
    np.maximum(d2, 0.0, out=d2)
    d2 *= -0.5
    K = np.exp(d2, out=d2)
    K *= np.exp(2.0 * log_sf)
    return K


def _chol_solve_inv(K: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Cholesky of K (overwritten): returns (L, K^-1 y, K^-1) or None if not positive definite."""
    from scipy.linalg import lapack  # scipy is imported on first fit, not by a prediction

    L, info = lapack.dpotrf(K, lower=1, clean=1, overwrite_a=1)
    if info != 0:
        return None
    alpha, _ = lapack.dpotrs(L, y, lower=1)
    Ki, info = lapack.dpotri(L, lower=1)
    if info != 0:
        return None
    Ki = np.tril(Ki)
    Ki += np.tril(Ki, -1).T
    return L, alpha, Ki


def _gp_nll(theta: np.ndarray, D: list[np.ndarray], y: np.ndarray,
            r: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood of an ARD-SE GP and its gradient (R&W eqs. 2.30, 5.9).

    theta = [log l_1..l_d, log sigma_f, log sigma_n]; noise covariance sigma_n^2 diag(r)
    (r = 1: homoscedastic).
    """
    d = len(D)
    n = y.shape[0]
    inv_l2 = np.exp(-2.0 * theta[:d])
    sf2 = np.exp(2.0 * theta[d])
    sn2 = np.exp(2.0 * theta[d + 1])
    E = D[0] * (-0.5 * inv_l2[0])
    for k in range(1, d):
        E += D[k] * (-0.5 * inv_l2[k])
    Kf = np.exp(E, out=E)
    Kf *= sf2
    K = Kf.copy()
    K.flat[:: n + 1] += sn2 * (1.0 if r is None else r) + 1e-8 * sf2
    out = _chol_solve_inv(K, y)
    if out is None:
        return 1e25, np.zeros_like(theta)
    L, alpha, Ki = out
    nll = 0.5 * float(y @ alpha) + float(np.log(np.diag(L)).sum()) + 0.5 * n * np.log(2 * np.pi)
    W = np.outer(alpha, alpha)
    W -= Ki
    g = np.empty_like(theta)
    WK = W * Kf
    for k in range(d):
        g[k] = -0.5 * inv_l2[k] * float(np.vdot(WK, D[k]))
    g[d] = -float(WK.sum())
    wd = np.diag(W)
    g[d + 1] = -sn2 * float(wd.sum() if r is None else wd @ r)
    return nll, g


def _optimise(D: list[np.ndarray], y: np.ndarray, X: np.ndarray, r: np.ndarray | None = None,
              th0: np.ndarray | None = None) -> np.ndarray:
    """Maximum-likelihood hyper-parameters (L-BFGS-B, analytic gradient) for a standardised target."""
    d = len(D)
    if th0 is None:
        ell0 = np.clip(X.std(axis=0), 0.02, 1.0)
        th0 = np.concatenate([np.log(ell0), [0.0, np.log(0.1)]])
    bounds = [(np.log(_ELL_MIN), np.log(20.0))] * d + [(np.log(1e-2), np.log(1e2)), (np.log(1e-4), np.log(3.0))]
    th0 = np.clip(th0, [b[0] for b in bounds], [b[1] for b in bounds])
    from scipy.optimize import minimize

    res = minimize(_gp_nll, th0, args=(D, y, r), jac=True, method="L-BFGS-B", bounds=bounds,
                   options={"maxiter": 200})
    return np.asarray(res.x if np.isfinite(res.fun) and res.fun < 1e24 else th0, dtype=np.float64)


def _noise_gp(th: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Input-dependent log noise (most-likely heteroscedastic GP, Kersting et al. 2007).

    ``l_i = log(LOO residual_i^2) - E[log chi^2_1]`` is regressed by a GP with the main
    GP's length-scales (after the refit: the refitted ones) and the known noise variance
    Var[log chi^2_1] = pi^2/2.
    Returns (theta_noise = [log l (3), log sf, log sn, mean, g_min, g_max], l); the last two
    (filled in by the caller) bound the log noise factor at prediction to its range over the
    training colours, so the noise GP cannot extrapolate to absurd variances.
    """
    l = np.log(z + 1e-6 * max(float(np.mean(z)), 1e-300)) - _LOG_CHI2_MEAN
    m = float(np.mean(l))
    sf2 = max(float(np.var(l)) - _LOG_CHI2_VAR, 0.05)
    thn = np.concatenate([th[:3], [0.5 * np.log(sf2), 0.5 * np.log(_LOG_CHI2_VAR), m, 0.0, 0.0]])
    return thn, l


def _noise_gp_weights(X: np.ndarray, thn: np.ndarray, l: np.ndarray) -> np.ndarray:
    K = _se_kernel(X, X, thn[:3], thn[3])
    K.flat[:: X.shape[0] + 1] += np.exp(2 * thn[4])
    from scipy.linalg import lapack  # scipy is imported on first fit, not by a prediction

    L, info = lapack.dpotrf(K, lower=1, clean=1, overwrite_a=1)
    if info != 0:  # pragma: no cover - noise variance pi^2/2 keeps K well conditioned
        raise ModelFileError("noise GP covariance is not positive definite")
    beta, _ = lapack.dpotrs(L, l - thn[5], lower=1)
    return beta


def _clip_bits(codes: np.ndarray, clip_code: float) -> np.ndarray:
    """Clip pattern of (M,3) codes: 4 R + 2 G + B for channels >= clip_code (0 = unclipped)."""
    c = codes >= clip_code
    return (4 * c[:, 0] + 2 * c[:, 1] + c[:, 2]).astype(np.int64)


def _fit_local_gp(X: np.ndarray, Z: np.ndarray, osel: np.ndarray, hetero: bool) -> tuple[np.ndarray, np.ndarray,
                                                                                      np.ndarray]:
    """Fit the three channel GPs of one cluster: returns theta (3,5), theta_noise (3,8), l (n,3)."""
    n = X.shape[0]
    Xs = X[osel]
    D = _sq_dists(Xs)
    thetas = np.zeros((3, 5))
    thn = np.zeros((3, 8))
    ls = np.zeros((n, 3))
    for ch in range(3):
        th = _optimise(D, Z[osel, ch], Xs)
        if hetero:
            K = _se_kernel(X, X, th[:3], th[3])
            K.flat[:: n + 1] += np.exp(2 * th[4]) + 1e-8 * np.exp(2 * th[3])
            out = _chol_solve_inv(K, Z[:, ch])
            if out is not None:
                _, alpha, Ki = out
                loo = alpha / np.diag(Ki)
                tn, l = _noise_gp(th, loo * loo)
                g = tn[5] + _se_kernel(X, X, tn[:3], tn[3]) @ _noise_gp_weights(X, tn, l)
                gmed = float(np.median(g))
                r = np.exp(g - gmed)
                th0 = np.concatenate([th[:4], [0.5 * gmed]])
                th = _optimise(D, Z[osel, ch], Xs, r=r[osel], th0=th0)
                tn[:3] = th[:3]    # noise GP shares the refitted length-scales (one kernel matrix at prediction)
                tn[5] -= gmed      # store the noise-GP mean relative to the median, so r = exp(g)
                gfit = tn[5] + _se_kernel(X, X, tn[:3], tn[3]) @ _noise_gp_weights(X, tn, l - gmed)
                tn[6], tn[7] = float(gfit.min()), float(gfit.max())
                thn[ch], ls[:, ch] = tn, l - gmed
                thetas[ch] = th
                continue
        thetas[ch] = th
        thn[ch] = [0.0, 0.0, 0.0, np.log(1e-6), 0.0, 0.0, 0.0, 0.0]   # g == 0: homoscedastic
    return thetas, thn, ls


class LocalGPModel(DerenderModel):
    """Offline local GP de-rendering (paper 2, Sec. 2.2 and 4): k-means + per-cluster ARD-SE GPs.

    Target ``t = log(max(raw, 0) + eps)`` per channel, standardised per cluster. Each
    GP has an ARD squared-exponential kernel (length-scale per input channel) and
    white noise, hyper-parameters by maximum likelihood. With ``heteroscedastic=True``
    (default) the noise variance varies with the input colour (most-likely
    heteroscedastic GP, Kersting et al. 2007): leave-one-out residuals of the first
    ML fit give a GP over log noise variance, and the hyper-parameters are refitted by
    maximum likelihood with that noise shape. This keeps clipped colours (which are
    one-to-many, paper 2 Sec. 2.1) from inflating the noise of well-determined ones.

    Parameters: ``n_clusters`` (k = 10), ``n_train`` (5000 pairs, random subset if more),
    ``max_cluster_points`` (cap on a cluster's GP size; a larger cluster is subsampled),
    ``opt_points`` (random subset per cluster used for the maximum-likelihood search;
    the final GP uses all its cluster points; 500 covers every clipped cluster of a chart
    session -- with 300 the ML search on a subset of a nearly uninformative clipped
    cluster sometimes picked a 1-code length-scale and the relative RMSE of the clipped
    colours varied from 0.48 to 0.54 with the seed), ``eps_rel`` (log offset relative to
    ``raw_white``), ``table_size`` (nodes per axis of the prediction table, see
    :func:`table_nodes`; 0 = always exact), ``heteroscedastic``, ``clip_code`` (colours
    whose largest code is >= this form their own clusters; the share of the k clusters
    follows their share of the data), ``clip_patterns`` (off by default: clipped colours
    clustered per clip pattern, at least one cluster per pattern with 20+ training colours,
    rarer patterns training with the nearest clipped cluster; measured with 5000 chart
    pairs: derender-table S90 relative RMSE 0.233 on vs 0.232 off, 5D II and D5100
    unchanged, but photometric stereo on the S90 sphere 5.17 vs 4.84 degrees), ``input_warp`` (0: inputs ``code / 255`` as
    in the paper; ``a > 0``: inputs ``log(1 + srgb_decode(code/255) / a)``, normalised,
    which spreads near-black codes -- measured on the S90 chart with a = 3e-3: relative
    RMSE of near-black colours 0.40 -> 0.34, all colours 0.233 -> 0.230, but on the unit
    tests' synthetic camera the noise GP then gave log-variances above 30 near
    near-zero raw channels, so it is off by default), ``n_jobs`` (threads for fitting), ``seed``.
    Defaults fit 5000 pairs in about 15-35 s on 2 shared cores.
    """

    method = "gp"
    _param_names = ("centroids", "cluster_group", "X", "T", "offsets", "theta", "theta_noise", "log_noise",
                    "t_mean", "t_std", "eps", "raw_white", "table_nodes", "table_values")

    def __init__(self, n_clusters: int = 10, n_train: int = 5000, max_cluster_points: int = 1000,
                 opt_points: int = 500, eps_rel: float = 1e-4, table_size: int = 40,
                 heteroscedastic: bool = True, clip_code: float = 254.5, clip_patterns: bool = False,
                 input_warp: float = 0.0, n_jobs: int | None = None, seed: int = 0, metadata: dict | None = None):
        super().__init__(seed=seed, metadata=metadata)
        if n_clusters < 1 or n_train < 20 or max_cluster_points < 10 or opt_points < 10:
            raise InputError("invalid GP model settings (n_clusters >= 1, n_train >= 20, "
                             "max_cluster_points >= 10, opt_points >= 10)")
        if not eps_rel > 0:
            raise InputError("eps_rel must be > 0")
        self.n_clusters = int(n_clusters)
        self.n_train = int(n_train)
        self.max_cluster_points = int(max_cluster_points)
        self.opt_points = int(opt_points)
        self.eps_rel = float(eps_rel)
        self.table_size = int(table_size)
        self.heteroscedastic = bool(heteroscedastic)
        self.clip_code = float(clip_code)
        if input_warp < 0:
            raise InputError("input_warp must be >= 0 (0 = inputs code/255)")
        self.input_warp = float(input_warp)
        self.clip_patterns = bool(clip_patterns)
        self.n_jobs = n_jobs
        self._factors: dict[tuple[int, int], tuple[np.ndarray, ...]] = {}
        self._table: _Table | None = None

    def _inputs(self, Y: np.ndarray) -> np.ndarray:
        """GP input space from ``Y = code / 255``: ``Y`` itself, or with ``input_warp = a > 0`` the
        log-decoded ``log(1 + srgb_decode(Y) / a) / log(1 + 1 / a)`` (0 -> 0, 1 -> 1)."""
        a = self.input_warp
        if a <= 0:
            return Y
        return np.log1p(_srgb_decode(Y) / a) / np.log1p(1.0 / a)

    # ------------------------------------------------------------------ fitting
    def _fit(self, jf: np.ndarray, rf: np.ndarray) -> None:
        from concurrent.futures import ThreadPoolExecutor

        from sklearn.cluster import KMeans
        from threadpoolctl import threadpool_limits

        rng, jf, rf, Y, T = _log_training_targets(self, jf, rf)
        Y = self._inputs(Y)
        # clip-aware k-means: colours with a clipped (255) channel are one-to-many and get their
        # own clusters, so their spread neither smooths nor inflates the unclipped GPs
        clipped = jf.max(axis=1) >= self.clip_code
        k_total = int(min(self.n_clusters, max(1, jf.shape[0] // 20)))
        n_clip = int(np.count_nonzero(clipped))
        leftover = np.zeros(0, dtype=np.intp)
        if k_total >= 2 and n_clip >= 20 and jf.shape[0] - n_clip >= 20:
            k_clip = int(np.clip(round(k_total * n_clip / jf.shape[0]), 1, k_total - 1))
            if self.clip_patterns:
                # one face of the code cube per clip pattern (which channels are at 255)
                bits = _clip_bits(jf, self.clip_code)
                pats, counts = np.unique(bits[clipped], return_counts=True)
                big = [(int(b), int(n)) for b, n in zip(pats, counts) if n >= 20]
                if big:
                    k_clip = int(min(max(k_clip, len(big)), k_total - 1)) if len(big) < k_total else k_clip
                    nb = sum(n for _, n in big)
                    groups = [(np.flatnonzero(~clipped), k_total - k_clip, 0)]
                    for b, n in sorted(big, key=lambda t: -t[1]):
                        groups.append((np.flatnonzero(clipped & (bits == b)), max(1, round(k_clip * n / nb)), 1 + b))
                    leftover = np.flatnonzero(clipped & ~np.isin(bits, [b for b, _ in big]))
                else:
                    groups = [(np.flatnonzero(~clipped), k_total - k_clip, 0), (np.flatnonzero(clipped), k_clip, 1)]
            else:
                groups = [(np.flatnonzero(~clipped), k_total - k_clip, 0), (np.flatnonzero(clipped), k_clip, 1)]
        else:
            groups = [(np.arange(jf.shape[0]), k_total, -1)]
        members, centroids, flags = [], [], []
        for gidx, kg, flag in groups:
            kg = min(kg, np.unique(jf[gidx], axis=0).shape[0])   # no more clusters than distinct colours
            with threadpool_limits(1):   # tiny problem: OpenMP threads only add overhead
                km = KMeans(n_clusters=kg, n_init=4, random_state=self.seed).fit(Y[gidx])
            for c in range(kg):
                sel = gidx[km.labels_ == c]
                if sel.size:
                    members.append(sel)
                    centroids.append(km.cluster_centers_[c])
                    flags.append(flag)
        if leftover.size:   # rare clip patterns: train with the nearest clipped cluster
            cand = np.flatnonzero(np.asarray(flags) >= 1)
            d2 = ((Y[leftover][:, None, :] - np.asarray(centroids)[cand][None]) ** 2).sum(-1)
            near = cand[np.argmin(d2, axis=1)]
            for c in np.unique(near):
                members[c] = np.sort(np.concatenate([members[c], leftover[near == c]]))
        tasks = []
        for idx in members:
            if idx.shape[0] > self.max_cluster_points:
                idx = np.sort(rng.choice(idx, self.max_cluster_points, replace=False))
            Tc = T[idx]
            m = Tc.mean(axis=0)
            s = np.maximum(Tc.std(axis=0), 1e-3)
            if idx.shape[0] > self.opt_points:
                osel = np.sort(rng.choice(idx.shape[0], self.opt_points, replace=False))
            else:
                osel = np.arange(idx.shape[0])
            tasks.append((Y[idx], Tc, m, s, osel))
        n_jobs = self.n_jobs or min(2, os.cpu_count() or 1)
        # small dense problems: one BLAS thread per task is far faster than oversubscription
        with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(max_workers=max(1, n_jobs)) as ex:
            fits = list(ex.map(lambda t: _fit_local_gp(t[0], (t[1] - t[2]) / t[3], t[4], self.heteroscedastic),
                               tasks))
        self.centroids = np.stack(centroids).astype(np.float64)
        self.cluster_group = np.asarray(flags, dtype=np.int64)
        self.X = np.concatenate([t[0] for t in tasks])
        self.T = np.concatenate([t[1] for t in tasks])
        self.offsets = np.concatenate([[0], np.cumsum([t[0].shape[0] for t in tasks])]).astype(np.int64)
        self.t_mean = np.stack([t[2] for t in tasks])
        self.t_std = np.stack([t[3] for t in tasks])
        self.theta = np.stack([f[0] for f in fits])
        self.theta_noise = np.stack([f[1] for f in fits])
        self.log_noise = np.concatenate([f[2] for f in fits])
        self._factors = {}
        self._build_table()
        self.metadata.setdefault("training", {}).update(
            {"n_train": int(jf.shape[0]), "n_clusters": len(tasks), "cluster_sizes": np.diff(self.offsets).tolist(),
             "kernel": "squared-exponential ARD + white noise", "heteroscedastic": self.heteroscedastic,
             "target": "log(max(raw,0)+eps)", "eps": self.eps, "raw_white": self.raw_white})

    # ------------------------------------------------------------------ exact GP prediction
    def _factor(self, c: int, ch: int) -> tuple[np.ndarray, ...]:
        key = (c, ch)
        if key not in self._factors:
            from threadpoolctl import threadpool_limits

            with threadpool_limits(1, user_api="blas"):
                self._factors[key] = self._compute_factor(c, ch)
        return self._factors[key]

    def _compute_factor(self, c: int, ch: int) -> tuple[np.ndarray, ...]:
        X = self.X[self.offsets[c]:self.offsets[c + 1]]
        y = (self.T[self.offsets[c]:self.offsets[c + 1], ch] - self.t_mean[c, ch]) / self.t_std[c, ch]
        th, tn = self.theta[c, ch], self.theta_noise[c, ch]
        l = self.log_noise[self.offsets[c]:self.offsets[c + 1], ch]
        beta = _noise_gp_weights(X, tn, l)
        r = np.exp(tn[5] + _se_kernel(X, X, tn[:3], tn[3]) @ beta)
        K = _se_kernel(X, X, th[:3], th[3])
        K.flat[:: X.shape[0] + 1] += np.exp(2 * th[4]) * r + 1e-8 * np.exp(2 * th[3])
        out = _chol_solve_inv(K, y)
        if out is None:  # pragma: no cover - guarded by the noise floor
            raise ModelFileError("GP covariance is not positive definite (corrupt parameters?)")
        return out[1], out[2], beta

    def _latent_exact(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact local-GP prediction at inputs Y (M,3) in [0,1]: mean and variance of t (incl. noise)."""
        lab = self._assign(Y)
        Y = self._inputs(Y)
        mu = np.empty((Y.shape[0], 3))
        s2 = np.empty((Y.shape[0], 3))
        for c in range(self.centroids.shape[0]):
            sel = np.flatnonzero(lab == c)
            if sel.size == 0:
                continue
            X = self.X[self.offsets[c]:self.offsets[c + 1]]
            for ch in range(3):
                alpha, Ki, beta = self._factor(c, ch)
                th, tn = self.theta[c, ch], self.theta_noise[c, ch]
                sf2, sn2 = np.exp(2 * th[3]), np.exp(2 * th[4])
                for s in range(0, sel.size, 8192):
                    rows = sel[s:s + 8192]
                    Ks = _se_kernel(Y[rows], X, th[:3], th[3])
                    m = Ks @ alpha
                    lat = np.maximum(sf2 - np.einsum("ij,ij->i", Ks @ Ki, Ks), 0.0)
                    g = tn[5] + (Ks @ beta) * np.exp(2 * (tn[3] - th[3]))   # noise GP: same length-scales
                    noise = sn2 * np.exp(np.clip(g, tn[6], tn[7]))
                    mu[rows, ch] = m * self.t_std[c, ch] + self.t_mean[c, ch]
                    s2[rows, ch] = (lat + noise) * self.t_std[c, ch] ** 2
        return mu, np.minimum(s2, self._log_var_cap())

    def _log_var_cap(self) -> np.ndarray:
        """(3,) bound on the predictive variance of ``t``: its variance over all training
        colours. A local GP extrapolating with long length-scales (ML signal variance up to
        ~125 in standardised units) otherwise reports a log-variance far beyond anything in
        the data: measured on the simulated 5D Mark II, 3 of 44,280 test colours (purples
        such as (105, 20, 106)) had blue log-variances of 40-48 (a predictive mean 2.6e9x
        the median) against a training variance of 7.3; the cap touches no other colour."""
        return np.var(self.T, axis=0)

    def _assign(self, Y: np.ndarray) -> np.ndarray:
        """Nearest cluster centre within the colour's clip group (paper: nearest exemplar).

        ``cluster_group``: -1 no grouping, 0 unclipped colours, 1 any clipped colour,
        ``1 + bits`` clipped colours of one clip pattern (bit 2 = R, 1 = G, 0 = B at 255); a
        clipped colour whose pattern has no cluster uses the nearest clipped cluster.
        """
        d2 = ((self._inputs(Y)[:, None, :] - self.centroids[None, :, :]) ** 2).sum(-1)
        g = self.cluster_group
        if np.any(g == 0) and np.any(g >= 1):
            bits = _clip_bits(Y * 255.0, self.clip_code)
            clipped = (bits > 0)[:, None]
            allowed = np.where(clipped, g[None, :] >= 1, g[None, :] == 0)
            if np.any(g >= 2):
                own = g[None, :] == (1 + bits)[:, None]
                allowed &= np.where(own.any(axis=1, keepdims=True) & clipped, own, True)
            d2 = np.where(allowed, d2, np.inf)
        return np.argmin(d2, axis=1)

    def _build_table(self) -> None:
        if self.table_size <= 0:
            self._table = None
            self.table_nodes_ = np.zeros(0)
            self.table_values_ = np.zeros((0, 0, 0, 6))
            return
        nodes = table_nodes(self.table_size)
        g = np.stack(np.meshgrid(nodes, nodes, nodes, indexing="ij"), axis=-1).reshape(-1, 3) / 255.0
        mu, s2 = self._latent_exact(g)
        self._factors = {}      # free the O(n^2) factors; exact predictions rebuild them lazily
        n = nodes.shape[0]
        vals = np.concatenate([mu, np.log(s2)], axis=1).reshape(n, n, n, 6)
        self.table_nodes_, self.table_values_ = nodes, vals
        self._table = _Table(nodes, vals)

    def _predict_codes(self, codes, integer, exact, median):
        if exact or self._table is None:
            mu, s2 = self._latent_exact(codes / 255.0)
        elif integer:
            mu, lv = self._table.at_codes(codes)
            return _lognormal_moments_inplace(mu, lv, self.eps, median)
        else:
            v = self._table.at_float(codes)
            mu, s2 = v[:, :3], np.exp(np.minimum(v[:, 3:], np.log(_MAX_LOG_VAR)))
        return _lognormal_moments(mu, s2, self.eps, median)

    def predict_log(self, colours, exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The GP's own Gaussian over ``t = log(max(raw,0) + eps)``: (mean, variance), float64, colours.shape.

        ``exp(mean) - eps`` is the predictive median of the raw colour.
        """
        if not self.fitted:
            raise InputError("LocalGPModel is not fitted; call fit() or load a model file")
        shape = np.shape(colours)
        flat, is_codes = _as_colour_array(colours)
        codes = flat.astype(np.float64) if is_codes else flat * 255.0
        if exact or self._table is None:
            mu, s2 = self._latent_exact(codes / 255.0)
        elif is_codes:
            mu, lv = self._table.at_codes(flat)
            mu, s2 = mu.astype(np.float64), np.exp(lv.astype(np.float64))
        else:
            v = self._table.at_float(codes)
            mu, s2 = v[:, :3], np.exp(v[:, 3:])
        return mu.reshape(shape), s2.reshape(shape)

    # ------------------------------------------------------------------ persistence
    def _get_params(self):
        return {"centroids": self.centroids, "cluster_group": self.cluster_group, "clip_code": np.array(self.clip_code),
                "X": self.X, "T": self.T, "offsets": self.offsets,
                "theta": self.theta, "theta_noise": self.theta_noise, "log_noise": self.log_noise,
                "t_mean": self.t_mean, "t_std": self.t_std,
                "eps": np.array(self.eps), "raw_white": np.array(self.raw_white),
                "table_nodes": self.table_nodes_, "table_values": self.table_values_,
                "settings": np.array([self.n_clusters, self.n_train, self.max_cluster_points,
                                      self.opt_points, self.table_size, int(self.heteroscedastic),
                                      int(self.clip_patterns)], dtype=np.int64),
                "eps_rel": np.array(self.eps_rel), "input_warp": np.array(self.input_warp)}

    def _set_params(self, p):
        self.centroids = np.asarray(p["centroids"], dtype=np.float64)
        self.cluster_group = np.asarray(p["cluster_group"], dtype=np.int64)
        self.clip_code = float(p.get("clip_code", np.array(254.5)))
        self.X = np.asarray(p["X"], dtype=np.float64)
        self.T = np.asarray(p["T"], dtype=np.float64)
        self.offsets = np.asarray(p["offsets"], dtype=np.int64)
        self.theta = np.asarray(p["theta"], dtype=np.float64)
        self.theta_noise = np.asarray(p["theta_noise"], dtype=np.float64)
        self.log_noise = np.asarray(p["log_noise"], dtype=np.float64)
        self.t_mean = np.asarray(p["t_mean"], dtype=np.float64)
        self.t_std = np.asarray(p["t_std"], dtype=np.float64)
        self.eps = float(p["eps"])
        self.raw_white = float(p["raw_white"])
        k = self.centroids.shape[0]
        if (self.centroids.shape != (k, 3) or self.cluster_group.shape != (k,) or self.offsets.shape != (k + 1,)
                or self.offsets[0] != 0
                or np.any(np.diff(self.offsets) < 1) or self.theta.shape != (k, 3, 5)
                or self.theta_noise.shape != (k, 3, 8) or self.X.shape != (self.offsets[-1], 3)
                or self.T.shape != self.X.shape or self.log_noise.shape != self.X.shape
                or self.t_mean.shape != (k, 3) or self.t_std.shape != (k, 3) or not self.eps > 0):
            raise ModelFileError("GP model arrays have inconsistent shapes")
        if "settings" in p:
            s = np.asarray(p["settings"]).astype(int).tolist()
            if len(s) not in (6, 7):
                raise ModelFileError("GP model settings have an unexpected length")
            (self.n_clusters, self.n_train, self.max_cluster_points, self.opt_points, self.table_size,
             het) = s[:6]
            self.heteroscedastic = bool(het)
            self.clip_patterns = bool(s[6]) if len(s) > 6 else False
        if "eps_rel" in p:
            self.eps_rel = float(p["eps_rel"])
        self.input_warp = float(p["input_warp"]) if "input_warp" in p else 0.0
        if not (np.isfinite(self.input_warp) and self.input_warp >= 0):
            raise ModelFileError("GP model input_warp must be a finite value >= 0")
        nodes = np.asarray(p["table_nodes"], dtype=np.float64)
        vals = np.asarray(p["table_values"], dtype=np.float64)
        for a in (self.centroids, self.X, self.T, self.theta, self.theta_noise, self.log_noise, self.t_mean,
                  self.t_std, vals):
            if not np.all(np.isfinite(a)):
                raise ModelFileError("GP model arrays contain NaN or inf")
        self._factors = {}
        if nodes.size:
            n = nodes.shape[0]
            if vals.shape != (n, n, n, 6):
                raise ModelFileError("GP prediction table has an inconsistent shape")
            vals = vals.copy()      # tables of files written before the variance cap get it too
            vals[..., 3:] = np.minimum(vals[..., 3:], np.log(self._log_var_cap()))
            self._table = _Table(nodes, vals)
        else:
            self._table = None
        self.table_nodes_, self.table_values_ = nodes, vals


# ============================================================================ polynomial baseline
def _srgb_encode(u: np.ndarray) -> np.ndarray:
    """sRGB OETF (IEC 61966-2-1) of ``clip(u, 0, 1)``, float64."""
    u = np.clip(u, 0.0, 1.0)
    return np.where(u <= 0.0031308, 12.92 * u, 1.055 * np.power(np.maximum(u, 0.0031308), 1.0 / 2.4) - 0.055)


def _srgb_encode_slope(u: np.ndarray) -> np.ndarray:
    """d/du of :func:`_srgb_encode` (0 outside (0, 1), where the clip makes it flat)."""
    inside = (u > 0.0) & (u < 1.0)
    slope = np.where(u <= 0.0031308, 12.92, (1.055 / 2.4) * np.power(np.maximum(u, 0.0031308), 1.0 / 2.4 - 1.0))
    return slope * inside


def _bernstein(t: np.ndarray, n: int) -> np.ndarray:
    """Bernstein basis ``B_k,n(t) = binom(n, k) t^k (1 - t)^(n - k)``, k = 0..n: (M, n + 1)."""
    from math import comb

    t = np.asarray(t, dtype=np.float64)
    tp = np.empty((t.shape[0], n + 1))      # t^k by repeated products (far faster than float powers)
    sp = np.empty((t.shape[0], n + 1))      # (1 - t)^(n - k)
    tp[:, 0] = 1.0
    sp[:, n] = 1.0
    s = 1.0 - t
    for k in range(1, n + 1):
        np.multiply(tp[:, k - 1], t, out=tp[:, k])
        np.multiply(sp[:, n - k + 1], s, out=sp[:, n - k])
    tp *= sp
    tp *= np.array([comb(n, k) for k in range(n + 1)], dtype=np.float64)
    return tp


def _bernstein_slope(t: np.ndarray, n: int) -> np.ndarray:
    """d/dt of the Bernstein basis: ``n (B_k-1,n-1 - B_k,n-1)``: (M, n + 1)."""
    b = _bernstein(t, n - 1)
    out = np.zeros((b.shape[0], n + 1))
    out[:, 1:] += n * b
    out[:, :-1] -= n * b
    return out


class PolynomialModel(DerenderModel):
    """Chakrabarti-style deterministic baseline (paper 2, Sec. 4.1, ref. [3]).

    Forward model (per output channel c, rendered value ``y_c = code_c / 255``)::

        y_c = f_c(s(u_c)),   u = C x,   x = raw / raw_white

    with a 3x3 matrix C, ``s`` the sRGB encoding of ``clip(u, 0, 1)`` (so that f_c is close
    to the identity and smooth in the space where the codes are quantised), and ``f_c`` a
    polynomial of degree ``degree`` in Bernstein form, ``f_c(t) = sum_k b_ck B_k,n(t)``,
    whose coefficients are non-decreasing in k -- monotone by construction (the constraint
    is ``b_ck - b_c,k-1 >= 0``, a bound in the solver).

    Fitting, on pairs whose codes all lie in ``fit_range`` (clipped codes excluded, as in
    [3]): C is initialised by trimmed, relatively weighted least squares from ``x`` to the
    sRGB-decoded codes of mid-range pairs (f = identity); then each channel's row of C and
    its curve are fitted jointly (channel c depends only on row c of C and on f_c) by
    bounded nonlinear least squares on the code residuals with a Cauchy loss
    (``scipy.optimize.least_squares``), whose scale is lowered from 10x to 1x
    ``robust_scale`` codes (graduated non-convexity; without it the fit of the blue row
    ended in different local minima for different initialisations). The
    robust loss ignores pairs the model cannot explain: colours that saturated the sensor
    but still render below 255 (their stored raw is the unclipped truth, up to ~50x the
    raw white on a chart session) and strongly gamut-mapped colours.

    De-rendering inverts each ``f_c o s`` numerically with a monotone look-up table over
    ``t in [0, 1]`` (values outside the curve's range are clamped, so u in [0, 1]), then
    applies C^-1; 8-bit codes use a per-channel 256-entry table. Variance: constant per
    channel, the mean squared residual of the de-rendered training colours (all training
    pairs).
    """

    method = "poly"
    _param_names = ("C", "bernstein", "raw_white", "resid_var")

    def __init__(self, degree: int = 10, fit_range: tuple[int, int] = (1, 254), n_iter: int = 100,
                 lut_size: int = 4096, robust_scale: float = 3.0, seed: int = 0, metadata: dict | None = None):
        super().__init__(seed=seed, metadata=metadata)
        if degree < 1 or lut_size < 16 or n_iter < 1 or not robust_scale > 0:
            raise InputError("polynomial settings: degree >= 1, lut_size >= 16, n_iter >= 1, robust_scale > 0")
        self.degree = int(degree)
        self.fit_range = (int(fit_range[0]), int(fit_range[1]))
        self.n_iter = int(n_iter)
        self.lut_size = int(lut_size)
        self.robust_scale = float(robust_scale)

    @staticmethod
    def _init_matrix(xs: np.ndarray, codes: np.ndarray) -> np.ndarray:
        """C0: least squares x -> srgb_decode(y), relative weights, on mid-range pairs, 3 trimming rounds."""
        mid = np.all((codes >= 20) & (codes <= 235), axis=1)
        if np.count_nonzero(mid) < 30:
            mid = np.ones(codes.shape[0], dtype=bool)
        X = xs[mid]
        Y = _srgb_decode(codes[mid] / 255.0)
        w = 1.0 / np.maximum(np.linalg.norm(Y, axis=1), 1e-3)
        keep = np.ones(X.shape[0], dtype=bool)
        for _ in range(3):
            C = np.linalg.lstsq(X[keep] * w[keep, None], Y[keep] * w[keep, None], rcond=None)[0].T
            rel = np.linalg.norm(X @ C.T - Y, axis=1) * w
            keep = rel <= np.percentile(rel, 80)   # sensor-saturated and gamut-mapped pairs drop out
        return C

    def _fit_channel(self, xs: np.ndarray, yc: np.ndarray, row0: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Row of C and Bernstein coefficients of one channel: robust bounded least squares."""
        from scipy.optimize import least_squares

        n = self.degree

        def residuals(p):
            return _bernstein(_srgb_encode(xs @ p[:3]), n) @ np.cumsum(p[3:]) - yc

        def jacobian(p):
            u = xs @ p[:3]
            t = _srgb_encode(u)
            J = np.empty((yc.shape[0], 4 + n))
            J[:, :3] = ((_bernstein_slope(t, n) @ np.cumsum(p[3:])) * _srgb_encode_slope(u))[:, None] * xs
            J[:, 3:] = np.cumsum(_bernstein(t, n)[:, ::-1], axis=1)[:, ::-1]   # b = cumsum(p[3:])
            return J

        lb = np.concatenate([np.full(4, -np.inf), np.zeros(n)])   # b_0 and C row free; increments >= 0
        p = np.concatenate([row0, [0.0], np.full(n, 1.0 / n)])   # f = identity
        nfev = 0
        for g in (10.0, 3.0, 1.0):
            r = least_squares(residuals, np.maximum(p, lb), jac=jacobian, bounds=(lb, np.inf), loss="cauchy",
                              f_scale=g * self.robust_scale / 255.0, method="trf", x_scale="jac",
                              max_nfev=self.n_iter)
            p, nfev = r.x, nfev + r.nfev
        return p[:3], np.cumsum(p[3:]), nfev

    def _fit(self, jf, rf):
        self.raw_white = _raw_white(jf, rf)
        x = rf / self.raw_white
        lo, hi = self.fit_range
        sel = np.all((jf >= lo) & (jf <= hi), axis=1)
        if np.count_nonzero(sel) < 3 * (self.degree + 4):
            sel = np.ones(jf.shape[0], dtype=bool)
        xs, js = x[sel], jf[sel]
        C0 = self._init_matrix(xs, js)
        if not np.all(np.isfinite(C0)) or np.linalg.cond(C0) > 1e8:
            raise InputError("polynomial model: the fitted 3x3 colour matrix is singular "
                             "(training colours do not span three dimensions)")
        from threadpoolctl import threadpool_limits

        C = np.empty((3, 3))
        b = np.empty((3, self.degree + 1))
        nfev = 0
        with threadpool_limits(1, user_api="blas"):   # tiny SVDs: threaded BLAS is 50x slower on a busy machine
            for c in range(3):
                C[c], b[c], k = self._fit_channel(xs, js[:, c] / 255.0, C0[c])
                nfev += k
        self.C, self.bernstein = C, b
        self._make_lut()
        mean = self._invert(jf)
        self.resid_var = np.maximum(np.mean((mean - rf) ** 2, axis=0), 1e-30)
        self.metadata.setdefault("training", {}).update(
            {"n_fit": int(np.count_nonzero(sel)), "degree": self.degree, "fit_range": list(self.fit_range),
             "robust_scale_codes": self.robust_scale, "solver_evaluations": int(nfev),
             "forward_model": "code/255 = bernstein_c(srgb_encode((C raw/raw_white)_c)), monotone"})

    def _make_lut(self):
        if not np.all(np.isfinite(self.C)) or np.linalg.cond(self.C) > 1e8:
            raise InputError("polynomial model: the fitted 3x3 colour matrix is singular "
                             "(training colours do not span three dimensions)")
        t = np.linspace(0.0, 1.0, self.lut_size)
        u = _srgb_decode(t)
        f = np.maximum.accumulate(_bernstein(t, self.degree) @ self.bernstein.T, axis=0)   # (lut, 3)
        self._inverse = []
        for c in range(3):
            # np.interp needs increasing xp: plateaus resolve to their first u; outside: clamped
            fq, first = np.unique(f[:, c], return_index=True)
            self._inverse.append((fq, u[first]))
        self._Cinv = np.linalg.inv(self.C)
        y = np.arange(256.0) / 255.0
        self._u_of_code = np.stack([np.interp(y, *self._inverse[c]) for c in range(3)], axis=1)  # (256, 3)

    def _invert(self, codes: np.ndarray, integer: bool = False) -> np.ndarray:
        """De-render (M,3) codes: per-channel monotone inversion of f_c o s, then C^-1 (raw units)."""
        if integer:
            c = codes.astype(np.intp)
            u = np.stack([self._u_of_code[c[:, k], k] for k in range(3)], axis=1)
        else:
            y = np.asarray(codes, dtype=np.float64) / 255.0
            u = np.stack([np.interp(y[:, k], *self._inverse[k]) for k in range(3)], axis=1)
        return (u @ self._Cinv.T) * self.raw_white

    def _predict_codes(self, codes, integer, exact, median):
        mean = self._invert(codes, integer)
        var = np.broadcast_to(self.resid_var, mean.shape).copy()
        return mean, var

    def _get_params(self):
        return {"C": self.C, "bernstein": self.bernstein, "raw_white": np.array(self.raw_white),
                "resid_var": self.resid_var, "robust_scale": np.array(self.robust_scale),
                "settings": np.array([self.degree, self.fit_range[0], self.fit_range[1], self.n_iter,
                                      self.lut_size], dtype=np.int64)}

    def _set_params(self, p):
        self.C = np.asarray(p["C"], dtype=np.float64)
        self.bernstein = np.asarray(p["bernstein"], dtype=np.float64)
        self.raw_white = float(p["raw_white"])
        self.resid_var = np.asarray(p["resid_var"], dtype=np.float64)
        if (self.C.shape != (3, 3) or self.bernstein.ndim != 2 or self.bernstein.shape[0] != 3
                or self.bernstein.shape[1] < 2 or self.resid_var.shape != (3,)):
            raise ModelFileError("polynomial model arrays have inconsistent shapes")
        if not (np.all(np.isfinite(self.bernstein)) and self.raw_white > 0):
            raise ModelFileError("polynomial model arrays hold non-finite or non-positive values")
        if "settings" in p:
            s = np.asarray(p["settings"]).astype(int).tolist()
            self.degree, lo, hi, self.n_iter, self.lut_size = s
            self.fit_range = (lo, hi)
        if "robust_scale" in p:
            self.robust_scale = float(p["robust_scale"])
        self.degree = self.bernstein.shape[1] - 1
        self._make_lut()


# ============================================================================ RBF baseline
class RBFModel(DerenderModel):
    """Lin-style RBF regression (paper 2, Sec. 4.1, ref. [18]): code/255 -> log(max(raw,0)+eps).

    A smoothing thin-plate spline ``r^2 log r`` with a linear polynomial tail on at most
    ``n_train`` pairs (the linear system of ``scipy.interpolate.RBFInterpolator`` with
    ``kernel="thin_plate_spline", degree=1``; ``smoothing`` is added to the kernel
    diagonal, 1e-3 chosen on held-out synthetic colours). Same log target as the GP.
    Variance: constant per channel in log space, the mean squared training residual,
    returned as log-normal moments (so the raw-space variance scales with the squared
    mean). Predictions go through the same interpolated table as the GP (``exact=True``
    evaluates the RBF itself).
    """

    method = "rbf"
    _param_names = ("centers", "coeffs", "eps", "resid_var", "table_nodes", "table_values")

    def __init__(self, n_train: int = 5000, smoothing: float = 1e-3, kernel: str = "thin_plate_spline",
                 eps_rel: float = 1e-4, table_size: int = 40, seed: int = 0, metadata: dict | None = None):
        super().__init__(seed=seed, metadata=metadata)
        if n_train < 20 or smoothing < 0 or not eps_rel > 0:
            raise InputError("invalid RBF settings (n_train >= 20, smoothing >= 0, eps_rel > 0)")
        if kernel != "thin_plate_spline":
            raise InputError("only kernel='thin_plate_spline' is supported (scale-free, no shape parameter)")
        self.n_train = int(n_train)
        self.smoothing = float(smoothing)
        self.kernel = kernel
        self.eps_rel = float(eps_rel)
        self.table_size = int(table_size)
        self._table: _Table | None = None

    def _fit(self, jf, rf):
        _, jf, rf, Y, T = _log_training_targets(self, jf, rf)
        # smoothing thin-plate spline with linear tail (same system as scipy's RBFInterpolator):
        # [K + smoothing I, P; P^T, 0] [w; c] = [T; 0],  K_ij = r_ij^2 log r_ij,  P = [1, y]
        n = Y.shape[0]
        P = np.hstack([np.ones((n, 1)), Y])
        A = np.zeros((n + 4, n + 4))
        A[:n, :n] = self._tps(Y, Y)
        A.flat[: n * (n + 4): n + 5] += self.smoothing
        A[:n, n:] = P
        A[n:, :n] = P.T
        rhs = np.vstack([T, np.zeros((4, 3))])
        from scipy.linalg import LinAlgError, solve
        from threadpoolctl import threadpool_limits

        try:
            with threadpool_limits(1, user_api="blas"):   # threaded sytrf is very slow on a busy machine
                self.coeffs = solve(A, rhs, assume_a="sym")
        except LinAlgError:
            raise InputError("RBF system is singular (use smoothing > 0 or more distinct colours)") from None
        self.centers = Y
        self.resid_var = np.maximum(np.mean((self._latent_exact(Y) - T) ** 2, axis=0), 1e-12)
        self._build_table()
        self.metadata.setdefault("training", {}).update(
            {"n_train": int(n), "kernel": self.kernel, "smoothing": self.smoothing,
             "target": "log(max(raw,0)+eps)"})

    @staticmethod
    def _tps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d2 = a @ b.T
        d2 *= -2.0
        d2 += (a * a).sum(1)[:, None]
        d2 += (b * b).sum(1)[None, :]
        np.maximum(d2, 1e-300, out=d2)
        k = np.log(d2)
        k *= d2
        k *= 0.5
        return k  # r^2 log r

    def _latent_exact(self, Y: np.ndarray) -> np.ndarray:
        """Evaluate the fitted RBF (thin-plate spline + linear tail) at Y (M,3) in [0,1]."""
        out = np.empty((Y.shape[0], 3))
        n = self.centers.shape[0]
        for s in range(0, Y.shape[0], 2048):
            y = Y[s:s + 2048]
            out[s:s + 2048] = self._tps(y, self.centers) @ self.coeffs[:n] + self.coeffs[n] + y @ self.coeffs[n + 1:]
        return out

    def _build_table(self):
        if self.table_size <= 0:
            self._table = None
            self.table_nodes_ = np.zeros(0)
            self.table_values_ = np.zeros((0, 0, 0, 3))
            return
        nodes = table_nodes(self.table_size)
        g = np.stack(np.meshgrid(nodes, nodes, nodes, indexing="ij"), axis=-1).reshape(-1, 3) / 255.0
        n = nodes.shape[0]
        self.table_nodes_ = nodes
        self.table_values_ = self._latent_exact(g).reshape(n, n, n, 3)
        self._table = _Table(nodes, self.table_values_)

    def _predict_codes(self, codes, integer, exact, median):
        if exact or self._table is None:
            mu = self._latent_exact(codes / 255.0)
        elif integer:
            (mu,) = self._table.at_codes(codes)
            lv = np.empty_like(mu)
            lv[...] = np.log(self.resid_var).astype(np.float32)
            return _lognormal_moments_inplace(mu, lv, self.eps, median)
        else:
            mu = self._table.at_float(codes)
        return _lognormal_moments(mu, np.broadcast_to(self.resid_var, mu.shape), self.eps, median)

    def _get_params(self):
        return {"centers": self.centers, "coeffs": self.coeffs, "eps": np.array(self.eps),
                "raw_white": np.array(self.raw_white),
                "resid_var": self.resid_var, "table_nodes": self.table_nodes_,
                "table_values": self.table_values_, "smoothing": np.array(self.smoothing),
                "n_train": np.array(self.n_train), "eps_rel": np.array(self.eps_rel)}

    def _set_params(self, p):
        self.centers = np.asarray(p["centers"], dtype=np.float64)
        self.coeffs = np.asarray(p["coeffs"], dtype=np.float64)
        self.eps = float(p["eps"])
        self.raw_white = float(p.get("raw_white", np.array(1.0)))
        self.resid_var = np.asarray(p["resid_var"], dtype=np.float64)
        n = self.centers.shape[0]
        if (self.centers.ndim != 2 or self.centers.shape[1] != 3 or self.coeffs.shape != (n + 4, 3)
                or self.resid_var.shape != (3,) or not self.eps > 0):
            raise ModelFileError("RBF model arrays have inconsistent shapes")
        for key, attr in (("smoothing", "smoothing"), ("eps_rel", "eps_rel")):
            if key in p:
                setattr(self, attr, float(p[key]))
        if "n_train" in p:
            self.n_train = int(p["n_train"])
        nodes = np.asarray(p["table_nodes"], dtype=np.float64)
        vals = np.asarray(p["table_values"], dtype=np.float64)
        if nodes.size:
            m = nodes.shape[0]
            if vals.shape != (m, m, m, 3):
                raise ModelFileError("RBF prediction table has an inconsistent shape")
            self._table = _Table(nodes, vals)
        else:
            self._table = None
        self.table_nodes_, self.table_values_ = nodes, vals


# ============================================================================ registry, metrics
MODEL_TYPES: dict[str, type[DerenderModel]] = {
    "gp": LocalGPModel,
    "poly": PolynomialModel,
    "rbf": RBFModel,
}

def model_metadata(pairs) -> dict:
    """Metadata a de-rendering model keeps from its calibration pairs (camera, WB, colour matrix)."""
    return {"camera": {"name": pairs.camera, "make": pairs.make, "model": pairs.model},
            "camera_to_srgb": np.asarray(pairs.camera_to_srgb).tolist(), "wb": np.asarray(pairs.wb).tolist()}


def fit_model(method: str, jpeg, raw, seed: int = 0, **kw) -> DerenderModel:
    """Fit a de-rendering model by name (``"gp"``, ``"poly"``, ``"rbf"``); extra keywords go to the class."""
    if method not in MODEL_TYPES:
        raise InputError(f"unknown de-rendering method '{method}' (choose from {', '.join(MODEL_TYPES)})")
    try:
        model = MODEL_TYPES[method](seed=seed, **kw)
    except TypeError as exc:
        raise InputError(f"bad option for method '{method}': {exc}") from None
    return model.fit(jpeg, raw)


def _pair_arrays(pred, truth) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(pred, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    if p.shape != t.shape:
        raise InputError(f"prediction and truth shapes differ: {np.shape(pred)} vs {np.shape(truth)}")
    return p, t


def relative_rmse(pred, truth) -> float:
    """sqrt(mean_i ||x_hat_i - x_i||^2 / ||x_i||^2) over colours with ||x_i|| > 0 (paper 2, Table 1)."""
    p, t = _pair_arrays(pred, truth)
    n2 = (t * t).sum(1)
    ok = n2 > 0
    return float(np.sqrt(np.mean(((p[ok] - t[ok]) ** 2).sum(1) / n2[ok])))


def rmse(pred, truth) -> float:
    """sqrt(mean_i ||x_hat_i - x_i||^2): RMS Euclidean error per colour vector."""
    p, t = _pair_arrays(pred, truth)
    return float(np.sqrt(np.mean(((p - t) ** 2).sum(1))))


def median_relative_error(pred, truth) -> float:
    """median_i ||x_hat_i - x_i|| / ||x_i|| over colours with ||x_i|| > 0."""
    p, t = _pair_arrays(pred, truth)
    n = np.sqrt((t * t).sum(1))
    ok = n > 0
    return float(np.median(np.sqrt(((p[ok] - t[ok]) ** 2).sum(1)) / n[ok]))


def code_floor_errors(codes, truth) -> np.ndarray:
    """Per-colour squared relative errors of the best possible function of the 8-bit code.

    Colours sharing a code get the one point ``v = sum_i x_i/|x_i|^2 / sum_i 1/|x_i|^2``
    minimising ``sum_i ||v - x_i||^2 / ||x_i||^2`` over them, fitted to ``truth`` itself; so
    ``sqrt(mean(errors))`` is a lower bound on the :func:`relative_rmse` that *any* model
    predicting from the code alone (GP, polynomial, RBF, a look-up table) can reach on these
    colours. It is far from zero where rendering is one-to-many: clipped (255) channels and
    near-black codes. Colours with ``||x|| = 0`` are left out (as in :func:`relative_rmse`).
    """
    c = np.asarray(codes)
    t = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    c = c.reshape(-1, 3)
    if c.shape != t.shape:
        raise InputError(f"codes and truth shapes differ: {np.shape(codes)} vs {np.shape(truth)}")
    n2 = (t * t).sum(1)
    ok = n2 > 0
    c, t, n2 = c[ok], t[ok], n2[ok]
    if t.shape[0] == 0:
        return np.zeros(0)
    _, inv = np.unique(np.rint(c).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    w = 1.0 / n2
    k = int(inv.max()) + 1
    wsum = np.bincount(inv, w, k)
    v = np.stack([np.bincount(inv, t[:, ch] * w, k) for ch in range(3)], axis=1) / wsum[:, None]
    return ((v[inv] - t) ** 2).sum(1) * w


def interval_coverage(mean, var, truth, level: float = 0.95) -> np.ndarray:
    """Per-channel fraction of truths inside the central Gaussian interval mean +- z sqrt(var)."""
    if not 0 < level < 1:
        raise InputError("level must be in (0, 1)")
    m, t = _pair_arrays(mean, truth)
    v = np.asarray(var, dtype=np.float64).reshape(-1, 3)
    if v.shape != m.shape:
        raise InputError("variance shape differs from mean shape")
    from scipy.special import ndtri

    z = float(ndtri(0.5 + level / 2))
    return np.mean(np.abs(t - m) <= z * np.sqrt(np.maximum(v, 0.0)), axis=0)
