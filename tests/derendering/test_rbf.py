"""The Lin et al. baseline (``derender.derendering.rbf``, paper 2 Sec. 4.1, ref. [18])."""

from __future__ import annotations

import numpy as np

from derender.derendering.rbf import RBFModel

pytest_plugins = ["synthetic_pairs"]   # fixtures data, gp, poly, rbf


def test_rbf_matches_scipy_rbfinterpolator(data):
    from scipy.interpolate import RBFInterpolator

    j, r = data[0][:400], data[1][:400]
    model = RBFModel(smoothing=1e-3, table_size=0).fit(j, r)
    t = np.log(np.maximum(r, 0) + model.eps)
    peer = RBFInterpolator(j / 255.0, t, kernel="thin_plate_spline", smoothing=1e-3, degree=1)
    q = data[2][:500] / 255.0
    np.testing.assert_allclose(model._latent_exact(q), peer(q), rtol=1e-6, atol=1e-6)
