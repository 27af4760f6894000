"""Commands of the photometry stage and the report: ``derender illuminance``, ``derender falsecolor``,
``derender vignetting``, ``derender report``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from derender.cli.app import (
    INVERSE_HELP,
    TIMES_FILE_HELP,
    TIMES_HELP,
    absolute_units,
    app,
    check_times_options,
    map_summary,
    read_mask_codes,
    read_radiance_map,
)
from derender.core.errors import InputError


@app.command()
def illuminance(
    radiance_map: Path = typer.Argument(..., metavar="MAP", help="Radiance map (.hdr with a VIEW= line, or .exr)."),
    view: Optional[str] = typer.Option(None, "--view", help="Radiance view, e.g. '-vta -vh 180 -vv 180' "
                                       "(default: the .hdr's VIEW= line)."),
    variance: Optional[Path] = typer.Option(None, "--variance", help="Per-pixel variance (.exr): Ev's standard "
                                            "deviation, pixels taken as independent."),
    mask: Optional[Path] = typer.Option(None, "--mask", help="The merge's --mask PNG: the share of Ev carried by "
                                        "pixels over-exposed in every frame (a lower bound there)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Vertical illuminance Ev (lx) at the lens, as Radiance's 'evalglare -V' computes it.

    Ev is the sum of L cos(theta) Omega over the view, L = 179 (w·RGB) cd/m2 (docs: luminance maps)."""
    from derender.io.rgbe import read_radiance
    from derender.photometry.illuminance import vertical_illuminance
    from derender.photometry.projection import parse_view

    rad, header, primaries = read_radiance_map(radiance_map)
    text = view if view is not None else header.get("VIEW")
    if text is None:
        raise InputError(f"{radiance_map} states no view; give --view (e.g. '-vta -vh 180 -vv 180')")
    v = parse_view(text)
    var = read_radiance(variance) if variance is not None else None
    flagged = None if mask is None else read_mask_codes(mask, "--mask", rad.shape[:2]) == 128
    res = vertical_illuminance(rad, v, primaries=primaries, variance=var, flagged=flagged)
    if as_json:
        typer.echo(json.dumps({"ev_lx": res.ev, "ev_sd_lx": res.ev_sd, "solid_angle_sr": res.solid_angle,
                               "clipped_share": res.flagged_share, "view": v.header()}))
        return
    sd = f" +- {res.ev_sd:.4g}" if res.ev_sd is not None else ""
    typer.echo(f"Ev {res.ev:.6g}{sd} lx over {res.solid_angle:.4f} sr ({v.header()})")
    if res.flagged_share is not None:
        typer.echo(f"{100 * res.flagged_share:.2f} % of Ev from pixels over-exposed in every frame (a lower bound)")


@app.command()
def falsecolor(
    radiance_map: Path = typer.Argument(..., metavar="MAP", help="Radiance map (.hdr or .exr)."),
    output: Path = typer.Option(..., "--output", "-o", help="Figure (.png/.pdf/.svg)."),
    log: float = typer.Option(4.0, "--log", help="Decades shown below the top of the scale (0: linear scale)."),
    top: Optional[float] = typer.Option(None, "--max", help="Top of the scale (cd/m2; default: the 99.9th "
                                        "percentile rounded up to 1, 2 or 5 x 10^n)."),
    relative: bool = typer.Option(False, "--relative", help="Label the scale as relative luminance, whatever "
                                  "the map's header says."),
    absolute: bool = typer.Option(False, "--absolute", help="Label the scale in cd/m2, whatever the map's header "
                                  "says (a map calibrated by another program)."),
) -> None:
    """Falsecolor luminance map with a legend (179 (w·RGB), as Radiance's falsecolor).

    The legend is in cd/m2 only when the map says it is absolute (derender merge --spot,
    --absolute exif or a --profile with a factor: the EXR's whiteLuminance, the .hdr's
    DERENDER_PHOTOMETRY line) or --absolute is given; any other map is labelled relative."""
    from derender.io.files import OutputTransaction
    from derender.photometry.falsecolor import falsecolor_figure

    if log < 0:
        raise InputError(f"--log takes a number of decades >= 0, got {log}")
    rad, header, primaries = read_radiance_map(radiance_map)
    in_cd = absolute_units(header, absolute, relative, radiance_map)
    with OutputTransaction([radiance_map]) as tx:
        tmp = tx.add(output, "--output", (".png", ".pdf", ".svg"))
        scale = falsecolor_figure(rad, tmp, primaries=primaries, top=top, decades=log if log > 0 else None,
                                  absolute=in_cd, title=radiance_map.name, inputs=[radiance_map])
    typer.echo(f"falsecolor {'log' if scale['log'] else 'linear'} scale {scale['bottom']:.4g}..{scale['top']:.4g} "
               f"{scale['units']} -> {output}")


