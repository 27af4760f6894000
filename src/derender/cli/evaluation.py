"""``derender evaluate``, ``derender score`` and ``derender diagnose``: scoring a map against a truth,
a JPEG merge against the RAW merge of the same shots, and checking a bracket without a truth (is
the response constant; does a merge give back its own frames)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from derender.cli.app import (
    INVERSE_HELP,
    TIMES_FILE_HELP,
    TIMES_HELP,
    app,
    check_choice,
    read_mask_codes,
    read_stack_from_cli,
)
from derender.cli.merge import motion_options
from derender.core.errors import InputError


@app.command()
def evaluate(
    result: Path = typer.Argument(..., help="Radiance map to score (.exr or .hdr)."),
    truth_arg: Optional[Path] = typer.Argument(None, metavar="[TRUTH]",
                                               help="Ground truth radiance map (.exr or .hdr); or give --truth."),
    truth_opt: Optional[Path] = typer.Option(None, "--truth", help="Ground truth radiance map (.exr or .hdr)."),
    remap: str = typer.Option("lstsq", "--remap", help="lstsq (least-squares scale, default) | minmax (paper 1's remap)."),
    fit: str = typer.Option("matrix", "--fit", help="Relative error after a 3x3 'matrix' (default) or one 'scale' (both fitted by trimmed least squares), or 'none'."),
    variance: Optional[Path] = typer.Option(None, "--variance",
                                            help="RESULT's per-pixel variance (.exr): also print the coverage of its "
                                                 "50/80/95/99 % intervals and the median |z|."),
    merge_mask: Optional[Path] = typer.Option(None, "--mask", help="The merge's --mask PNG: with --variance, pixels "
                                              "over-exposed in every frame are scored on their own."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Score RESULT against the ground truth: PSNR, relative error, log PSNR; with --variance its coverage.

    PSNR on R, G, B and luminance L (scale fitted per plane; docs/paper1.md), per-pixel
    relative error (median, p90, after a 3x3 'matrix' or one 'scale' fitted to RESULT by
    trimmed least squares on relative errors) and log-luminance PSNR.

    The scores are not symmetric (the fit maps RESULT onto the truth, PSNR's peak is the
    truth's): the first line printed names which file was taken as the truth."""
    from derender.evaluation.metrics import hdr_scores
    from derender.io.rgbe import read_radiance

    if (truth_arg is None) == (truth_opt is None):
        raise InputError("give the ground truth once: 'derender evaluate RESULT --truth TRUTH' "
                         "(or RESULT TRUTH)")
    truth = truth_arg if truth_arg is not None else truth_opt
    check_choice("--remap", remap, ("lstsq", "minmax"))
    check_choice("--fit", fit, ("matrix", "scale", "none"))
    if merge_mask is not None and variance is None:
        raise InputError("--mask applies to the coverage of a --variance; give one")
    res_map, truth_map = read_radiance(result), read_radiance(truth)
    scores = hdr_scores(res_map, truth_map, remap=remap, fit=fit)
    cover = None
    if variance is not None:
        from derender.evaluation.uncertainty import coverage_table

        mask_codes = None if merge_mask is None else read_mask_codes(merge_mask, "--mask", res_map.shape[:2])
        var_map = read_radiance(variance)
        if var_map.shape != res_map.shape:
            raise InputError(f"--variance {variance} is {var_map.shape[1]}x{var_map.shape[0]}, the result "
                             f"{res_map.shape[1]}x{res_map.shape[0]}")
        cover = coverage_table(res_map, var_map, truth_map, fit=fit, merge_mask=mask_codes)
    if as_json:
        scores = {"result": str(result), "truth": str(truth), **scores}
        out = {k: (round(float(v), 6) if not isinstance(v, str) else v) for k, v in scores.items()}
        if cover is not None:
            out["coverage"] = {part: {"coverage": {str(p): round(c, 6) for p, c in d["coverage"].items()},
                                      "median_abs_z": round(d["median_abs_z"], 6),
                                      **{t: round(d[t], 6) for t in ("tail3", "tail3_edge", "tail3_flat")}, "n": d["n"],
                                      "n_unscored": d["n_unscored"]} for part, d in cover.items()}
        typer.echo(json.dumps(out))
    else:
        typer.echo(f"{result} scored against the truth {truth}")
        typer.echo("  ".join(f"{k} {scores[k]:.2f} dB" for k in "RGBL"))
        typer.echo(f"relative error ({fit} fit): median {scores['rel_median']:.4f}, p90 {scores['rel_p90']:.4f};  "
                   f"log-luminance PSNR {scores['log_psnr_L']:.2f} dB")
        if cover is not None:
            typer.echo("variance: coverage of the central 50 / 80 / 95 / 99 % intervals (ideal 0.50 / 0.80 / 0.95 / "
                       "0.99), median |z| (ideal 0.67), pixel-channels scored")
            for part, d in cover.items():
                typer.echo(f"  {part:9s} " + " / ".join(f"{c:.3f}" for c in d["coverage"].values())
                           + f"   median |z| {d['median_abs_z']:.2f}   |z|>3 edge {d['tail3_edge']:.3f} flat "
                           f"{d['tail3_flat']:.3f}   n {d['n']}"
                           + (f" ({d['n_unscored']} without a usable variance)" if d["n_unscored"] else ""))


