"""Camera profiles on the command line: ``derender profile import-rsp / export-rsp / show`` and the
photometric steps of ``derender merge`` (``--profile``, ``--save-profile``, ``--spot``,
``--absolute exif``, ``--vignetting``), a thin shell over :mod:`derender.photometry.profile`
and :mod:`derender.photometry.calibration`."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import typer

from derender.cli.app import app
from derender.core.errors import InputError

profile_app = typer.Typer(no_args_is_help=True, help="Camera profiles: show them, import and export hdrgen's .rsp.")
app.add_typer(profile_app, name="profile")


@profile_app.command("import-rsp")
def import_rsp(
    rsp: Path = typer.Argument(..., help="hdrgen response file (.rsp: three polynomials, R, G, B)."),
    output: Path = typer.Option(..., "--output", "-o", help="Camera profile to write (.json)."),
    make: Optional[str] = typer.Option(None, "--make", help="Camera make (EXIF Make) the response is for."),
    model: Optional[str] = typer.Option(None, "--model", help="Camera model (EXIF Model)."),
    lens: Optional[str] = typer.Option(None, "--lens", help="Lens (EXIF LensModel)."),
) -> None:
    """A camera profile holding hdrgen's response ('derender merge --profile' merges with it)."""
    from derender.io.files import OutputTransaction
    from derender.io.rsp import read_rsp
    from derender.photometry.profile import CameraProfile, curves_from_rsp, save_profile

    polys = read_rsp(rsp)
    prof = CameraProfile(make=make, model=model, lens=lens, curves=curves_from_rsp(polys), rsp=polys)
    with OutputTransaction([rsp]) as tx:
        save_profile(prof, tx.add(output, "--output", (".json",)), inputs=[rsp])
    typer.echo(f"response of orders {', '.join(str(len(p) - 1) for p in polys)} (R, G, B) from {rsp} -> {output}")


@profile_app.command("export-rsp")
def export_rsp(
    profile: Path = typer.Argument(..., help="Camera profile (.json) with response curves."),
    output: Path = typer.Option(..., "--output", "-o", help="hdrgen response file to write (.rsp)."),
    order: int = typer.Option(5, "--order", help="Polynomial order (1..5) when the curves are fitted."),
) -> None:
    """hdrgen's response file ('hdrgen -r X.rsp') from a profile: its imported polynomials as they
    were, else polynomials fitted to its curves."""
    import numpy as np

    from derender.io.files import OutputTransaction
    from derender.io.rsp import rsp_tables, write_rsp
    from derender.photometry.profile import load_profile, rsp_from_curves

    prof = load_profile(profile)
    if prof.rsp is None and prof.curves is None:
        raise InputError(f"{profile} holds no response curves (save one with a debevec or robertson merge)")
    polys = prof.rsp if prof.rsp is not None else rsp_from_curves(prof.curves, order=order)
    fit = ""
    if prof.rsp is None:
        g = np.log(rsp_tables(polys))
        d = (g - g[128, 1]) - prof.curves.log_inverse
        err = np.abs(np.expm1(d[19:]))
        fit = f"; fitted within {100 * err.max():.2f} % (codes 19-255, max), {100 * np.median(err):.2f} % (median)"
    with OutputTransaction([profile]) as tx:
        write_rsp(tx.add(output, "--output", (".rsp",)), polys, inputs=[profile])
    typer.echo(f"hdrgen response{fit} -> {output}")


@profile_app.command("show")
def show(profile: Path = typer.Argument(..., help="Camera profile (.json).")) -> None:
    """Print what a profile holds."""
    from derender.photometry.profile import load_profile

    p = load_profile(profile)
    typer.echo(json.dumps({"make": p.make, "model": p.model, "lens": p.lens, "curves": p.curves is not None,
                           "rsp": p.rsp is not None, "factor_at_f1_iso100": p.factor, "factor_method": p.factor_method,
                           "factor_source": p.factor_source, "vignetting": p.vignetting is not None,
                           "view": p.view}, indent=1))


# --------------------------------------------------------------------------- merge's photometry
@dataclass
class Photometry:
    """What ``derender merge`` does after the merge: the parsed options of its photometric steps."""

    profile: object = None
    vignetting: object = None
    spot: object = None
    absolute: str | None = None
    notes: list = field(default_factory=list)

    @property
    def active(self) -> bool:
        return any(v is not None for v in (self.profile, self.vignetting, self.spot, self.absolute))


