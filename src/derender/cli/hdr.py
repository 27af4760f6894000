"""``derender`` commands of the HDR side: simulate, merge, methods, ground truth, datasets, demo (the
merge command's flag records and outputs are in :mod:`derender.cli.merge`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import List, Optional

import typer

from derender.cli.app import (
    INVERSE_HELP,
    TIMES_FILE_HELP,
    TIMES_HELP,
    app,
    check_choice,
    check_times_options,
    console,
    is_float,
    load_camera_cli,
    parse_size,
    progress,
)
from derender.cli.merge import (
    check_method_flags,
    compile_notice,
    flag_record,
    merge_report,
    merge_summary,
    method_record,
    motion_options,
    side_outputs,
    with_model,
)
from derender.core.errors import InputError
from derender.io.headers import DEFAULT_MAX_MEGAPIXELS


# --------------------------------------------------------------------------- simulate
def _render_help() -> str:
    from derender.camera.families import FAMILIES

    fams = "; ".join(f"{k}: {v}" for k, v in FAMILIES.items())
    return ("simple (matrix + gamma) | camera (picture style), with --pipeline; or a pipeline family "
            f"(overrides --pipeline and --tone-curve): {fams}.")


RENDER_HELP = _render_help()


@app.command("cameras")
def cameras_cmd() -> None:
    """List every camera the simulator can use by name (--camera), and where it looked for more.

    Built-in cameras come with colour-science; rawtoaces camera JSON files are found in one
    search order for the whole tool, the same from any working directory."""
    from derender.camera.spectral import available_cameras, camera_search_order

    for name, source in available_cameras():
        typer.echo(f"{name:40s} {source}")
    typer.echo("searched for camera JSON files (in order; DERENDER_SHARED_DATA sets the data root):", err=True)
    for d in camera_search_order():
        typer.echo(f"  {d}{'' if d.is_dir() else '  (absent)'}", err=True)


@app.command()
def simulate(
    outdir: Path = typer.Argument(..., help="Output folder (raw/, jpeg/, truth.exr, scene.json)."),
    exposures: int = typer.Option(9, "--exposures", "-n", help="Number of exposures in the bracket."),
    size: str = typer.Option("384x256", "--size", help="Image size WxH."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed (scene, pipeline, noise)."),
    camera: str = typer.Option("nikon-d5100", "--camera", help="Built-in camera or rawtoaces camera name."),
    camera_file: Optional[Path] = typer.Option(None, "--camera-file", help="rawtoaces camera JSON."),
    pipeline: str = typer.Option("auto", "--pipeline", help="fixed | auto (camera changes WB, gain, gamma)."),
    render: str = typer.Option("camera", "--render", help=RENDER_HELP),
    scene: str = typer.Option("outdoor", "--scene", help="outdoor | indoor | night."),
    tone_curve: bool = typer.Option(False, "--tone-curve", help="Extra S-shaped tone curve (simple style)."),
    bits: int = typer.Option(14, "--bits", help="ADC bit depth: 12 or 14."),
    stops: Optional[float] = typer.Option(None, "--stops", help="Stops between exposures (default: cover the scene)."),
    moving: int = typer.Option(0, "--moving", help="Objects (discs of the scene's texture) moving across the "
                               "bracket; the truth is then the middle frame's instant (docs/simulator.md)."),
    shake: int = typer.Option(0, "--shake", help="Camera shake: each frame offset by up to this many pixels "
                              "(handheld); the middle frame is the truth's grid."),
    luminance: Optional[str] = typer.Option(None, "--luminance", help="time | aperture-iso | flat-field: the "
                                            "luminance-truth family (1..1e6 cd/m2, grey card and its --spot in "
                                            "scene.json, EXIF t/N/ISO; docs/luminance.md). --render: gamma (fixed "
                                            "gamma 2.2) or a family; --stops default 2."),
    lens_falloff: Optional[float] = typer.Option(None, "--lens-falloff", help="With --luminance: lens vignetting, "
                                                 "the corner transmission (e.g. 0.55)."),
) -> None:
    """Simulate a bracket with a spectral camera model: real DNG and JPEG files plus exact truth."""
    from derender.camera import simulate_bracket, write_bracket

    w, h = parse_size(size)
    if luminance is not None or lens_falloff is not None:
        from derender.camera.luminance import simulate_to_folder_cli

        simulate_to_folder_cli(outdir, mode=luminance, render=render, size=(w, h), exposures=exposures,
                               stops=stops, seed=seed, camera=load_camera_cli(camera, camera_file).with_bits(bits),
                               falloff=lens_falloff)
        return
    check_choice("--pipeline", pipeline, ("fixed", "auto"))
    from derender.camera.families import FAMILIES

    check_choice("--render", render, ("simple", "camera", *[f for f in FAMILIES if f != "camera"]))
    family = None if render in ("simple", "camera") else render
    check_choice("--scene", scene, ("outdoor", "indoor", "night"))
    if exposures < 1 or exposures > 64:
        raise InputError("--exposures must be between 1 and 64")
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"{outdir} exists and is not a folder")
    if moving < 0 or shake < 0:
        raise InputError("--moving and --shake take a count of objects and pixels (0 or more)")
    motion = None
    if moving or shake:
        from derender.camera.motion import MotionSpec

        motion = MotionSpec(objects=moving, shake=shake)
    cam = load_camera_cli(camera, camera_file).with_bits(bits)
    with progress() as prog:
        task = prog.add_task("simulating exposures", total=exposures)
        bracket = simulate_bracket(camera=cam, kind=scene, size=(w, h), exposures=exposures, pipeline=pipeline,
                                   style=render if family is None else "camera", seed=seed,
                                   tone_curve=tone_curve, stops=stops, family=family, motion=motion,
                                   progress=lambda i, n: prog.update(task, completed=i))
    outdir.mkdir(parents=True, exist_ok=True)
    write_bracket(bracket, outdir)
    typer.echo(f"wrote {exposures} DNG + JPEG exposures, truth.exr and scene.json to {outdir}")


@app.command("merge")
def merge_cmd(
    images: List[Path] = typer.Argument(..., help="Bracketed images (JPEG/PNG/TIFF/HEIC/AVIF) or RAW files (DNG, CR2, "
                                        "CR3, NEF, ARW, RAF, ...), or folders of them."),
    output: Path = typer.Option(..., "--output", "-o",
                                help="Output radiance map: OpenEXR (.exr) or Radiance RGBE (.hdr, with FORMAT, "
                                     "EXPOSURE, PRIMARIES and --view in its header)."),
    method: Optional[str] = typer.Option(None, "--method", help="Merge method (see 'derender methods'; default: "
                                         "debevec, or raw for RAW files)."),
    view: Optional[str] = typer.Option(None, "--view", help="Radiance view of a .hdr output, e.g. "
                                       "'-vta -vh 180 -vv 180' (equidistant 180-degree fisheye), for evalglare."),
    vignetting: Optional[Path] = typer.Option(None, "--vignetting", help="Vignetting profile ('derender "
                                              "vignetting'): its radial falloff is divided out of the map."),
    spot: Optional[str] = typer.Option(None, "--spot", help="X,Y,W,H=NITS: a luminance-meter reading (cd/m2) over "
                                       "that rectangle of the output; the map (and variance) are scaled to absolute "
                                       "units, luminance 179 (w·RGB) cd/m2 as Radiance reads it."),
    absolute: Optional[str] = typer.Option(None, "--absolute", help="'exif': absolute units without a meter, from "
                                           "EXIF t, N, S and the ISO rating the camera states (SOS: 15 %, "
                                           "saturation or unstated: 44 %; docs/luminance.md)."),
    profile: Optional[Path] = typer.Option(None, "--profile", help="Camera profile (.json): its response curves "
                                           "(debevec, robertson), photometric factor, vignetting and view."),
    save_profile: Optional[Path] = typer.Option(None, "--save-profile", help="Write this merge's camera profile "
                                                "(.json): curves, the --spot factor, vignetting, view, camera."),
    model: Optional[Path] = typer.Option(None, "--model", "-m", help="De-rendering model (.npz or folder) for --method probabilistic."),
    variance: Optional[Path] = typer.Option(None, "--variance", help="Per-pixel variance of the radiance (.exr); every method "
                                            "'derender methods' lists with a variance."),
    times: Optional[str] = typer.Option(None, "--times", help=TIMES_HELP),
    times_file: Optional[Path] = typer.Option(None, "--times-file", help=TIMES_FILE_HELP),
    times_inverse: bool = typer.Option(False, "--times-inverse", help=INVERSE_HELP),
    preview: Optional[Path] = typer.Option(None, "--preview", help="Tone-mapped PNG preview (Reinhard 2002)."),
    mask: Optional[Path] = typer.Option(None, "--mask", help="PNG mask of this method's saturation policy: 0 merged, 128 taken from the shortest exposure (no frame usable by the method's weights), 255 from the longest."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Figure of the recovered response curves (if any)."),
    report: Optional[Path] = typer.Option(None, "--report", help="Self-contained HTML report of the merge (tone "
                                          "mapping, falsecolor, uncertainty, masks, curves, cursor readout)."),
    half: bool = typer.Option(False, "--half", help="Write half-float EXR."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed for sampling / RANSAC."),
    max_megapixels: float = typer.Option(DEFAULT_MAX_MEGAPIXELS, "--max-megapixels",
                                         help="Refuse images larger than this (decoded size, read from the header)."),
    strict_camera: bool = typer.Option(False, "--strict-camera",
                                       help="Refuse a -m model calibrated for another camera than the images' EXIF "
                                            "names (default: a warning)."),
    reference: Optional[str] = typer.Option(None, "--reference", help="Reference frame: N (the N-th image as "
                                            "given, from 1) or 'auto' (fewest clipped pixels). The result shows the "
                                            "scene at that frame's instant, on its pixel grid."),
    align: Optional[str] = typer.Option(None, "--align", help="Register the frames to the reference: none, "
                                        "translation (Ward's MTB), homography (features) or flow (MTB, then a dense "
                                        "residual flow per frame: handheld, with parallax). Default: translation "
                                        "for the stabilised methods, none for the others."),
    deghost: bool = typer.Option(False, "--deghost", help="Leave out, per pixel, the frames that disagree with the "
                                 "reference under the method's noise model (moving people, leaves, cars)."),
    ghost_threshold: Optional[float] = typer.Option(None, "--ghost-threshold", help="Ghost test threshold (window "
                                                    "mean of z^2 per channel; default 4: lower removes more)."),
    ghost_mask: Optional[Path] = typer.Option(None, "--ghost-mask", help="PNG of where frames were left out "
                                              "(ghosts, also where their motion-compensated view replaced them, "
                                              "or not covered after alignment): 0 none, 255 all but the "
                                              "reference."),
    option: List[str] = typer.Option([], "--option", "-O",
                                     help="A method option as NAME=VALUE (repeat; 'derender methods' lists them), "
                                          "e.g. --option exposure_rounds=0 or --option colour_space=camera_rgb."),
) -> None:
    """Merge a bracket into a linear HDR radiance map (OpenEXR).

    Every output is checked before any work and written as one transaction: on an error or
    an interruption none of them is left behind."""

    from derender.engine.options import EngineOptions, OutputOptions
    from derender.hdr.files import merge_files
    from derender.hdr.registry import method_spec, parse_options
    from derender.io.exif import parse_times
    from derender.io.files import OutputTransaction, expand_image_paths
    from derender.io.preview import IMAGE8_SUFFIXES

    check_times_options(times, times_file, times_inverse)
    engine = flag_record(EngineOptions, max_megapixels=max_megapixels)
    images = expand_image_paths(images, raw=True)
    if method is None:
        from derender.io.files import RAW_SUFFIXES

        method = "raw" if any(p.suffix.lower() in RAW_SUFFIXES for p in images) else "debevec"
    spec = method_spec(method)
    from derender.cli.profiles import apply_photometry, hdr_header_lines, merge_photometry, profile_options

    ph = merge_photometry(profile=profile, vignetting=vignetting, spot=spot, absolute=absolute, method=method,
                          image=images[0], strict=strict_camera)
    check_method_flags(spec, variance=variance is not None, model=model is not None, plot=plot is not None)
    # the method's record, the motion and the engine's settings: each built once, checked before any work
    record = method_record(spec, {**parse_options(method, option), **profile_options(ph, method)}, seed=seed,
                            with_model=model is not None, with_variance=variance is not None, n_images=len(images))
    motion = motion_options(reference, align, deghost, ghost_threshold, ghost_mask, len(images), seed)
    t0 = time.perf_counter()
    inputs = list(images) + [p for p in (times_file, model, vignetting, profile) if p]
    with OutputTransaction(inputs) as tx, compile_notice():
        out_tmp = tx.add(output, "--output", (".exr", ".hdr"))
        as_hdr = output.suffix.lower() == ".hdr"
        view = view if view is not None or not as_hdr or ph.profile is None else ph.profile.view
        profile_tmp = tx.add(save_profile, "--save-profile", (".json",))
        if view is not None:
            if not as_hdr:
                raise InputError("--view is written into a Radiance .hdr output; give -o MAP.hdr")
            from derender.io.rgbe import check_view

            view = check_view(view)
        var_tmp = tx.add(variance, "--variance", (".exr",))
        preview_tmp = tx.add(preview, "--preview", IMAGE8_SUFFIXES)
        mask_tmp = tx.add(mask, "--mask", (".png", ".tif", ".tiff"))
        plot_tmp = tx.add(plot, "--plot", (".png", ".pdf", ".svg"))
        report_tmp = tx.add(report, "--report", (".html", ".htm"))
        ghost_tmp = tx.add(ghost_mask, "--ghost-mask", (".png", ".tif", ".tiff"))
        if model is not None:
            record = with_model(record, model, images[0], strict_camera)
        # 8-bit files run on the engine (streamed or held frames, parallel EXR write); others: read_stack + merge
        direct = not as_hdr and not ph.active and profile_tmp is None   # the engine writes the EXR (band by band)
        out = OutputOptions(output=out_tmp if direct else None, variance_output=var_tmp if direct else None,
                            half=half, hold_outputs=preview_tmp is not None or report_tmp is not None or not direct)
        result = merge_files(images, parse_times(times) if times is not None else None, method, record,
                             motion=motion, output=out, engine=engine, times_file=times_file,
                             times_file_inverse=times_inverse, inputs=inputs)
        absolute_source = apply_photometry(ph, result, images, method) if ph.active else None
        result.info["summary"] = result.info["summary"].with_photometry(result.info.get("photometric_factor"),
                                                                        absolute_source)
        if profile_tmp is not None:
            from derender.cli.profiles import save_merge_profile

            save_merge_profile(profile_tmp, ph, result, images, method, view, inputs)
        if not direct:
            from derender.engine.outputs import write_outputs

            write_outputs(result, None if as_hdr else out_tmp, var_tmp, half=half, inputs=inputs, name=method)
        if as_hdr:
            from derender.io.rgbe import write_hdr

            write_hdr(out_tmp, result.radiance, view=view, software=f"derender merge --method {method}",
                      inputs=inputs, header_lines=hdr_header_lines(result.info))
        side_outputs(result, images, inputs, preview=preview_tmp, mask=mask_tmp, ghost_mask=ghost_tmp,
                      plot=plot_tmp)
        if report_tmp is not None:
            merge_report(report_tmp, result, method, absolute_source is not None, view, inputs)
    merge_summary(result, images, method, output, time.perf_counter() - t0, variance is not None)


@app.command("methods")
def methods_cmd() -> None:
    """List the merge methods: what each does, what it needs and gives, and its output colour space."""
    import textwrap

    from derender.hdr.registry import METHODS, settable_options

    for name, spec in sorted(METHODS.items()):
        typer.echo(name)
        lines = [spec.summary]
        if spec.needs_model:
            lines.append("Needs a de-rendering model (-m MODEL.npz, from 'derender calibrate').")
        gives = ["a variance (--variance)"] if spec.gives_variance else []
        if spec.gives_curves:
            gives.append("response curves (--plot)")
        if gives:
            lines.append("Also gives " + " and ".join(gives) + ".")
        lines.append(f"Output: {spec.output_space}.")
        opts = settable_options(name)
        if opts:
            lines.append("Options (--option NAME=VALUE): " + "; ".join(
                f"{k} = {'none' if d is None else d}" for k, (_t, d) in opts.items()) + ".")
        for line in lines:
            typer.echo(textwrap.fill(line, width=96, initial_indent="    ", subsequent_indent="    "))


@app.command()
def groundtruth(
    raws: List[Path] = typer.Argument(..., help="RAW/DNG frames of the bracket (or a single frame)."),
    output: Path = typer.Option(..., "--output", "-o", help="Output linear sRGB radiance (.exr)."),
    method: str = typer.Option("optimal", "--method", help="optimal: the noise-optimal merge (censored "
                               "Poisson-Gaussian ML, noise from the frames; docs/raw.md) | paper1: paper 1's eq. 11 "
                               "(binary weights), to reproduce the paper."),
    variance: Optional[Path] = typer.Option(None, "--variance", help="Per-pixel variance of the radiance (.exr; "
                                            "--method optimal)."),
    wb: Optional[str] = typer.Option(None, "--wb", help="White-balance multipliers R,G,B (default: as shot)."),
    wb_patch: Optional[str] = typer.Option(None, "--wb-patch", help="Neutral region x,y,w,h for white balance."),
    times: Optional[str] = typer.Option(None, "--times", help="Exposure times (default: from the files)."),
    preview: Optional[Path] = typer.Option(None, "--preview", help="Tone-mapped PNG preview."),
) -> None:
    """Ground truth in linear sRGB from RAW: the noise-optimal merge, or paper 1's (Sec. 4.2, Alg. 2) with --method paper1."""
    from derender.io.files import OutputTransaction
    from derender.io.preview import IMAGE8_SUFFIXES

    check_choice("--method", method, ("optimal", "paper1"))
    if variance is not None and method != "optimal":
        raise InputError("--variance needs --method optimal (paper 1's eq. 11 has no noise model)")
    wb_value, patch = _white_balance_options(wb, wb_patch)
    with OutputTransaction(raws) as tx:
        out_tmp = tx.add(output, "--output", (".exr",))
        var_tmp = tx.add(variance, "--variance", (".exr",))
        preview_tmp = tx.add(preview, "--preview", IMAGE8_SUFFIXES)
        n = _groundtruth(raws, out_tmp, wb_value, patch, times, preview_tmp, method, var_tmp)
    typer.echo(f"ground truth ({method}) from {n} RAW frame(s) -> {output}")


