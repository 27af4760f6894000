"""Tests for derender.derendering (paper 2: probabilistic colour de-rendering).

Training pairs come from a known synthetic forward rendering written here (independent of
the simulator): chart-like camera colours (140 patches x 16 illuminants x exposures over
five decades), sensor saturation, fixed white balance, a 3x3 camera->sRGB matrix with
out-of-gamut colours, a *non-separable* hue-preserving gamut mapping (out-of-gamut
colours are pulled towards grey) and highlight roll-off (bright colours desaturate
towards white), clipping, an S-shaped tone curve on the sRGB OETF, 8-bit quantisation.
"""

from __future__ import annotations

import copy
import zipfile

import numpy as np
import pytest

from derender.core.errors import InputError, ModelFileError
from derender.derendering import models as D

CAM_TO_SRGB = np.array([[1.55, -0.45, -0.10], [-0.20, 1.45, -0.25], [0.03, -0.40, 1.37]])
WB = np.array([1.9, 1.0, 1.6])
LUM = np.array([0.2126, 0.7152, 0.0722])

GP_TEST_SETTINGS = dict(n_train=1500, max_cluster_points=300, opt_points=150, table_size=28)


def render(raw: np.ndarray) -> np.ndarray:
    """Synthetic camera: raw camera RGB (N,3) -> 8-bit sRGB codes (N,3)."""
    x = np.minimum(raw, 1.0) * WB                          # sensor saturation, white balance
    rgb = x @ CAM_TO_SRGB.T
    lum = np.maximum(rgb @ LUM, 0.2 * x.mean(axis=1) + 1e-12)[:, None]
    mn = rgb.min(axis=1, keepdims=True)                    # gamut mapping towards grey (non-separable)
    rgb = lum + (rgb - lum) * np.where(mn < 0, lum / (lum - mn), 1.0)
    mx = rgb.max(axis=1, keepdims=True)                    # highlight roll-off (non-separable)
    t = np.clip((mx - 0.6) / 0.8, 0, 1) ** 2
    rgb = rgb + (np.maximum(mx, 1.0) - rgb) * t
    v = np.clip(rgb, 0, 1)
    s = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
    s = s + 0.06 * np.sin(2 * np.pi * s)                   # S-shaped tone curve
    return np.round(255 * np.clip(s, 0, 1)).astype(np.uint8)


def make_pairs(seed: int = 0, noise: float = 0.003) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    refl = rng.uniform(0.03, 0.9, (140, 3)) ** rng.uniform(0.5, 2.0, (140, 1))
    sat = rng.random(140) < 0.3
    refl[sat] = 0.05 + 0.9 * rng.dirichlet([2.0, 2.0, 2.0], sat.sum())
    illum = rng.uniform(0.5, 1.0, (16, 3))
    illum /= illum.max(axis=1, keepdims=True)
    base = (refl[None] * illum[:, None] / WB * 0.7).reshape(-1, 3)
    stops = np.arange(-7, 3.01, 0.5)
    raw = (base[None] * (2.0 ** stops)[:, None, None]).reshape(-1, 3)
    raw = raw * (1 + noise * rng.standard_normal(raw.shape))
    return render(raw), raw


@pytest.fixture(scope="module")
def data():
    jpeg, raw = make_pairs()
    perm = np.random.default_rng(1).permutation(jpeg.shape[0])
    tr, te = perm[:2000], perm[-10000:]
    return jpeg[tr], raw[tr], jpeg[te], raw[te]


@pytest.fixture(scope="module")
def gp(data):
    return D.LocalGPModel(seed=0, **GP_TEST_SETTINGS).fit(data[0], data[1])


@pytest.fixture(scope="module")
def poly(data):
    return D.PolynomialModel().fit(data[0], data[1])


@pytest.fixture(scope="module")
def rbf(data):
    return D.RBFModel(n_train=800, table_size=24).fit(data[0], data[1])


