"""The offline local Gaussian process of paper 2 (Sec. 2.2 and 4): method ``"gp"``.

Paper 2 (Xiong et al., CVPR 2012, "From pixels to physics: probabilistic color
de-rendering"), Sec. 4: k-means (k = 10) on
the rendered inputs ``y = code / 255``, one GP per cluster and output channel (eq. 1,
``x^c = z^c(y) + eps``), squared-exponential kernel with automatic relevance
determination (one length-scale per input channel) plus white noise,
``k(a, b) = sf^2 exp(-0.5 sum_d (a_d - b_d)^2 / l_d^2) + sn^2 [a = b]``, hyper-parameters
by maximum marginal likelihood (L-BFGS-B on the exact log marginal likelihood and its
gradient, Rasmussen & Williams eq. 2.30, 5.8/5.9: :mod:`derender.derendering.heteroscedastic_gp`,
compiled as :func:`derender.derendering.gp_kernels.gp_nll` for the search). A test colour uses the
GP of its nearest cluster centre (eq. 2 with D_N(y) = that cluster). The target is the
log raw colour ``t = log(max(raw, 0) + eps)`` of :mod:`derender.derendering.log_space`,
standardised per cluster; with the cluster's training inputs X, targets z and noise
covariance ``S = sn^2 diag(r(X))`` the prediction at ``y`` is

    mu(y) = k(y, X) (K + S)^-1 z,
    s2(y) = min(sf^2 - k(y, X) (K + S)^-1 k(X, y), 1) + sn^2 r(y)     (predictive, incl. noise)

(Rasmussen & Williams eqs. 2.25-2.26), then un-standardised, returned as log-normal
moments in raw space (:func:`~derender.derendering.log_space.lognormal_moments`). The ``min(., 1)``
is beyond the textbook: the latent variance of the standardised target never exceeds the
variance of the cluster's own targets (1), so where the GP extrapolates (clipped channels,
colours far from every training colour) it says "as uncertain as the whole cluster" instead of
tending to the ML signal variance sf^2 (up to 15 measured). The predictive mean
``exp(mu + s2/2) - eps`` is then at most ``exp(t_std^2 (1 + sn^2 r_max) / 2)`` times the median
``exp(mu) - eps`` (``docs/paper2.md`` gives what the cap changed).

Two departures from the paper's plain local GP, both to keep the variance calibrated
where the rendering is one-to-many (paper 2, Sec. 2.1 and Fig. 2): colours with a
clipped (255) channel are clustered separately from unclipped ones (optionally one group
per clip pattern), and each GP has an input-dependent noise variance ``sn^2 r(y)``,
``r = exp(g)`` with ``g`` a GP regression of ``log(loo_i^2) - E[log chi^2_1]`` on the
leave-one-out residuals ``loo_i`` (most-likely heteroscedastic GP, Kersting et al. 2007),
bounded at prediction by its range over the training colours. The whole predictive
variance of ``t`` is also capped at the variance of ``t`` over the training colours (a
cluster extrapolating with a huge signal variance otherwise reported log-variances of 40+).

Where the error comes from (measured on the simulated S90 chart, MAP point): 75 % of the
GP's squared relative error is colours with a channel at 255 (18 % of the colours,
relative RMSE 0.48) and 15 % near-black codes (max code <= 6, 5 %, 0.40). On the clipped
colours the GP matches a leave-one-out look-up of the best point per code over all
49,280 pairs (0.47-0.49): that error is the rendering's, not the model's. The ``floor``
row of ``derender experiment derender-table``
(:func:`derender.evaluation.derendering_metrics.code_floor_errors`) is the bound no
function of the code can beat on the test colours.
"""

from __future__ import annotations

import os

import numpy as np

from derender.core.errors import InputError, ModelFileError
from derender.derendering.base import DerenderModel, as_colour_array
from derender.derendering.heteroscedastic_gp import fit_channel, noise_gp_weights, se_kernel
from derender.derendering.log_space import (
    MAX_LOG_VAR,
    LatentTable,
    log_training_targets,
    lognormal_moments,
    lognormal_moments_inplace,
    srgb_decode64,
    table_nodes,
)

