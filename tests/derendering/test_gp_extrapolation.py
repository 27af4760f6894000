"""The local GP where it extrapolates (issue 27): clipped colours far from every training code.

Simulated calibration session of the Nikon D5100 rendered by the ``camera`` pipeline family (a
tuning family), 5000 random training pairs, every other pair a test colour -- the ``random`` split
of ``derender experiment derender-families``. The truth is the simulator's exact RAW colour.
"""

from __future__ import annotations

import numpy as np
import pytest

import derender.derendering.heteroscedastic_gp as heteroscedastic_gp
from derender.derendering.local_gp import LocalGPModel
from derender.evaluation.derendering_metrics import relative_rmse


@pytest.fixture(scope="module")
def session():
    from scipy.spatial import cKDTree

    from derender.camera.chart import chart_pairs

    pairs = chart_pairs("nikon-d5100", n_illuminants=16, n_exposures=22, seed=0, family="camera")
    perm = np.random.default_rng([0, 0]).permutation(pairs.jpeg.shape[0])   # derender_families' random split
    tr, te = perm[:5000], perm[5000:]
    dist, _ = cKDTree(pairs.jpeg[tr].astype(float)).query(pairs.jpeg[te].astype(float))
    return pairs.jpeg[tr], pairs.raw[tr], pairs.jpeg[te], pairs.raw[te].astype(np.float64), dist


@pytest.fixture(scope="module")
def gp(session):
    return LocalGPModel(seed=0).fit(session[0], session[1])


def test_no_single_colour_dominates_the_error_and_extrapolated_clipped_colours_stay_bounded(session, gp):
    """Before the latent-variance cap, one unclipped colour 25 codes from the training codes,
    (59, 46, 112), got a blue log-variance of 7.45 (ML signal variance 15 of its cluster) with its
    log mean right within 0.06: a predictive mean 36x the truth carrying 11.9 % of the squared
    relative error of 44,280 colours. Measured after: largest share 0.17 %; on the 133 test colours
    with a channel at 255 and >= 20 codes from every training code: mean relative error <= 3.2
    (median 0.40), log-space 99 % interval covering the truth on 100 / 98.5 / 93.2 % (R/G/B)."""
    _, _, jt, x, dist = session
    mean, _ = gp.predict(jt)
    err2 = ((mean - x) ** 2).sum(1) / (x * x).sum(1)
    assert err2.max() / err2.sum() < 0.10                     # the bound on one colour's share
    far = (dist >= 20) & np.any(jt == 255, axis=1)
    assert far.sum() >= 50                                    # the session does have such colours
    assert np.sqrt(err2[far]).max() < 4.0                     # stated bound: the mean within 4x |x| of x
    mu, s2 = gp.predict_log(jt[far])
    z = np.abs(np.log(x[far] + gp.eps) - mu) / np.sqrt(s2)
    assert np.all((z < 2.576).mean(axis=0) >= 0.90)          # the variance still covers the truth
    # the bound behind it (exact GP; the table interpolates between nodes of other clusters): latent
    # variance <= the cluster target's, so mean / median <= exp(cap / 2)
    mu, s2 = gp.predict_log(jt[far], exact=True)
    lab = gp._assign(jt[far] / 255.0)
    noise_max = np.exp(2 * gp.theta[lab, :, 4] + gp.theta_noise[lab, :, 7])
    cap = (1.0 + noise_max) * gp.t_std[lab] ** 2
    assert np.all(s2 <= cap * (1 + 1e-9))
    mean_exact, _ = gp.predict(jt[far], exact=True)
    assert np.all(mean_exact + gp.eps <= np.exp(mu + cap / 2) * (1 + 1e-5))


def test_errors_do_not_swing_with_the_first_search_subsample(session, gp, monkeypatch):
    """The first (homoscedastic) ML search of the heteroscedastic fit runs on ``_FIRST_POINTS``
    of each cluster's points. Before the cap the relative RMSE of the predictive mean was 0.489 /
    0.497 / 0.484 with 200 / 250 / 400 points (2.5 % apart: the colour above moved from 29x to 36x);
    after 0.452 / 0.451 / 0.449. The MAP point (what the tables score) moved by < 0.2 % both times."""
    _, _, jt, x, _ = session
    figs = []
    for n in (200, None, 400):
        if n is None:
            model = gp                                        # the default, 250
        else:
            monkeypatch.setattr(heteroscedastic_gp, "_FIRST_POINTS", n)
            model = LocalGPModel(seed=0).fit(session[0], session[1])
        figs.append([relative_rmse(model.predict(jt, point=p)[0], x) for p in ("mean", "map")])
    figs = np.array(figs)
    print("relative RMSE (mean, MAP) with 200 / 250 / 400 first-search points:", figs.round(4).tolist())
    assert np.all(figs.max(axis=0) <= 1.02 * figs.min(axis=0))
