"""Spectral data for the camera simulator: cameras, reflectances, illuminants.

All spectra are sampled on :data:`WAVELENGTHS` (380-780 nm, 5 nm), the grid of the
rawtoaces data. Built-in data comes from colour-science (so a fresh install works):
camera sensitivities ``colour.MSDS_CAMERA_SENSITIVITIES`` (NPL measurements of the
Nikon D5100 and Sigma SD Merrill), ColorChecker 24 reflectances (``ColorChecker N
Ohta``), the 190 rawtoaces training reflectances shipped inside colour-science, the
sRGB basis of Mallett & Yuksel (2019) for turning RGB textures into plausible
reflectances, and CIE illuminants. Any rawtoaces camera JSON (schema 0.1) can be
loaded with :func:`load_camera_file`.
"""

from __future__ import annotations

import functools
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "WAVELENGTHS",
    "CameraSpectral",
    "builtin_camera_names",
    "load_camera_file",
    "load_camera",
    "reflectance_library",
    "illuminant_spd",
    "cmfs_xyz",
    "camera_search_dirs",
    "camera_search_order",
    "available_cameras",
]


#: Wavelength grid (nm) of every spectrum in the simulator.
WAVELENGTHS = np.arange(380.0, 781.0, 5.0)


_BUILTIN = {
    "nikon-d5100": ("Nikon 5100 (NPL)", "NIKON CORPORATION", "NIKON D5100"),
    "sigma-sd-merrill": ("Sigma SDMerill (NPL)", "SIGMA", "SIGMA SD1 Merrill"),
}


@dataclass
class CameraSpectral:
    """A camera's spectral sensitivities and sensor characteristics.

    sensitivities : (len(WAVELENGTHS), 3) relative R, G, B responses (max of G = 1).
    bits : ADC depth (12 or 14); black_level / white_level in DN.
    full_well : electrons at white level; read_noise : Gaussian read noise, DN.
    """

    name: str
    make: str
    model: str
    sensitivities: np.ndarray
    bits: int = 14
    black_level: int = 512
    white_level: int = 16383
    full_well: float = 24000.0
    read_noise: float = 2.5
    source: str = ""
    extra: dict = field(default_factory=dict)

    def with_bits(self, bits: int) -> "CameraSpectral":
        """Same camera with a 12- or 14-bit ADC (levels scaled accordingly)."""
        if bits not in (12, 14):
            raise InputError(f"--bits must be 12 or 14, got {bits}")
        scale = 2 ** (bits - self.bits)
        return CameraSpectral(
            self.name, self.make, self.model, self.sensitivities, bits,
            int(round(self.black_level * scale)), int(2**bits - 1), self.full_well,
            self.read_noise * scale, self.source, dict(self.extra),
        )


def _resample(wl: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation of (n,) or (n, k) spectra onto WAVELENGTHS (zero outside)."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        return np.interp(WAVELENGTHS, wl, values, left=0.0, right=0.0)
    return np.stack([np.interp(WAVELENGTHS, wl, values[:, i], left=0.0, right=0.0)
                     for i in range(values.shape[1])], axis=1)


def _normalise_sensitivities(s: np.ndarray) -> np.ndarray:
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, None)
    peak = s[:, 1].max()
    if not np.isfinite(peak) or peak <= 0:
        raise InputError("camera sensitivities have no green response")
    return s / peak


def builtin_camera_names() -> list[str]:
    """Names accepted by :func:`load_camera` without a file."""
    return sorted(_BUILTIN)


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")