__all__ = [
    "LocalGPModel",
]

#: Cap on the latent (signal) predictive variance of a standardised cluster target: the variance of the
#: cluster's own training targets (1 after standardisation). Where the GP extrapolates, the posterior
#: variance tends to the ML signal variance sf^2, which reached 15 (simulated camera family, blue channel
#: of an unclipped cluster, length-scale 12 codes): a colour 25 codes from the nearest training colour got a
#: log-variance of 7.45 with its log mean right within 0.06, a predictive mean 36x the truth and 11.9 % of
#: the family's squared relative error (predictive mean). Capped, it says "as uncertain as the cluster".
_LATENT_VAR_CAP = 1.0


# ============================================================================ helpers
def _clip_bits(codes: np.ndarray, clip_code: float) -> np.ndarray:
    """Clip pattern of (M,3) codes: 4 R + 2 G + B for channels >= clip_code (0 = unclipped)."""
    c = codes >= clip_code
    return (4 * c[:, 0] + 2 * c[:, 1] + c[:, 2]).astype(np.int64)


def _map_threads(fn, items: list, n_jobs: int) -> list:
    """``[fn(*it) for it in items]`` on ``n_jobs`` threads with one BLAS thread each, largest first.

    The items are small dense problems (n <= 1000): one BLAS thread per task is far faster than
    oversubscription (measured: a threaded BLAS on a loaded 2-core machine made the ML search ~50x
    slower)."""
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"):
        if n_jobs <= 1 or len(items) <= 1:
            return [fn(*it) for it in items]
        with ThreadPoolExecutor(max_workers=n_jobs) as ex:
            return list(ex.map(lambda it: fn(*it), items))