def _white_balance_options(wb: Optional[str], wb_patch: Optional[str]):
    wb_value = "as_shot"
    patch = None
    if wb is not None:
        vals = [float(v) for v in wb.split(",")] if all(is_float(v) for v in wb.split(",")) else []
        if len(vals) != 3 or min(vals) <= 0:
            raise InputError(f"--wb needs three positive numbers R,G,B, got {wb!r}")
        wb_value = vals
    if wb_patch is not None:
        parts = wb_patch.split(",")
        if len(parts) != 4 or not all(p.strip().isdigit() for p in parts):
            raise InputError(f"--wb-patch needs x,y,w,h in pixels, got {wb_patch!r}")
        patch = tuple(int(p) for p in parts)
    return wb_value, patch


def _groundtruth(raws: List[Path], output: Path, wb_value, patch, times: Optional[str],
                 preview: Optional[Path], method: str = "optimal", variance: Optional[Path] = None) -> int:
    """The groundtruth command's work, writing to the transaction's temporaries."""
    from derender.io.exif import parse_times
    from derender.io.exr import write_exr
    from derender.io.preview import write_preview
    from derender.io.raw import read_raw_stack
    from derender.raw.groundtruth import raw_ground_truth

    frames = read_raw_stack(raws, times=parse_times(times) if times else None)
    if method == "paper1":
        result = raw_ground_truth(frames, wb=wb_value, wb_patch=patch)
    else:
        from derender.hdr.raw import check_one_camera
        from derender.raw.optimal import raw_merge

        check_one_camera(frames)
        result = raw_merge(frames, wb=None if wb_value == "as_shot" else wb_value, wb_patch=patch,
                           variance=variance is not None)
    write_exr(output, result.radiance, inputs=raws)
    if variance is not None:
        write_exr(variance, result.variance, inputs=list(raws) + [output])
    if preview is not None:
        write_preview(preview, result.radiance, inputs=raws)
    return len(frames)