# ----------------------------------------------------------------------------- accuracy
def test_gp_and_polynomial_accuracy(data, gp, poly, rbf):
    _, _, jte, rte = data
    nonblack = jte.max(axis=1) >= 8          # a colour rendered black has unbounded relative error
    unclipped = nonblack & (jte.max(axis=1) < 255)
    rel = {}
    for name, model in (("gp", gp), ("poly", poly), ("rbf", rbf)):
        mean, var = model.predict(jte)
        assert mean.dtype == np.float32 and np.all(np.isfinite(mean)) and np.all(np.isfinite(var))
        rel[name] = (D.relative_rmse(mean[nonblack], rte[nonblack]), D.relative_rmse(mean[unclipped], rte[unclipped]))
    print("relative RMSE (non-black, unclipped):", rel,
          "ratio gp/poly: %.2f, %.2f" % (rel["gp"][0] / rel["poly"][0], rel["gp"][1] / rel["poly"][1]))
    # measured: gp 0.33 / 0.151, poly 0.28 / 0.155, rbf 0.30 / 0.20. This renderer is a
    # Chakrabarti-family camera except for its gamut mapping and highlight roll-off, so the
    # (robustly fitted) polynomial baseline is strong here; the GP's edge is its variance.
    assert rel["gp"][1] < 0.2 and rel["poly"][1] < 0.2
    assert rel["gp"][1] < 1.1 * rel["poly"][1]
    # clipped colours have wide, skewed posteriors: the predictive median is the better point
    # estimate under relative error (measured 0.26 vs mean 0.33)
    med, msd = gp.predict(jte, point="median")
    mean, var = gp.predict(jte)
    assert np.all(med <= mean) and np.all(msd >= var)
    rel_med = D.relative_rmse(med[nonblack], rte[nonblack])
    print("gp point=median relative RMSE (non-black): %.3f" % rel_med)
    assert rel_med < 0.85 * rel["gp"][0] and rel_med < rel["poly"][0]
    mu, _ = gp.predict_log(jte)
    np.testing.assert_allclose(med, np.exp(mu) - gp.eps, rtol=1e-5, atol=1e-6 * gp.eps)


def test_gp_interval_coverage(data, gp):
    _, _, jte, rte = data
    mean, var = gp.predict(jte)
    cov = D.interval_coverage(mean, var, rte, level=0.95)
    print("95% coverage per channel:", cov)
    assert np.all(cov >= 0.90) and np.all(cov <= 0.98)
    # the log-space Gaussian is what the GP calibrates; check it too
    mu, s2 = gp.predict_log(jte)
    z = np.abs(np.log(np.maximum(rte, 0) + gp.eps) - mu) / np.sqrt(s2)
    assert np.all((z < 1.96).mean(axis=0) >= 0.88)


def test_gp_table_matches_exact_gp(data, gp):
    _, _, jte, _ = data
    cols = jte[:3000]
    mu_t, s2_t = gp.predict_log(cols)
    mu_e, s2_e = gp.predict_log(cols, exact=True)
    dz = np.abs(mu_t - mu_e) / np.sqrt(s2_e)
    assert np.median(dz) < 0.1 and np.percentile(dz, 90) < 1.0
    assert np.median(np.abs(np.log(s2_t / s2_e))) < 0.1
    nodes = gp.table_nodes_.astype(np.uint8)             # at grid nodes the table is the exact GP
    grid = np.stack(np.meshgrid(nodes[::5], nodes[::5], nodes[::5], indexing="ij"), -1).reshape(-1, 3)
    a, b = gp.predict_log(grid)
    c, d = gp.predict_log(grid, exact=True)
    np.testing.assert_allclose(a, c, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.log(b), np.log(d), atol=1e-4)


