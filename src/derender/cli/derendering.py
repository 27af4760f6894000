"""``derender`` commands of the de-rendering side: chart pairs, calibrate, derender, stereo."""

from __future__ import annotations

import time
from pathlib import Path
from typing import List, Optional

import typer

from derender.cli.app import (
    app,
    check_choice,
    check_model_camera,
    load_camera_cli,
    progress,
)
from derender.core.errors import InputError
from derender.io.headers import DEFAULT_MAX_MEGAPIXELS


# --------------------------------------------------------------------------- de-rendering data
@app.command("chart-pairs")
def chart_pairs_cmd(
    outdir: Path = typer.Argument(..., help="Folder for <camera>.npz pair files."),
    camera: List[str] = typer.Option(["nikon-d5100"], "--camera", help="Camera name(s) (repeat the option)."),
    camera_file: Optional[Path] = typer.Option(None, "--camera-file", help="rawtoaces camera JSON."),
    illuminants: int = typer.Option(16, "--illuminants", help="Number of gel-filtered tungsten illuminants."),
    exposures: int = typer.Option(22, "--exposures", help="Exposures from all-black to all-white."),
    render: str = typer.Option("camera", "--render", help="simple | camera."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed."),
) -> None:
    """Simulate paper 2's calibration session (ColorChecker SG, 16 illuminants) into RAW/JPEG pairs."""
    from derender.camera.chart import chart_pairs, save_pairs

    check_choice("--render", render, ("simple", "camera"))
    cams = [load_camera_cli("", camera_file)] if camera_file else [load_camera_cli(c, None) for c in camera]
    outdir.mkdir(parents=True, exist_ok=True)
    for cam in cams:
        with progress() as prog:
            task = prog.add_task(f"{cam.name}: illuminants", total=illuminants)
            pairs = chart_pairs(cam, n_illuminants=illuminants, n_exposures=exposures, style=render, seed=seed,
                                progress=lambda i, n: prog.update(task, completed=i))
        path = save_pairs(pairs, outdir / f"{cam.name}.npz")
        typer.echo(f"{cam.name}: {pairs.jpeg.shape[0]} pairs ({100 * pairs.out_of_gamut.mean():.0f} % out of the "
                   f"sRGB gamut) -> {path}")


# --------------------------------------------------------------------------- de-rendering
@app.command()
def calibrate(
    output: Path = typer.Option(..., "--output", "-o", help="Model file to write (.npz)."),
    pairs: Optional[Path] = typer.Option(None, "--pairs", help="Pairs file from 'derender chart-pairs' (.npz)."),
    raw: List[Path] = typer.Option([], "--raw", help="RAW/DNG file(s) registered with --jpeg (repeat)."),
    jpeg: List[Path] = typer.Option([], "--jpeg", help="JPEG file(s) registered with --raw (repeat)."),
    method: str = typer.Option("auto", "--method",
                               help="auto (cross-validate gp, poly and rbf on the pairs, keep the best) | gp | poly | rbf."),
    n_train: int = typer.Option(5000, "--n-train", help="Training pairs of the model (random subset)."),
    folds: int = typer.Option(4, "--folds", help="auto: cross-validation folds (whole illuminants when the pairs "
                                                 "record them, else random)."),
    cv_train: int = typer.Option(2000, "--cv-train", help="auto: training pairs per fold fit (seeded subsample; "
                                                          "bounds the time; capped at --n-train)."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed (subset, folds, k-means)."),
) -> None:
    """Learn a de-rendering model p(RAW colour | JPEG colour) from calibration pairs.

    With --method auto (the default) each of gp, poly and rbf is scored on the pairs by
    cross-validation (relative RMSE of held-out pairs, paper 2's protocol); the table is
    printed and stored in the model file, and the best is fitted on all pairs.
    """
    from derender.derendering.calibration import pairs_from_images
    from derender.derendering.model_selection import SELECTION_METHODS, fit_auto, fit_calibration
    from derender.io.files import OutputTransaction, check_output

    check_choice("--method", method, ("auto", *SELECTION_METHODS))
    check_output(output, list(raw) + list(jpeg) + ([pairs] if pairs else []))
    if output.suffix.lower() != ".npz":
        raise InputError(f"--output must end in .npz, got {output.name}")
    if pairs is None and not raw:
        raise InputError("give --pairs PAIRS.npz or --raw ... --jpeg ... image pairs")
    if pairs is not None and raw:
        raise InputError("give either --pairs or --raw/--jpeg, not both")
    if n_train < 10:
        raise InputError("--n-train must be at least 10")
    groups = oog = None
    truth_floor = 0.0
    if pairs is not None:
        from derender.camera.chart import load_pairs
        from derender.derendering.base import model_metadata

        pr = load_pairs(pairs)
        jp, rw, meta = pr.jpeg, pr.raw, model_metadata(pr)
        groups, oog = pr.illuminant, pr.out_of_gamut
        inputs = [pairs]
    else:
        from derender.derendering.model_selection import IMAGE_TRUTH_FLOOR

        jp, rw, meta = pairs_from_images(raw, jpeg)
        inputs = list(raw) + list(jpeg)
        truth_floor = IMAGE_TRUTH_FLOOR     # one noisy RAW pixel per pair: leave the near-black out of the score
    if method == "auto":   # bad pairs or folds: one error line before any progress output
        from derender.derendering.base import check_pairs
        from derender.derendering.model_selection import MIN_FOLD_TRAIN, cv_folds

        if cv_train < MIN_FOLD_TRAIN:
            raise InputError(f"--cv-train must be at least {MIN_FOLD_TRAIN}")
        check_pairs(jp, rw)
        cv_folds(jp.shape[0], groups=groups, n_folds=folds, seed=seed)
    t0 = time.perf_counter()
    selection = None
    with OutputTransaction(inputs) as tx:
        out_tmp = tx.add(output, "--output", (".npz",))
        if method == "auto":
            with progress() as prog:
                task = prog.add_task("auto: cross-validation fits", total=None)

                def report(done: int, total: int, label: str) -> None:
                    prog.update(task, completed=done, total=total, description=f"auto: {label}")

                model, selection = fit_auto(jp, rw, n_train=n_train, seed=seed, groups=groups, out_of_gamut=oog,
                                            n_folds=folds, cv_train=cv_train, truth_floor=truth_floor,
                                            progress=report)
        else:
            model = fit_calibration(method, jp, rw, n_train=n_train, seed=seed)
        model.metadata.update(meta)
        model.save(out_tmp)
    if selection is not None:
        _print_selection(selection)
    n_fit = model.metadata.get("training", {}).get("n_pairs", min(jp.shape[0], n_train))
    typer.echo(f"{model.method} model from {n_fit} pairs in {time.perf_counter() - t0:.1f} s -> {output}")


def _print_selection(sel) -> None:
    """The cross-validation table of ``--method auto`` (stdout) and the line naming the choice."""
    from rich.console import Console
    from rich.table import Table

    def f(v, fmt="{:.4f}"):
        return "-" if v is None else fmt.format(v)

    scored = sel.rows[0]["n_scored"]
    floor = f" (||x|| >= {sel.truth_floor:g} x raw white)" if sel.truth_floor > 0 else ""
    table = Table(title=f"calibrate --method auto: {sel.describe_folds()}, {sel.n_pairs} pairs, fits on "
                        f"{sel.cv_train} pairs per fold, scored on {scored} held-out pairs{floor}")
    for col in ("method", "rel RMSE all", "rel RMSE out-of-gamut", "coverage 95 % (R G B)", "fit s", "chosen"):
        table.add_column(col, justify="left" if col in ("method", "chosen") else "right")
    for r in sel.rows:
        cov = "-" if r["coverage95"] is None else " ".join(f"{c:.2f}" for c in r["coverage95"])
        table.add_row(r["method"], f(r["rel_rmse_all"]), f(r["rel_rmse_oog"]), cov, f(r["fit_seconds"], "{:.1f}"),
                      "yes" if r["chosen"] else (f"failed: {r['error']}" if r["error"] else ""))
    Console(width=max(100, Console().width)).print(table)
    best = next(r for r in sel.rows if r["chosen"])
    typer.echo(f"auto chose {sel.chosen}: lowest held-out relative RMSE {best['rel_rmse_all']:.4f} "
               f"({sel.describe_folds()})")


@app.command("derender")
def derender_cmd(
    image: Path = typer.Argument(..., help="8-bit rendered image (JPEG/PNG/TIFF)."),
    model: Path = typer.Option(..., "--model", "-m", help="Model file, or a folder of models (picked by EXIF camera)."),
    output: Path = typer.Option(..., "--output", "-o", help="Mean linear camera RGB (.exr)."),
    variance: Optional[Path] = typer.Option(None, "--variance", help="Per-pixel variance (.exr)."),
    srgb: bool = typer.Option(False, "--srgb", help="Output linear sRGB instead of camera RGB (needs model camera metadata)."),
    compression: str = typer.Option("none", "--compression",
                                    help="EXR compression: none (fastest) or zip (~30 % smaller files, ~3x slower at 24 MP)."),
    strict_camera: bool = typer.Option(False, "--strict-camera",
                                       help="Refuse a model calibrated for another camera than the image's EXIF names "
                                            "(default: a warning)."),
    max_megapixels: float = typer.Option(DEFAULT_MAX_MEGAPIXELS, "--max-megapixels",
                                         help="Refuse images larger than this (decoded size, read from the header)."),
) -> None:
    """De-render an image: per-pixel Gaussian over the linear RAW colour (mean and variance)."""
    from derender.derendering.apply import derender_to_exr
    from derender.io.exr import EXR_COMPRESSION
    from derender.io.files import OutputTransaction

    if compression not in EXR_COMPRESSION:
        raise InputError(f"--compression must be one of {', '.join(EXR_COMPRESSION)}, got {compression!r}")
    t0 = time.perf_counter()
    with OutputTransaction([image, model]) as tx:
        out_tmp = tx.add(output, "--output", (".exr",))
        var_tmp = tx.add(variance, "--variance", (".exr",))
        check_model_camera(model, image, strict_camera)
        info = derender_to_exr(image, model, out_tmp, variance=var_tmp, srgb=srgb, compression=compression,
                               max_megapixels=max_megapixels)
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
    from derender.io.files import OutputTransaction

    inputs = list(images) + [lights] + ([model] if model else [])
    with OutputTransaction(inputs) as tx:
        normals_tmp = tx.add(output, "--output", (".exr",))
        depth_tmp = tx.add(depth, "--depth", (".exr",))
        used, n = _stereo(images, lights, model, normals_tmp, depth_tmp, mask_threshold)
    typer.echo(f"normals of {n} pixels from {len(images)} images ({used}) -> {output}")


def _stereo(images: List[Path], lights: Path, model: Optional[Path], output: Path, depth: Optional[Path],
            mask_threshold: int) -> tuple[str, int]:
    """The stereo command's work, writing to the transaction's temporaries."""
    import numpy as np

    from derender.applications.photometric_stereo import frankot_chellappa, read_lights, solve_normals
    from derender.io.exr import write_exr
    from derender.io.headers import probe_images
    from derender.io.images import read_image

    probe_images(images)
    L = read_lights(lights)
    if len(images) != L.shape[0]:
        raise InputError(f"{len(images)} images but {L.shape[0]} lights in {lights}")
    imgs = []
    for p in images:
        img, depth_bits = read_image(p)
        if depth_bits != 8:
            raise InputError(f"{p}: photometric stereo with a de-rendering model needs 8-bit images")
        imgs.append(img)
    codes = np.rint(np.stack(imgs) * 255).astype(np.uint8)
    mask = codes.max(axis=(0, 3)) > mask_threshold
    if model is not None:
        from derender.derendering.library import resolve_model

        m, used = resolve_model(model, images[0])
        check_model_camera(model, images[0], False)
        mean, var = m.predict(codes, point="map")
        normals, albedo = solve_normals(mean, L, variances=var, mask=mask)
    else:
        used = "gamma 2.2 inversion"
        normals, albedo = solve_normals((codes / 255.0) ** 2.2, L, mask=mask)
    write_exr(output, normals.astype(np.float32), inputs=list(images) + [lights])
    if depth is not None:
        write_exr(depth, frankot_chellappa(normals, mask).astype(np.float32), inputs=list(images) + [lights])
    return used, int(mask.sum())