# --------------------------------------------------------------------------- benchmark
@app.command("simulate-dataset")
def simulate_dataset_cmd(
    outdir: Path = typer.Argument(..., help="Dataset folder to create."),
    scenes: int = typer.Option(18, "--scenes", help="Number of scenes (paper 1: 18)."),
    exposures: int = typer.Option(9, "--exposures", "-n", help="Exposures per scene (paper 1: 9)."),
    cameras: Optional[str] = typer.Option(None, "--cameras", help="Comma-separated camera names (default: several real cameras)."),
    size: str = typer.Option("384x256", "--size", help="Image size WxH."),
    pipelines: str = typer.Option("auto,fixed", "--pipelines", help="Pipelines to cycle through."),
    renders: str = typer.Option("camera", "--renders", help="Rendering styles to cycle through (simple, camera)."),
    seed: int = typer.Option(0, "--seed", min=0, help="Dataset seed."),
) -> None:
    """Simulate a dataset of brackets (raw/ + jpeg/ + truth per scene) for 'derender benchmark'."""
    from derender.evaluation.table1 import simulate_dataset

    pl = [p.strip() for p in pipelines.split(",") if p.strip()]
    st = [p.strip() for p in renders.split(",") if p.strip()]
    for p in pl:
        check_choice("--pipelines", p, ("fixed", "auto"))
    for p in st:
        check_choice("--renders", p, ("simple", "camera"))
    cams = [c.strip() for c in cameras.split(",")] if cameras else None
    with progress() as prog:
        task = prog.add_task("simulating scenes", total=scenes)
        rows = simulate_dataset(outdir, scenes=scenes, exposures=exposures, cameras=cams, size=parse_size(size),
                                pipelines=pl, styles=st, seed=seed,
                                progress=lambda i, n: prog.update(task, completed=i))
    typer.echo(f"wrote {len(rows)} scenes to {outdir}")


