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

from .errors import DerenderError, InputError


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
    from .spectral import load_camera, load_camera_file

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
    from .camera import simulate_bracket, write_bracket

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
    from .io import parse_times, read_stack

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
    method: str = typer.Option("debevec", "--method", "-m", help="Merge method (see 'derender methods')."),
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

    from .benchmark import merge_seeded
    from .io import write_exr, write_png, write_preview

    if output.suffix.lower() != ".exr":
        raise InputError(f"--output must end in .exr, got {output.name}")
    stack = _read_stack_from_cli(images, times, times_file, times_inverse)
    t0 = time.perf_counter()
    result = merge_seeded(stack, method, seed)
    inputs = list(images) + ([times_file] if times_file else [])
    write_exr(output, result.radiance, half=half, inputs=inputs)
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
        from .response import plot_response

        plot_response(curves, plot, inputs=inputs)
    n_bright = int((result.mask == 1).sum())
    n_dark = int((result.mask == 2).sum())
    typer.echo(f"{method}: {stack.n} images {stack.shape[1]}x{stack.shape[0]} -> {output} "
               f"({time.perf_counter() - t0:.2f} s; {n_bright} px over-exposed everywhere, {n_dark} px under-exposed)")


@app.command("methods")
def methods_cmd() -> None:
    """List the merge methods."""
    from .merge import MERGE_METHODS, _load_plugins

    _load_plugins()
    for name, fn in sorted(MERGE_METHODS.items()):
        doc = (fn.__doc__ or "").strip().splitlines()[0] if fn.__doc__ else ""
        typer.echo(f"{name:20s} {doc}")


@app.command()
def evaluate(
    result: Path = typer.Argument(..., help="Radiance map to score (.exr or .hdr)."),
    truth: Path = typer.Argument(..., help="Ground truth radiance map (.exr or .hdr)."),
    remap: str = typer.Option("lstsq", "--remap", help="lstsq (least-squares scale, default) | minmax (paper 1's remap)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """PSNR on R, G, B and luminance L after the protocol of DESIGN.md (scale fitted per plane)."""
    from .evaluate import psnr_rgbl
    from .io import read_radiance

    _check_choice("--remap", remap, ("lstsq", "minmax"))
    scores = psnr_rgbl(read_radiance(result), read_radiance(truth), remap=remap)
    if as_json:
        typer.echo(json.dumps({k: round(float(v), 4) for k, v in scores.items()}))
    else:
        typer.echo("  ".join(f"{k} {v:.2f} dB" for k, v in scores.items()))


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
    from .diagnose import diagnose_constant_response, plot_diagnose

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
    from .groundtruth import raw_ground_truth
    from .io import parse_times, read_raw_stack, write_exr, write_preview

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
    from .benchmark import simulate_dataset

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
    from .benchmark import run_benchmark, write_benchmark_outputs

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
    from .chart import chart_pairs, save_pairs

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
    from .camera import bracket_paths, simulate_bracket, write_bracket
    from .io import read_exr, read_stack, write_exr, write_preview

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
    from .evaluate import psnr_rgbl
    from .benchmark import default_methods, merge_seeded

    methods = default_methods()
    with _progress() as prog:
        task = prog.add_task("merging", total=len(methods) + 1)
        try:
            from .groundtruth import raw_ground_truth
            from .io import read_raw_stack

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


if __name__ == "__main__":  # pragma: no cover
    main()
