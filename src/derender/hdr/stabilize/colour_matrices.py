"""Colour matrices H_j onto the reference (paper 1, Sec. 3.1, Algorithm 1 step 3.2; eq. 9-10) and a joint variant.

Linearised images are related by 3x3 matrices (eq. 9): ``L_ref = H_j L_j`` with
``H_j = A_ref A_j^-1``. The paper solves the overdetermined system of corresponding pixels
by least squares, "discarding over and under-exposed pixels", inside RANSAC:
:func:`fit_frame_matrix` (weighted least squares in a seeded RANSAC, code-domain error,
block means of :mod:`.blocks`). :func:`colour_matrices_to_reference` fits every image
against the reference directly, or composes neighbouring pairs towards it when the pair
shares too few well-exposed blocks. **The exposure ratio is absorbed in H_j** (as the
paper does after eq. 9): the stabilised images ``I'_j = H_j L_j`` (eq. 10) are all in the
reference's exposure and colour rendering, and the merge divides by ``t_ref``; wrong EXIF
times and gain changes therefore do not bias the colours.

Beyond the paper (its Fig. 5: the result depends on the reference):
:func:`joint_colour_matrices` fits all ``K_j`` at once so that ``K_j L_j / t_j`` agree on
every overlapping pair of images, with the gauge ``mean_j K_j = I`` (times folded in),
i.e. a common linear space equal to the bracket's *average* rendering, no reference at
all (method ``"stabilized-joint"``).

**One rendering, one map** (beyond the paper, issue 36). When every frame has the same
rendering up to exposure, gain and white balance (``A_j = D_j A`` with ``D_j`` diagonal: a
fixed pipeline, one film), ``H_j = A D_ref D_j^-1 A^-1 t_ref / t_j`` is, for any reference, the
same per-channel gains in the rendering's own basis, and the map must not depend on the
reference. Fitting each ``H_j`` on its own path to the reference breaks that: the paths
disagree (on Debevec's Memorial, loops of diagonal pair maps close to 0.95-1.11 per channel;
full 3x3 maps of its near-collinear brown colours add off-diagonals the data do not fix), and
references 7 and 9 gave block chroma changes of 0.92 (p95). Both modes therefore first fit
the neighbour pairs of :func:`_pair_graph` (each a full map and, on the same inliers, a
diagonal one); :func:`diagonal_bracket` calls the bracket diagonal when the median over the
pairs of the diagonal map's robust code residual over the full map's is at most
``1 + DIAGONAL_GAIN``, and then every matrix comes from one set of per-channel gains
consistent over the whole graph (:func:`graph_gains`, ``ln G_j - ln G_k = ln h_jk`` by least
squares): ``H_j = diag(G_j / G_ref)``, ``K_j = c t_j diag(G_j)``. Changing the reference then
multiplies every matrix by one diagonal, which the grey balance (:mod:`.grey_balance`) takes
out again: the map is the same to float32 rounding. Brackets whose rendering changes keep
paper 1's per-reference fits (measured ratios in ``docs/paper1.md``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709
from derender.core.errors import InputError, StackError
from derender.hdr.stabilize.blocks import FIT_FLOOR, FIT_HIGH, FIT_LOW, Blocks
from derender.hdr.stabilize.curves import Curve, as_curve
from derender.hdr.stabilize.pair_fit import RIDGE, effective_codes, fit_pair, pair_weights, predict_codes

__all__ = ["DIAGONAL_GAIN", "fit_frame_matrix", "colour_matrices_to_reference", "joint_colour_matrices",
           "diagonal_bracket", "graph_gains"]


_W = LUMINANCE_WEIGHTS_REC709


#: A bracket counts as one rendering up to per-channel gains (:func:`diagonal_bracket`) when, over
#: the pairs of :func:`_pair_graph`, the median ratio of the diagonal map's robust code residual to
#: the full 3x3 map's is at most ``1 + DIAGONAL_GAIN`` (measured in ``docs/paper1.md``).
DIAGONAL_GAIN = 0.07


def fit_frame_matrix(src_codes: np.ndarray, dst_codes: np.ndarray, gamma_src: "float | Curve",
                     gamma_dst: "float | Curve",
                     *, n_iter: int = 100, sample: int = 4, threshold: float | None = None,
                     seed: int = 0, ridge: float | None = None,
                     max_score: int = 1000, model: str = "full",
                     info: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """H with ``dst_codes ** gamma_dst ~ H @ src_codes ** gamma_src`` (paper 1, eq. 9), by
    weighted least squares inside a seeded RANSAC. ``gamma_*`` are display gammas or
    :class:`Curve` linearisations.

    ``src_codes``, ``dst_codes``: (n, 3) corresponding rendered values in [0, 1] (pixels or
    block means) already restricted to well-exposed ones. Hypotheses are fitted to
    ``sample`` random correspondences; a correspondence is an inlier when its largest
    channel residual in destination code units, divided by its noise scale (errors of
    both images propagated through the map), is below ``threshold`` (default: 3 robust
    standard deviations of the all-data fit, at least 2/255). The best hypothesis' inliers
    are refitted by weighted least squares (code-domain error, 2 reweighting passes) with
    the off-diagonal ridge ``ridge`` (default :data:`RIDGE`; 0 for plain least squares).
    Hypotheses are ranked on at most ``max_score`` evenly spread correspondences (their
    inlier count only orders them); the winner's inliers are found on all.
    Returns ``(H, inlier_mask)``.
    """
    if model not in ("full", "diagonal"):
        raise InputError(f"model must be 'full' or 'diagonal', got {model!r}")
    src = np.asarray(src_codes, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst_codes, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape:
        raise InputError(f"correspondences differ in shape: {src.shape} vs {dst.shape}")
    n = src.shape[0]
    if n < max(sample, 3):
        raise StackError(f"only {n} well-exposed correspondences between two images; cannot fit a 3x3 colour matrix")
    c_src, c_dst = as_curve(gamma_src), as_curve(gamma_dst)
    ls, ld = c_src.lin(src), c_dst.lin(dst)

    def norm_resid(h: np.ndarray) -> np.ndarray:
        pred = predict_codes(h, ls, gamma_dst)
        v, _ = pair_weights(src, np.clip(pred, 1e-3, 1.0), gamma_src, gamma_dst, least_squares=False)
        return (np.abs(pred - dst) * np.sqrt(v)).max(axis=1)

    h_all, _ = fit_pair(src, dst, gamma_src, gamma_dst, ridge=ridge)
    r_all = norm_resid(h_all)
    if threshold is None:
        med = float(np.median(r_all))
        threshold = max(med + 3.0 * 1.4826 * float(np.median(np.abs(r_all - med))), 2.0 / 255.0)
    best = r_all <= threshold
    # hypotheses are scored on at most `max_score` evenly spread correspondences (preemptive
    # RANSAC: the count only ranks hypotheses); the winner's inliers are taken on all of them
    sub = np.arange(n) if n <= max_score else np.linspace(0, n - 1, int(max_score)).astype(np.int64)
    best_cnt, best_h = int(best[sub].sum()), None
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
    # all hypotheses at once: least squares on `sample` distinct random correspondences each
    idx = np.array([np.sort(rng.choice(n, size=sample, replace=False)) for _ in range(int(n_iter))],
                   dtype=np.int64).reshape(-1, sample)
    a = ls[idx]                                            # (iters, sample, 3)
    ata = np.einsum("isk,isl->ikl", a, a)
    atb = np.einsum("isk,isl->ikl", a, ld[idx])
    det = np.linalg.det(ata)
    ok = np.isfinite(det) & (np.abs(det) > 1e-12 * np.einsum("ikk->i", ata) ** 3)
    if ok.any():
        hyp = np.transpose(np.linalg.solve(ata[ok], atb[ok]), (0, 2, 1))     # (m, 3, 3)
        ls_s, src_s, dst_s = ls[sub], src[sub], dst[sub]
        for start in range(0, hyp.shape[0], 64):
            hh = hyp[start:start + 64]
            pred = c_dst.code(np.maximum(np.matmul(ls_s, hh.transpose(0, 2, 1)), 1e-12))
            v, _ = pair_weights(src_s[None], np.clip(pred, 1e-3, 1.0), gamma_src, gamma_dst,
                                least_squares=False)
            inl = (np.abs(pred - dst_s[None]) * np.sqrt(v)).max(axis=2) <= threshold
            cnt = inl.sum(axis=1)
            m = int(np.argmax(cnt))
            if cnt[m] > best_cnt:
                best_cnt, best_h = int(cnt[m]), hh[m]
    if best_h is not None:
        best = norm_resid(best_h) <= threshold
    if best.sum() < 3:
        best = np.ones(n, dtype=bool)
    h, _ = fit_pair(src[best], dst[best], gamma_src, gamma_dst, ridge=ridge)
    inl = norm_resid(h) <= threshold
    if inl.sum() >= max(3, best.sum() // 2):
        h, _ = fit_pair(src[inl], dst[inl], gamma_src, gamma_dst, ridge=ridge)
        best = inl
    if info is not None or model == "diagonal":
        # one gain per channel on the same inliers, and both maps' robust code residuals
        hd, _ = fit_pair(src[best], dst[best], gamma_src, gamma_dst, diagonal=True)
        if info is not None:
            # both residuals on every correspondence (the median is the robust part), not only on
            # the full map's inliers, which its own residuals selected
            info.update(diagonal=hd, rms_full=_code_rms(h, src, dst, gamma_src, gamma_dst),
                        rms_diagonal=_code_rms(hd, src, dst, gamma_src, gamma_dst),
                        inliers=int(best.sum()))
        if model == "diagonal":
            h = hd
    return h, best


def _code_rms(h: np.ndarray, src: np.ndarray, dst: np.ndarray, c_src: "float | Curve", c_dst: "float | Curve") -> float:
    """Robust code-domain residual of ``dst ~ H src``: 1.4826 x the median absolute residual
    over blocks and channels (code units in [0, 1])."""
    pred = predict_codes(h, as_curve(c_src).lin(src), c_dst)
    return float(1.4826 * np.median(np.abs(pred - dst)))


def _neighbour_matrix(blocks: Blocks, j: int, a: int, gammas, *, low: float, high: float, floor: float,
                      n_iter: int, seed: int) -> np.ndarray | None:
    """H (a <- j) fitted on the blocks images j and a share, or None when fewer than 8 blocks
    (too few to pin down 9 entries against noise) or the fit is implausible."""
    jj, ja = _pair_effective(blocks, j, a, gammas, low, high, floor)
    if jj.shape[0] < 8:
        return None
    h, _ = fit_frame_matrix(jj, ja, gammas[j], gammas[a], n_iter=n_iter, seed=seed + 101 * j + a)
    return h if _plausible_matrix(h) else None


def _plausible_matrix(h: np.ndarray) -> bool:
    """A colour matrix between two renderings of one scene: positive luminance gain of
    white and a dominant positive diagonal (each diagonal entry above the sum of the
    absolute off-diagonals of its row, up to a factor 2)."""
    if not np.all(np.isfinite(h)):
        return False
    if float(_W @ h @ np.ones(3)) <= 0:
        return False
    d = np.diag(h)
    off = np.abs(h).sum(axis=1) - np.abs(d)
    return bool(np.all(d > 0) and np.all(2.0 * d > off))


def _pair_effective(blocks: Blocks, j: int, k: int, gammas: np.ndarray, low: float, high: float,
                    floor: float) -> tuple[np.ndarray, np.ndarray]:
    common = blocks.pair(j, k, low, high, floor)
    return (effective_codes(blocks.codes[j][common], gammas[j]),
            effective_codes(blocks.codes[k][common], gammas[k]))


def _pair_graph(blocks: Blocks, gammas: np.ndarray, n: int, *, low: float, high: float, floor: float,
                min_blocks: int, max_gap: int, seed: int, n_iter: int) -> dict:
    """RANSAC-fitted maps for pairs (j, k), k - j <= max_gap:
    {(j, k): (H_k<-j, jj_in, jk_in, info)}, ``info`` that of :func:`fit_frame_matrix` (the
    diagonal map on the same inliers and both robust residuals)."""
    out = {}
    for j in range(n):
        for k in range(j + 1, min(n, j + 1 + max_gap)):
            jj, jk = _pair_effective(blocks, j, k, gammas, low, high, floor)
            if jj.shape[0] < min_blocks:
                continue
            info: dict = {}
            h, inl = fit_frame_matrix(jj, jk, gammas[j], gammas[k], n_iter=n_iter, seed=seed + 31 * j + k,
                                      info=info)
            out[(j, k)] = (h, jj[inl], jk[inl], info)
    return out


def diagonal_bracket(graph: dict, gain: float | None = None) -> tuple[bool, float]:
    """Whether the frames of a bracket differ by per-channel gains only (one rendering up to
    exposure, gain and white balance): the median over the pairs of ``graph`` (:func:`_pair_graph`)
    of the diagonal map's robust code residual over the full 3x3 map's is at most
    ``1 + gain`` (default :data:`DIAGONAL_GAIN`). Returns (decision, median ratio); an empty
    graph is not diagonal."""
    g = DIAGONAL_GAIN if gain is None else float(gain)
    ratios = [_diagonal_ratio(v[3]) for v in graph.values()]
    if not ratios:
        return False, float("nan")
    med = float(np.median(ratios))
    return bool(med <= 1.0 + g), med


def _diagonal_ratio(info: dict) -> float:
    """Diagonal over full robust code residual of one pair (:func:`fit_frame_matrix`'s ``info``)."""
    return float(info["rms_diagonal"] / max(info["rms_full"], 1e-12))


def graph_gains(graph: dict, n: int, times: np.ndarray | None) -> np.ndarray:
    """Per-frame, per-channel gains ``G_j`` (N, 3) that make ``G_j L_j`` agree across the pair
    graph, from the pairs' diagonal maps ``L_k = diag(h) L_j``: weighted least squares of
    ``ln G_j - ln G_k = ln h`` per channel (weights ``sqrt`` of each pair's inlier count) over
    the largest connected component of the graph. Every pair takes part, so the gains do not depend on any
    reference (the paths of :func:`colour_matrices_to_reference` do: on Memorial the loops
    ``H(c<-b) H(b<-a) H(c<-a)^-1`` of direct fits are 0.95-1.11 per channel). Frames in no pair,
    and components other than the largest, are tied to their nearest frame of the largest
    component by the exposure ratio (``G_j = G_a t_a / t_j``; equal gains without times)."""
    t = np.ones(n) if times is None else np.asarray(times, dtype=np.float64).reshape(-1)
    # connected components of the graph
    comp = list(range(n))

    def root(i: int) -> int:
        while comp[i] != i:
            comp[i] = comp[comp[i]]
            i = comp[i]
        return i

    for (j, k) in graph:
        comp[root(j)] = root(k)
    roots = [root(i) for i in range(n)]
    paired = {i for key in graph for i in key}
    sizes = {r: sum(1 for i in range(n) if roots[i] == r and i in paired) for r in set(roots)}
    main = max(sizes, key=lambda r: (sizes[r], -min(i for i in range(n) if roots[i] == r)))
    members = [i for i in range(n) if roots[i] == main and i in paired]
    rows, rhs, wts = [], [], []
    for (j, k), val in graph.items():
        if roots[j] != main:
            continue
        r = np.zeros(n)
        r[j], r[k] = 1.0, -1.0
        rows.append(r)
        rhs.append(np.log(np.maximum(np.diag(val[3]["diagonal"]), 1e-300)))
        wts.append(np.sqrt(max(val[3]["inliers"], 1)))
    r = np.zeros(n)
    r[members] = 1.0
    rows.append(r)                       # gauge: sum of the component's log gains = 0
    rhs.append(np.zeros(3))
    wts.append(1.0)
    a = np.asarray(rows) * np.asarray(wts)[:, None]
    b = np.asarray(rhs) * np.asarray(wts)[:, None]
    logg = np.zeros((n, 3))
    if members:
        sol = np.linalg.lstsq(a[:, members], b, rcond=None)[0]
        logg[members] = sol
    done = set(members)
    rest = [j for j in range(n) if j not in done]
    while rest:
        j = min(rest, key=lambda i: (min(abs(i - d) for d in done) if done else 0, i))
        rest.remove(j)
        if done:
            a_ = min(done, key=lambda d: (abs(d - j), d))
            logg[j] = logg[a_] + np.log(t[a_] / t[j])
        done.add(j)
    return np.exp(logg)


def colour_matrices_to_reference(blocks: Blocks, gammas: Sequence, reference: int, *, low: float = FIT_LOW,
                                high: float = FIT_HIGH, floor: float = FIT_FLOOR, min_blocks: int = 12,
                                path: str = "auto", seed: int = 0, n_iter: int = 100,
                                times: np.ndarray | None = None, info: dict | None = None) -> tuple[np.ndarray, list]:
    """H_j (N, 3, 3) mapping image j's linear values onto the reference's (paper 1, eq. 9-10).

    ``path="direct"`` fits every (I_j, I_ref) pair as the paper does; ``"chain"`` fits
    neighbouring pairs and composes them towards the reference; ``"auto"`` (default)
    fits directly when the pair shares at least ``4 * min_blocks`` usable blocks and at
    least half as many as image j shares with its neighbour towards the reference, and
    the fitted matrix is plausible (:func:`_plausible_matrix`); otherwise it chains
    (distant exposures share only a few noisy pixels with the reference). The exposure
    ratio (and any gain change) is absorbed in H_j. An image that shares nothing usable
    with its neighbour gets the neighbour's matrix times ``t_neighbour / t_j``
    ("assumed"). ``gammas``: display gammas or :class:`Curve` objects. Returns (H, how)
    with ``how[j]`` in {"reference", "direct", "chain", "assumed"}; with ``path="auto"`` a bracket
    that :func:`diagonal_bracket` finds diagonal takes :func:`graph_gains` instead (``"gains"``:
    the same map for every reference). ``info`` receives ``diagonal`` and ``diagonal_ratio``.
    """
    n = blocks.codes.shape[0]
    if path == "auto":
        graph = _pair_graph(blocks, gammas, n, low=low, high=high, floor=floor, min_blocks=min_blocks, max_gap=2,
                            seed=seed, n_iter=n_iter)
        diag, ratio = diagonal_bracket(graph)
        if info is not None:
            info.update(diagonal=diag, diagonal_ratio=ratio)
        if diag:
            g = graph_gains(graph, n, times)
            how = ["gains"] * n
            how[reference] = "reference"
            return np.stack([np.diag(g[j] / g[reference]) for j in range(n)]), how
    eye = np.eye(3)
    mats = np.repeat(eye[None], n, axis=0)
    how = ["reference"] * n
    order = list(range(reference - 1, -1, -1)) + list(range(reference + 1, n))
    for j in order:
        a = j + 1 if j < reference else j - 1           # neighbour towards the reference
        if path in ("direct", "auto"):
            jj, jr = _pair_effective(blocks, j, reference, gammas, low, high, floor)
            if path == "direct":
                need = min_blocks
            else:
                need = max(4 * min_blocks, int(0.5 * blocks.pair(j, a, low, high, floor).sum()))
            if jj.shape[0] >= need:
                h, _ = fit_frame_matrix(jj, jr, gammas[j], gammas[reference], n_iter=n_iter,
                                        seed=seed + 101 * j + reference)
                if path == "direct" or _plausible_matrix(h):
                    mats[j] = h
                    how[j] = "direct"
                    continue
            elif path == "direct":
                raise StackError(f"image {j} shares only {jj.shape[0]} usable blocks with the reference "
                                 f"{reference}; use path='chain'")
        elif path != "chain":
            raise InputError(f"path must be 'auto', 'direct' or 'chain', got {path!r}")
        h = _neighbour_matrix(blocks, j, a, gammas, low=low, high=high, floor=floor, n_iter=n_iter, seed=seed)
        if h is None:
            # nothing well exposed in common (exposure step too large, frame nearly black or
            # white): assume the neighbour's rendering, scaled by the exposure ratio
            h = np.eye(3) * (times[a] / times[j]) if times is not None else np.eye(3)
            how[j] = "assumed"
        else:
            how[j] = "chain"
        mats[j] = mats[a] @ h
    return mats, how


def joint_colour_matrices(blocks: Blocks, gammas: np.ndarray, times: np.ndarray, *, low: float = FIT_LOW,
                         high: float = FIT_HIGH, floor: float = FIT_FLOOR, min_blocks: int = 12,
                         max_gap: int = 2, seed: int = 0, n_iter: int = 100,
                         info: dict | None = None) -> np.ndarray:
    """Reference-free colour matrices: K_j (N, 3, 3) such that ``K_j L_j / t_j`` agree on every
    overlapping pair (beyond paper 1; its Fig. 5 limitation).

    Minimises ``sum_pairs sum_blocks w ||K_j l_j / t_j - K_k l_k / t_k||^2`` over the RANSAC
    inliers of every pair (k - j <= ``max_gap``) subject to ``mean_j K_j = I``: the common
    space is the bracket's average rendering (if ``L_j = t_j B_j E`` then
    ``K_j = (mean_i B_i^-1)^-1 B_j^-1``), independent of any reference. Weights ``w`` make
    the residual relative (noise of both images, in code units, propagated). Times only
    set the gauge; wrong times are absorbed into K_j. Each output row of the K_j is an
    equality-constrained least-squares problem (KKT system). The fit covers the longest
    run of neighbouring images that share pixels; images outside it (nearly black or
    white frames) are chained to their neighbour afterwards, or assumed to share its
    rendering when nothing is usable in common. A bracket that :func:`diagonal_bracket` finds
    diagonal takes ``K_j = c t_j diag(G_j)`` from :func:`graph_gains` (``c`` sets the gauge);
    ``info`` receives ``diagonal`` and ``diagonal_ratio``.
    """
    n = blocks.codes.shape[0]
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    graph = _pair_graph(blocks, gammas, n, low=low, high=high, floor=floor, min_blocks=min_blocks, max_gap=max_gap,
                        seed=seed, n_iter=n_iter)
    diag, ratio = diagonal_bracket(graph)
    if info is not None:
        info.update(diagonal=diag, diagonal_ratio=ratio)
    if diag:
        # per-channel gains only: K_j = c t_j G_j with the gauge mean_j K_j = I
        kt = graph_gains(graph, n, t) * t[:, None]
        kt = kt / kt.mean(axis=0, keepdims=True)
        return np.stack([np.diag(v) for v in kt])
    # the joint fit runs over the largest connected run of images; the others are attached
    # afterwards to their nearest fitted neighbour (see the end)
    lo_i, hi_i = _longest_run(graph, n)
    mats = np.empty((n, 3, 3))
    # only images that share pixels with another take part: a frame skipped by a pair
    # across it (e.g. an all-white middle frame) has no data, and the constraint
    # mean K_j = I would put the whole rendering on it
    paired = {i for key in graph for i in key}
    members = [i for i in range(lo_i, hi_i + 1) if i in paired]
    if len(members) < 2:        # no neighbours share pixels: all renderings assumed alike
        mats[:] = np.eye(3)
        return mats
    lo_i, hi_i = members[0], members[-1]
    graph = {key: val for key, val in graph.items() if lo_i <= key[0] and key[1] <= hi_i}
    normal = _joint_normal_equations(graph, gammas, t, members)
    mats[members] = _gauged_solution(normal, len(members))
    # images outside the fit (outside the run, or without pixels in common): chained to the
    # nearest fitted image, nearest first (or assumed alike)
    done = set(members)
    rest = [j for j in range(n) if j not in done]
    while rest:
        j = min(rest, key=lambda i: (min(abs(i - d) for d in done), i))
        a = min(done, key=lambda d: (abs(d - j), d))
        rest.remove(j)
        done.add(j)
        h = _neighbour_matrix(blocks, j, a, gammas, low=low, high=high, floor=floor, n_iter=n_iter, seed=seed)
        mats[j] = mats[a] @ (h * (t[j] / t[a]) if h is not None else np.eye(3))
    return mats


def _longest_run(graph: dict, n: int) -> tuple[int, int]:
    """The first and last image of the longest run of neighbours linked by the pair ``graph``
    (ties: the run nearest the bracket's middle)."""
    adj = np.zeros(n - 1, dtype=bool)
    for (j, k) in graph:
        adj[j:k] = True
    runs, start = [], 0
    for i in range(n - 1):
        if not adj[i]:
            runs.append((start, i))
            start = i + 1
    runs.append((start, n - 1))
    return max(runs, key=lambda r: (r[1] - r[0], -abs((r[0] + r[1]) / 2 - (n - 1) / 2)))


def _joint_normal_equations(graph: dict, gammas: np.ndarray, t: np.ndarray, members: list) -> list:
    """Per output channel, the normal matrix (3M, 3M) of ``sum w ||K_j l_j / t_j - K_k l_k / t_k||^2``
    over the pairs of ``graph`` (M = ``len(members)``, the unknowns of member ``i`` at ``3 i:3 i + 3``)."""
    sub = {j: i for i, j in enumerate(members)}
    m = 3 * len(members)
    normal = [np.zeros((m, m)) for _ in range(3)]
    for (j, k), (_, jj, jk, _) in graph.items():
        cj, ck = as_curve(gammas[j]), as_curve(gammas[k])
        mj = cj.lin(jj) / t[j]
        mk = ck.lin(jk) / t[k]
        # relative noise of each linear value, (dL/dJ) sigma / L with equal code noise sigma;
        # floored (Curve.noise_log_slope): a flat segment of a fitted response table would
        # otherwise claim a noise-free value and give its few blocks 1e6-1e10 times the weight
        # of all others (the iPhone 6 bracket: per-channel gains drifted 2.4x, a green sky)
        rel = cj.noise_log_slope(jj) ** 2 + ck.noise_log_slope(jk) ** 2
        scale2 = np.maximum(mj * mk, 1e-300)       # ~ E^2 in either image's rendering
        # each block's row of the design matrix is [.. mj .. -mk ..]: only the 6x6 block of
        # the pair's unknowns is non-zero (a dense (blocks, 3N) design cost 4 s on Memorial)
        u = np.concatenate([mj, -mk], axis=1)
        idx = np.r_[3 * sub[j]:3 * sub[j] + 3, 3 * sub[k]:3 * sub[k] + 3]
        for c in range(3):
            w = 1.0 / (scale2[:, c] * rel[:, c])
            normal[c][np.ix_(idx, idx)] += (u * w[:, None]).T @ u
    return normal


def _gauged_solution(normal: list, nm: int) -> np.ndarray:
    """The ``nm`` matrices (nm, 3, 3) minimising the normal equations row by row subject to
    ``mean_j K_j = I`` (a KKT system per output channel, :data:`RIDGE` on off-diagonal entries)."""
    m = 3 * nm
    mats = np.empty((nm, 3, 3))
    cons = np.zeros((3, m))
    for i in range(nm):
        cons[:, 3 * i:3 * i + 3] = np.eye(3) / nm
    for c in range(3):
        kkt = np.zeros((m + 3, m + 3))
        scale = np.trace(normal[c]) / m
        kkt[:m, :m] = normal[c] / scale
        off = np.ones(m)
        off[c::3] = 0.0                        # ridge on off-diagonal entries (see RIDGE)
        kkt[:m, :m] += np.diag(RIDGE * off)
        kkt[:m, m:] = cons.T
        kkt[m:, :m] = cons
        rhs = np.zeros(m + 3)
        rhs[m + c] = 1.0
        sol = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
        mats[:, c, :] = sol[:m].reshape(nm, 3)
    return mats
