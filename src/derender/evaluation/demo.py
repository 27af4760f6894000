"""The demo job of ``derender demo``: simulate an auto-pipeline bracket, merge it with every method,
score each against the exact scene radiance.

The simulator (:func:`derender.camera.bracket.simulate_bracket`) writes real DNG and JPEG
files and the exact truth (``truth.exr``); the RAW ground truth of paper 1 (Alg. 2,
:func:`derender.raw.groundtruth.raw_ground_truth`), every merge method of the JPEG frames
and the ``raw`` method on the DNG frames (:mod:`derender.raw.optimal`) are scored with
the PSNR protocol (:func:`derender.evaluation.metrics.psnr_rgbl`). The two methods of paper
2 need a de-rendering model of the camera: the demo makes one as a user would, from paper 2's
calibration session of the same simulated camera (:func:`derender.camera.chart.chart_pairs`,
16 illuminants x 22 exposures of a ColorChecker SG, rendered in the bracket's picture style)
and a local GP fitted on 5000 of its pairs (saved as ``model-gp.npz``). That session renders
every shot with one fixed white balance, as paper 2 assumes; the demo's bracket changes white
balance and gain between frames (``pipeline="auto"``), which the model does not describe, so
the probabilistic rows also show what that assumption costs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

__all__ = ["run_demo", "MODEL_METHODS", "DEMO_TRAIN_PAIRS"]


#: Methods of paper 2 the demo runs with the model it calibrates (the others need no model).
MODEL_METHODS = ("probabilistic", "stabilized-probabilistic")

#: Training pairs of the demo's GP (``derender calibrate``'s default ``--n-train``).
DEMO_TRAIN_PAIRS = 5000


def run_demo(outdir: str | Path, size: tuple[int, int] = (480, 320), seed: int = 0, exposures: int = 9,
             pipeline: str = "auto", render: str = "camera",
             progress: Callable[[str, int, int], None] | None = None, with_model: bool = True) -> list[dict]:
    """Run the demo into ``outdir``; one row per method: ``{"method", "R", "G", "B", "L", "seconds"}``.

    Writes the bracket (``raw/``, ``jpeg/``, ``truth.exr``, ``scene.json``), each merge as
    ``merge-METHOD.exr`` with a PNG preview, and ``scores.json``. ``with_model`` (default):
    also calibrate a GP on the simulated chart session of the same camera (``model-gp.npz``;
    the first of them carries ``calibration_seconds``) and run :data:`MODEL_METHODS` with it.
    ``progress(stage, done, total)`` is called as the simulation and the merges advance.
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
    methods = default_methods() + (list(MODEL_METHODS) if with_model else []) + ["raw"]
    total = len(methods) + 1
    report("merging", 0, total)
    t0 = time.perf_counter()
    raw_frames = read_raw_stack(bracket_paths(outdir, "raw"))
    gt = raw_ground_truth(raw_frames)
    rows: list[dict] = [{"method": "raw-groundtruth (DNG)", **psnr_rgbl(gt.radiance, truth),
                         "seconds": time.perf_counter() - t0}]
    write_exr(outdir / "groundtruth-from-raw.exr", gt.radiance)
    report("merging", 1, total)
    model, model_seconds = None, 0.0
    for k, name in enumerate(methods, start=2):
        t0 = time.perf_counter()
        options = {}
        if name in MODEL_METHODS:
            if model is None:
                report("calibrating a GP on the simulated chart", 0, 1)
                model = _demo_model(bracket.camera, render, seed)
                model.save(outdir / "model-gp.npz")
                model_seconds = time.perf_counter() - t0
                report("calibrating a GP on the simulated chart", 1, 1)
            options["model"] = model
        result = merge_seeded(raw_frames if name == "raw" else stack, name, seed, options)
        dt = time.perf_counter() - t0 if name != MODEL_METHODS[0] else time.perf_counter() - t0 - model_seconds
        write_exr(outdir / f"merge-{name}.exr", result.radiance)
        write_preview(outdir / f"merge-{name}.png", result.radiance)
        row = {"method": name, **psnr_rgbl(result.radiance, truth), "seconds": dt}
        if name == MODEL_METHODS[0]:
            row["calibration_seconds"] = model_seconds
        rows.append(row)
        report("merging", k, total)
    with open(outdir / "scores.json", "w", encoding="utf-8") as fh:
        json.dump(rows, fh, indent=2)
    return rows


def _demo_model(camera, render: str, seed: int):
    """Paper 2's calibration as ``derender chart-pairs`` + ``derender calibrate --method gp`` do it."""
    import numpy as np

    from derender.camera.chart import chart_pairs
    from derender.derendering.base import fit_model, model_metadata

    pairs = chart_pairs(camera, style="simple" if render == "simple" else "camera", seed=seed)
    rng = np.random.default_rng(seed)
    sel = rng.choice(pairs.jpeg.shape[0], size=min(DEMO_TRAIN_PAIRS, pairs.jpeg.shape[0]), replace=False)
    model = fit_model("gp", pairs.jpeg[sel], pairs.raw[sel], seed=seed, n_train=DEMO_TRAIN_PAIRS)
    model.metadata.update(model_metadata(pairs))
    return model