# ============================================================================ the model
class LocalGPModel(DerenderModel):
    """Offline local GP de-rendering (paper 2, Sec. 2.2 and 4): k-means + per-cluster ARD-SE GPs.

    Target ``t = log(max(raw, 0) + eps)`` per channel, standardised per cluster. Each GP has an
    ARD squared-exponential kernel (a length-scale per input channel) and white noise,
    hyper-parameters by maximum likelihood. With ``heteroscedastic=True`` the noise variance
    varies with the input colour (most-likely heteroscedastic GP, Kersting et al. 2007):
    leave-one-out residuals of the first ML fit give a GP over log noise variance, and the
    hyper-parameters are refitted by maximum likelihood with that noise shape, so clipped
    colours (one-to-many, paper 2 Sec. 2.1) do not inflate the noise of well-determined ones.
    Why each default is what it is, with the measurements, is in ``docs/paper2.md``
    ("Models").

    Parameters
    ----------
    n_clusters : int
        k of the k-means (paper 2: 10).
    n_train : int
        Training pairs (a random subset when there are more).
    max_cluster_points : int
        A cluster's GP size at most (a larger cluster is subsampled).
    opt_points : int
        Points per cluster for the maximum-likelihood search (the final GP uses all its
        cluster's points).
    eps_rel : float
        The log offset ``eps``, relative to the raw white level.
    table_size : int
        Nodes per axis of the prediction table (:func:`table_nodes`; 0: always exact).
    heteroscedastic : bool
        Input-dependent noise (above).
    clip_code : float
        Colours whose largest code is at least this form their own clusters, their share of
        the k clusters following their share of the data.
    clip_patterns : bool
        Clipped colours clustered per clip pattern (at least one cluster per pattern with 20+
        training colours; rarer patterns train with the nearest clipped cluster).
    input_warp : float
        0: inputs ``code / 255`` as in the paper; ``a > 0``: inputs
        ``log(1 + srgb_decode(code / 255) / a)``, normalised (spreads near-black codes).
    n_jobs : int, optional
        Threads for fitting (None: every CPU).
    seed : int
        Seeds the subsets and the k-means.
    metadata : dict, optional
        Stored with the model (camera, illuminants, matrices).

    References
    ----------
    * Y. Xiong, K. Saenko, T. Darrell, T. Zickler, "From pixels to physics: Probabilistic color
      de-rendering", CVPR 2012, Sec. 2.2 and 4.
    * C. E. Rasmussen, C. K. I. Williams, "Gaussian Processes for Machine Learning", MIT Press
      2006, eqs. 2.25-2.26, 2.30, 5.8-5.9.
    * K. Kersting, C. Plagemann, P. Pfaff, W. Burgard, "Most likely heteroscedastic Gaussian
      process regression", ICML 2007. doi:10.1145/1273496.1273546

    Examples
    --------
    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> model = derender.LocalGPModel(n_clusters=2, table_size=0, n_jobs=1).fit(jpeg, raw)
    >>> mean, variance = model.predict(np.array([[128, 128, 128], [255, 255, 255]], np.uint8))
    >>> bool(np.allclose(mean[0], 0.5 ** 2.2, atol=0.01)), mean.dtype, variance.shape
    (True, dtype('float32'), (2, 3))
    """

    method = "gp"
    _param_names = ("centroids", "cluster_group", "X", "T", "offsets", "theta", "theta_noise", "log_noise",
                    "t_mean", "t_std", "eps", "raw_white", "table_nodes", "table_values")

    def __init__(self, *, n_clusters: int = 10, n_train: int = 5000, max_cluster_points: int = 1000,
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
        self._noise_cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._table: LatentTable | None = None

    def _inputs(self, Y: np.ndarray) -> np.ndarray:
        """GP input space from ``Y = code / 255``: ``Y`` itself, or with ``input_warp = a > 0`` the
        log-decoded ``log(1 + srgb_decode(Y) / a) / log(1 + 1 / a)`` (0 -> 0, 1 -> 1)."""
        a = self.input_warp
        if a <= 0:
            return Y
        return np.log1p(srgb_decode64(Y) / a) / np.log1p(1.0 / a)

    # ------------------------------------------------------------------ fitting
    def _fit(self, jf: np.ndarray, rf: np.ndarray) -> None:
        rng, jf, rf, Y, T = log_training_targets(self, jf, rf)
        Y = self._inputs(Y)
        groups, leftover = self._cluster_groups(jf)
        members, centroids, flags = self._clusters(Y, jf, groups, leftover)
        tasks = self._cluster_tasks(members, Y, T, rng)
        n_jobs = self.n_jobs or min(2, os.cpu_count() or 1)
        # one task per (cluster, channel), largest clusters first: the two threads stay balanced
        jobs = sorted(((c, ch) for c in range(len(tasks)) for ch in range(3)), key=lambda j: -tasks[j[0]][0].shape[0])
        res = _map_threads(lambda c, ch: fit_channel(tasks[c][0], (tasks[c][1][:, ch] - tasks[c][2][ch]) / tasks[c][3][ch],
                                                      tasks[c][4], self.heteroscedastic), jobs, n_jobs)
        by = dict(zip(jobs, res))
        fits = [(np.stack([by[c, ch][0] for ch in range(3)]), np.stack([by[c, ch][1] for ch in range(3)]),
                 np.stack([by[c, ch][2] for ch in range(3)], axis=1)) for c in range(len(tasks))]
        self._noise_cache = {key: f[3:] for key, f in by.items()}   # (beta, r) for the table's factors
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

    def _cluster_groups(self, jf: np.ndarray) -> tuple[list, np.ndarray]:
        """Clip-aware k-means groups ``(indices, k, flag)`` (flag as ``cluster_group``), and the
        clipped colours of rare clip patterns left to the nearest clipped cluster.

        Colours with a clipped (255) channel are one-to-many and get their own clusters, so their
        spread neither smooths nor inflates the unclipped GPs."""
        clipped = jf.max(axis=1) >= self.clip_code
        k_total = int(min(self.n_clusters, max(1, jf.shape[0] // 20)))
        n_clip = int(np.count_nonzero(clipped))
        leftover = np.zeros(0, dtype=np.intp)
        if not (k_total >= 2 and n_clip >= 20 and jf.shape[0] - n_clip >= 20):
            return [(np.arange(jf.shape[0]), k_total, -1)], leftover
        k_clip = int(np.clip(round(k_total * n_clip / jf.shape[0]), 1, k_total - 1))
        groups = [(np.flatnonzero(~clipped), k_total - k_clip, 0), (np.flatnonzero(clipped), k_clip, 1)]
        if not self.clip_patterns:
            return groups, leftover
        # one face of the code cube per clip pattern (which channels are at 255)
        bits = _clip_bits(jf, self.clip_code)
        pats, counts = np.unique(bits[clipped], return_counts=True)
        big = [(int(b), int(n)) for b, n in zip(pats, counts) if n >= 20]
        if not big:
            return groups, leftover
        k_clip = int(min(max(k_clip, len(big)), k_total - 1)) if len(big) < k_total else k_clip
        nb = sum(n for _, n in big)
        groups = [(np.flatnonzero(~clipped), k_total - k_clip, 0)]
        for b, n in sorted(big, key=lambda t: -t[1]):
            groups.append((np.flatnonzero(clipped & (bits == b)), max(1, round(k_clip * n / nb)), 1 + b))
        return groups, np.flatnonzero(clipped & ~np.isin(bits, [b for b, _ in big]))

    def _clusters(self, Y: np.ndarray, jf: np.ndarray, groups: list, leftover: np.ndarray) -> tuple[list, list, list]:
        """k-means within each group: the clusters' member indices, centres and group flags (the
        ``leftover`` colours joined to their nearest clipped cluster)."""
        from sklearn.cluster import KMeans
        from threadpoolctl import threadpool_limits

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
        return members, centroids, flags

    def _cluster_tasks(self, members: list, Y: np.ndarray, T: np.ndarray, rng: np.random.Generator) -> list:
        """Per cluster ``(inputs, targets, target mean, target std, optimisation subset)``: at most
        ``max_cluster_points`` members, hyper-parameters fitted on at most ``opt_points`` of them."""
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
        return tasks

    # ------------------------------------------------------------------ exact GP prediction
    def _factor(self, c: int, ch: int) -> tuple[np.ndarray, ...]:
        key = (c, ch)
        if key not in self._factors:   # callers (_latent_exact) hold one BLAS thread per task
            self._factors[key] = self._compute_factor(c, ch)
        return self._factors[key]

    def _compute_factor(self, c: int, ch: int) -> tuple[np.ndarray, ...]:
        X = self.X[self.offsets[c]:self.offsets[c + 1]]
        y = (self.T[self.offsets[c]:self.offsets[c + 1], ch] - self.t_mean[c, ch]) / self.t_std[c, ch]
        th, tn = self.theta[c, ch], self.theta_noise[c, ch]
        cached = self._noise_cache.get((c, ch))
        if cached is not None:      # right after fitting: the fit's own noise GP (same inputs, same values)
            beta, r = cached
        else:
            l = self.log_noise[self.offsets[c]:self.offsets[c + 1], ch]
            beta = noise_gp_weights(X, tn, l)
            r = np.exp(tn[5] + se_kernel(X, X, tn[:3], tn[3]) @ beta)
        K = se_kernel(X, X, th[:3], th[3])
        K.flat[:: X.shape[0] + 1] += np.exp(2 * th[4]) * r + 1e-8 * np.exp(2 * th[3])
        from scipy.linalg import lapack

        L, info = lapack.dpotrf(K, lower=1, clean=1, overwrite_a=1)
        if info != 0:  # pragma: no cover - guarded by the noise floor
            raise ModelFileError("GP covariance is not positive definite (corrupt parameters?)")
        alpha, _ = lapack.dpotrs(L, y, lower=1)
        return alpha, L, beta

    def _latent_exact(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact local-GP prediction at inputs Y (M,3) in [0,1]: mean and variance of t (incl. noise).

        The latent variance is ``sf^2 - ||L^-1 k(X, y)||^2`` (one triangular solve, half the
        flops of ``k^T (K + S)^-1 k``); the (cluster, channel) blocks run on ``n_jobs`` threads."""
        lab = self._assign(Y)
        Y = self._inputs(Y)
        mu = np.empty((Y.shape[0], 3))
        s2 = np.empty((Y.shape[0], 3))
        jobs = []
        for c in range(self.centroids.shape[0]):
            sel = np.flatnonzero(lab == c)
            if sel.size:
                jobs += [(c, ch, sel) for ch in range(3)]
        jobs.sort(key=lambda j: -j[2].size * float(self.offsets[j[0] + 1] - self.offsets[j[0]]) ** 2)

        def block(c: int, ch: int, sel: np.ndarray) -> None:
            from scipy.linalg.blas import dtrsm

            X = self.X[self.offsets[c]:self.offsets[c + 1]]
            alpha, L, beta = self._factor(c, ch)
            th, tn = self.theta[c, ch], self.theta_noise[c, ch]
            sf2, sn2 = np.exp(2 * th[3]), np.exp(2 * th[4])
            for s in range(0, sel.size, 8192):
                rows = sel[s:s + 8192]
                Ks = se_kernel(Y[rows], X, th[:3], th[3])
                m = Ks @ alpha
                g = tn[5] + (Ks @ beta) * np.exp(2 * (tn[3] - th[3]))   # noise GP: same length-scales
                # V = L^-1 Ks^T (triangular solve in place on the Fortran-ordered view Ks^T)
                V = dtrsm(1.0, L, Ks.T, lower=1, overwrite_b=1)
                lat = np.maximum(sf2 - np.einsum("ij,ij->j", V, V), 0.0)
                noise = sn2 * np.exp(np.clip(g, tn[6], tn[7]))
                np.minimum(lat, _LATENT_VAR_CAP, out=lat)   # "I don't know" = the cluster's own spread
                mu[rows, ch] = m * self.t_std[c, ch] + self.t_mean[c, ch]
                s2[rows, ch] = (lat + noise) * self.t_std[c, ch] ** 2

        n_jobs = self.n_jobs or min(2, os.cpu_count() or 1)
        _map_threads(block, jobs, n_jobs if Y.shape[0] >= 4096 else 1)
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
        self._noise_cache = {}
        n = nodes.shape[0]
        vals = np.concatenate([mu, np.log(s2)], axis=1).reshape(n, n, n, 6)
        self.table_nodes_, self.table_values_ = nodes, vals
        self._table = LatentTable(nodes, vals)

    def _predict_codes(self, codes, integer, exact, median):
        if exact or self._table is None:
            mu, s2 = self._latent_exact(codes / 255.0)
        elif integer:
            mu, lv = self._table.at_codes(codes)
            return lognormal_moments_inplace(mu, lv, self.eps, median)
        else:
            v = self._table.at_float(codes)
            mu, s2 = v[:, :3], np.exp(np.minimum(v[:, 3:], np.log(MAX_LOG_VAR)))
        return lognormal_moments(mu, s2, self.eps, median)

    def predict_log(self, colours, exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The GP's own Gaussian over ``t = log(max(raw,0) + eps)``: (mean, variance), float64, colours.shape.

        ``exp(mean) - eps`` is the predictive median of the raw colour.
        """
        if not self.fitted:
            raise InputError("LocalGPModel is not fitted; call fit() or load a model file")
        shape = np.shape(colours)
        flat, is_codes = as_colour_array(colours)
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
        self._noise_cache = {}
        if nodes.size:
            n = nodes.shape[0]
            if vals.shape != (n, n, n, 6):
                raise ModelFileError("GP prediction table has an inconsistent shape")
            vals = vals.copy()      # tables of files written before the variance cap get it too
            vals[..., 3:] = np.minimum(vals[..., 3:], np.log(self._log_var_cap()))
            self._table = LatentTable(nodes, vals)
        else:
            self._table = None
        self.table_nodes_, self.table_values_ = nodes, vals