def load_camera_file(path: str | os.PathLike) -> CameraSpectral:
    """Load a rawtoaces camera JSON (``spectral_data.data.main["<nm>"] = [R, G, B]``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such camera file: {path}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        main = doc["spectral_data"]["data"]["main"]
        wl = np.array(sorted(float(k) for k in main))
        vals = np.array([main[k] for k in sorted(main, key=float)], dtype=np.float64)
        header = doc.get("header", {})
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path} is not a rawtoaces camera JSON ({type(exc).__name__})") from None
    if vals.ndim != 2 or vals.shape[1] != 3 or wl.size < 10:
        raise InputError(f"{path}: expected [R, G, B] sensitivities per wavelength")
    make = str(header.get("manufacturer", "")).strip() or "Unknown"
    model = str(header.get("model", "")).strip() or path.stem
    return CameraSpectral(
        name=_slug(f"{make}-{model}"), make=make, model=f"{make} {model}" if not model.startswith(make) else model,
        sensitivities=_normalise_sensitivities(_resample(wl, vals)), source=str(path),
    )


def load_camera(name_or_path: str | os.PathLike,
                search_dirs: Sequence[str | os.PathLike] | None = None) -> CameraSpectral:
    """A built-in camera by name (see :func:`builtin_camera_names`), a rawtoaces JSON path,
    or a camera name found as a JSON file in ``search_dirs`` (e.g. ``canon-powershot-s90``).

    ``search_dirs=None`` (the default, and what every command uses) searches
    :func:`camera_search_dirs`: one search order for the whole tool. An unknown name is an
    :class:`InputError` that lists the built-in names and every folder looked in."""
    key = str(name_or_path)
    if key in _BUILTIN:
        return _load_builtin(key)
    p = Path(key)
    if p.suffix.lower() == ".json" or p.is_file():
        return load_camera_file(p)
    dirs = camera_search_dirs() if search_dirs is None else tuple(Path(d) for d in search_dirs)
    slug = _slug(key)
    for f in _camera_files(dirs):
        s = _slug(re.sub(r"_380_780_5$", "", f.stem))
        if s == slug or s.endswith(slug):
            return load_camera_file(f)
    known = ", ".join(builtin_camera_names())
    looked = "; ".join(str(d) for d in camera_search_order()) if search_dirs is None else \
        "; ".join(str(d) for d in search_dirs) or "no folder"
    raise InputError(f"unknown camera {key!r}: use one of {known}, a name from 'derender cameras', or a rawtoaces "
                     f"JSON file (--camera-file); looked for camera JSON files in: {looked}")


def _camera_files(dirs: Sequence[str | os.PathLike]) -> list[Path]:
    out = []
    for d in dirs:
        d = Path(d)
        if d.is_dir():
            out.extend(sorted(d.glob("*.json")))
    return out


def available_cameras(search_dirs: Sequence[str | os.PathLike] | None = None) -> list[tuple[str, str]]:
    """Every camera :func:`load_camera` accepts by name: ``(name, source)`` pairs, the built-in
    cameras first (source ``"built-in (colour-science)"``), then one per rawtoaces JSON file of
    the search folders (name as accepted, source the file)."""
    out = [(n, "built-in (colour-science)") for n in builtin_camera_names()]
    dirs = camera_search_dirs() if search_dirs is None else search_dirs
    seen = {n for n, _ in out}
    for f in _camera_files(dirs):
        name = _slug(re.sub(r"_380_780_5$", "", f.stem))
        if name not in seen:
            seen.add(name)
            out.append((name, str(f)))
    return out


@functools.lru_cache(maxsize=None)
def _load_builtin(key: str) -> CameraSpectral:
    import colour

    label, make, model = _BUILTIN[key]
    msds = colour.MSDS_CAMERA_SENSITIVITIES[label]
    sens = _resample(np.asarray(msds.wavelengths), np.asarray(msds.values))
    return CameraSpectral(name=key, make=make, model=model, sensitivities=_normalise_sensitivities(sens),
                          source=f"colour-science MSDS_CAMERA_SENSITIVITIES['{label}']")


@functools.lru_cache(maxsize=None)
def reflectance_library() -> tuple[tuple[str, ...], np.ndarray, dict[str, slice]]:
    """All built-in reflectances on :data:`WAVELENGTHS`.

    Returns ``(names, reflectances (L, 81), groups)`` where ``groups`` maps
    ``"mallett"`` (3 sRGB basis spectra, Mallett & Yuksel 2019), ``"colorchecker24"``
    (ColorChecker N Ohta) and ``"rawtoaces190"`` (rawtoaces training set) and
    ``"white"`` (a flat 0.9 reflector) to slices of the rows.
    """
    import colour
    from colour.characterisation import read_training_data_rawtoaces_v1

    names: list[str] = []
    rows: list[np.ndarray] = []
    groups: dict[str, slice] = {}

    basis = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019
    start = len(rows)
    b = _resample(np.asarray(basis.wavelengths), np.asarray(basis.values))
    for i, lab in enumerate(basis.labels):
        names.append(f"mallett-{lab}")
        rows.append(b[:, i])
    groups["mallett"] = slice(start, len(rows))

    start = len(rows)
    for nm, sd in colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].items():
        names.append(f"cc24-{nm}")
        rows.append(_resample(np.asarray(sd.wavelengths), np.asarray(sd.values)))
    groups["colorchecker24"] = slice(start, len(rows))

    start = len(rows)
    training = read_training_data_rawtoaces_v1()
    tv = _resample(np.asarray(training.wavelengths), np.asarray(training.values))
    for i, lab in enumerate(training.labels):
        names.append(f"rawtoaces-{lab}")
        rows.append(tv[:, i])
    groups["rawtoaces190"] = slice(start, len(rows))

    start = len(rows)
    names.append("white-0.9")
    rows.append(np.full(WAVELENGTHS.size, 0.9))
    groups["white"] = slice(start, len(rows))

    refl = np.clip(np.stack(rows), 0.0, 1.0)
    # Mallett basis sums to 1 (a perfect reflector); edges of the grid may extrapolate to 0.
    return tuple(names), refl, groups


@functools.lru_cache(maxsize=None)
def illuminant_spd(name: str) -> np.ndarray:
    """CIE illuminant ``name`` (colour-science ``SDS_ILLUMINANTS``) on WAVELENGTHS, Y = 1."""
    import colour

    if name not in colour.SDS_ILLUMINANTS:
        raise InputError(f"unknown illuminant {name!r}")
    sd = colour.SDS_ILLUMINANTS[name]
    spd = _resample(np.asarray(sd.wavelengths), np.asarray(sd.values))
    y = float(cmfs_xyz()[:, 1] @ spd)
    return spd / y


@functools.lru_cache(maxsize=None)
def cmfs_xyz() -> np.ndarray:
    """CIE 1931 2-degree colour-matching functions on WAVELENGTHS, (81, 3)."""
    import colour

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    return _resample(np.asarray(cmfs.wavelengths), np.asarray(cmfs.values))


#: Where a camera JSON folder is looked for below a data root (``shared/data`` layout).
_CAMERA_SUBDIR = Path("rawtoaces-spectral") / "data" / "camera"


def camera_search_order(extra: Sequence[str | os.PathLike] = ()) -> tuple[Path, ...]:
    """Every folder the tool looks in for rawtoaces camera JSON files, in order, whether it
    exists or not: ``extra``; ``$DERENDER_SHARED_DATA/rawtoaces-spectral/data/camera``; then
    the same below ``shared/data`` in the working directory, beside it (``../shared/data``),
    and beside the source checkout the package runs from (``<checkout>/../shared/data``)."""
    here = Path(__file__).resolve()
    cands = [Path(p) for p in extra]
    env = os.environ.get("DERENDER_SHARED_DATA")
    if env:
        cands.append(Path(env) / _CAMERA_SUBDIR)
    cwd = Path.cwd()
    cands += [cwd / "shared" / "data" / _CAMERA_SUBDIR, cwd.parent / "shared" / "data" / _CAMERA_SUBDIR]
    if len(here.parents) > 3 and here.parents[2].name == "src":      # an editable / source checkout
        cands.append(here.parents[3].parent / "shared" / "data" / _CAMERA_SUBDIR)
    out, seen = [], set()
    for c in cands:
        key = os.path.abspath(c)
        if key not in seen:
            seen.add(key)
            out.append(c)
    return tuple(out)


def camera_search_dirs(extra: Sequence[str | os.PathLike] = ()) -> tuple[Path, ...]:
    """The folders of :func:`camera_search_order` that exist (each folder once)."""
    seen, out = set(), []
    for c in camera_search_order(extra):
        if c.is_dir() and c.resolve() not in seen:
            seen.add(c.resolve())
            out.append(c)
    return tuple(out)
