"""The log-space output of the GP and RBF de-rendering models and its prediction table.

Output space. Raw values span several decades, so the GP and RBF model the *log* raw
colour ``t = log(max(raw, 0) + eps)`` with ``eps = eps_rel * raw_white`` (``raw_white``
= median raw maximum of bright, unclipped training colours; eps_rel = 1e-4 puts eps
below one 8-bit code step). Rendering errors are multiplicative (quantisation of a
gamma-encoded code is a relative error), so a Gaussian is a far better noise model for
``t`` than for ``raw``, and predictions are scale-equivariant in the raw units. The
Gaussian over ``t`` is returned as the moments of the implied log-normal in raw space
(:func:`lognormal_moments`): ``mean = exp(mu + s2/2) - eps``,
``var = (exp(s2) - 1) exp(2 mu + s2)``, where ``s2`` includes the noise variance
(predictive distribution of an observation). The log-space Gaussian itself is available
from :meth:`LocalGPModel.predict_log <derender.derendering.local_gp.LocalGPModel.predict_log>`
(``exp(mu) - eps`` is the predictive median).

Speed path. :meth:`DerenderModel.predict <derender.derendering.base.DerenderModel.predict>`
computes one prediction per *distinct* colour and gathers. For the GP and RBF the
per-colour prediction is a trilinear interpolation of a table of the
latent ``(mu, log s2)`` (:class:`LatentTable`), evaluated exactly on a rectilinear grid
of codes (denser where the log curve bends, see :func:`table_nodes`; exact at the grid
nodes) and expanded once to every (G, B) code pair, so a colour costs one interpolation
along R. ``exact=True`` evaluates the GP/RBF itself (slow; for evaluation). The table is
built at fit time and stored in the model file.
"""

from __future__ import annotations

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "MAX_LOG_VAR",
    "MAX_LOG_MEAN",
    "srgb_decode64",
    "estimate_raw_white",
    "log_training_targets",
    "lognormal_moments",
    "lognormal_moments_inplace",
    "table_nodes",
    "LatentTable",
]

#: Cap on the latent log-space variance (keeps moments finite in float32).
MAX_LOG_VAR = 60.0
#: Cap on the magnitude of the latent log mean.
MAX_LOG_MEAN = 80.0


def srgb_decode64(v: np.ndarray) -> np.ndarray:
    """Inverse sRGB OETF in float64 (IEC 61966-2-1); :func:`derender.core.colorimetry.srgb_decode` is float32."""
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def estimate_raw_white(jf: np.ndarray, rf: np.ndarray) -> float:
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


def log_training_targets(model, jf: np.ndarray, rf: np.ndarray):
    """Shared by the log-space models: seeded subsample to ``model.n_train`` pairs, set
    ``model.raw_white`` and ``model.eps``; returns (rng, jf, rf, inputs code/255, log targets)."""
    rng = np.random.default_rng(model.seed)
    if jf.shape[0] > model.n_train:
        sel = np.sort(rng.choice(jf.shape[0], model.n_train, replace=False))
        jf, rf = jf[sel], rf[sel]
    model.raw_white = estimate_raw_white(jf, rf)
    model.eps = model.eps_rel * model.raw_white
    return rng, jf, rf, jf / 255.0, np.log(np.maximum(rf, 0.0) + model.eps)


def lognormal_moments(mu: np.ndarray, s2: np.ndarray, eps: float,
                      median: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Raw-space (centre, spread) of raw = exp(t) - eps with t ~ N(mu, s2), float64.

    ``median=False``: mean ``exp(mu + s2/2) - eps`` and variance ``(exp(s2) - 1) exp(2 mu + s2)``.
    ``median=True``: median ``exp(mu) - eps`` and the mean squared deviation about it,
    ``exp(2 mu) ((exp(s2) - 1) exp(s2) + (exp(s2/2) - 1)^2)``.
    """
    s2 = np.clip(s2, 0.0, MAX_LOG_VAR)
    big = np.finfo(np.float32).max / 4
    with np.errstate(over="ignore"):
        if not median:
            e = np.exp(np.minimum(np.maximum(mu, -MAX_LOG_MEAN) + 0.5 * s2, 40.0))
            return np.minimum(e - eps, big), np.minimum(np.expm1(s2) * (e * e), big)
        e = np.exp(np.minimum(np.maximum(mu, -MAX_LOG_MEAN), 40.0))
        h = np.exp(0.5 * s2)
        return np.minimum(e - eps, big), np.minimum((np.expm1(s2) * h * h + (h - 1.0) ** 2) * (e * e), big)


def lognormal_moments_inplace(mu: np.ndarray, logvar: np.ndarray, eps: float,
                              median: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Same as :func:`lognormal_moments` from (mu, log s2), float32, reusing the input buffers."""
    big = np.float32(np.finfo(np.float32).max / 4)
    np.minimum(logvar, np.float32(np.log(MAX_LOG_VAR)), out=logvar)
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
    w = np.log(srgb_decode64(codes / 255.0) + offset)
    targets = np.linspace(w[0], w[-1], n - 10)
    nodes = np.interp(targets, w, codes)
    nodes = np.unique(np.concatenate([np.rint(nodes), [0, 1, 2, 3, 250, 251, 252, 253, 254, 255]]))
    return nodes.astype(np.float64)


class LatentTable:
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
