"""Command-line interface (typer): a thin shell over the library API.

Every user mistake raises :class:`~derender.errors.DerenderError`; :func:`main` prints it
as one line ``error: ...`` on stderr and exits with code 2 (click usage errors too).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import List, Optional

import typer

from derender.core.errors import DerenderError, InputError


def _click_exception_types() -> tuple[tuple[type, ...], tuple[type, ...], tuple[type, ...]]:
    """(ClickException, Abort, Exit) classes of the click typer uses (vendored since typer 0.2x)."""
    errs, aborts, exits = [], [typer.Abort], [typer.Exit]
    for modname in ("typer._click.exceptions", "click.exceptions"):
        try:
            mod = __import__(modname, fromlist=["ClickException"])
        except ImportError:
            continue
        errs.append(mod.ClickException)
        if hasattr(mod, "Abort"):
            aborts.append(mod.Abort)
        if hasattr(mod, "Exit"):
            exits.append(mod.Exit)
    return tuple(errs), tuple(aborts), tuple(exits)

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Recover linear scene radiance, with uncertainty, from rendered camera images.")


def main() -> None:
    """Console-script entry point: user errors print one line and exit with code 2."""
    click_errors, aborts, exits = _click_exception_types()
    _fast_exit_gc()
    try:
        rv = app(standalone_mode=False)
    except DerenderError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(exc.exit_code)
    except aborts:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except exits as exc:
        sys.exit(getattr(exc, "exit_code", 0))
    except click_errors as exc:
        typer.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(2)
    except (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError) as exc:
        typer.echo(f"error: {exc.strerror or exc}: {exc.filename}", err=True)
        sys.exit(2)
    sys.exit(rv if isinstance(rv, int) else 0)


_FAST_EXIT = False


def _fast_exit_gc() -> None:
    """At interpreter exit, move every live object to the collector's permanent generation
    (``gc.freeze``) so that shutdown does not walk them: with numba loaded (stabilised
    merges) that walk cost 0.3-0.4 s per run here, against 0.03-0.05 s frozen. Registered
    with atexit, so it runs only once the command is over (outputs written and closed) and
    in-process callers keep a normal collector; other atexit handlers and module teardown
    still run."""
    global _FAST_EXIT
    if not _FAST_EXIT:
        import atexit
        import gc

        atexit.register(gc.freeze)
        _FAST_EXIT = True


def _console():
    from rich.console import Console

    return Console(stderr=True)


def _progress():
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), console=_console(), transient=False)


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 480x320, got {text!r}") from None
    if w < 32 or h < 32 or w * h > 400_000_000:
        raise InputError(f"--size {text} out of range (32x32 to 400 MP)")
    return w, h


def _check_choice(option: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise InputError(f"{option} must be one of {', '.join(choices)}, got {value!r}")


def _shared_camera_dirs() -> tuple[Path, ...]:
    here = Path.cwd()
    cands = [here.parent / "shared" / "data" / "rawtoaces-spectral" / "data" / "camera",
             here / "shared" / "data" / "rawtoaces-spectral" / "data" / "camera"]
    return tuple(p for p in cands if p.is_dir())


def _load_camera(camera: str, camera_file: Optional[Path]):
    from derender.camera.spectral import load_camera, load_camera_file

    if camera_file is not None:
        return load_camera_file(camera_file)
    return load_camera(camera, search_dirs=_shared_camera_dirs())


# --------------------------------------------------------------------------- simulate
@app.command()
def simulate(
    outdir: Path = typer.Argument(..., help="Output folder (raw/, jpeg/, truth.exr, scene.json)."),
    exposures: int = typer.Option(9, "--exposures", "-n", help="Number of exposures in the bracket."),
    size: str = typer.Option("384x256", "--size", help="Image size WxH."),
    seed: int = typer.Option(0, "--seed", help="Random seed (scene, pipeline, noise)."),
    camera: str = typer.Option("nikon-d5100", "--camera", help="Built-in camera or rawtoaces camera name."),
    camera_file: Optional[Path] = typer.Option(None, "--camera-file", help="rawtoaces camera JSON."),
    pipeline: str = typer.Option("auto", "--pipeline", help="fixed | auto (camera changes WB, gain, gamma)."),
    render: str = typer.Option("camera", "--render", help="simple (matrix + gamma) | camera (picture style)."),
    scene: str = typer.Option("outdoor", "--scene", help="outdoor | indoor | night."),
    tone_curve: bool = typer.Option(False, "--tone-curve", help="Extra S-shaped tone curve (simple style)."),
    bits: int = typer.Option(14, "--bits", help="ADC bit depth: 12 or 14."),
    stops: Optional[float] = typer.Option(None, "--stops", help="Stops between exposures (default: cover the scene)."),
) -> None:
    """Simulate a bracket with a spectral camera model: real DNG and JPEG files plus exact truth."""
    from derender.camera.simulate import simulate_bracket, write_bracket

    w, h = _parse_size(size)
    _check_choice("--pipeline", pipeline, ("fixed", "auto"))
    _check_choice("--render", render, ("simple", "camera"))
    _check_choice("--scene", scene, ("outdoor", "indoor", "night"))
    if exposures < 1 or exposures > 64:
        raise InputError("--exposures must be between 1 and 64")
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"{outdir} exists and is not a folder")
    cam = _load_camera(camera, camera_file).with_bits(bits)
    with _progress() as prog:
        task = prog.add_task("simulating exposures", total=exposures)
        bracket = simulate_bracket(camera=cam, kind=scene, size=(w, h), exposures=exposures, pipeline=pipeline,
                                   style=render, seed=seed, tone_curve=tone_curve, stops=stops,
                                   progress=lambda i, n: prog.update(task, completed=i))
    outdir.mkdir(parents=True, exist_ok=True)
    write_bracket(bracket, outdir)
    typer.echo(f"wrote {exposures} DNG + JPEG exposures, truth.exr and scene.json to {outdir}")


# --------------------------------------------------------------------------- merge / evaluate
def _read_stack_from_cli(images: List[Path], times: Optional[str], times_file: Optional[Path],
                         times_inverse: bool):
    from derender.io.exif import parse_times
    from derender.io.images import read_stack

    if times is not None and times_file is not None:
        raise InputError("give either --times or --times-file, not both")
    t = parse_times(times) if times is not None else None
    return read_stack(images, times=t, times_file=times_file, times_file_inverse=times_inverse)


_TIMES_HELP = "Exposure times in seconds, comma separated (default: EXIF ExposureTime)."
_TIMES_FILE_HELP = "File of 'FILENAME SECONDS' lines."
_INVERSE_HELP = "The times file's 2nd column is 1/time (HDRShop / Debevec image lists)."


@app.command("merge")
def merge_cmd(
    images: List[Path] = typer.Argument(..., help="Bracketed images (JPEG/PNG/TIFF)."),
    output: Path = typer.Option(..., "--output", "-o", help="Output radiance map (.exr)."),
    method: str = typer.Option("debevec", "--method", help="Merge method (see 'derender methods')."),
    model: Optional[Path] = typer.Option(None, "--model", "-m", help="De-rendering model (.npz or folder) for --method probabilistic."),
    variance: Optional[Path] = typer.Option(None, "--variance", help="Per-pixel variance (.exr), probabilistic methods."),
    times: Optional[str] = typer.Option(None, "--times", help=_TIMES_HELP),
    times_file: Optional[Path] = typer.Option(None, "--times-file", help=_TIMES_FILE_HELP),
    times_inverse: bool = typer.Option(False, "--times-inverse", help=_INVERSE_HELP),
    preview: Optional[Path] = typer.Option(None, "--preview", help="Tone-mapped PNG preview (Reinhard 2002)."),
    mask: Optional[Path] = typer.Option(None, "--mask", help="PNG mask: 0 ok, 128 over-exposed everywhere, 255 under-exposed."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Figure of the recovered response curves (if any)."),
    half: bool = typer.Option(False, "--half", help="Write half-float EXR."),
    seed: int = typer.Option(0, "--seed", help="Seed for sampling / RANSAC."),
) -> None:
    """Merge a bracket into a linear HDR radiance map (OpenEXR)."""
    import numpy as np

    from derender.hdr.files import merge_files
    from derender.io.exif import parse_times
    from derender.io.preview import write_png, write_preview

    if output.suffix.lower() != ".exr":
        raise InputError(f"--output must end in .exr, got {output.name}")
    if times is not None and times_file is not None:
        raise InputError("give either --times or --times-file, not both")
    if variance is not None and variance.suffix.lower() != ".exr":
        raise InputError(f"--variance must end in .exr, got {variance.name}")
    t0 = time.perf_counter()
    inputs = list(images) + ([times_file] if times_file else []) + ([model] if model else [])
    from derender.io.files import check_output

    check_output(output, inputs)
    if variance is not None:
        if variance.resolve() == output.resolve():
            raise InputError(f"--variance and --output are the same file: {output}")
        check_output(variance, inputs)
        from derender.hdr.registry import MERGE_METHODS, load_plugins

        load_plugins()
        if method in MERGE_METHODS and not getattr(MERGE_METHODS[method], "gives_variance", False):
            raise InputError(f"method {method!r} gives no variance (drop --variance)")
    extra = {}
    if model is not None:
        from derender.derendering.library import resolve_model

        model_obj, used = resolve_model(model, images[0])
        typer.echo(f"de-rendering model: {used}", err=True)
        extra["model"] = model_obj
    # 8-bit files run on the engine (streamed or held frames, parallel EXR write); others: read_stack + merge
    result = merge_files(images, parse_times(times) if times is not None else None, method,
                         times_file=times_file, times_file_inverse=times_inverse, output=output,
                         variance_output=variance, half=half, inputs=inputs, seed=seed, **extra)
    if preview is not None:
        write_preview(preview, result.radiance, inputs=inputs)
    if mask is not None:
        m = np.zeros(result.mask.shape, np.uint8)
        m[result.mask == 1] = 128
        m[result.mask == 2] = 255
        write_png(mask, np.repeat(m[:, :, None], 3, axis=2), inputs=inputs)
    if plot is not None:
        curves = result.info.get("curves")
        if curves is None:
            raise InputError(f"method {method!r} has no response curves to plot")
        from derender.response.curves import plot_response

        plot_response(curves, plot, inputs=inputs)
    n_bright = int((result.mask == 1).sum())
    n_dark = int((result.mask == 2).sum())
    typer.echo(f"{method}: {len(images)} images {result.radiance.shape[1]}x{result.radiance.shape[0]} -> {output} "
               f"({time.perf_counter() - t0:.2f} s; {n_bright} px over-exposed everywhere, {n_dark} px under-exposed)")


@app.command("methods")
def methods_cmd() -> None:
    """List the merge methods."""
    from derender.hdr.registry import MERGE_METHODS, load_plugins

    load_plugins()
    for name, fn in sorted(MERGE_METHODS.items()):
        doc = (fn.__doc__ or "").strip().splitlines()[0] if fn.__doc__ else ""
        typer.echo(f"{name:20s} {doc}")


@app.command()
def evaluate(
    result: Path = typer.Argument(..., help="Radiance map to score (.exr or .hdr)."),
    truth: Path = typer.Argument(..., help="Ground truth radiance map (.exr or .hdr)."),
    remap: str = typer.Option("lstsq", "--remap", help="lstsq (least-squares scale, default) | minmax (paper 1's remap)."),
    fit: str = typer.Option("matrix", "--fit", help="Relative error after a 3x3 'matrix' (default) or one 'scale'."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """PSNR on R, G, B and luminance L (scale fitted per plane; docs/paper1.md), per-pixel relative error
    (median, p90, after a 3x3 fit weighted 1/||g||^2) and log-luminance PSNR."""
    from derender.evaluation.metrics import hdr_scores
    from derender.io.rgbe import read_radiance

    _check_choice("--remap", remap, ("lstsq", "minmax"))
    _check_choice("--fit", fit, ("matrix", "scale"))
    scores = hdr_scores(read_radiance(result), read_radiance(truth), remap=remap, fit=fit)
    if as_json:
        typer.echo(json.dumps({k: (round(float(v), 6) if not isinstance(v, str) else v) for k, v in scores.items()}))
    else:
        typer.echo("  ".join(f"{k} {scores[k]:.2f} dB" for k in "RGBL"))
        typer.echo(f"relative error ({fit} fit): median {scores['rel_median']:.4f}, p90 {scores['rel_p90']:.4f};  "
                   f"log-luminance PSNR {scores['log_psnr_L']:.2f} dB")


@app.command()
def diagnose(
    images: List[Path] = typer.Argument(..., help="Bracketed images (JPEG/PNG/TIFF)."),
    output: Path = typer.Option(..., "--output", "-o", help="Figure (.png/.pdf/.svg)."),
    times: Optional[str] = typer.Option(None, "--times", help=_TIMES_HELP),
    times_file: Optional[Path] = typer.Option(None, "--times-file", help=_TIMES_FILE_HELP),
    times_inverse: bool = typer.Option(False, "--times-inverse", help=_INVERSE_HELP),
    seed: int = typer.Option(0, "--seed", help="Sampling seed."),
) -> None:
    """Paper 1's Fig. 2: log(g(J_i)/dt_i) against merged log radiance; spread in stops (0 = constant response)."""
    from derender.evaluation.diagnose import diagnose_constant_response, plot_diagnose

    stack = _read_stack_from_cli(images, times, times_file, times_inverse)
    result = diagnose_constant_response(stack, seed=seed)
    inputs = list(images) + ([times_file] if times_file else [])
    plot_diagnose(result, output, inputs=inputs)
    per = ", ".join(f"{v:.3f}" for v in result.rms_stops_per_exposure)
    typer.echo(f"spread (RMS deviation from slope-1 line): {result.rms_stops:.3f} stops overall; "
               f"median {result.median_stops:.3f}; per exposure [{per}] -> {output}")


