"""The deterministic baseline of Chakrabarti et al. (paper 2, Sec. 4.1, ref. [3]): method ``"poly"``.

Forward model, per output channel c, rendered value ``y_c = code_c / 255``::

    y_c = f_c(s(u_c)),   u = C x,   x = raw / raw_white,
    f_c(t) = sum_k b_ck B_k,n(t),   B_k,n(t) = binom(n, k) t^k (1 - t)^(n - k),   b_c,k >= b_c,k-1

a 3x3 linear map C, the sRGB encoding ``s`` of ``clip(u, 0, 1)``, then a monotone
polynomial curve per channel in Bernstein form, fitted jointly with C by robust (Cauchy)
least squares on the code residuals. De-rendering inverts it numerically:
``u_c = (f_c o s)^-1(y_c)`` by a monotone look-up table per channel, then
``x_hat = raw_white C^-1 u``. The variance is constant per channel (mean squared
training residual). Details and the fitting procedure: :class:`PolynomialModel`.
"""

from __future__ import annotations

import numpy as np

from derender.core.errors import InputError, ModelFileError
from derender.derendering.base import DerenderModel
from derender.derendering.log_space import estimate_raw_white, srgb_decode64

__all__ = [
    "PolynomialModel",
]


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

    Parameters
    ----------
    degree : int
        Degree n of each channel's Bernstein polynomial ``f_c`` (at least 1).
    fit_range : (int, int)
        The codes a training pair's three codes must all lie in (clipped codes excluded).
    n_iter : int
        Iterations of each nonlinear least-squares stage (at least 1).
    lut_size : int
        Entries of the look-up table that inverts ``f_c o s`` for real-valued inputs (at
        least 16).
    robust_scale : float
        The Cauchy loss's final scale, in codes (positive).
    seed : int
        Seed of the fit's random steps.
    metadata : dict, optional
        Stored with the model (camera, illuminants, matrices).

    Raises
    ------
    InputError
        Settings out of range.

    Examples
    --------
    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> model = derender.PolynomialModel(degree=4).fit(jpeg, raw)
    >>> mean, variance = model.predict(np.array([[128, 128, 128]], np.uint8))
    >>> bool(np.allclose(mean, 0.5 ** 2.2, atol=0.01)), variance.shape
    (True, (1, 3))
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
        Y = srgb_decode64(codes[mid] / 255.0)
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
        self.raw_white = estimate_raw_white(jf, rf)
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
        u = srgb_decode64(t)
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