def test_polynomial_inverts_separable_rendering_exactly():
    rng = np.random.default_rng(3)
    raw = rng.uniform(0.01, 1.0, (3000, 3)) * rng.uniform(0.05, 1.0, (3000, 1))
    C = np.array([[0.8, 0.15, 0.05], [0.1, 0.8, 0.1], [0.05, 0.15, 0.8]])
    u = raw @ C.T                                        # in-gamut, unclipped: exactly the poly forward model
    jpeg = np.round(255 * np.clip(u, 0, 1) ** (1 / 2.2)).astype(np.uint8)
    model = D.PolynomialModel().fit(jpeg[:2000], raw[:2000])
    mean, _ = model.predict(jpeg[2000:])
    ok = jpeg[2000:].min(axis=1) >= 20
    assert D.median_relative_error(mean[ok], raw[2000:][ok]) < 0.01


def test_rbf_matches_scipy_rbfinterpolator(data):
    from scipy.interpolate import RBFInterpolator

    j, r = data[0][:400], data[1][:400]
    model = D.RBFModel(smoothing=1e-3, table_size=0).fit(j, r)
    t = np.log(np.maximum(r, 0) + model.eps)
    peer = RBFInterpolator(j / 255.0, t, kernel="thin_plate_spline", smoothing=1e-3, degree=1)
    q = data[2][:500] / 255.0
    np.testing.assert_allclose(model._latent_exact(q), peer(q), rtol=1e-6, atol=1e-6)


def test_gp_marginal_likelihood_matches_sklearn():
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    rng = np.random.default_rng(0)
    X = rng.random((60, 3))
    y = np.sin(3 * X[:, 0]) + X[:, 1] ** 2 + 0.05 * rng.standard_normal(60)
    theta = np.log([0.3, 0.5, 0.8, 1.2, 0.07])
    nll, grad = D._gp_nll(theta, D._sq_dists(X), y)
    kernel = ConstantKernel(1.2 ** 2) * RBF([0.3, 0.5, 0.8]) + WhiteKernel(0.07 ** 2 + 1e-8 * 1.2 ** 2)
    gpr = GaussianProcessRegressor(kernel, optimizer=None, alpha=0.0, normalize_y=False).fit(X, y)
    assert nll == pytest.approx(-gpr.log_marginal_likelihood_value_, rel=1e-7)
    h = 1e-6                                              # analytic gradient vs central differences
    num = [(D._gp_nll(theta + h * e, D._sq_dists(X), y)[0] - D._gp_nll(theta - h * e, D._sq_dists(X), y)[0]) / (2 * h)
           for e in np.eye(5)]
    np.testing.assert_allclose(grad, num, rtol=1e-4, atol=1e-6)
    r = rng.uniform(0.5, 3.0, 60)                         # heteroscedastic noise gradient too
    g2 = D._gp_nll(theta, D._sq_dists(X), y, r)[1]
    num2 = (D._gp_nll(theta + h * np.eye(5)[4], D._sq_dists(X), y, r)[0]
            - D._gp_nll(theta - h * np.eye(5)[4], D._sq_dists(X), y, r)[0]) / (2 * h)
    assert g2[4] == pytest.approx(num2, rel=1e-4)


# ----------------------------------------------------------------------------- interface
def test_image_prediction_equals_pixel_list(data, gp, poly, rbf, monkeypatch):
    _, _, jte, _ = data
    img = jte[:1200].reshape(30, 40, 3)
    for model in (gp, poly, rbf):
        m_img, v_img = model.predict(img)
        assert m_img.shape == img.shape and v_img.shape == img.shape
        m_list, v_list = model.predict(img.reshape(-1, 3))
        assert np.array_equal(m_img.reshape(-1, 3), m_list) and np.array_equal(v_img.reshape(-1, 3), v_list)
        sub = np.random.default_rng(0).permutation(1200)[:300]       # other colours present do not matter
        m_sub, v_sub = model.predict(img.reshape(-1, 3)[sub])
        assert np.array_equal(m_sub, m_list[sub]) and np.array_equal(v_sub, v_list[sub])
        m_f, v_f = model.predict(img.astype(np.float32) / 255.0)   # floats code/255 == uint8 codes
        assert np.array_equal(m_f, m_img) and np.array_equal(v_f, v_img)
        m1, v1 = model.predict(img[3, 7])                            # a single colour
        assert m1.shape == (3,) and np.array_equal(m1, m_img[3, 7])
    monkeypatch.setattr(D, "_BINCOUNT_THRESHOLD", 10)                # force the 2^24-bincount path
    m_big, v_big = gp.predict(img)
    monkeypatch.undo()
    assert np.array_equal(m_big, gp.predict(img)[0]) and np.array_equal(v_big, gp.predict(img)[1])


