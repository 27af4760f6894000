"""Camera profiles: a calibration made once (response, photometric factor, vignetting, view) reused.

The luminance-map procedure of the lighting literature (Inanici 2006; Pierson et al., LEUKOS
2021) calibrates a camera once, a response curve and a photometric factor from a
luminance-meter reading, and applies both to later brackets of the same camera and lens.
A :class:`CameraProfile` holds:

* ``curves``: the response curves of a classic merge (``g = ln f^-1`` per channel, 256 codes;
  :class:`~derender.response.curves.ResponseCurves`), used instead of fitting new ones by the
  methods that take curves (``debevec``, ``robertson``); or hdrgen's polynomials
  (:mod:`derender.io.rsp`), imported, kept as they were for an exact export;
* ``factor``: the photometric factor in cd/m2 per unit of the merged map at the reference
  exposure :data:`REFERENCE_EXPOSURE` (f/1, ISO 100). A merge divides every frame by its
  exposure ``t S / N^2`` relative to the first frame as given (:func:`derender.io.exif.exposure_factors`),
  so a map is ``m = L C S_0 / N_0^2`` (``L`` the scene's luminance, ``C`` the camera's
  constant with these curves, ``t`` in seconds) and the factor of a bracket whose first frame
  has f-number ``N_0`` and ISO ``S_0`` is

      k = F (N_0 / N_ref)^2 (S_ref / S_0),        F = k_spot (N_ref / N_0)^2 (S_0 / S_ref)

  at saving. A value missing from the EXIF is taken as the reference's at both ends (exact
  when the missing setting is the same as at calibration). The factor transfers exactly only
  with the same curves (a merge's scale is its curves' ``g_G(128) = 0``): a profile's factor
  taken with one method and applied with another is a warning in the CLI;
* ``vignetting``: :class:`~derender.photometry.vignetting.Vignetting`, divided out;
* ``view``: the lens's Radiance view (``-vta -vh 180 -vv 180``), written into ``.hdr`` outputs;
* ``make``, ``model``, ``lens``: the EXIF of the calibration bracket; a profile applied to
  images of another make or model is a warning (an error with ``--strict-camera``).

The file is JSON with ``"format": "derender-camera-profile"`` and ``"version": 1``
(:data:`PROFILE_FORMAT`); a file of another version is refused, not guessed at.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from derender.core.errors import InputError
from derender.photometry.vignetting import Vignetting
from derender.response.curves import ResponseCurves

__all__ = ["PROFILE_FORMAT", "REFERENCE_EXPOSURE", "CameraProfile", "save_profile", "load_profile",
           "factor_at_reference", "factor_for_bracket", "curves_from_rsp", "rsp_from_curves", "camera_mismatch",
           "CURVE_METHODS"]

#: The ``format`` field of a camera-profile file, and the version this code reads and writes.
PROFILE_FORMAT = ("derender-camera-profile", 1)
#: The exposure the stored photometric factor refers to: f-number and ISO speed (times in seconds).
REFERENCE_EXPOSURE = {"f_number": 1.0, "iso": 100.0}
#: Methods that merge with given response curves (their maps share a scale with the same curves).
CURVE_METHODS = ("debevec", "robertson")


@dataclass
class CameraProfile:
    """A camera calibration (module docstring). Every part is optional."""

    make: str | None = None
    model: str | None = None
    lens: str | None = None
    curves: ResponseCurves | None = None
    factor: float | None = None
    factor_method: str | None = None
    factor_source: str | None = None
    calibration_exposure: dict = field(default_factory=dict)
    vignetting: Vignetting | None = None
    view: str | None = None
    rsp: list | None = None

    def photometric_factor(self, f_number: float | None, iso: float | None) -> float | None:
        """The factor ``k`` (cd/m2 per unit of the map) of a bracket whose first frame has
        ``f_number`` and ``iso`` (None: the reference's)."""
        return None if self.factor is None else factor_for_bracket(self.factor, f_number, iso)


def factor_at_reference(k: float, f_number: float | None, iso: float | None) -> float:
    """``F = k (N_ref / N_0)^2 (S_0 / S_ref)``: a bracket's factor restated at :data:`REFERENCE_EXPOSURE`."""
    n = REFERENCE_EXPOSURE["f_number"] if f_number is None else float(f_number)
    s = REFERENCE_EXPOSURE["iso"] if iso is None else float(iso)
    return float(k) * (REFERENCE_EXPOSURE["f_number"] / n) ** 2 * (s / REFERENCE_EXPOSURE["iso"])


def factor_for_bracket(factor: float, f_number: float | None, iso: float | None) -> float:
    """``k = F (N_0 / N_ref)^2 (S_ref / S_0)``, the inverse of :func:`factor_at_reference`."""
    n = REFERENCE_EXPOSURE["f_number"] if f_number is None else float(f_number)
    s = REFERENCE_EXPOSURE["iso"] if iso is None else float(iso)
    return float(factor) * (n / REFERENCE_EXPOSURE["f_number"]) ** 2 * (REFERENCE_EXPOSURE["iso"] / s)


def curves_from_rsp(polys) -> ResponseCurves:
    """hdrgen's polynomials as response curves: ``g = ln p`` on the 256 codes as hdrgen
    evaluates them (linear toe, :func:`derender.io.rsp.rsp_tables`), shifted so that
    ``g_G(128) = 0`` (one shift for the three channels: hdrgen's colour balance is kept)."""
    from derender.io.rsp import rsp_tables

    g = np.log(rsp_tables(polys))
    return ResponseCurves(g - g[128, 1], method="external", params={"source": "hdrgen rsp"})


def rsp_from_curves(curves: ResponseCurves, order: int = 5) -> list[np.ndarray]:
    """Response curves as hdrgen polynomials of ``order`` (:func:`derender.io.rsp.fit_rsp` on
    ``exp g``), scaled together so that the green polynomial is 1 at ``x = 1`` (hdrgen's own
    normalisation per channel would change the colour balance; hdrgen does not require it)."""
    from derender.io.rsp import fit_rsp

    if curves.n_levels != 256:
        raise InputError(f"hdrgen's response is over 256 codes; these curves have {curves.n_levels} levels")
    polys = fit_rsp(np.exp(curves.log_inverse), order=order)
    s = float(np.polynomial.polynomial.polyval(1.0, polys[1]))
    if not s > 0:
        raise InputError("the fitted green polynomial is not positive at the top code")
    return [p / s for p in polys]


def camera_mismatch(profile: CameraProfile, exif: dict) -> str | None:
    """A sentence when the image's EXIF make or model differs from the profile's (None: same,
    or not stated on either side)."""
    diffs = []
    for key, attr in (("Make", "make"), ("Model", "model")):
        a, b = getattr(profile, attr), exif.get(key)
        if a and b and a.strip().lower() != str(b).strip().lower():
            diffs.append(f"{key.lower()} {b!r}, the profile's {a!r}")
    if not diffs:
        return None
    return "the camera profile is for another camera (the images' " + "; ".join(diffs) + ")"


def _curves_doc(c: ResponseCurves) -> dict:
    return {"quantity": "g = ln f^-1 (natural log of relative radiance x seconds) per 8-bit code, columns R, G, B",
            "method": c.method, "log_inverse": [[round(float(v), 9) for v in row] for row in c.log_inverse]}


def save_profile(profile: CameraProfile, path: str | os.PathLike, inputs=()) -> Path:
    """Write ``profile`` as a versioned JSON file (atomically)."""
    from dataclasses import asdict

    from derender.io.files import atomic_output

    doc = {"format": PROFILE_FORMAT[0], "version": PROFILE_FORMAT[1],
           "camera": {"make": profile.make, "model": profile.model, "lens": profile.lens},
           "response": None if profile.curves is None else _curves_doc(profile.curves),
           "rsp": None if profile.rsp is None else [[float(v) for v in p] for p in profile.rsp],
           "photometric": None if profile.factor is None else {
               "factor": profile.factor, "units": "cd/m2 per unit of the merged map at the reference exposure",
               "reference_exposure": REFERENCE_EXPOSURE, "method": profile.factor_method,
               "source": profile.factor_source, "calibration_exposure": profile.calibration_exposure},
           "vignetting": None if profile.vignetting is None else asdict(profile.vignetting),
           "view": profile.view}
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=1), encoding="utf-8")
    return path