@app.command()
def groundtruth(
    raws: List[Path] = typer.Argument(..., help="RAW/DNG frames of the bracket (or a single frame)."),
    output: Path = typer.Option(..., "--output", "-o", help="Output linear sRGB radiance (.exr)."),
    wb: Optional[str] = typer.Option(None, "--wb", help="White-balance multipliers R,G,B (default: as shot)."),
    wb_patch: Optional[str] = typer.Option(None, "--wb-patch", help="Neutral region x,y,w,h for white balance."),
    times: Optional[str] = typer.Option(None, "--times", help="Exposure times (default: from the files)."),
    preview: Optional[Path] = typer.Option(None, "--preview", help="Tone-mapped PNG preview."),
) -> None:
    """Ground truth from RAW (paper 1 Sec. 4.2, Alg. 2): binary-weight merge, WB, Malvar demosaic, sRGB."""
    from derender.io.exif import parse_times
    from derender.io.exr import write_exr
    from derender.io.preview import write_preview
    from derender.io.raw import read_raw_stack
    from derender.raw.groundtruth import raw_ground_truth

    if output.suffix.lower() != ".exr":
        raise InputError(f"--output must end in .exr, got {output.name}")
    frames = read_raw_stack(raws, times=parse_times(times) if times else None)
    wb_value = "as_shot"
    patch = None
    if wb is not None:
        vals = [float(v) for v in wb.split(",")] if all(_is_float(v) for v in wb.split(",")) else []
        if len(vals) != 3 or min(vals) <= 0:
            raise InputError(f"--wb needs three positive numbers R,G,B, got {wb!r}")
        wb_value = vals
    if wb_patch is not None:
        parts = wb_patch.split(",")
        if len(parts) != 4 or not all(p.strip().isdigit() for p in parts):
            raise InputError(f"--wb-patch needs x,y,w,h in pixels, got {wb_patch!r}")
        patch = tuple(int(p) for p in parts)
    result = raw_ground_truth(frames, wb=wb_value, wb_patch=patch)
    write_exr(output, result.radiance, inputs=raws)
    if preview is not None:
        write_preview(preview, result.radiance, inputs=raws)
    typer.echo(f"ground truth from {len(frames)} RAW frame(s) -> {output}")


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


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
    seed: int = typer.Option(0, "--seed", help="Dataset seed."),
) -> None:
    """Simulate a dataset of brackets (raw/ + jpeg/ + truth per scene) for 'derender benchmark'."""
    from derender.evaluation.table1 import simulate_dataset

    pl = [p.strip() for p in pipelines.split(",") if p.strip()]
    st = [p.strip() for p in renders.split(",") if p.strip()]
    for p in pl:
        _check_choice("--pipelines", p, ("fixed", "auto"))
    for p in st:
        _check_choice("--renders", p, ("simple", "camera"))
    cams = [c.strip() for c in cameras.split(",")] if cameras else None
    with _progress() as prog:
        task = prog.add_task("simulating scenes", total=scenes)
        rows = simulate_dataset(outdir, scenes=scenes, exposures=exposures, cameras=cams, size=_parse_size(size),
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
    seed: int = typer.Option(0, "--seed", help="Seed passed to every method."),
) -> None:
    """Paper 1's Table 1: every method on every scene, PSNR R/G/B/L against the RAW ground truth."""
    from derender.evaluation.table1 import run_benchmark, write_benchmark_outputs

    ms = [m.strip() for m in methods.split(",") if m.strip()] if methods else None
    with _progress() as prog:
        task = prog.add_task("scenes", total=None)
        result = run_benchmark(dataset, methods=ms, scheduler=scheduler, workers=workers, seed=seed,
                               progress=lambda i, n: prog.update(task, completed=i, total=n))
    files = write_benchmark_outputs(result, output)
    typer.echo(result.markdown())
    typer.echo(f"per-scene results: {files['csv']} and {files['json']}")


