"""The radial-basis-function baseline of Lin et al. (paper 2, Sec. 4.1, ref. [18]): method ``"rbf"``.

Regression from the rendered colour ``y = code / 255`` to the log raw colour
``t = log(max(raw, 0) + eps)`` (the target of :mod:`derender.derendering.log_space`): a
smoothing thin-plate spline with a linear tail,
``t(y) = sum_i w_i phi(||y - y_i||) + c_0 + c^T y`` with ``phi(r) = r^2 log r``, solving
``[K + smoothing I, P; P^T, 0] [w; c] = [T; 0]`` with ``K_ij = phi(||y_i - y_j||)`` and
``P_i = [1, y_i]`` (the same linear system as ``scipy.interpolate.RBFInterpolator``). The
variance is constant per channel in log space (mean squared training residual) and the
Gaussian over ``t`` is returned as log-normal moments in raw space, as for the GP.
"""

from __future__ import annotations

import numpy as np

from derender.core.errors import InputError, ModelFileError
from derender.derendering.base import DerenderModel
from derender.derendering.log_space import (
    LatentTable,
    log_training_targets,
    lognormal_moments,
    lognormal_moments_inplace,
    table_nodes,
)

__all__ = [
    "RBFModel",
]


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

    Parameters
    ----------
    n_train : int
        Training pairs at most (a random subset when there are more; at least 20).
    smoothing : float
        Added to the kernel diagonal (0: interpolation).
    kernel : str
        ``"thin_plate_spline"`` (the only one: scale-free, no shape parameter).
    eps_rel : float
        The log offset ``eps``, relative to the raw white level.
    table_size : int
        Nodes per axis of the prediction table (0: always exact).
    seed : int
        Seeds the subset.
    metadata : dict, optional
        Stored with the model (camera, illuminants, matrices).

    Raises
    ------
    InputError
        Settings out of range, or another kernel.

    Examples
    --------
    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> model = derender.RBFModel(table_size=0).fit(jpeg, raw)
    >>> mean, variance = model.predict(np.array([[128, 128, 128]], np.uint8))
    >>> bool(np.allclose(mean, 0.5 ** 2.2, atol=0.02)), mean.dtype
    (True, dtype('float32'))
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
        self._table: LatentTable | None = None

    def _fit(self, jf, rf):
        _, jf, rf, Y, T = log_training_targets(self, jf, rf)
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
        self._table = LatentTable(nodes, self.table_values_)

    def _predict_codes(self, codes, integer, exact, median):
        if exact or self._table is None:
            mu = self._latent_exact(codes / 255.0)
        elif integer:
            (mu,) = self._table.at_codes(codes)
            lv = np.empty_like(mu)
            lv[...] = np.log(self.resid_var).astype(np.float32)
            return lognormal_moments_inplace(mu, lv, self.eps, median)
        else:
            mu = self._table.at_float(codes)
        return lognormal_moments(mu, np.broadcast_to(self.resid_var, mu.shape), self.eps, median)

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
            self._table = LatentTable(nodes, vals)
        else:
            self._table = None
        self.table_nodes_, self.table_values_ = nodes, vals
