"""De-rendering models, common part: p(raw camera colour | 8-bit rendered colour).

Paper 2 (Xiong et al., CVPR 2012, "From pixels to physics: probabilistic color
de-rendering"), Sec. 2.2 and 4.1, learns from
calibration pairs (rendered code ``y``, raw camera colour ``x``) a predictive
distribution of ``x`` given ``y``. One module per published method, each a
:class:`DerenderModel`:

* ``"gp"`` -- :class:`~derender.derendering.local_gp.LocalGPModel`, the offline local
  Gaussian process of paper 2 (Sec. 2.2, 4);
* ``"poly"`` -- :class:`~derender.derendering.polynomial.PolynomialModel`, the
  deterministic baseline of Chakrabarti et al. (ref. [3]);
* ``"rbf"`` -- :class:`~derender.derendering.rbf.RBFModel`, the radial-basis-function
  baseline of Lin et al. (ref. [18]).

This module holds what they share: the interface, input validation, the model file format
and the method registry (:data:`MODEL_TYPES`, :func:`fit_model`, :func:`load_model`). The
GP and RBF model the log of the raw colour; that output space and its prediction table are
:mod:`derender.derendering.log_space`.

:meth:`DerenderModel.predict` computes one prediction per *distinct* colour (24-bit packed
codes; a 2^24 bincount for large images) and gathers; ``exact=True`` asks the model itself
instead of its table (slow; for evaluation).

Model files are ``.npz`` (never pickled) with ``format="derender-model"``,
``format_version=2``, ``method``, ``p_*`` parameter arrays and ``metadata_json``. The
``method`` entry names the class through :data:`MODEL_TYPES`, which imports a method's
module only when it is used.
"""

from __future__ import annotations

import importlib
import json
import os
import time
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from derender.core.errors import InputError, ModelFileError
from derender.derendering.log_space import MAX_LOG_MEAN, MAX_LOG_VAR

