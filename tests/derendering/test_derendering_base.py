"""The common de-rendering interface (``derender.derendering.base``): predict, model files, registry."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from derender.core.errors import InputError, ModelFileError
from derender.derendering import base
from derender.derendering.base import MODEL_FORMAT_VERSION, MODEL_TYPES, DerenderModel, fit_model, load_model
from derender.derendering.local_gp import LocalGPModel
from derender.derendering.polynomial import PolynomialModel
from derender.derendering.rbf import RBFModel

pytest_plugins = ["synthetic_pairs"]   # fixtures data, gp, poly, rbf


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
    monkeypatch.setattr(base, "_BINCOUNT_THRESHOLD", 10)                # force the 2^24-bincount path
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
    loaded = load_model(path)
    assert type(loaded) is type(model) and loaded.method == method
    assert loaded.metadata["camera"]["model"] == "Test 1"
    cols = data[2][:2000]
    for a, b in zip(model.predict(cols), loaded.predict(cols)):
        assert np.array_equal(a, b)
    if method == "gp":
        for a, b in zip(model.predict(cols[:200], exact=True), loaded.predict(cols[:200], exact=True)):
            assert np.array_equal(a, b)
    assert isinstance(DerenderModel.load(path), type(model))
    other = {"gp": PolynomialModel, "poly": RBFModel, "rbf": LocalGPModel}[method]
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
    np.savez(future, **{**arrays, "format_version": np.array(MODEL_FORMAT_VERSION + 1)})
    unknown = tmp_path / "unknown.npz"
    np.savez(unknown, **{**arrays, "method": np.array("magic")})
    missing = tmp_path / "missing.npz"
    np.savez(missing, **{k: v for k, v in arrays.items() if k != "p_C"})
    badshape = tmp_path / "badshape.npz"
    np.savez(badshape, **{**arrays, "p_C": np.ones((2, 2))})
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, **{**arrays, "metadata_json": np.array([{"a": 1}], dtype=object)})
    cases = {junk: "not a readable", truncated: "not a readable", foreign: "not a derender model",
             future: f"version {MODEL_FORMAT_VERSION + 1}", unknown: "unknown model method", missing: "lacks parameters",
             badshape: "inconsistent", pickled: "not a readable", tmp_path / "absent.npz": "not found"}
    for path, msg in cases.items():
        with pytest.raises(ModelFileError, match=msg):
            load_model(path)
    assert zipfile.is_zipfile(good)


def test_input_validation(gp):
    j = np.random.default_rng(0).integers(0, 256, (50, 3)).astype(np.uint8)
    r = np.random.default_rng(1).random((50, 3))
    bad_raw = r.copy()
    bad_raw[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        PolynomialModel().fit(j, bad_raw)
    with pytest.raises(InputError, match="NaN"):
        PolynomialModel().fit(np.where(np.arange(50)[:, None] == 2, np.inf, j.astype(float)), r)
    with pytest.raises(InputError, match="shape"):
        PolynomialModel().fit(j[:, :2], r)
    with pytest.raises(InputError, match="numbers of colours"):
        PolynomialModel().fit(j[:40], r)
    with pytest.raises(InputError, match=r"\[0, 255\]"):
        PolynomialModel().fit(j.astype(np.int32) * 2, r)
    with pytest.raises(InputError, match="look like floats"):
        PolynomialModel().fit(j / 255.0, r)
    with pytest.raises(InputError, match="alpha"):
        gp.predict(np.zeros((4, 4, 4), np.uint8))
    with pytest.raises(InputError, match="16-bit"):
        gp.predict(np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        gp.predict(np.full((2, 3), 2.0))
    with pytest.raises(InputError, match="NaN"):
        gp.predict(np.array([[0.1, np.nan, 0.2]]))
    with pytest.raises(InputError, match="not fitted"):
        LocalGPModel().predict(j)
    with pytest.raises(InputError, match="unknown de-rendering method"):
        fit_model("magic", j, r)
    assert set(MODEL_TYPES) == {"gp", "poly", "rbf"}
    m, v = gp.predict(np.array([[0, 0, 0], [255, 255, 255], [255, 0, 255]], np.int64))  # extremes stay finite
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(v)) and np.all(v > 0)


def test_registry_imports_a_method_module_only_when_used():
    import subprocess
    import sys

    code = ("import sys, derender.derendering.base as b; "
            "mods = ('local_gp', 'polynomial', 'rbf'); "
            "assert not any('derender.derendering.' + m in sys.modules for m in mods); "
            "assert list(b.MODEL_TYPES) == ['gp', 'poly', 'rbf'] and 'rbf' in b.MODEL_TYPES; "
            "assert not any('derender.derendering.' + m in sys.modules for m in mods); "
            "cls = b.MODEL_TYPES['poly']; "
            "assert cls.method == 'poly' and 'derender.derendering.polynomial' in sys.modules; "
            "assert 'derender.derendering.local_gp' not in sys.modules")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert MODEL_TYPES["gp"] is LocalGPModel and MODEL_TYPES["poly"] is PolynomialModel
    assert MODEL_TYPES["rbf"] is RBFModel and len(MODEL_TYPES) == 3
    with pytest.raises(KeyError):
        MODEL_TYPES["magic"]