def merge_photometry(*, profile: Optional[Path], vignetting: Optional[Path], spot: Optional[str],
                     absolute: Optional[str], method: str, image: Path, strict: bool) -> Photometry:
    """Read and check the photometric options of ``derender merge`` before any work."""
    ph = Photometry(absolute=absolute)
    if absolute is not None and absolute != "exif":
        raise InputError(f"--absolute takes 'exif' (the nominal factor from EXIF t, N, S), got {absolute!r}")
    if absolute is not None and spot is not None:
        raise InputError("give either --spot (a meter reading) or --absolute exif (nominal), not both")
    if vignetting is not None:
        from derender.photometry.vignetting import load_vignetting

        ph.vignetting = load_vignetting(vignetting)
    if spot is not None:
        from derender.photometry.calibration import parse_spot

        ph.spot = parse_spot(spot)
    if profile is not None:
        from derender.io.exif import read_exif
        from derender.photometry.profile import CURVE_METHODS, camera_mismatch, load_profile

        prof = load_profile(profile)
        note = camera_mismatch(prof, read_exif(image))
        if note is not None:
            if strict:
                raise InputError(note + " (--strict-camera)")
            typer.echo(f"warning: {note}; its response and factor may not fit (--strict-camera makes this an "
                       "error)", err=True)
        if prof.factor is not None and spot is None and absolute is None and prof.factor_method is not None and \
                prof.factor_method != method and not {prof.factor_method, method} <= set(CURVE_METHODS):
            typer.echo(f"warning: the profile's photometric factor was taken with --method {prof.factor_method}; "
                       f"a {method} merge may have another scale", err=True)
        ph.profile = prof
        if ph.vignetting is None:
            ph.vignetting = prof.vignetting
    return ph


def profile_options(ph: Photometry, method: str) -> dict:
    """The merge options a profile sets: its response curves for the methods that take curves."""
    from derender.photometry.profile import CURVE_METHODS

    prof = ph.profile
    if prof is None or prof.curves is None:
        return {}
    if method in CURVE_METHODS:
        return {"curves": prof.curves}
    typer.echo(f"note: {method} fits its own per-frame curves; the profile's response curves are not used", err=True)
    return {}


def _first_exposure(image: Path) -> tuple[float | None, float | None]:
    from derender.io.exif import read_exif

    ex = read_exif(image)
    return ex.get("FNumber"), ex.get("ISO")


def apply_photometry(ph: Photometry, result, images: list, method: str) -> str | None:
    """Vignetting, then the photometric factor (spot, nominal EXIF or the profile's) applied to
    ``result`` in place; the factor's source (None: the map stays relative)."""
    import numpy as np

    from derender.io.rgbe import SRGB_PRIMARIES

    if ph.vignetting is not None:
        from derender.photometry.vignetting import correct_vignetting

        result.radiance, result.variance = correct_vignetting(result.radiance, ph.vignetting, result.variance)
    k, source, unc = None, None, None
    if ph.spot is not None:
        from derender.photometry.calibration import spot_factor

        cal = spot_factor(result.radiance, ph.spot, primaries=SRGB_PRIMARIES, mask=result.mask)
        k, s = cal.factor, ph.spot
        source = f"spot {s.x},{s.y},{s.width},{s.height}={s.nits:g}"
        typer.echo(f"photometric factor {k:.6g} from the spot ({s.nits:g} cd/m2; luminance spread in it "
                   f"{100 * cal.spread:.1f} %)", err=True)
    elif ph.absolute == "exif":
        cal = _exif_factor(result, images)
        from derender.photometry.calibration import RAW_SATURATION_EXPOSURE, SENSITIVITY_RATINGS

        k, unc, rating = cal.factor, cal.uncertainty, SENSITIVITY_RATINGS[cal.rating]
        if result.info.get("engine_path") == "raw":
            basis = ("ISO 12232 saturation speed" if cal.rating == "saturation" else
                     "ISO speed not stated as saturation-based (EXIF SensitivityType), taken as one") + \
                f": a neutral at the RAW white level is {RAW_SATURATION_EXPOSURE:.1f} N^2/(t S) cd/m2"
        else:
            basis = f"{rating.name}: a surface rendered at code 118 is {rating.constant:.1f} N^2/(t S) cd/m2"
        source = f"exif nominal ({basis})"
        typer.echo(f"photometric factor {k:.6g} nominal from EXIF ({basis}; relative standard uncertainty "
                   f"{100 * unc:.0f} %)", err=True)
    elif ph.profile is not None and ph.profile.factor is not None:
        n0, s0 = _first_exposure(images[0])
        k = ph.profile.photometric_factor(n0, s0)
        source = "profile"
        typer.echo(f"photometric factor {k:.6g} from the profile (f/{n0 if n0 else '?'}, ISO {s0 if s0 else '?'})",
                   err=True)
    if k is None:
        return None
    result.radiance *= np.float32(k)
    if result.variance is not None:
        result.variance *= np.float32(k ** 2)
    result.info.update({"photometric_factor": k, "photometric_source": source, "white_luminance": 179.0})
    attrs = {"derender:photometry": f"absolute: L = 179 (0.2126 R + 0.7152 G + 0.0722 B) cd/m2; factor {k:.6g} "
                                    f"from {source}"}
    if unc is not None:
        result.info["photometric_uncertainty"] = unc
        attrs["derender:photometry"] += f"; relative standard uncertainty {unc:.2f}"
    result.info["exr_attributes"] = {**result.info.get("exr_attributes", {}), **attrs}
    return source


