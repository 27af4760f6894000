"""Dataset benchmark reproducing paper 1's Table 1 on simulated (or real) brackets.

A *dataset* is a folder of scenes; each scene folder holds ``raw/`` (DNG/RAW frames) and
``jpeg/`` (rendered frames of the same bracket), optionally ``truth.exr`` and
``scene.json`` (simulated scenes). For every scene the benchmark builds the ground truth
from the RAW frames (:func:`derender.groundtruth.raw_ground_truth`, paper 1 Sec. 4.2,
Algorithm 2), merges the JPEG bracket with every merge method, and scores PSNR on R, G, B
and luminance L (:func:`derender.evaluation.metrics.psnr_rgbl`: least-squares scale, peak = max of
the ground truth). The table reports means over scenes and, per method, the share of
scenes in which it beats the baseline (``debevec``) on at least 3 of the 4 planes.

Scenes run in parallel on Dask (``dask.distributed``): a local cluster by default, any
scheduler by address, or ``scheduler="serial"``. Each scene is independent and
deterministic, and results are sorted by scene name, so all three give identical tables.
"""

from __future__ import annotations

import csv
import inspect
import io as _io
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from derender.camera.spectral import camera_search_dirs
from derender.core.errors import InputError
from derender.core.types import Stack
from derender.hdr.registry import merge_seeded

__all__ = [
    "DEFAULT_DATASET_CAMERAS",
    "PLANES",
    "default_methods",
    "resolve_cameras",
    "simulate_dataset",
    "list_scenes",
    "evaluate_scene",
    "BenchmarkResult",
    "run_benchmark",
    "write_benchmark_outputs",
    "fusion_gain",
]


#: Cameras of the default simulated dataset: rawtoaces measurements (when the shared data
#: folder is present) plus colour-science's built-in NPL measurement.
DEFAULT_DATASET_CAMERAS = (
    "nikon-d5100",
    "canon-eos-5d-mark-ii",
    "sony-ilce-7m3",
    "canon-powershot-s90",
    "fujifilm-x-t3",
    "panasonic-dc-gx9",
)


#: Paper 1 used 10 outdoor, 6 indoor and 2 night scenes.
_KIND_CYCLE = ("outdoor",) * 10 + ("indoor",) * 6 + ("night",) * 2


#: Planes scored by the HDR PSNR protocol: the three channels and Rec. 709 luminance.
PLANES = ("R", "G", "B", "L")


def default_methods() -> list[str]:
    """Registered merge methods of rendered images that need no extra input (e.g. no de-rendering
    model; the RAW method merges the RAW frames, not the images)."""
    from derender.hdr.registry import METHODS

    out = []
    for name, spec in sorted(METHODS.items()):
        if spec.inputs != "rendered":
            continue
        params = list(inspect.signature(spec.load()).parameters.values())[1:]
        if any(p.default is inspect.Parameter.empty and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
               for p in params):
            continue
        out.append(name)
    if "debevec" in out:  # baseline first
        out.remove("debevec")
        out.insert(0, "debevec")
    return out


def resolve_cameras(names: Sequence[str] | None, search_dirs: Sequence[str | os.PathLike] = ()) -> list:
    """Load cameras by name; with ``names=None`` the default list, skipping those not found."""
    from derender.camera.spectral import load_camera

    dirs = camera_search_dirs(search_dirs)
    if names:
        return [load_camera(n, search_dirs=dirs) for n in names]
    cams = []
    for n in DEFAULT_DATASET_CAMERAS:
        try:
            cams.append(load_camera(n, search_dirs=dirs))
        except InputError:
            continue
    return cams


