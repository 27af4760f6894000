"""``derender experiment ...``: the papers' experiments on simulated cameras."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from derender.cli.app import (
    app,
    console,
    parse_size,
)
from derender.core.errors import InputError

experiment_app = typer.Typer(no_args_is_help=True, help="Paper experiments on simulated cameras.")
app.add_typer(experiment_app, name="experiment")


def _cams(cameras: Optional[str]):
    return [c.strip() for c in cameras.split(",") if c.strip()] if cameras else None


@experiment_app.command("derender-table")
def exp_derender_table(
    cameras: Optional[str] = typer.Option(None, "--cameras", help="Comma-separated cameras (default: S90, 5D II, D5100)."),
    n_train: int = typer.Option(5000, "--n-train", help="Training pairs."),
    methods: str = typer.Option("gp,poly,rbf", "--methods", help="Methods."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write the rows as JSON."),
) -> None:
    """Paper 2 Table 1: RMSE / relative RMSE, all and out-of-gamut, plus 95 % interval coverage."""
    from derender.evaluation.experiments import derender_table, format_table

    rows = derender_table(_cams(cameras), methods=[m.strip() for m in methods.split(",")], n_train=n_train,
                          seed=seed, progress=lambda msg: console().print(msg))
    typer.echo(format_table(rows, [("camera", "camera", ""), ("method", "method", ""),
                                   ("rmse_all", "RMSE all", ".4f"), ("rmse_oog", "RMSE oog", ".4f"),
                                   ("rel_rmse_all", "rel RMSE all", ".3f"), ("rel_rmse_in", "rel in-gamut", ".3f"),
                                   ("rel_rmse_all_mean", "rel RMSE all (mean)", ".3f"),
                                   ("rel_rmse_oog", "rel out-of-gamut", ".3f"), ("median_rel", "median rel", ".3f"),
                                   ("ratio_to_poly", "/poly", ".2f"),
                                   ("coverage95", "95% coverage R/G/B", ".3f"), ("fit_seconds", "fit s", ".1f")]))
    if output is not None:
        output.write_text(json.dumps(rows, indent=2, default=float))


@experiment_app.command("derender-families")
def exp_derender_families(
    families: Optional[str] = typer.Option(None, "--families", help="Pipeline families, comma separated (default: all; see 'derender simulate --help')."),
    cameras: Optional[str] = typer.Option(None, "--cameras", help="Comma-separated cameras (default: nikon-d5100)."),
    n_train: int = typer.Option(5000, "--n-train", help="Training pairs."),
    methods: str = typer.Option("gp,poly,rbf", "--methods", help="Methods."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write the rows as JSON."),
) -> None:
    """Paper 2's de-rendering models on chart sessions rendered by every pipeline family
    (random split and 4 held-out illuminants); relative RMSE all / clipped / out-of-gamut, 95 % coverage;
    tuning families (paper, camera) vs held out."""
    from derender.evaluation.derendering_families import derender_families
    from derender.evaluation.experiments import format_table
    from derender.io.files import OutputTransaction

    with OutputTransaction() as tx:
        json_tmp = tx.add(output, "--json", (".json",))
        rows = derender_families(_cams(families), cameras=_cams(cameras), methods=[m.strip() for m in methods.split(",")],
                                 n_train=n_train, seed=seed, progress=lambda msg: console().print(msg))
        if json_tmp is not None:
            json_tmp.write_text(json.dumps(rows, indent=2, default=float) + "\n")
    typer.echo(format_table(rows, [("family", "family", ""), ("role", "role", ""), ("split", "split", ""),
                                   ("method", "method", ""), ("rel_rmse_all", "rel RMSE all", ".3f"),
                                   ("rel_rmse_clipped", "rel clipped", ".3f"), ("rel_rmse_oog", "rel out-of-gamut", ".3f"),
                                   ("coverage95", "95% coverage R/G/B", ".3f"), ("fit_seconds", "fit s", ".1f")]))


@experiment_app.command("threshold-sweep")
def exp_threshold_sweep(
    cameras: Optional[str] = typer.Option(None, "--cameras", help="Comma-separated cameras."),
    holdouts: Optional[str] = typer.Option(None, "--holdouts", help="Illuminants to hold out (default: all 16)."),
    n_train: int = typer.Option(5000, "--n-train", help="Training pairs."),
    methods: str = typer.Option("gp,poly,rbf", "--methods", help="Methods."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Figure like paper 2 Fig. 4."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed."),
) -> None:
    """Paper 2 Fig. 4: relative RMSE of scene colour from exposure sequences vs the JPEG interval used."""
    from derender.evaluation.experiments import format_table, plot_threshold_sweep, threshold_sweep

    ho = [int(v) for v in holdouts.split(",")] if holdouts else None
    rows = threshold_sweep(_cams(cameras), methods=[m.strip() for m in methods.split(",")], n_train=n_train,
                           holdouts=ho, seed=seed, progress=lambda msg: console().print(msg))
    typer.echo(format_table(rows, [("camera", "camera", ""), ("method", "method", ""), ("interval", "interval", ""),
                                   ("rel_rmse_all", "rel RMSE all", ".4f"), ("rel_rmse_in", "rel RMSE in-gamut", ".4f"),
                                   ("rel_rmse_oog", "rel RMSE oog", ".4f"), ("no_valid", "patches w/o valid obs", ".1f"),
                                   ("runs", "held-out runs", "")]))
    if plot is not None:
        plot_threshold_sweep(rows, plot)
        typer.echo(f"figure -> {plot}")


@experiment_app.command("photometric-stereo")
def exp_photometric_stereo(
    camera: str = typer.Option("canon-powershot-s90", "--camera", help="Camera."),
    lights: int = typer.Option(20, "--lights", help="Number of lights."),
    size: int = typer.Option(128, "--size", help="Image size (square)."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Angular-error maps and depth cross-sections."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed."),
) -> None:
    """Paper 2 Sec. 4.3: GP weighted LS vs polynomial LS vs gamma-2.2 LS on a sphere and bumps."""
    from derender.evaluation.experiments import format_table, photometric_stereo_experiment

    rows = photometric_stereo_experiment(camera, n_lights=lights, size=size, seed=seed, plot=plot,
                                         progress=lambda msg: console().print(msg))
    typer.echo(format_table(rows, [("shape", "shape", ""), ("method", "method", ""),
                                   ("mean_angular_error_deg", "mean angular error (deg)", ".2f"),
                                   ("median_angular_error_deg", "median (deg)", ".2f"), ("pixels", "pixels", "")]))


@experiment_app.command("fusion-gain")
def exp_fusion_gain(
    styles: str = typer.Option("simple,camera", "--styles", help="Rendering styles, comma separated."),
    seeds: str = typer.Option("0,1,2", "--seeds", help="Scene seeds, comma separated."),
    kinds: str = typer.Option("outdoor,indoor,night", "--kinds", help="Scene kinds, comma separated."),
    size: str = typer.Option("192x128", "--size", help="Image size WxH."),
    pipeline: str = typer.Option("auto", "--pipeline", help="'auto' (settings change per exposure) or 'fixed'."),
    methods: str = typer.Option("stabilized", "--methods", help="Methods compared with debevec."),
) -> None:
    """Paper 1: PSNR gain of the stabilised merge over debevec on simulated brackets, per scene and mean."""
    from derender.evaluation.experiments import format_table
    from derender.evaluation.table1 import fusion_gain

    w, h = parse_size(size)
    try:
        seed_list = [int(v) for v in seeds.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--seeds must be integers separated by commas, got {seeds!r}") from None
    rows = fusion_gain(styles=[v.strip() for v in styles.split(",") if v.strip()],
                       kinds=[v.strip() for v in kinds.split(",") if v.strip()], seeds=seed_list, size=(w, h),
                       pipeline=pipeline, methods=[v.strip() for v in methods.split(",") if v.strip()],
                       progress=lambda msg: console().print(msg))
    typer.echo(format_table(rows, [("style", "style", ""), ("scene", "scene", ""), ("method", "method", ""),
                                   ("dR", "dR", "+.2f"), ("dG", "dG", "+.2f"), ("dB", "dB", "+.2f"),
                                   ("dL", "dL", "+.2f"), ("wins", "wins >=3/4", ".0%")]))


@experiment_app.command("families")
def exp_families(
    families: Optional[str] = typer.Option(None, "--families", help="Pipeline families, comma separated (default: all; see 'derender simulate --help')."),
    kinds: str = typer.Option("outdoor,indoor", "--kinds", help="Scene kinds, comma separated."),
    seeds: str = typer.Option("0,1", "--seeds", help="Scene seeds, comma separated."),
    size: str = typer.Option("192x128", "--size", help="Image size WxH."),
    exposures: int = typer.Option(7, "--exposures", help="Exposures per bracket."),
    camera: str = typer.Option("nikon-d5100", "--camera", help="Simulated camera."),
    methods: str = typer.Option("debevec,robertson,stabilized,stabilized-joint", "--methods", help="derender methods."),
    peers: str = typer.Option("opencv-debevec,opencv-robertson", "--peers", help="OpenCV peers ('' for none)."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write every bracket's scores as JSON."),
) -> None:
    """Issues 16/18: every HDR method on every camera-pipeline family, beside OpenCV and the oracle that
    inverts the true pipeline; PSNR L, relative error (median/p90, 3x3 fit) and log PSNR over all pixels
    and over smooth ones (where demosaicing keeps the truth); hold-outs marked (tuned on paper, camera)."""
    from derender.evaluation.experiments import format_table
    from derender.evaluation.families import family_comparison, summarise_families
    from derender.io.files import OutputTransaction

    w, h = parse_size(size)
    try:
        seed_list = [int(v) for v in seeds.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--seeds must be integers separated by commas, got {seeds!r}") from None
    split = lambda s: [v.strip() for v in s.split(",") if v.strip()]
    with OutputTransaction() as tx:
        json_tmp = tx.add(output, "--json", (".json",))
        rows = family_comparison(split(families) if families else None, kinds=split(kinds), seeds=seed_list,
                                 size=(w, h), exposures=exposures, camera=camera, methods=split(methods),
                                 peers=split(peers), progress=lambda msg: console().print(msg))
        summary = summarise_families(rows)
        if json_tmp is not None:
            json_tmp.write_text(json.dumps({"brackets": rows, "summary": summary}, indent=2, default=float) + "\n")
    typer.echo(format_table(summary, [("family", "family", ""), ("held_out", "held out", ""),
                                      ("method", "method", ""), ("L", "PSNR L", ".2f"), ("dL", "vs debevec", "+.2f"),
                                      ("rel_median", "rel. err. median", ".3f"), ("rel_p90", "p90", ".3f"),
                                      ("rel_to_oracle", "median / oracle", ".2f"), ("log_psnr_L", "log PSNR L", ".2f"),
                                      ("L_smooth", "smooth: PSNR L", ".2f"),
                                      ("rel_median_smooth", "smooth: rel. median", ".3f")]))


@experiment_app.command("ghosts")
def exp_ghosts(
    families: Optional[str] = typer.Option("paper,camera,dslr-lut,phone-local,drift", "--families",
                                           help="Pipeline families, comma separated (paper and camera are the "
                                                "tuning families, the others held out)."),
    settings: str = typer.Option("tripod,handheld", "--settings", help="tripod (objects move) and/or handheld "
                                 "(objects move and the camera shakes)."),
    methods: str = typer.Option("debevec,robertson,stabilized,stabilized-joint,probabilistic", "--methods",
                                help="Merge methods (probabilistic: the camera's chart GP)."),
    seeds: str = typer.Option("0", "--seeds", help="Seeds, comma separated."),
    size: str = typer.Option("192x128", "--size", help="Image size WxH."),
    exposures: int = typer.Option(7, "--exposures", help="Exposures per bracket."),
    objects: int = typer.Option(3, "--objects", help="Moving objects."),
    shake: Optional[int] = typer.Option(None, "--shake", help="Camera shake in pixels (default 2 % of the width)."),
    deghost: bool = typer.Option(False, "--deghost", help="Merge with ghost removal."),
    align: Optional[str] = typer.Option(None, "--align", help="none, translation, homography or flow (default: each "
                                        "method's own)."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write the rows as JSON."),
) -> None:
    """Every method on brackets where objects move (and the camera shakes): median relative
    error per zone (static / swept / object, and the object pixels the reference frame sees
    unclipped) against the still twin's (the same objects, frozen at the reference instant),
    with or without ``--deghost``."""
    from derender.cli.merge import flag_record
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.experiments import format_table
    from derender.evaluation.ghosts import ghost_comparison, summarise_ghosts

    try:
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except ValueError:
        raise InputError(f"--seeds must be integers, got {seeds!r}") from None
    rows = ghost_comparison(families=[f.strip() for f in (families or "").split(",") if f.strip()],
                            settings=[s.strip() for s in settings.split(",") if s.strip()],
                            seeds=seed_list, size=parse_size(size), exposures=exposures, objects=objects,
                            shake=shake, methods=[m.strip() for m in methods.split(",") if m.strip()],
                            motion=flag_record(MotionOptions, deghost=deghost, align=align),
                            progress=lambda msg: console().print(msg))
    summary = summarise_ghosts(rows)
    for r in summary:
        r["family"] = f"{r['family']} ({'held out' if r['held_out'] else 'tuning'})"
    cols = [("family", "family", ""), ("setting", "setting", ""), ("method", "method", "")]
    for zone in ("static", "swept", "object"):
        cols += [(f"{zone}_moving", f"{zone} moving", ".3f"), (f"{zone}_still", "still", ".3f"),
                 (f"{zone}_ratio", "ratio", ".2f")]
    cols += [("object_seen_ratio", "object seen unclipped: ratio", ".2f")]
    typer.echo(format_table(summary, cols))
    if output is not None:
        output.write_text(json.dumps(rows, indent=2, default=float))


@experiment_app.command("uncertainty")
def exp_uncertainty(
    families: str = typer.Option("paper,camera,dslr-lut,phone-local,drift", "--families",
                                 help="Pipeline families (paper and camera tuning, the others held out)."),
    seeds: str = typer.Option("0", "--seeds", help="Seeds, comma separated."),
    size: str = typer.Option("192x128", "--size", help="Image size WxH."),
    exposures: int = typer.Option(7, "--exposures", help="Exposures per bracket."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write the rows as JSON."),
) -> None:
    """Does each method's variance cover the truth? Coverage of the 50/80/95/99 %
    intervals and median abs(z) on a bracket of every family (GP calibrated on the camera's chart)."""
    from derender.evaluation.experiments import format_table
    from derender.evaluation.uncertainty import uncertainty_experiment

    try:
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except ValueError:
        raise InputError(f"--seeds must be integers, got {seeds!r}") from None
    rows = uncertainty_experiment(families=[f.strip() for f in families.split(",") if f.strip()], seeds=seed_list,
                                  size=parse_size(size), exposures=exposures, progress=lambda m: console().print(m))
    shown = []
    for r in rows:
        r2 = dict(r)
        r2["family"] = f"{r['family']} ({'held out' if r['held_out'] else 'tuning'})"
        if not r["gives_variance"]:
            r2["method"] = f"{r['method']} (no variance)"
        shown.append(r2)
    typer.echo(format_table(shown, [("family", "family", ""), ("method", "method", ""), ("cov50", "50 %", ".3f"),
                                    ("cov80", "80 %", ".3f"), ("cov95", "95 %", ".3f"), ("cov99", "99 %", ".3f"),
                                    ("median_abs_z", "median abs(z)", ".2f"), ("tail3_edge", "|z|>3 edge", ".3f"),
                                    ("tail3_flat", "|z|>3 flat", ".3f")]))
    if output is not None:
        output.write_text(json.dumps(rows, indent=2, default=float))


@experiment_app.command("linearity")
def exp_linearity(
    renders: str = typer.Option("gamma,paper,camera,dslr-lut,phone-local,drift", "--renders",
                                help="Renderings of the luminance family (gamma, paper, camera: tuning; dslr-lut, "
                                     "phone-local, drift: held out)."),
    modes: str = typer.Option("time", "--modes", help="EXIF brackets: time, aperture-iso (comma separated)."),
    seeds: str = typer.Option("0", "--seeds", help="Seeds, comma separated."),
    size: str = typer.Option("192x128", "--size", help="Image size WxH."),
    exposures: int = typer.Option(9, "--exposures", help="Exposures per bracket (2 stops apart)."),
    methods: str = typer.Option("debevec,robertson,stabilized,stabilized-joint,probabilistic", "--methods",
                                help="derender methods (probabilistic: paper 2's GP from the camera's chart session)."),
    n_train: int = typer.Option(5000, "--n-train", help="GP training pairs for probabilistic."),
    readback: Optional[str] = typer.Option(None, "--readback",
                                           help="'pvalue': score the spot-scaled map written as .hdr and read back "
                                                "by Radiance's pvalue -h -H -o -d (PATH or pyradiance)."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write the rows as JSON."),
) -> None:
    """Linearity over 5 decades. Each method's map, scaled on the grey card (--spot), against the
    absolute truth: median and p90 relative error and the median ratio per decade 1..10, ..., 1e5..1e6 cd/m2."""
    from derender.camera.luminance import LUMINANCE_MODES, RENDERS
    from derender.evaluation.experiments import format_table
    from derender.evaluation.linearity import LINEARITY_METHODS, format_decades, linearity_experiment
    from derender.io.files import OutputTransaction

    w, h = parse_size(size)
    split = lambda s: [v.strip() for v in s.split(",") if v.strip()]
    try:
        seed_list = [int(v) for v in split(seeds)]
    except ValueError:
        raise InputError(f"--seeds must be integers separated by commas, got {seeds!r}") from None
    for name, given, allowed in (("--renders", split(renders), RENDERS), ("--modes", split(modes), ("time", "aperture-iso")),
                                 ("--methods", split(methods), LINEARITY_METHODS)):
        bad = [v for v in given if v not in allowed]
        if bad or not given:
            raise InputError(f"{name} takes {', '.join(allowed)}; got {', '.join(bad) or 'nothing'}")
    _ = LUMINANCE_MODES
    if readback is not None:
        from derender.evaluation.linearity import radiance_program

        if readback != "pvalue":
            raise InputError(f"--readback takes pvalue, got {readback!r}")
        if radiance_program("pvalue") is None:
            raise InputError("--readback pvalue: Radiance's pvalue not found (PATH or pip install pyradiance)")
    with OutputTransaction() as tx:
        json_tmp = tx.add(output, "--json", (".json",))
        rows = linearity_experiment(split(renders), modes=split(modes), seeds=seed_list, size=(w, h), exposures=exposures,
                                    methods=split(methods), n_train=n_train, readback=readback,
                                    progress=lambda msg: console().print(msg))
        if json_tmp is not None:
            json_tmp.write_text(json.dumps(rows, indent=2, default=float) + "\n")
    for r in rows:
        r["decades_text"] = format_decades(r["decades"])
    typer.echo(format_table(rows, [("render", "render", ""), ("role", "role", ""), ("mode", "EXIF", ""),
                                   ("method", "method", ""), ("median_abs", "median abs err", ".2%"),
                                   ("p90_abs", "p90", ".2%"),
                                   ("decades_text", "median ratio per decade 1..1e6 cd/m2", "")]))


@experiment_app.command("consistency")
def exp_consistency(
    brackets: str = typer.Option("iphone,memorial,frobisher", "--brackets",
                                 help="Still real brackets of ../shared/data (iphone, memorial, frobisher)."),
    methods: str = typer.Option("debevec,robertson,stabilized,stabilized-joint", "--methods", help="Merge methods."),
    data: Optional[Path] = typer.Option(None, "--data", help="The shared data folder (default: $DERENDER_SHARED_DATA or ../shared/data)."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write the rows as JSON."),
) -> None:
    """Checks without truth on still real brackets: every method with against without ``--deghost``
    (same reference and alignment): block chroma and luminance change (median, p95, p99) and the
    fraction of the other frames' pixels ghost removal left out. Then, per bracket, whether its
    frames can share one rendering (:func:`derender.evaluation.rendering_change.one_rendering`:
    where they cannot, the one-curve methods' model does not hold). ``--json`` writes
    ``{"flag_invariance": [...], "one_rendering": [...]}``."""
    from derender.evaluation.consistency import STILL_BRACKETS, flag_invariance
    from derender.evaluation.experiments import format_table
    from derender.evaluation.rendering_change import bracket_one_rendering
    from derender.io.files import OutputTransaction

    names = [b.strip() for b in brackets.split(",") if b.strip()]
    unknown = [b for b in names if b not in STILL_BRACKETS]
    if unknown:
        raise InputError(f"unknown bracket {unknown[0]!r}; choose from {', '.join(STILL_BRACKETS)}")
    ms = [m.strip() for m in methods.split(",") if m.strip()]
    with OutputTransaction() as tx:
        json_tmp = tx.add(output, "--json", (".json",))
        rows, one = [], []
        for b in names:
            rows += flag_invariance(b, methods=ms, root=data, progress=lambda msg: console().print(msg))
            one.append({"bracket": b, **bracket_one_rendering(b, root=data).row()})
        if json_tmp is not None:
            json_tmp.write_text(json.dumps({"flag_invariance": rows, "one_rendering": one}, indent=2, default=float)
                                + "\n")
    typer.echo(format_table(rows, [("bracket", "bracket", ""), ("method", "method", ""),
                                   ("rejected", "left out", ".3f"), ("chroma_median", "chroma median", ".3f"),
                                   ("chroma_p95", "chroma p95", ".3f"), ("chroma_p99", "chroma p99", ".3f"),
                                   ("luminance_p95", "lum p95", ".3f"), ("luminance_p99", "lum p99", ".3f")]))
    for r in one:
        r["where"] = (f"{r['channel']} {r['code']}: {r['pair_q']} -> {r['imf_q']:.0f} (ratio {r['ratio_q']:.2f}), "
                      f"{r['pair_p']} -> {r['imf_p']:.0f} (ratio {r['ratio_p']:.2f})") if r["pair_p"] else ""
    typer.echo("\none rendering (intensity mappings must grow with the exposure ratio):")
    typer.echo(format_table(one, [("bracket", "bracket", ""), ("one_rendering", "one rendering", ""),
                                  ("tests", "tests", "d"), ("fraction", "violating", ".3f"),
                                  ("violation", "largest (codes)", ".1f"), ("where", "where", "")]))