@app.command()
def benchmark(
    dataset: Path = typer.Argument(..., help="Dataset folder (scenes with raw/ and jpeg/)."),
    output: Path = typer.Option(Path("benchmark-results"), "--output", "-o", help="Folder for table.md, scenes.csv, results.json."),
    methods: Optional[str] = typer.Option(None, "--methods", help="Comma-separated merge methods (default: all)."),
    scheduler: str = typer.Option("local", "--scheduler", help="'local' (Dask local cluster), 'serial', or a Dask scheduler address."),
    workers: int = typer.Option(2, "--workers", help="Workers of the local cluster."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed passed to every method."),
) -> None:
    """Paper 1's Table 1: every method on every scene, PSNR R/G/B/L against the RAW ground truth."""
    from derender.evaluation.table1 import run_benchmark, write_benchmark_outputs

    ms = [m.strip() for m in methods.split(",") if m.strip()] if methods else None
    with progress() as prog:
        task = prog.add_task("scenes", total=None)
        result = run_benchmark(dataset, methods=ms, scheduler=scheduler, workers=workers, seed=seed,
                               progress=lambda i, n: prog.update(task, completed=i, total=n))
    files = write_benchmark_outputs(result, output)
    typer.echo(result.markdown())
    typer.echo(f"per-scene results: {files['csv']} and {files['json']}")


# --------------------------------------------------------------------------- demo
@app.command()
def demo(
    outdir: Path = typer.Option(Path("derender-demo"), "--outdir", "-o", help="Where to write the demo outputs."),
    size: str = typer.Option("480x320", "--size", help="Image size WxH."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed."),
    pipeline: str = typer.Option("auto", "--pipeline", help="fixed | auto."),
    render: str = typer.Option("camera", "--render", help="simple | camera."),
    no_model: bool = typer.Option(False, "--no-model",
                                  help="Skip paper 2's two methods and the GP calibration they need."),
) -> None:
    """Simulate an auto-pipeline bracket, merge it with every method, score each against the truth.

    Paper 2's two methods (probabilistic, stabilized-probabilistic) need a de-rendering model:
    the demo calibrates a GP on the simulated chart session of the same camera first."""
    from rich.console import Console
    from rich.table import Table

    from derender.evaluation.demo import run_demo

    with progress() as prog:
        tasks: dict = {}

        def report(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = prog.add_task(stage, total=total)
            prog.update(tasks[stage], completed=done, total=total)

        rows = run_demo(outdir, parse_size(size), seed=seed, pipeline=pipeline, render=render, progress=report,
                        with_model=not no_model)
    table = Table(title=f"derender demo: {pipeline} pipeline, {render} rendering, PSNR (dB) vs truth.exr")
    for col in ("method", "R", "G", "B", "L", "seconds"):
        table.add_column(col, justify="left" if col == "method" else "right")
    for r in rows:
        table.add_row(r["method"], *(f"{r[c]:.2f}" for c in ("R", "G", "B", "L")), f"{r['seconds']:.2f}")
    Console().print(table)
    cal = [r["calibration_seconds"] for r in rows if "calibration_seconds" in r]
    if cal:
        console().print(f"probabilistic and stabilized-probabilistic use a GP calibrated in {cal[0]:.1f} s on the "
                        f"simulated chart session of the same camera ({outdir}/model-gp.npz; not in their seconds). "
                        "That session keeps one white balance, as paper 2 assumes; "
                        + ("this bracket changes white balance and gain between frames, which the model does not "
                           "describe." if pipeline == "auto" else "so does this bracket."))
    else:
        console().print("probabilistic and stabilized-probabilistic skipped (--no-model): they need a de-rendering "
                        "model ('derender calibrate')")
    console().print(f"outputs in {outdir}/ (EXR radiance maps, PNG previews, scene.json, scores.json)")


@app.command("merge-batch")
def merge_batch_cmd(
    stacks: List[Path] = typer.Argument(..., help="Stack folders (images, or jpeg/ subfolder; optional times.txt)."),
    outdir: Path = typer.Option(..., "--output", "-o", help="Folder for <stack>.exr outputs."),
    method: str = typer.Option("debevec", "--method", help="Merge method."),
    scheduler: str = typer.Option("local", "--scheduler", help="'local' (Dask local cluster), 'serial', or a Dask scheduler address."),
    workers: int = typer.Option(2, "--workers", help="Workers of the local cluster."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed."),
    half: bool = typer.Option(False, "--half", help="Half-float EXR."),
) -> None:
    """Merge many brackets in parallel (Dask); one EXR per stack folder; identical to a serial run."""
    from derender.hdr.batch import merge_batch

    with progress() as prog:
        task = prog.add_task("stacks", total=len(stacks))
        rows = merge_batch(stacks, outdir, method=method, scheduler=scheduler, workers=workers, seed=seed, half=half,
                           progress=lambda i, n: prog.update(task, completed=i))
    failed = [r for r in rows if not r["ok"]]
    for r in rows:
        typer.echo(f"{r['stack']}: " + (f"{r['output']} ({r['seconds']:.2f} s)" if r["ok"] else f"error: {r['error']}"))
    if failed:
        raise InputError(f"{len(failed)} of {len(rows)} stacks failed (see above)")