@app.command()
def score(
    images: List[Path] = typer.Argument(..., help="The bracket's RAW files and the camera's JPEGs of the same shots "
                                        "(files or folders; a folder with raw/ and jpeg/ stands for both)."),
    method: str = typer.Option("debevec", "--method", help="Merge method for the JPEGs (derender methods)."),
    truth_method: str = typer.Option("optimal", "--truth-method", help="RAW merge taken as the truth: optimal (the "
                                     "noise-optimal merge, as derender groundtruth) | paper1 (paper 1's eq. 11)."),
    output: Optional[Path] = typer.Option(None, "--output", "-o", help="Also write the JPEG merge (.exr)."),
    truth_output: Optional[Path] = typer.Option(None, "--truth-output", help="Also write the RAW merge (.exr)."),
    remap: str = typer.Option("lstsq", "--remap", help="lstsq (least-squares scale, default) | minmax (paper 1's remap)."),
    fit: str = typer.Option("matrix", "--fit", help="Relative error after a 3x3 'matrix' (default) or one 'scale', or 'none'."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of methods that sample."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Paper 1's protocol on your own camera: merge the JPEGs, merge the RAWs, score the one against the other.

    A RAW+JPEG bracket: as many RAW files as JPEGs, one camera, one size, the same exposure
    times. The RAW merge (linear sRGB, as derender groundtruth) is the truth; the JPEG merge is
    scored as derender evaluate scores (PSNR R/G/B/L, relative error, log-luminance PSNR) on
    the pixels some RAW frame measured."""
    from derender.evaluation.raw_jpeg import score_raw_jpeg, split_raw_rendered
    from derender.io.exr import write_exr
    from derender.io.files import OutputTransaction

    check_choice("--truth-method", truth_method, ("optimal", "paper1"))
    check_choice("--remap", remap, ("lstsq", "minmax"))
    check_choice("--fit", fit, ("matrix", "scale", "none"))
    raws, jpegs = split_raw_rendered(images)
    with OutputTransaction(list(raws) + list(jpegs)) as tx:
        out_tmp = tx.add(output, "--output", (".exr",))
        truth_tmp = tx.add(truth_output, "--truth-output", (".exr",))
        res = score_raw_jpeg(raws, jpegs, method, truth_method=truth_method, seed=seed, remap=remap, fit=fit)
        if out_tmp is not None:
            write_exr(out_tmp, res.result.radiance, inputs=jpegs)
        if truth_tmp is not None:
            write_exr(truth_tmp, res.truth.radiance, inputs=raws)
    sc = res.scores
    if as_json:
        typer.echo(json.dumps({"method": method, "truth_method": truth_method, "pairs": res.pairs,
                               "n_scored": res.n_scored, "n_unscored": res.n_unscored,
                               **{k: (round(float(v), 6) if not isinstance(v, str) else v) for k, v in sc.items()}}))
        return
    typer.echo(f"{method} on {len(res.pairs)} JPEGs scored against the RAW merge ({truth_method}) of the same shots")
    typer.echo("  ".join(f"{k} {sc[k]:.2f} dB" for k in "RGBL"))
    typer.echo(f"relative error ({fit} fit): median {sc['rel_median']:.4f}, p90 {sc['rel_p90']:.4f};  "
               f"log-luminance PSNR {sc['log_psnr_L']:.2f} dB")
    if res.n_unscored:
        typer.echo(f"{res.n_unscored} px over-exposed in every RAW frame not scored ({res.n_scored} scored)")


@app.command()
def diagnose(
    images: List[Path] = typer.Argument(..., help="Bracketed images (JPEG/PNG/TIFF/HEIC/AVIF) or RAW files (DNG, CR2, "
                                        "CR3, NEF, ARW, RAF, ...), or folders of them."),
    output: Path = typer.Option(..., "--output", "-o", help="Figure (.png/.pdf/.svg)."),
    times: Optional[str] = typer.Option(None, "--times", help=TIMES_HELP),
    times_file: Optional[Path] = typer.Option(None, "--times-file", help=TIMES_FILE_HELP),
    times_inverse: bool = typer.Option(False, "--times-inverse", help=INVERSE_HELP),
    seed: int = typer.Option(0, "--seed", min=0, help="Sampling seed."),
    round_trip: Optional[str] = typer.Option(None, "--round-trip", help="Also merge with this method and render the "
                                             "map back through its own forward model (curve and exposure, or per-frame "
                                             "gamma and 3x3): per frame and region, how far the codes come back from "
                                             "each frame's own (median, p95; codes)."),
    reference: Optional[str] = typer.Option(None, "--reference", help="With --round-trip: the reference frame (N from "
                                            "1, or auto)."),
    align: str = typer.Option("none", "--align", help="With --round-trip: none, translation, homography or flow (the "
                              "merge's warps applied to the frames again before they are compared)."),
    deghost: bool = typer.Option(False, "--deghost", help="With --round-trip: merge with ghost removal (pixels any "
                                 "frame was left out of are not scored)."),
    fail_map: Optional[Path] = typer.Option(None, "--fail-map", help="With --round-trip: a PNG of where the round trip "
                                            "fails (grey level: how many frames miss by more than 4 codes)."),
    tolerance: float = typer.Option(0.0, "--tolerance", min=0.0, max=4.0, help="With --round-trip: registration tolerance in "
                                  "pixels: each 32-px block of a frame first takes the shift (0.5 px steps, at most "
                                  "this far) that fits the map best (a misregistered edge is not a model error; 0: none)."),
    scale: int = typer.Option(1, "--scale", min=1, max=15, help="With --round-trip: compare SCALE x SCALE box means of "
                              "the codes (in-camera sharpening, demosaicing and noise are not the forward model's; "
                              "1: pixel by pixel)."),
) -> None:
    """Paper 1's Fig. 2: log(g(J_i)/dt_i) against merged log radiance; spread in stops (0 = constant response).
    With --round-trip METHOD: does the merge give back each frame's codes?"""
    from derender.evaluation.diagnose import diagnose_constant_response, plot_diagnose
    from derender.io.files import OutputTransaction

    check_choice("--align", align, ("none", "translation", "homography", "flow"))
    if round_trip is None and (fail_map is not None or deghost or reference is not None or tolerance or scale > 1):
        raise InputError("--fail-map, --deghost, --reference, --tolerance and --scale need --round-trip METHOD")
    if round_trip is not None:
        from derender.hdr.registry import method_spec

        method_spec(round_trip)             # an unknown method is an error before any work
    stack = read_stack_from_cli(images, times, times_file, times_inverse)
    result = diagnose_constant_response(stack, seed=seed)
    inputs = list(images) + ([times_file] if times_file else [])
    with OutputTransaction() as tx:
        fig_tmp = tx.add(output, "-o", None)
        map_tmp = tx.add(fail_map, "--fail-map", (".png",))
        plot_diagnose(result, fig_tmp, inputs=inputs)
        per = ", ".join(f"{v:.3f}" for v in result.rms_stops_per_exposure)
        typer.echo(f"spread (RMS deviation from slope-1 line): {result.rms_stops:.3f} stops overall; "
                   f"median {result.median_stops:.3f}; per exposure [{per}] -> {output}")
        if round_trip is not None:
            _round_trip_report(images, round_trip, times=times, times_file=times_file, times_inverse=times_inverse,
                               reference=reference, align=align, deghost=deghost, map_path=(map_tmp, fail_map),
                               inputs=inputs, tolerance=tolerance, scale=scale)


def _round_trip_report(images, method, *, times, times_file, times_inverse, reference, align, deghost, map_path,
                       inputs, tolerance=0, scale=1) -> None:
    """`diagnose --round-trip`: the per-frame and per-region table, and the failure map
    (``map_path``: the transaction's temporary and the user's name, or (None, None))."""
    from derender.evaluation.roundtrip import FAIL_CODES, REGIONS, bracket_round_trip
    from derender.io.files import expand_image_paths
    from derender.io.preview import write_png

    images = expand_image_paths(images)
    motion = motion_options(reference, align, deghost, None, None, len(images))
    tlist = [float(x) for x in times.split(",")] if times else None
    rt, res, names = bracket_round_trip(images, method, times=tlist, times_file=times_file,
                                        times_file_inverse=times_inverse, motion=motion, tolerance=tolerance,
                                        scale=scale)
    tol = (f", registration tolerance {tolerance:g} px" if tolerance else "") + (f", {scale}x{scale} means" if scale > 1
                                                                                else "")
    typer.echo(f"round trip through {method}'s forward model (codes{tol}; the issue's line: median <= 1.5, p95 <= 4):")
    if rt.black is not None and any(rt.black):
        typer.echo(f"  the bracket's black floor (film base), codes R G B {' '.join(str(b) for b in rt.black)}: "
                   "counted as a black clip, not scored")
    for row in rt.rows(names):
        typer.echo(f"  {row['frame']}: median {row['median']:.2f}  p95 {row['p95']:.2f}  ({row['pixels']} px, "
                   f"{100 * row['share']:.0f} % of the weight)")
    typer.echo(f"  all frames, each residual counted by its merge weight: median {rt.weighted_median:.2f}  "
               f"p95 {rt.weighted_p95:.2f}")
    import numpy as np

    worst = np.nanmax(rt.regions, axis=0)
    typer.echo(f"  worst frame's median per region ({REGIONS}x{REGIONS}, top row first): "
               + " | ".join(" ".join("  - " if not np.isfinite(v) else f"{v:4.1f}" for v in r) for r in worst))
    tmp, final = map_path
    if tmp is not None:
        n = max(1, len(names))
        grey = np.clip(np.rint(255.0 * rt.fail.astype(np.float64) / n), 0, 255).astype(np.uint8)
        write_png(tmp, np.repeat(grey[..., None], 3, axis=-1), inputs)
        typer.echo(f"  pixels some frame misses by more than {FAIL_CODES:g} codes -> {final}")