def test_float_inputs_between_codes_interpolate(gp):
    a = np.array([[100, 120, 140]], np.uint8)
    b = np.array([[101, 121, 141]], np.uint8)
    mid = (a.astype(np.float64) + 0.5) / 255.0
    ma, _ = gp.predict(a)
    mb, _ = gp.predict(b)
    mm, vm = gp.predict(mid)
    assert np.all(mm >= np.minimum(ma, mb) * 0.999) and np.all(mm <= np.maximum(ma, mb) * 1.001)
    assert np.all(np.isfinite(vm))


@pytest.mark.parametrize("method", ["gp", "poly", "rbf"])
def test_save_load_roundtrip(tmp_path, data, gp, poly, rbf, method):
    model = {"gp": gp, "poly": poly, "rbf": rbf}[method]
    model.metadata["camera"] = {"make": "Synthetic", "model": "Test 1"}
    path = model.save(tmp_path / f"m_{method}.npz")
    loaded = D.load_model(path)
    assert type(loaded) is type(model) and loaded.method == method
    assert loaded.metadata["camera"]["model"] == "Test 1"
    cols = data[2][:2000]
    for a, b in zip(model.predict(cols), loaded.predict(cols)):
        assert np.array_equal(a, b)
    if method == "gp":
        for a, b in zip(model.predict(cols[:200], exact=True), loaded.predict(cols[:200], exact=True)):
            assert np.array_equal(a, b)
    assert isinstance(D.DerenderModel.load(path), type(model))
    other = {"gp": D.PolynomialModel, "poly": D.RBFModel, "rbf": D.LocalGPModel}[method]
    with pytest.raises(ModelFileError, match="holds a"):
        other.load(path)
    with np.load(path, allow_pickle=False) as z:                   # no object arrays anywhere
        assert all(z[k].dtype != object for k in z.files)


def test_bad_model_files_raise(tmp_path, poly):
    good = poly.save(tmp_path / "good.npz")
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}

    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"this is not a zip file at all")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[:200])
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, weights=np.ones(3))
    future = tmp_path / "future.npz"
    np.savez(future, **{**arrays, "format_version": np.array(D.MODEL_FORMAT_VERSION + 1)})
    unknown = tmp_path / "unknown.npz"
    np.savez(unknown, **{**arrays, "method": np.array("magic")})
    missing = tmp_path / "missing.npz"
    np.savez(missing, **{k: v for k, v in arrays.items() if k != "p_C"})
    badshape = tmp_path / "badshape.npz"
    np.savez(badshape, **{**arrays, "p_C": np.ones((2, 2))})
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, **{**arrays, "metadata_json": np.array([{"a": 1}], dtype=object)})
    cases = {junk: "not a readable", truncated: "not a readable", foreign: "not a derender model",
             future: f"version {D.MODEL_FORMAT_VERSION + 1}", unknown: "unknown model method", missing: "lacks parameters",
             badshape: "inconsistent", pickled: "not a readable", tmp_path / "absent.npz": "not found"}
    for path, msg in cases.items():
        with pytest.raises(ModelFileError, match=msg):
            D.load_model(path)
    assert zipfile.is_zipfile(good)