@app.command()
def vignetting(
    images: List[Path] = typer.Argument(..., help="A bracket of a flat field: a uniform, evenly lit surface "
                                        "filling the frame (or a folder of it)."),
    output: Path = typer.Option(..., "--output", "-o", help="Vignetting profile to write (.json)."),
    method: Optional[str] = typer.Option(None, "--method", help="Merge method for the flat field (default: "
                                         "debevec, or raw for RAW files)."),
    times: Optional[str] = typer.Option(None, "--times", help=TIMES_HELP),
    times_file: Optional[Path] = typer.Option(None, "--times-file", help=TIMES_FILE_HELP),
    times_inverse: bool = typer.Option(False, "--times-inverse", help=INVERSE_HELP),
    max_residual: float = typer.Option(0.05, "--max-residual", help="Largest rms deviation (relative) of the flat "
                                       "field from the radial model."),
) -> None:
    """Fit the lens's radial falloff on a merged flat field, for 'derender merge --vignetting'.

    V(r) = 1 + a1 r^2 + a2 r^4 + a3 r^6, r the distance to the centre over half the diagonal;
    'derender merge --vignetting V' divides it out."""
    from derender.hdr.files import merge_files
    from derender.io.exif import parse_times
    from derender.io.files import RAW_SUFFIXES, OutputTransaction, expand_image_paths
    from derender.photometry.vignetting import fit_vignetting, save_vignetting

    check_times_options(times, times_file, times_inverse)
    images = expand_image_paths(images, raw=True)
    if method is None:
        method = "raw" if any(p.suffix.lower() in RAW_SUFFIXES for p in images) else "debevec"
    inputs = list(images) + ([times_file] if times_file else [])
    with OutputTransaction(inputs) as tx:
        tmp = tx.add(output, "--output", (".json",))
        res = merge_files(images, parse_times(times) if times is not None else None, method, times_file=times_file,
                          times_file_inverse=times_inverse, inputs=inputs)
        vig = fit_vignetting(res.radiance, max_residual=max_residual, usable=res.mask == 0)
        save_vignetting(vig, tmp, inputs=inputs)
    corner = float(vig.gain()[0, 0])
    typer.echo(f"vignetting: V = 1 {vig.coefficients[0]:+.4f} r^2 {vig.coefficients[1]:+.4f} r^4 "
               f"{vig.coefficients[2]:+.4f} r^6 (corner {corner:.3f}, rms residual {100 * vig.rms_residual:.2f} %) "
               f"-> {output}")


@app.command()
def report(
    radiance_map: Path = typer.Argument(..., metavar="MAP", help="Radiance map (.exr or .hdr)."),
    output: Path = typer.Option(..., "--output", "-o", help="Report to write (.html, one self-contained file)."),
    variance: Optional[Path] = typer.Option(None, "--variance", help="Per-pixel variance (.exr): sigma/mu view and "
                                            "the readout's standard deviation."),
    mask: Optional[Path] = typer.Option(None, "--mask", help="The merge's --mask PNG (over-/under-exposed overlays)."),
    ghost_mask: Optional[Path] = typer.Option(None, "--ghost-mask", help="PNG, nonzero where frames were rejected."),
    view: Optional[str] = typer.Option(None, "--view", help="Radiance view for the illuminance in the summary "
                                       "(default: the .hdr's VIEW= line)."),
    absolute: bool = typer.Option(False, "--absolute", help="Legends and readout in cd/m2 whatever the map's header "
                                  "says (default: cd/m2 only for a map that says it is absolute, e.g. after --spot)."),
    relative: bool = typer.Option(False, "--relative", help="Legends and readout in relative units whatever the "
                                  "map's header says."),
    max_pixels: int = typer.Option(1_000_000, "--max-pixels", help="Largest page image (the map is reduced by an "
                                   "integer factor)."),
) -> None:
    """A self-contained HTML report of a radiance map, to look at it in any browser, offline.

    Panels: tone mapping with an exposure slider (linear or Reinhard); falsecolor luminance with
    a legend; relative uncertainty sigma/mu (with --variance); overlays of the masks; the
    response curves (merge --report); a summary; a readout under the mouse or arrow keys."""
    from derender.applications.report import write_report
    from derender.io.files import OutputTransaction

    rad, extras, header, primaries = _report_inputs(radiance_map, variance, mask, ghost_mask)
    v = _report_view(view, header)
    inputs = [p for p in (radiance_map, variance, mask, ghost_mask) if p is not None]
    in_cd = absolute_units(header, absolute, relative, radiance_map)
    summary = {"map": str(radiance_map), "size": f"{rad.shape[1]}x{rad.shape[0]}"}
    if "SOFTWARE" in header:
        summary["software"] = header["SOFTWARE"]
    record = map_summary(header)       # the merge's own record, as 'derender merge' printed it
    if record is not None:
        summary.update(record.rows())
    with OutputTransaction(inputs) as tx:
        tmp = tx.add(output, "--output", (".html", ".htm"))
        info = write_report(tmp, rad, **extras, absolute=in_cd, primaries=primaries,
                            summary=summary, view=v, title=f"derender report: {radiance_map.name}",
                            max_pixels=max_pixels, inputs=inputs)
    typer.echo(f"report {info['width']}x{info['height']} (reduced {info['factor']}x), {info['bytes'] / 1e6:.2f} MB "
               f"-> {output}")


def _report_inputs(radiance_map: Path, variance, mask, ghost_mask):
    from derender.io.rgbe import read_radiance

    rad, header, primaries = read_radiance_map(radiance_map)
    extras: dict = {}
    if variance is not None:
        extras["variance"] = read_radiance(variance)
    for key, option, p in (("mask", "--mask", mask), ("ghost_mask", "--ghost-mask", ghost_mask)):
        if p is not None:
            extras[key] = read_mask_codes(p, option, rad.shape[:2])
    return rad, extras, header, primaries


def _report_view(view, header):
    from derender.photometry.projection import parse_view

    text = view if view is not None else header.get("VIEW")
    return parse_view(text) if text else None