__all__ = [
    "model_camera_to_srgb",
    "MODEL_FORMAT",
    "MODEL_FORMAT_VERSION",
    "check_pairs",
    "as_colour_array",
    "DerenderModel",
    "finite32",
    "load_model",
    "ModelTypes",
    "MODEL_TYPES",
    "model_metadata",
    "fit_model",
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


#: The ``format`` field of a model file.
MODEL_FORMAT = "derender-model"
#: Model file version (2: GP inputs may be warped (p_input_warp), clip-pattern cluster groups).
MODEL_FORMAT_VERSION = 2
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


def check_pairs(jpeg, raw) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 copies of training pairs (what :meth:`DerenderModel.fit` accepts):
    ``jpeg`` (N,3) 8-bit codes, ``raw`` (N,3) finite, N >= 20; else :class:`InputError`."""
    return _check_pairs(jpeg, raw)


def as_colour_array(x) -> tuple[np.ndarray, bool]:
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


# ============================================================================ base class
class DerenderModel:
    """Common interface: ``fit(jpeg, raw)``, ``predict(colours) -> (mean, var)``, ``save``, ``load``.

    ``jpeg``: (N,3) 8-bit codes; ``raw``: (N,3) linear camera RGB (white balance fixed,
    relative units). ``predict`` takes uint8 codes (..., 3) or floats code/255 in [0, 1]
    and returns float32 ``mean`` and ``variance`` of the raw colour, shape (..., 3).

    The methods are subclasses (:class:`~derender.derendering.local_gp.LocalGPModel`,
    :class:`~derender.derendering.polynomial.PolynomialModel`,
    :class:`~derender.derendering.rbf.RBFModel`), listed by name in :data:`MODEL_TYPES`;
    :func:`fit_model` and :func:`load_model` make one by name or from a file.

    Parameters
    ----------
    seed : int
        Seed of every random step of the fit.
    metadata : dict, optional
        Stored with the model (camera, white balance, colour matrix).

    Attributes
    ----------
    method : str
        The model's name in :data:`MODEL_TYPES` (class attribute).
    fitted : bool
        Whether :meth:`fit` (or :meth:`load`) has run.

    Examples
    --------
    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> model = derender.PolynomialModel(degree=4).fit(jpeg, raw)
    >>> isinstance(model, derender.DerenderModel), model.method, model.fitted
    (True, 'poly', True)
    >>> mean, variance = model.predict(np.full((2, 2, 3), 128, np.uint8))   # an image
    >>> mean.shape, mean.dtype, bool(np.allclose(mean, 0.5 ** 2.2, atol=0.01))
    ((2, 2, 3), dtype('float32'), True)
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
        models ignore ``point``. ``"mean"`` stays the exact mean of the log-normal, so it grows
        as ``exp(s2/2)`` with the spread: the GP bounds ``s2`` where it extrapolates (its latent
        variance is capped at its cluster's target variance, :mod:`~derender.derendering.local_gp`),
        and the tables score ``"map"`` (``docs/paper2.md`` compares the three).
        """
        if point not in ("mean", "median", "map"):
            raise InputError(f"point must be 'mean', 'median' or 'map', got {point!r}")
        median = point == "median"
        if not self.fitted:
            raise InputError(f"{type(self).__name__} is not fitted; call fit() or load a model file")
        if point == "map" and hasattr(self, "predict_log"):
            return self._predict_map(colours, exact)
        shape = np.shape(colours)
        flat, is_codes = as_colour_array(colours)
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
        s2 = np.clip(np.asarray(s2, dtype=np.float64), 0.0, MAX_LOG_VAR)
        mu = np.clip(np.asarray(mu, dtype=np.float64), -MAX_LOG_MEAN, MAX_LOG_MEAN)
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
    """Load any de-rendering model file; corrupt, foreign or mismatched files raise ModelFileError.

    Parameters
    ----------
    path : path-like
        A ``.npz`` model file written by :meth:`DerenderModel.save` (``derender fit``).

    Returns
    -------
    DerenderModel
        The fitted model, of the class its file names (:data:`MODEL_TYPES`).

    Raises
    ------
    ModelFileError
        A missing or unreadable file, one that is not a derender model, of another format
        version or an unknown method, or with parameters that do not fit the class.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> model = derender.fit_model("rbf", jpeg, raw, table_size=0)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     back = derender.load_model(model.save(os.path.join(folder, "camera.npz")))
    >>> type(back).__name__
    'RBFModel'
    >>> codes = np.array([[30, 128, 250]], np.uint8)
    >>> bool(np.array_equal(back.predict(codes)[0], model.predict(codes)[0]))
    True
    """
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


# ============================================================================ registry
class ModelTypes(Mapping[str, "type[DerenderModel]"]):
    """Read-only ``method -> model class`` map whose classes are imported on first use.

    Each method lives in its own module (:mod:`~derender.derendering.local_gp`,
    :mod:`~derender.derendering.polynomial`, :mod:`~derender.derendering.rbf`), which
    imports this one; listing the names (``in``, iteration, ``len``) imports nothing, and
    loading a model file imports only the module of its method.
    """

    def __init__(self, classes: dict[str, str]):
        self._classes = dict(classes)   # method -> "module:Class"

    def __getitem__(self, method: str) -> type[DerenderModel]:
        module, name = self._classes[method].split(":")
        return getattr(importlib.import_module(module), name)

    def __contains__(self, method: object) -> bool:   # Mapping's default would import the class
        return method in self._classes

    def __iter__(self) -> Iterator[str]:
        return iter(self._classes)

    def __len__(self) -> int:
        return len(self._classes)

    def __repr__(self) -> str:
        return f"ModelTypes({self._classes!r})"


#: De-rendering model classes by method name, imported on first use.
#:
#: Examples
#: --------
#: >>> import derender
#: >>> sorted(derender.MODEL_TYPES)
#: ['gp', 'poly', 'rbf']
#: >>> derender.MODEL_TYPES["poly"].__name__
#: 'PolynomialModel'
MODEL_TYPES = ModelTypes({
    "gp": "derender.derendering.local_gp:LocalGPModel",
    "poly": "derender.derendering.polynomial:PolynomialModel",
    "rbf": "derender.derendering.rbf:RBFModel",
})


def model_metadata(pairs) -> dict:
    """Metadata a de-rendering model keeps from its calibration pairs (camera, WB, colour matrix)."""
    return {"camera": {"name": pairs.camera, "make": pairs.make, "model": pairs.model},
            "camera_to_srgb": np.asarray(pairs.camera_to_srgb).tolist(), "wb": np.asarray(pairs.wb).tolist()}


def fit_model(method: str, jpeg, raw, seed: int = 0, **kw) -> DerenderModel:
    """Fit a de-rendering model by name (``"gp"``, ``"poly"``, ``"rbf"``); extra keywords go to the class.

    Parameters
    ----------
    method : str
        ``"gp"`` (paper 2's local Gaussian process), ``"poly"`` (Chakrabarti et al.'s polynomial
        after a linear map) or ``"rbf"`` (Lin et al.'s radial basis functions); for a choice by
        cross-validation see :func:`derender.derendering.model_selection.fit_auto`.
    jpeg : array_like
        (N, 3) rendered colours: 8-bit codes (uint8) or values in [0, 1].
    raw : array_like
        (N, 3) linear RAW camera colours of the same pixels or patches.
    seed : int
        Seed of every random step (subsampling, k-means).
    **kw
        Options of the model class (e.g. ``n_train`` for the GP).

    Returns
    -------
    DerenderModel
        The fitted model; ``model.predict(colours)`` gives the per-colour Gaussian over the RAW
        colour, ``model.save(path)`` a versioned ``.npz``.

    Raises
    ------
    InputError
        An unknown method or option, or pairs that are not two (N, 3) arrays of the same
        length with finite values.

    References
    ----------
    Paper 2, Sec. 2.2 and 4 (``docs/paper2.md``); A. Chakrabarti, D. Scharstein, T. Zickler,
    "An Empirical Camera Model for Internet Color Vision", BMVC 2009; H. Lin, S. J. Kim,
    S. Süsstrunk, M. S. Brown, "Revisiting Radiometric Calibration for Color Computer Vision",
    ICCV 2011.

    Examples
    --------
    The local GP on 100 pairs of a gamma-2.2 camera (tiny settings; the defaults suit the
    thousands of pairs of a calibration): mid-grey code 128 comes back as raw ``0.5 ** 2.2``,
    with a variance:

    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> model = derender.fit_model("gp", jpeg, raw, n_clusters=2, table_size=0, n_jobs=1)
    >>> mean, variance = model.predict(np.array([[128, 128, 128]], np.uint8))
    >>> bool(np.allclose(mean, 0.5 ** 2.2, atol=0.01)), bool(np.all(variance > 0))
    (True, True)
    """
    if method not in MODEL_TYPES:
        raise InputError(f"unknown de-rendering method '{method}' (choose from {', '.join(MODEL_TYPES)})")
    try:
        model = MODEL_TYPES[method](seed=seed, **kw)
    except TypeError as exc:
        raise InputError(f"bad option for method '{method}': {exc}") from None
    return model.fit(jpeg, raw)