# --------------------------------------------------------------------------- de-rendering data
@app.command("chart-pairs")
def chart_pairs_cmd(
    outdir: Path = typer.Argument(..., help="Folder for <camera>.npz pair files."),
    camera: List[str] = typer.Option(["nikon-d5100"], "--camera", help="Camera name(s) (repeat the option)."),
    camera_file: Optional[Path] = typer.Option(None, "--camera-file", help="rawtoaces camera JSON."),
    illuminants: int = typer.Option(16, "--illuminants", help="Number of gel-filtered tungsten illuminants."),
    exposures: int = typer.Option(22, "--exposures", help="Exposures from all-black to all-white."),
    render: str = typer.Option("camera", "--render", help="simple | camera."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
) -> None:
    """Simulate paper 2's calibration session (ColorChecker SG, 16 illuminants) into RAW/JPEG pairs."""
    from derender.camera.chart import chart_pairs, save_pairs

    _check_choice("--render", render, ("simple", "camera"))
    cams = [_load_camera("", camera_file)] if camera_file else [_load_camera(c, None) for c in camera]
    outdir.mkdir(parents=True, exist_ok=True)
    for cam in cams:
        with _progress() as prog:
            task = prog.add_task(f"{cam.name}: illuminants", total=illuminants)
            pairs = chart_pairs(cam, n_illuminants=illuminants, n_exposures=exposures, style=render, seed=seed,
                                progress=lambda i, n: prog.update(task, completed=i))
        path = save_pairs(pairs, outdir / f"{cam.name}.npz")
        typer.echo(f"{cam.name}: {pairs.jpeg.shape[0]} pairs ({100 * pairs.out_of_gamut.mean():.0f} % out of the "
                   f"sRGB gamut) -> {path}")


# --------------------------------------------------------------------------- demo
def run_demo(outdir: Path, size: tuple[int, int] = (480, 320), seed: int = 0, exposures: int = 9,
             pipeline: str = "auto", render: str = "camera") -> list[dict]:
    """The demo job (library form): simulate, merge with every method, score against truth."""
    from derender.camera.simulate import bracket_paths, simulate_bracket, write_bracket
    from derender.io.exr import read_exr, write_exr
    from derender.io.images import read_stack
    from derender.io.preview import write_preview

    console = _console()
    outdir.mkdir(parents=True, exist_ok=True)
    with _progress() as prog:
        task = prog.add_task("simulating bracket", total=exposures)
        bracket = simulate_bracket(kind="outdoor", size=size, exposures=exposures, pipeline=pipeline, style=render,
                                   seed=seed, progress=lambda i, n: prog.update(task, completed=i))
    write_bracket(bracket, outdir)
    truth = read_exr(outdir / "truth.exr")
    write_preview(outdir / "truth.png", truth)
    stack = read_stack(bracket_paths(outdir, "jpeg"))
    rows: list[dict] = []
    from derender.evaluation.metrics import psnr_rgbl
    from derender.evaluation.table1 import default_methods
    from derender.hdr.registry import merge_seeded

    methods = default_methods()
    with _progress() as prog:
        task = prog.add_task("merging", total=len(methods) + 1)
        try:
            from derender.io.raw import read_raw_stack
            from derender.raw.groundtruth import raw_ground_truth

            t0 = time.perf_counter()
            gt = raw_ground_truth(read_raw_stack(bracket_paths(outdir, "raw")))
            dt = time.perf_counter() - t0
            write_exr(outdir / "groundtruth-from-raw.exr", gt.radiance)
            rows.append({"method": "raw-groundtruth (DNG)", **psnr_rgbl(gt.radiance, truth), "seconds": dt})
        except ImportError:
            pass
        prog.update(task, advance=1)
        for name in methods:
            t0 = time.perf_counter()
            result = merge_seeded(stack, name, seed)
            dt = time.perf_counter() - t0
            write_exr(outdir / f"merge-{name}.exr", result.radiance)
            write_preview(outdir / f"merge-{name}.png", result.radiance)
            rows.append({"method": name, **psnr_rgbl(result.radiance, truth), "seconds": dt})
            prog.update(task, advance=1)
    from rich.table import Table

    table = Table(title=f"derender demo: {pipeline} pipeline, {render} rendering, PSNR (dB) vs truth.exr")
    for col in ("method", "R", "G", "B", "L", "seconds"):
        table.add_column(col, justify="left" if col == "method" else "right")
    for r in rows:
        table.add_row(r["method"], *(f"{r[c]:.2f}" for c in ("R", "G", "B", "L")), f"{r['seconds']:.2f}")
    from rich.console import Console

    Console().print(table)
    console.print(f"outputs in {outdir}/ (EXR radiance maps, PNG previews, scene.json)")
    with open(outdir / "scores.json", "w", encoding="utf-8") as fh:
        json.dump(rows, fh, indent=2)
    return rows


@app.command()
def demo(
    outdir: Path = typer.Option(Path("derender-demo"), "--outdir", "-o", help="Where to write the demo outputs."),
    size: str = typer.Option("480x320", "--size", help="Image size WxH."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    pipeline: str = typer.Option("auto", "--pipeline", help="fixed | auto."),
    render: str = typer.Option("camera", "--render", help="simple | camera."),
) -> None:
    """Simulate an auto-pipeline bracket, merge it with every method, score each against the truth."""
    run_demo(outdir, _parse_size(size), seed=seed, pipeline=pipeline, render=render)


@app.command("merge-batch")
def merge_batch_cmd(
    stacks: List[Path] = typer.Argument(..., help="Stack folders (images, or jpeg/ subfolder; optional times.txt)."),
    outdir: Path = typer.Option(..., "--output", "-o", help="Folder for <stack>.exr outputs."),
    method: str = typer.Option("debevec", "--method", help="Merge method."),
    scheduler: str = typer.Option("local", "--scheduler", help="'local' (Dask local cluster), 'serial', or a Dask scheduler address."),
    workers: int = typer.Option(2, "--workers", help="Workers of the local cluster."),
    seed: int = typer.Option(0, "--seed", help="Seed."),
    half: bool = typer.Option(False, "--half", help="Half-float EXR."),
) -> None:
    """Merge many brackets in parallel (Dask); one EXR per stack folder; identical to a serial run."""
    from derender.hdr.batch import merge_batch

    with _progress() as prog:
        task = prog.add_task("stacks", total=len(stacks))
        rows = merge_batch(stacks, outdir, method=method, scheduler=scheduler, workers=workers, seed=seed, half=half,
                           progress=lambda i, n: prog.update(task, completed=i))
    failed = [r for r in rows if not r["ok"]]
    for r in rows:
        typer.echo(f"{r['stack']}: " + (f"{r['output']} ({r['seconds']:.2f} s)" if r["ok"] else f"error: {r['error']}"))
    if failed:
        raise InputError(f"{len(failed)} of {len(rows)} stacks failed (see above)")


# --------------------------------------------------------------------------- de-rendering
@app.command()
def calibrate(
    output: Path = typer.Option(..., "--output", "-o", help="Model file to write (.npz)."),
    pairs: Optional[Path] = typer.Option(None, "--pairs", help="Pairs file from 'derender chart-pairs' (.npz)."),
    raw: List[Path] = typer.Option([], "--raw", help="RAW/DNG file(s) registered with --jpeg (repeat)."),
    jpeg: List[Path] = typer.Option([], "--jpeg", help="JPEG file(s) registered with --raw (repeat)."),
    method: str = typer.Option("gp", "--method", help="gp | poly | rbf."),
    n_train: int = typer.Option(5000, "--n-train", help="Training pairs (random subset)."),
    seed: int = typer.Option(0, "--seed", help="Random seed (subset, k-means)."),
) -> None:
    """Learn a de-rendering model p(RAW colour | JPEG colour) from calibration pairs."""
    from derender.derendering.base import fit_model
    from derender.derendering.calibration import pairs_from_images

    if output.suffix.lower() != ".npz":
        raise InputError(f"--output must end in .npz, got {output.name}")
    if pairs is None and not raw:
        raise InputError("give --pairs PAIRS.npz or --raw ... --jpeg ... image pairs")
    if pairs is not None and raw:
        raise InputError("give either --pairs or --raw/--jpeg, not both")
    if pairs is not None:
        from derender.camera.chart import load_pairs
        from derender.derendering.base import model_metadata

        pr = load_pairs(pairs)
        jp, rw, meta = pr.jpeg, pr.raw, model_metadata(pr)
        inputs = [pairs]
    else:
        jp, rw, meta = pairs_from_images(raw, jpeg)
        inputs = list(raw) + list(jpeg)
    if n_train < 10:
        raise InputError("--n-train must be at least 10")
    rng = __import__("numpy").random.default_rng(seed)
    if jp.shape[0] > n_train:
        sel = rng.choice(jp.shape[0], size=n_train, replace=False)
        jp, rw = jp[sel], rw[sel]
    kw = {} if method != "gp" else {"n_train": n_train}
    t0 = time.perf_counter()
    model = fit_model(method, jp, rw, seed=seed, **kw)
    model.metadata.update(meta)
    from derender.io.files import check_not_input

    check_not_input(output, inputs)
    model.save(output)
    typer.echo(f"{method} model from {jp.shape[0]} pairs in {time.perf_counter() - t0:.1f} s -> {output}")


@app.command("derender")
def derender_cmd(
    image: Path = typer.Argument(..., help="8-bit rendered image (JPEG/PNG/TIFF)."),
    model: Path = typer.Option(..., "--model", "-m", help="Model file, or a folder of models (picked by EXIF camera)."),
    output: Path = typer.Option(..., "--output", "-o", help="Mean linear camera RGB (.exr)."),
    variance: Optional[Path] = typer.Option(None, "--variance", help="Per-pixel variance (.exr)."),
    srgb: bool = typer.Option(False, "--srgb", help="Output linear sRGB instead of camera RGB (needs model camera metadata)."),
    compression: str = typer.Option("none", "--compression",
                                    help="EXR compression: none (fastest) or zip (~30 % smaller files, ~3x slower at 24 MP)."),
) -> None:
    """De-render an image: per-pixel Gaussian over the linear RAW colour (mean and variance)."""
    from derender.derendering.apply import derender_to_exr

    for out in (output, variance):
        if out is not None and out.suffix.lower() != ".exr":
            raise InputError(f"outputs must end in .exr, got {out.name}")
    from derender.io.exr import EXR_COMPRESSION

    if compression not in EXR_COMPRESSION:
        raise InputError(f"--compression must be one of {', '.join(EXR_COMPRESSION)}, got {compression!r}")
    t0 = time.perf_counter()
    info = derender_to_exr(image, model, output, variance=variance, srgb=srgb, compression=compression)
    typer.echo(f"de-rendered {image.name} ({info['width']}x{info['height']}, {info['distinct_colours']} distinct "
               f"colours) with {info['model']} in {time.perf_counter() - t0:.2f} s -> {output}")


@app.command()
def stereo(
    images: List[Path] = typer.Argument(..., help="Images of the object, one per light (same order as --lights)."),
    lights: Path = typer.Option(..., "--lights", help="Text file: 'lx ly lz [intensity]' per image."),
    model: Optional[Path] = typer.Option(None, "--model", "-m", help="De-rendering model (default: gamma 2.2 inversion)."),
    output: Path = typer.Option(..., "--output", "-o", help="Normals (.exr, RGB = xyz)."),
    depth: Optional[Path] = typer.Option(None, "--depth", help="Depth from the normals (Frankot-Chellappa), .exr."),
    mask_threshold: int = typer.Option(0, "--mask-threshold", help="Pixels whose max code over all images is <= this are background."),
) -> None:
    """Lambertian photometric stereo; with a model, inverse-variance weighted least squares (paper 2 eq. 7)."""
    import numpy as np

    from derender.applications.photometric_stereo import frankot_chellappa, read_lights, solve_normals
    from derender.io.exr import write_exr
    from derender.io.images import read_image

    L = read_lights(lights)
    if len(images) != L.shape[0]:
        raise InputError(f"{len(images)} images but {L.shape[0]} lights in {lights}")
    imgs = []
    for p in images:
        img, depth_bits = read_image(p)
        if depth_bits != 8:
            raise InputError(f"{p}: photometric stereo with a de-rendering model needs 8-bit images")
        if imgs and img.shape != imgs[0].shape:
            raise InputError(f"images differ in size: {images[0].name} vs {p.name}")
        imgs.append(img)
    codes = np.rint(np.stack(imgs) * 255).astype(np.uint8)
    mask = codes.max(axis=(0, 3)) > mask_threshold
    if model is not None:
        from derender.derendering.library import resolve_model

        m, used = resolve_model(model, images[0])
        mean, var = m.predict(codes, point="map")
        normals, albedo = solve_normals(mean, L, variances=var, mask=mask)
    else:
        used = "gamma 2.2 inversion"
        normals, albedo = solve_normals((codes / 255.0) ** 2.2, L, mask=mask)
    write_exr(output, normals.astype(np.float32), inputs=list(images) + [lights])
    if depth is not None:
        write_exr(depth, frankot_chellappa(normals, mask).astype(np.float32), inputs=list(images) + [lights])
    typer.echo(f"normals of {int(mask.sum())} pixels from {len(images)} images ({used}) -> {output}")


experiment_app = typer.Typer(no_args_is_help=True, help="Paper experiments on simulated cameras.")
app.add_typer(experiment_app, name="experiment")


def _cams(cameras: Optional[str]):
    return [c.strip() for c in cameras.split(",") if c.strip()] if cameras else None


@experiment_app.command("derender-table")
def exp_derender_table(
    cameras: Optional[str] = typer.Option(None, "--cameras", help="Comma-separated cameras (default: S90, 5D II, D5100)."),
    n_train: int = typer.Option(5000, "--n-train", help="Training pairs."),
    methods: str = typer.Option("gp,poly,rbf", "--methods", help="Methods."),
    seed: int = typer.Option(0, "--seed", help="Seed."),
    output: Optional[Path] = typer.Option(None, "--json", help="Also write the rows as JSON."),
) -> None:
    """Paper 2 Table 1: RMSE / relative RMSE, all and out-of-gamut, plus 95 % interval coverage."""
    from derender.evaluation.experiments import derender_table, format_table

    rows = derender_table(_cams(cameras), methods=[m.strip() for m in methods.split(",")], n_train=n_train,
                          seed=seed, progress=lambda msg: _console().print(msg))
    typer.echo(format_table(rows, [("camera", "camera", ""), ("method", "method", ""),
                                   ("rmse_all", "RMSE all", ".4f"), ("rmse_oog", "RMSE oog", ".4f"),
                                   ("rel_rmse_all", "rel RMSE all", ".3f"), ("rel_rmse_in", "rel in-gamut", ".3f"),
                                   ("rel_rmse_all_mean", "rel RMSE all (mean)", ".3f"),
                                   ("rel_rmse_oog", "rel out-of-gamut", ".3f"), ("median_rel", "median rel", ".3f"),
                                   ("ratio_to_poly", "/poly", ".2f"),
                                   ("coverage95", "95% coverage R/G/B", ".3f"), ("fit_seconds", "fit s", ".1f")]))
    if output is not None:
        output.write_text(json.dumps(rows, indent=2, default=float))


@experiment_app.command("threshold-sweep")
def exp_threshold_sweep(
    cameras: Optional[str] = typer.Option(None, "--cameras", help="Comma-separated cameras."),
    holdouts: Optional[str] = typer.Option(None, "--holdouts", help="Illuminants to hold out (default: all 16)."),
    n_train: int = typer.Option(5000, "--n-train", help="Training pairs."),
    methods: str = typer.Option("gp,poly,rbf", "--methods", help="Methods."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Figure like paper 2 Fig. 4."),
    seed: int = typer.Option(0, "--seed", help="Seed."),
) -> None:
    """Paper 2 Fig. 4: relative RMSE of scene colour from exposure sequences vs the JPEG interval used."""
    from derender.evaluation.experiments import format_table, plot_threshold_sweep, threshold_sweep

    ho = [int(v) for v in holdouts.split(",")] if holdouts else None
    rows = threshold_sweep(_cams(cameras), methods=[m.strip() for m in methods.split(",")], n_train=n_train,
                           holdouts=ho, seed=seed, progress=lambda msg: _console().print(msg))
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
    seed: int = typer.Option(0, "--seed", help="Seed."),
) -> None:
    """Paper 2 Sec. 4.3: GP weighted LS vs polynomial LS vs gamma-2.2 LS on a sphere and bumps."""
    from derender.evaluation.experiments import format_table, photometric_stereo_experiment

    rows = photometric_stereo_experiment(camera, n_lights=lights, size=size, seed=seed, plot=plot,
                                         progress=lambda msg: _console().print(msg))
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

    w, h = _parse_size(size)
    try:
        seed_list = [int(v) for v in seeds.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--seeds must be integers separated by commas, got {seeds!r}") from None
    rows = fusion_gain(styles=[v.strip() for v in styles.split(",") if v.strip()],
                       kinds=[v.strip() for v in kinds.split(",") if v.strip()], seeds=seed_list, size=(w, h),
                       pipeline=pipeline, methods=[v.strip() for v in methods.split(",") if v.strip()],
                       progress=lambda msg: _console().print(msg))
    typer.echo(format_table(rows, [("style", "style", ""), ("scene", "scene", ""), ("method", "method", ""),
                                   ("dR", "dR", "+.2f"), ("dG", "dG", "+.2f"), ("dB", "dB", "+.2f"),
                                   ("dL", "dL", "+.2f"), ("wins", "wins >=3/4", ".0%")]))


if __name__ == "__main__":  # pragma: no cover
    main()