def simulate_dataset(outdir: str | os.PathLike, *, scenes: int = 18, exposures: int = 9,
                     cameras: Sequence[str] | None = None, size: tuple[int, int] = (384, 256),
                     pipelines: Sequence[str] = ("auto", "fixed"), styles: Sequence[str] = ("camera",),
                     seed: int = 0, progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Write ``scenes`` simulated brackets to ``outdir/scene-NN-<kind>-<camera>-<pipeline>/``.

    Scene kinds follow paper 1's mix (10 outdoor, 6 indoor, 2 night, cycled); cameras,
    pipelines and styles are cycled so every combination appears; scene ``i`` uses seed
    ``seed * 1000 + i``.
    """
    from derender.camera import simulate_bracket, write_bracket

    if scenes < 1:
        raise InputError("--scenes must be at least 1")
    cams = resolve_cameras(cameras)
    if not cams:
        raise InputError("no camera available for the dataset")
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    for i in range(scenes):
        kind = _KIND_CYCLE[i % len(_KIND_CYCLE)]
        cam = cams[i % len(cams)]
        pipeline = pipelines[i % len(pipelines)]
        style = styles[(i // len(pipelines)) % len(styles)]
        name = f"scene-{i:02d}-{kind}-{cam.name}-{pipeline}-{style}"
        b = simulate_bracket(camera=cam, kind=kind, size=size, exposures=exposures, pipeline=pipeline,
                             style=style, seed=seed * 1000 + i)
        params = write_bracket(b, outdir / name)
        written.append({"scene": name, "camera": cam.name, "kind": kind, "pipeline": pipeline, "style": style,
                        "seed": params["seed"]})
        if progress is not None:
            progress(i + 1, scenes)
    with open(outdir / "dataset.json", "w", encoding="utf-8") as fh:
        json.dump({"scenes": written, "exposures": exposures, "size": list(size)}, fh, indent=2)
    return written


def list_scenes(dataset_dir: str | os.PathLike) -> list[Path]:
    """Scene folders (those with both ``raw/`` and ``jpeg/``), sorted by name."""
    d = Path(dataset_dir)
    if not d.is_dir():
        raise InputError(f"no such dataset folder: {d}")
    scenes = sorted(p for p in d.iterdir() if (p / "raw").is_dir() and (p / "jpeg").is_dir())
    if not scenes:
        raise InputError(f"{d} holds no scene folders with raw/ and jpeg/ (see 'derender simulate-dataset')")
    return scenes


def _scene_files(scene_dir: Path) -> tuple[list[Path], list[Path]]:
    from derender.io.files import RASTER_SUFFIXES, RAW_SUFFIXES

    raws = sorted(p for p in (scene_dir / "raw").iterdir() if p.suffix.lower() in RAW_SUFFIXES)
    jpgs = sorted(p for p in (scene_dir / "jpeg").iterdir() if p.suffix.lower() in RASTER_SUFFIXES)
    if not raws or len(jpgs) < 2:
        raise InputError(f"{scene_dir}: needs RAW frames in raw/ and at least two images in jpeg/")
    return raws, jpgs


def evaluate_scene(scene_dir: str | os.PathLike, methods: Sequence[str], seed: int = 0) -> dict:
    """Ground truth from RAW, every method on the JPEGs, PSNR R/G/B/L of each against it."""
    from derender.evaluation.metrics import psnr_rgbl
    from derender.io.exr import read_exr
    from derender.io.images import read_stack
    from derender.io.raw import read_raw_stack
    from derender.raw.groundtruth import raw_ground_truth
    scene_dir = Path(scene_dir)
    raws, jpgs = _scene_files(scene_dir)
    t0 = time.perf_counter()
    gt = raw_ground_truth(read_raw_stack(raws)).radiance
    row: dict = {"scene": scene_dir.name, "gt_seconds": time.perf_counter() - t0, "methods": {}}
    truth_path = scene_dir / "truth.exr"
    if truth_path.is_file():
        row["gt_vs_truth"] = psnr_rgbl(gt, read_exr(truth_path))
    stack = read_stack(jpgs)
    for m in methods:
        t0 = time.perf_counter()
        result = merge_seeded(stack, m, seed)
        dt = time.perf_counter() - t0
        row["methods"][m] = {**psnr_rgbl(result.radiance, gt), "seconds": dt}
    return row


@dataclass
class BenchmarkResult:
    """Per-scene scores and their summary."""

    rows: list[dict]
    methods: list[str]
    baseline: str = "debevec"
    info: dict = field(default_factory=dict)

    def mean_table(self) -> dict[str, dict[str, float]]:
        return {m: {p: float(np.mean([r["methods"][m][p] for r in self.rows])) for p in (*PLANES, "seconds")}
                for m in self.methods}

    def win_share(self, method: str, min_planes: int = 3) -> float:
        """Share of scenes where ``method`` beats the baseline on >= ``min_planes`` of R, G, B, L."""
        if method == self.baseline or self.baseline not in self.methods:
            return float("nan")
        wins = 0
        for r in self.rows:
            better = sum(r["methods"][method][p] > r["methods"][self.baseline][p] for p in PLANES)
            wins += better >= min_planes
        return wins / len(self.rows)

    def markdown(self) -> str:
        table = self.mean_table()
        lines = [f"PSNR (dB) against RAW ground truth, mean over {len(self.rows)} scenes",
                 "", "| method | R | G | B | L | wins on >=3 of 4 vs " + self.baseline + " | s/scene |",
                 "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for m in self.methods:
            t = table[m]
            share = self.win_share(m)
            share_s = "-" if np.isnan(share) else f"{100 * share:.0f} %"
            lines.append(f"| {m} | {t['R']:.2f} | {t['G']:.2f} | {t['B']:.2f} | {t['L']:.2f} | {share_s} | "
                         f"{t['seconds']:.2f} |")
        gts = [r["gt_vs_truth"]["L"] for r in self.rows if "gt_vs_truth" in r]
        if gts:
            lines += ["", f"RAW ground truth vs simulator truth: PSNR L mean {np.mean(gts):.2f} dB, "
                          f"min {np.min(gts):.2f} dB"]
        return "\n".join(lines) + "\n"

    def csv(self) -> str:
        buf = _io.StringIO()
        w = csv.writer(buf)
        w.writerow(["scene", "method", *PLANES, "seconds"])
        for r in self.rows:
            for m in self.methods:
                s = r["methods"][m]
                w.writerow([r["scene"], m, *(f"{s[p]:.4f}" for p in PLANES), f"{s['seconds']:.3f}"])
        return buf.getvalue()

    def to_json(self) -> dict:
        return {"methods": self.methods, "baseline": self.baseline, "scenes": self.rows,
                "mean": self.mean_table(),
                "win_share_3of4": {m: (None if np.isnan(v) else v) for m in self.methods if m != self.baseline
                                   for v in [self.win_share(m)]},
                "info": self.info}


def run_benchmark(dataset_dir: str | os.PathLike, methods: Sequence[str] | None = None,
                  scheduler: str | None = "local", workers: int = 2, seed: int = 0,
                  progress: Callable[[int, int], None] | None = None) -> BenchmarkResult:
    """Evaluate every scene of a dataset with every method (``scheduler="serial"`` for no Dask)."""
    scenes = list_scenes(dataset_dir)
    methods = list(methods) if methods else default_methods()
    from derender.hdr.registry import METHODS

    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {', '.join(unknown)}; known: {', '.join(sorted(METHODS))}")
    from derender.core.parallel import run_tasks

    t0 = time.perf_counter()
    rows = run_tasks(evaluate_scene, [(str(s), methods, seed) for s in scenes], scheduler=scheduler,
                     workers=workers, progress=progress)
    rows.sort(key=lambda r: r["scene"])
    return BenchmarkResult(rows=rows, methods=methods,
                           info={"dataset": str(dataset_dir), "scheduler": scheduler or "local",
                                 "workers": workers, "wall_seconds": time.perf_counter() - t0})


def write_benchmark_outputs(result: BenchmarkResult, outdir: str | os.PathLike) -> dict[str, Path]:
    """Write ``table.md``, ``scenes.csv`` and ``results.json`` atomically into ``outdir``."""
    from derender.io.files import atomic_output

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    files = {"table": outdir / "table.md", "csv": outdir / "scenes.csv", "json": outdir / "results.json"}
    payloads = {"table": result.markdown(), "csv": result.csv(),
                "json": json.dumps(result.to_json(), indent=2, default=float) + "\n"}
    for key, path in files.items():
        with atomic_output(path) as tmp:
            Path(tmp).write_text(payloads[key], encoding="utf-8")
    return files


def fusion_gain(styles: Sequence[str] = ("simple", "camera"), *, kinds: Sequence[str] = ("outdoor", "indoor", "night"),
                seeds: Sequence[int] = (0, 1, 2), size: tuple[int, int] = (192, 128), pipeline: str = "auto",
                methods: Sequence[str] = ("stabilized",), camera: str = "nikon-d5100", exposures: int = 9,
                progress: Callable[[str], None] | None = None) -> list[dict]:
    """Paper 1's comparison on simulated brackets held in memory: PSNR (R, G, B, L against
    the simulator's exact radiance, :func:`derender.evaluation.metrics.psnr_rgbl`) of each method
    minus that of ``debevec``, per scene (rows with ``scene`` set) and as the mean over the
    scenes of each rendering style (rows with ``scene="mean"``, plus ``wins``: the share of
    scenes won on >= 3 of the 4 planes). The acceptance figures come from the default
    (auto pipeline, 3 scene kinds x seeds 0-2, 192x128, 9 exposures)."""
    from derender.camera import simulate_bracket
    from derender.core.types import Stack
    from derender.evaluation.metrics import psnr_rgbl

    planes = ("R", "G", "B", "L")
    rows: list[dict] = []
    for style in styles:
        per: dict[str, list] = {m: [] for m in methods}
        for kind in kinds:
            for seed in seeds:
                b = simulate_bracket(camera, kind=kind, size=size, exposures=exposures, pipeline=pipeline,
                                     style=style, seed=int(seed))
                st = Stack(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
                base = psnr_rgbl(merge_seeded(st, "debevec"), b.truth_linear_srgb)
                for m in methods:
                    sc = psnr_rgbl(merge_seeded(st, m, int(seed)), b.truth_linear_srgb)
                    d = {c: sc[c] - base[c] for c in planes}
                    per[m].append(d)
                    rows.append({"style": style, "scene": f"{kind}-{seed}", "method": m,
                                 "debevec_L": base["L"], **{f"d{c}": d[c] for c in planes}})
                    if progress is not None:
                        progress(f"{style} {kind}-{seed} {m}: " + " ".join(f"{c} {d[c]:+.2f}" for c in planes))
        for m in methods:
            ds = per[m]
            rows.append({"style": style, "scene": "mean", "method": m,
                         "debevec_L": float("nan"),
                         **{f"d{c}": float(np.mean([d[c] for d in ds])) for c in planes},
                         "wins": float(np.mean([sum(d[c] > 0 for c in planes) >= 3 for d in ds]))})
    return rows


def reference_spread(stack: Stack, truth_linear_srgb: np.ndarray, method: str = "stabilized",
                     references: Sequence[int] | None = None, options: Any = None) -> dict:
    """PSNR (R, G, B, L; :func:`derender.evaluation.metrics.psnr_rgbl`) of ``method`` (its
    ``options``) for every reference in ``references`` (default
    :func:`derender.engine.motion.reference_frame.reasonable_references`; the engine's
    :class:`~derender.engine.motion.run.MotionOptions`) and the spread (max - min) of each
    plane over them (paper 1, Fig. 5)."""
    from derender.engine.motion.reference_frame import reasonable_references
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.metrics import psnr_rgbl
    from derender.hdr.registry import merge

    refs = reasonable_references(stack.images) if references is None else [int(r) for r in references]
    if not refs:
        raise InputError("no reference images to compare")
    scores = {}
    for r in refs:
        res = merge(stack, method, options, motion=MotionOptions(reference=r))
        scores[r] = psnr_rgbl(res.radiance, truth_linear_srgb)
    spread = {c: float(max(s[c] for s in scores.values()) - min(s[c] for s in scores.values())) for c in "RGBL"}
    return {"method": method, "references": refs, "psnr": scores, "spread": spread}