def load_profile(path: str | os.PathLike) -> CameraProfile:
    """Read a profile written by :func:`save_profile`; another format or version, or a
    malformed file, is an :class:`InputError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such camera profile: {path}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError):
        raise InputError(f"{path} is not a camera profile (not JSON)") from None
    if not isinstance(doc, dict) or doc.get("format") != PROFILE_FORMAT[0]:
        raise InputError(f"{path} is not a derender camera profile (format {doc.get('format') if isinstance(doc, dict) else None!r})")
    if doc.get("version") != PROFILE_FORMAT[1]:
        raise InputError(f"{path} is a camera profile of version {doc.get('version')!r}; this derender reads "
                         f"version {PROFILE_FORMAT[1]}")
    try:
        return _profile_from_doc(doc)
    except (KeyError, TypeError, ValueError, AttributeError, InputError) as exc:
        raise InputError(f"{path} is not a readable camera profile ({exc.__class__.__name__}: {exc})") from None


def _opt_str(v) -> str | None:
    if v is None:
        return None
    if not isinstance(v, str):
        raise TypeError(f"expected text, got {v!r}")
    return v


def _profile_from_doc(doc: dict) -> CameraProfile:
    cam = doc.get("camera") or {}
    prof = CameraProfile(make=_opt_str(cam.get("make")), model=_opt_str(cam.get("model")),
                         lens=_opt_str(cam.get("lens")), view=_opt_str(doc.get("view")))
    if doc.get("view") is not None:
        from derender.io.rgbe import check_view

        prof.view = check_view(doc["view"])
    if doc.get("response") is not None:
        g = np.asarray(doc["response"]["log_inverse"], dtype=np.float64)
        if g.shape != (256, 3) or not np.all(np.isfinite(g)) or np.any(np.diff(g, axis=0) < 0):
            raise ValueError("response log_inverse must be 256 x 3 finite, non-decreasing values")
        prof.curves = ResponseCurves(g, method=str(doc["response"].get("method", "external")))
    if doc.get("rsp") is not None:
        polys = [np.asarray(p, dtype=np.float64) for p in doc["rsp"]]
        from derender.io.rsp import RSP_MAX_ORDER

        if len(polys) != 3 or any(p.ndim != 1 or not 1 <= p.size <= RSP_MAX_ORDER + 1 or
                                  not np.all(np.isfinite(p)) for p in polys):
            raise ValueError("rsp must be three polynomials of order 0..5")
        prof.rsp = polys
    ph = doc.get("photometric")
    if ph is not None:
        ref = ph.get("reference_exposure", REFERENCE_EXPOSURE)
        if {k: float(v) for k, v in ref.items()} != REFERENCE_EXPOSURE:
            raise ValueError(f"reference_exposure must be {REFERENCE_EXPOSURE}")
        f = float(ph["factor"])
        if not (np.isfinite(f) and f > 0):
            raise ValueError("the photometric factor must be a positive number")
        prof.factor, prof.factor_method = f, _opt_str(ph.get("method"))
        prof.factor_source = _opt_str(ph.get("source"))
        prof.calibration_exposure = dict(ph.get("calibration_exposure") or {})
    v = doc.get("vignetting")
    if v is not None:
        prof.vignetting = Vignetting(coefficients=tuple(float(x) for x in v["coefficients"]),
                                     centre=tuple(float(x) for x in v["centre"]),
                                     size=tuple(int(x) for x in v["size"]), rms_residual=float(v["rms_residual"]),
                                     r_max=float(v.get("r_max", 1.0)))
    return prof
