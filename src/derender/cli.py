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
    from .merge import available_methods, merge

    methods = available_methods(needs_model=False)
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
            result = merge(stack, method=name, seed=seed)
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