def test_determinism_same_seed(data):
    j, r = data[0][:900], data[1][:900]
    kw = dict(n_train=500, n_clusters=5, max_cluster_points=200, opt_points=100, table_size=12)
    a = D.fit_model("gp", j, r, seed=3, **kw)
    b = D.fit_model("gp", j, r, seed=3, **kw)
    cols = data[2][:500]
    for x, y in zip(a.predict(cols), b.predict(cols)):
        assert x.tobytes() == y.tobytes()
    assert a.predict(cols, exact=True)[0].tobytes() == b.predict(cols, exact=True)[0].tobytes()
    # predictions are equivariant to the (arbitrary) raw units
    c = D.fit_model("gp", j, r * 1000.0, seed=3, **kw)
    np.testing.assert_allclose(c.predict(cols)[0], 1000.0 * a.predict(cols)[0], rtol=1e-4, atol=1e-7)


def test_input_validation(gp):
    j = np.random.default_rng(0).integers(0, 256, (50, 3)).astype(np.uint8)
    r = np.random.default_rng(1).random((50, 3))
    bad_raw = r.copy()
    bad_raw[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        D.PolynomialModel().fit(j, bad_raw)
    with pytest.raises(InputError, match="NaN"):
        D.PolynomialModel().fit(np.where(np.arange(50)[:, None] == 2, np.inf, j.astype(float)), r)
    with pytest.raises(InputError, match="shape"):
        D.PolynomialModel().fit(j[:, :2], r)
    with pytest.raises(InputError, match="numbers of colours"):
        D.PolynomialModel().fit(j[:40], r)
    with pytest.raises(InputError, match=r"\[0, 255\]"):
        D.PolynomialModel().fit(j.astype(np.int32) * 2, r)
    with pytest.raises(InputError, match="look like floats"):
        D.PolynomialModel().fit(j / 255.0, r)
    with pytest.raises(InputError, match="alpha"):
        gp.predict(np.zeros((4, 4, 4), np.uint8))
    with pytest.raises(InputError, match="16-bit"):
        gp.predict(np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        gp.predict(np.full((2, 3), 2.0))
    with pytest.raises(InputError, match="NaN"):
        gp.predict(np.array([[0.1, np.nan, 0.2]]))
    with pytest.raises(InputError, match="not fitted"):
        D.LocalGPModel().predict(j)
    with pytest.raises(InputError, match="unknown de-rendering method"):
        D.fit_model("magic", j, r)
    assert set(D.MODEL_TYPES) == {"gp", "poly", "rbf"}
    m, v = gp.predict(np.array([[0, 0, 0], [255, 255, 255], [255, 0, 255]], np.int64))  # extremes stay finite
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(v)) and np.all(v > 0)


def test_metrics_on_known_values():
    truth = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    pred = np.array([[1.1, 0.0, 0.0], [0.0, 2.0, 0.4]])
    assert D.relative_rmse(pred, truth) == pytest.approx(np.sqrt((0.01 + 0.04) / 2))
    assert D.rmse(pred, truth) == pytest.approx(np.sqrt((0.01 + 0.16) / 2))
    assert D.median_relative_error(pred, truth) == pytest.approx(0.15)
    rng = np.random.default_rng(0)
    sd = rng.uniform(0.5, 2.0, (200000, 3))
    x = rng.standard_normal((200000, 3)) * sd
    cov = D.interval_coverage(np.zeros_like(x), sd ** 2, x, level=0.95)
    np.testing.assert_allclose(cov, 0.95, atol=0.003)
    assert D.interval_coverage(np.zeros_like(x), sd ** 2, x, level=0.5) == pytest.approx(0.5, abs=0.005)



def test_code_floor_is_the_best_function_of_the_code(data, gp, poly, rbf):
    # hand-computed: codes A, A, B; truths (1,0,0), (2,0,0), (0,3,0): v_A = (1 + 2/4) / (1 + 1/4) = 1.2
    codes = np.array([[9, 9, 9], [9, 9, 9], [1, 2, 3]])
    truth = np.array([[1.0, 0, 0], [2.0, 0, 0], [0, 3.0, 0]])
    np.testing.assert_allclose(D.code_floor_errors(codes, truth), [0.04, 0.16, 0.0])
    # no other value for code A does better (it is the minimiser of sum ||v - x||^2 / ||x||^2)
    vs = np.linspace(0.5, 2.5, 2001)
    risk = (vs - 1.0) ** 2 + (vs - 2.0) ** 2 / 4
    assert risk.min() >= 0.2 - 1e-12 and vs[np.argmin(risk)] == pytest.approx(1.2, abs=1e-3)
    # a lower bound for every model on held-out colours, and far from zero (clipped codes)
    _, _, jt, rt = data
    floor = np.sqrt(D.code_floor_errors(jt, rt).mean())
    for model in (gp, poly, rbf):
        assert D.relative_rmse(model.predict(jt, point="map")[0], rt) > floor
    assert floor > 0.05


def test_gp_clip_pattern_clusters_and_bounded_noise(data, gp):
    # with clip_patterns, clipped colours are clustered per clip pattern and a clipped test
    # colour uses a cluster of its own pattern when there is one
    jt = data[2]
    pat = D.LocalGPModel(seed=0, clip_patterns=True, **GP_TEST_SETTINGS).fit(data[0], data[1])
    bits = D._clip_bits(jt.astype(float), pat.clip_code)
    lab = pat._assign(jt / 255.0)
    g = pat.cluster_group
    assert np.all(g[lab[bits == 0]] == 0) and np.all(g[lab[bits > 0]] >= 1)
    own = np.isin(1 + bits, g) & (bits > 0)
    assert own.any() and np.all(g[lab[own]] == 1 + bits[own])
    # by default: one group for every clipped colour
    lab = gp._assign(jt / 255.0)
    assert np.all(gp.cluster_group[lab[bits == 0]] == 0) and np.all(gp.cluster_group[lab[bits > 0]] == 1)
    # the input-dependent noise never exceeds its largest value on the training colours, anywhere
    # in the code cube (an unbounded noise GP extrapolated to log-variances of 30+)
    codes = np.random.default_rng(3).integers(0, 256, (4000, 3))
    _, s2 = gp.predict_log(codes.astype(np.uint8), exact=True)
    lab = gp._assign(codes / 255.0)
    sf2 = np.exp(2 * gp.theta[lab, :, 3])
    noise_max = np.exp(2 * gp.theta[lab, :, 4] + gp.theta_noise[lab, :, 7])
    assert np.all(s2 <= (sf2 + noise_max) * gp.t_std[lab] ** 2 * (1 + 1e-9))


def test_gp_predictive_variance_never_exceeds_the_training_variance(tmp_path, data, gp):
    # a GP extrapolating with a huge signal variance (simulated 5D II: blue log-variances of
    # 40-48 for a few purples, a predictive mean 2.6e9x the median) is capped at var(t) of
    # the training colours, in the exact path, the table path and tables of older files
    cap = np.var(gp.T, axis=0)
    codes = np.random.default_rng(4).integers(0, 256, (3000, 3)).astype(np.uint8)
    wide = copy.deepcopy(gp)
    wide.theta = gp.theta.copy()
    wide.theta[..., 3] += 5.0                     # signal variance x e^10
    wide._factors = {}
    _, s2 = wide.predict_log(codes, exact=True)
    assert np.all(s2 <= cap * (1 + 1e-12))
    assert np.any(np.isclose(s2, cap))            # the cap binds for this model
    old = copy.deepcopy(gp)
    vals = old.table_values_.copy()
    vals[..., 3:] = 50.0                          # an uncapped table as older files hold
    old.table_values_ = vals
    path = old.save(tmp_path / "old.npz")
    back = D.load_model(path)
    _, s2_tab = back.predict_log(codes)
    assert np.all(s2_tab <= cap * (1 + 1e-6))
    mean, _ = back.predict(codes)
    med, _ = back.predict(codes, point="median")
    assert np.all(np.isfinite(mean)) and np.all(mean <= (med + back.eps) * np.exp(cap / 2) * 1.001)


# ----------------------------------------------------------------------------- polynomial baseline
POLY_C = np.array([[1.30, -0.25, -0.05], [-0.15, 1.25, -0.10], [0.02, -0.30, 1.28]])


def _chakrabarti_render(raw: np.ndarray) -> np.ndarray:
    """A camera *in* the Chakrabarti family (3x3 then per-channel monotone curves) plus sensor saturation.

    The curve (Reinhard shoulder, then the sRGB OETF) is not a polynomial. Colours whose raw
    value exceeds the sensor's white (1) are clipped before C and, as white renders below 255,
    keep unclipped codes: for them the stored raw is the unclipped truth and the rendering is not
    the model's -- the outliers of real calibration data that broke the earlier fit.
    """
    u = np.minimum(raw, 1.0) @ POLY_C.T
    g = np.clip(1.1 * u / (u + 0.25), 0.0, 1.0)         # white renders at code 241: saturated stays unclipped
    s = np.where(g <= 0.0031308, 12.92 * g, 1.055 * g ** (1 / 2.4) - 0.055)
    return np.round(255 * s).astype(np.uint8)


def _chakrabarti_pairs(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = rng.dirichlet([3.0, 3.0, 3.0], 3000) * rng.uniform(0.5, 1.5, (3000, 1))
    raw = base * 2.0 ** rng.uniform(-9.0, 3.0, (3000, 1))           # 12 stops, 15 % sensor-saturated
    return _chakrabarti_render(raw), raw


def test_polynomial_recovers_chakrabarti_camera_despite_saturated_pairs():
    jpeg, raw = _chakrabarti_pairs(0)
    model = D.PolynomialModel().fit(jpeg[:2000], raw[:2000])
    jte, rte = jpeg[2000:], raw[2000:]
    ok = (rte.max(axis=1) < 1.0) & (jte.min(axis=1) >= 20)          # not sensor-saturated, not dark
    mean, _ = model.predict(jte)
    err = D.median_relative_error(mean[ok], rte[ok])
    print("poly on a Chakrabarti-family camera: median relative error %.4f (%d colours)" % (err, ok.sum()))
    assert err < 0.012                                    # measured 0.0084; the pre-fix fit gave 0.56
    # the rows of C are identifiable up to scale (the curves absorb the scale)
    unit = lambda m: m / np.linalg.norm(m, axis=1, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(unit(model.C), unit(POLY_C), atol=0.01)
    # the curves are monotone, so the de-rendered u grows with the code in every channel
    assert np.all(np.diff(model.bernstein, axis=1) >= 0)
    assert np.all(np.diff(model._u_of_code, axis=0) >= 0)


def test_polynomial_stable_across_subsets_and_equivariant_to_raw_units():
    jpeg, raw = _chakrabarti_pairs(1)
    a = D.fit_model("poly", jpeg[:1500], raw[:1500])
    b = D.fit_model("poly", jpeg[1500:], raw[1500:])               # disjoint training set
    c = D.fit_model("poly", jpeg[:1500], raw[:1500] * 1000.0)      # other raw units
    cols = np.random.default_rng(2).integers(10, 250, (2000, 3)).astype(np.uint8)
    ma, mb, mc = a.predict(cols)[0], b.predict(cols)[0], c.predict(cols)[0]
    assert D.median_relative_error(mb, ma) < 0.01
    np.testing.assert_allclose(mc, 1000.0 * ma, rtol=1e-4, atol=1e-3 * np.abs(ma).max())
    again = D.fit_model("poly", jpeg[:1500], raw[:1500])
    assert again.predict(cols)[0].tobytes() == ma.tobytes()
