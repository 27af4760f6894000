"""The demo job of ``derender demo``: simulate an auto-pipeline bracket, merge it with every method,
score each against the exact scene radiance.

The simulator (:func:`derender.camera.bracket.simulate_bracket`) writes real DNG and JPEG
files and the exact truth (``truth.exr``); the RAW ground truth of paper 1 (Alg. 2,
:func:`derender.raw.groundtruth.raw_ground_truth`) and every merge method that needs no
extra input are scored with the PSNR protocol (:func:`derender.evaluation.metrics.psnr_rgbl`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

__all__ = ["run_demo"]


def run_demo(outdir: str | Path, size: tuple[int, int] = (480, 320), seed: int = 0, exposures: int = 9,
             pipeline: str = "auto", render: str = "camera",
             progress: Callable[[str, int, int], None] | None = None) -> list[dict]:
    """Run the demo into ``outdir``; one row per method: ``{"method", "R", "G", "B", "L", "seconds"}``.

    Writes the bracket (``raw/``, ``jpeg/``, ``truth.exr``, ``scene.json``), each merge as
    ``merge-METHOD.exr`` with a PNG preview, and ``scores.json``. ``progress(stage, done,
    total)`` is called as the simulation and the merges advance.
    """
    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.evaluation.metrics import psnr_rgbl
    from derender.evaluation.table1 import default_methods
    from derender.hdr.registry import merge_seeded
    from derender.io.exr import read_exr, write_exr
    from derender.io.images import read_stack
    from derender.io.preview import write_preview
    from derender.io.raw import read_raw_stack
    from derender.raw.groundtruth import raw_ground_truth

    report = progress or (lambda stage, done, total: None)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    bracket = simulate_bracket(kind="outdoor", size=size, exposures=exposures, pipeline=pipeline, style=render,
                               seed=seed, progress=lambda i, n: report("simulating bracket", i, n))
    write_bracket(bracket, outdir)
    truth = read_exr(outdir / "truth.exr")
    write_preview(outdir / "truth.png", truth)
    stack = read_stack(bracket_paths(outdir, "jpeg"))
    methods = default_methods()
    total = len(methods) + 1
    report("merging", 0, total)
    t0 = time.perf_counter()
    gt = raw_ground_truth(read_raw_stack(bracket_paths(outdir, "raw")))
    rows: list[dict] = [{"method": "raw-groundtruth (DNG)", **psnr_rgbl(gt.radiance, truth),
                         "seconds": time.perf_counter() - t0}]
    write_exr(outdir / "groundtruth-from-raw.exr", gt.radiance)
    report("merging", 1, total)
    for k, name in enumerate(methods, start=2):
        t0 = time.perf_counter()
        result = merge_seeded(stack, name, seed)
        dt = time.perf_counter() - t0
        write_exr(outdir / f"merge-{name}.exr", result.radiance)
        write_preview(outdir / f"merge-{name}.png", result.radiance)
        rows.append({"method": name, **psnr_rgbl(result.radiance, truth), "seconds": dt})
        report("merging", k, total)
    with open(outdir / "scores.json", "w", encoding="utf-8") as fh:
        json.dump(rows, fh, indent=2)
    return rows