def hdr_header_lines(info: dict) -> list[str]:
    """The .hdr header lines recording the photometric calibration (``DERENDER_PHOTOMETRY=``), if
    any, and the merge's summary record (``DERENDER_SUMMARY=``, :mod:`derender.hdr.summary`)."""
    text = (info.get("exr_attributes") or {}).get("derender:photometry")
    lines = [] if text is None else [f"DERENDER_PHOTOMETRY= {text}"]
    if info.get("summary") is not None:
        lines.append(f"DERENDER_SUMMARY= {info['summary'].to_json()}")
    return lines


def _exif_factor(result, images: list):
    from derender.io.exif import read_exif
    from derender.io.images import read_codes
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.calibration import exif_factor, sensitivity_rating

    if result.info.get("engine_path") == "raw":
        return _raw_exif_factor(images)
    exifs = [read_exif(p) for p in images]
    for p, e in zip(images, exifs):
        lacking = [k for k in ("ExposureTime", "FNumber", "ISO") if k not in e]
        if lacking:
            raise InputError(f"--absolute exif needs ExposureTime, FNumber and ISO in every frame's EXIF; {p.name} "
                             f"has no {', '.join(lacking)}")

    ratings = [sensitivity_rating(e) for e in exifs]
    if len({r for r, _ in ratings}) > 1:
        raise InputError("--absolute exif: the frames state their ISO speed under different ratings (EXIF "
                         f"SensitivityType: {', '.join(sorted({r for r, _ in ratings}))}); use --spot")

    def frames():
        for p, e, (_, speed) in zip(images, exifs, ratings):
            codes = read_codes(p, max_megapixels=None)
            if codes is None:
                raise InputError(f"--absolute exif reads 8-bit frames; {p.name} is not one")
            yield codes, e["ExposureTime"], e["FNumber"], speed

    return exif_factor(result.radiance, frames(), primaries=SRGB_PRIMARIES, mask=result.mask, rating=ratings[0][0])


def _raw_exif_factor(images: list):
    """``--absolute exif`` on a RAW merge: f-number and ISO from each file (no mosaic decoded)."""
    from derender.io.raw import read_raw_exposure
    from derender.photometry.calibration import raw_exif_factor, sensitivity_rating

    settings = [read_raw_exposure(p) for p in images]
    for p, e in zip(images, settings):
        lacking = [name for key, name in (("fnumber", "FNumber"), ("iso", "ISO")) if key not in e]
        if lacking:
            raise InputError(f"--absolute exif needs FNumber and ISO in every RAW file; {p.name} has no "
                             f"{', '.join(lacking)}")
    ratings = {sensitivity_rating({"SensitivityType": e.get("sensitivity_type", 0)})[0] for e in settings}
    if len(ratings) > 1:
        raise InputError("--absolute exif: the frames state their ISO speed under different ratings (EXIF "
                         f"SensitivityType: {', '.join(sorted(ratings))}); use --spot")
    return raw_exif_factor([(e["fnumber"], e["iso"]) for e in settings], rating=ratings.pop())


def save_merge_profile(path: Path, ph: Photometry, result, images: list, method: str, view: str | None,
                       inputs) -> None:
    """``--save-profile``: the merge's curves, the factor it applied, its vignetting and view, the camera."""
    from derender.io.exif import read_exif
    from derender.photometry.profile import CameraProfile, factor_at_reference, save_profile
    from derender.response.curves import ResponseCurves

    ex = read_exif(images[0])
    curves = result.info.get("curves")
    prof = CameraProfile(make=ex.get("Make"), model=ex.get("Model"), lens=ex.get("Lens"),
                         curves=curves if isinstance(curves, ResponseCurves) else None,
                         vignetting=ph.vignetting, view=view if view is not None or ph.profile is None else ph.profile.view)
    if ph.profile is not None and prof.curves is None:
        prof.curves, prof.rsp = ph.profile.curves, ph.profile.rsp
    k = result.info.get("photometric_factor")
    if k is not None:
        n0, s0 = ex.get("FNumber"), ex.get("ISO")
        prof.factor = factor_at_reference(k, n0, s0)
        prof.factor_method = method
        prof.factor_source = result.info.get("photometric_source")
        prof.calibration_exposure = {"f_number": n0, "iso": s0}
    save_profile(prof, path, inputs=inputs)
