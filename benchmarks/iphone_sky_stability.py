"""The iPhone sky's colour under the stabilised merge, across image sizes and alignments (issue 36 item 6).

Real bracket, no truth, nothing tuned on it. The *sky*: pixels the reference frame 3 sees unclipped
(every channel in 21-234) and frame 5 clips (every channel >= 250), as in docs/uncertainty.md.
Prints, per (size step, alignment): the merge's sky R/G and B/G (medians of the radiance ratios
over the sky), what frames 1-3 say the sky's B/G is through the merge's model
(:func:`derender.evaluation.rendering_change.frame_predictions`), the reference frame's
``ln L(226) - ln L(169)`` per channel, and how many of the curve fit's grid samples land in the sky.
Run: ``python benchmarks/iphone_sky_stability.py --steps 4 2 1 --align translation flow``; the
curve alone at grid seeds 0-3: ``--steps 4 2 --curve-only 0 1 2 3`` (with ``--set CURVE_SAMPLES=4096``,
``--set CURVE_OFFSET_PRIOR=1.0``, ``--bin-min 256`` or ``--options '{"exposure_rounds": 0}'``).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np


def run(step: int, align: str, method: str = "stabilized", options: dict | None = None) -> dict:
    from derender.core.types import Stack
    from derender.engine.motion.align import shift_into
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.rendering_change import frame_predictions
    from derender.hdr.registry import merge
    from derender.hdr.stabilize.curve_samples import CURVE_SAMPLES
    from derender.io.exif import file_times
    from derender.io.files import expand_image_paths
    from derender.io.images import read_codes
    from derender.response.curves import grid_positions

    root = Path(os.environ.get("DERENDER_SHARED_DATA", "../shared/data"))
    paths = expand_image_paths([root / "iphone6-bracket"])
    times = np.asarray(file_times(paths, None, None, False))
    frames = np.stack([read_codes(p)[::step, ::step] for p in paths])
    stack = Stack(images=frames.astype(np.float32) / 255.0, times=times)
    t0 = time.perf_counter()
    res = merge(stack, method, dict(options or {}), motion=MotionOptions(reference=2, align=align))
    sec = time.perf_counter() - t0
    shifts = res.info.get("alignment", {}).get("shifts")
    aligned = frames.copy()
    if align == "translation" and shifts is not None:
        for j, (dy, dx) in enumerate(shifts):
            shift_into(aligned[j], frames[j], int(dy), int(dx))
    sky = np.all((aligned[2] > 20) & (aligned[2] < 235), axis=-1) & np.all(aligned[4] >= 250, axis=-1)
    rad = np.asarray(res.radiance, dtype=np.float64)[sky]
    ok = np.all(rad > 0, axis=-1)
    rg = float(np.median(rad[ok, 0] / rad[ok, 1]))
    bg = float(np.median(rad[ok, 2] / rad[ok, 1]))
    row = {"step": step, "align": align, "method": method, "size": list(frames.shape[1:3]), "sky_fraction": float(sky.mean()),
           "R/G": rg, "B/G": bg, "seconds": round(sec, 1)}
    if align == "translation":
        pred = frame_predictions(res.plan, aligned, sky)
        row["frames_B/G"] = [float(np.exp(p[2] - p[1])) for p in pred[:3]]
        row["frames_spread_lnG"] = float(np.ptp(pred[:3, 1]))
    vals = np.asarray(res.plan.values[2], dtype=np.float64)
    row["ref_top_ln"] = [float(np.log(vals[226, c] / vals[169, c])) for c in range(3)]
    row["ref_mid_ln"] = [float(np.log(vals[169, c] / vals[100, c])) for c in range(3)]
    h, w = frames.shape[1:3]
    ys, xs = grid_positions(h, w, CURVE_SAMPLES, 0)
    s = sky[ys, xs]
    row["samples_in_sky"] = int(s.sum())
    hist = {}
    for j in range(3):
        z = aligned[j][ys[s], xs[s]]
        hist[f"frame{j + 1}"] = [int(((z[:, c] >= 170) & (z[:, c] <= 230)).sum()) for c in range(3)]
    row["sky_samples_codes_170_230"] = hist
    import derender.hdr.stabilize.curve_samples as curve_samples
    row["options"] = options or {}
    row["curve_bin_min"] = curve_samples.CURVE_BIN_MIN
    row["curve_samples_used"] = _find(res.info, "n_used")
    row["offsets"] = _find(res.info, "exposure_offsets")
    row["offsets_rejected"] = _find(res.info, "exposure_offsets_rejected")
    return row


def curve_only(step: int, seeds, exposure_rounds: int | None = None) -> dict:
    """The reference curve alone, without the H_j: frames registered by the stabilised merge
    (translation), then :func:`~derender.hdr.stabilize.filmic.unclipped_debevec` per grid seed; the
    median over the sky of ``exp(g_B(z_B) - g_G(z_G))`` at frame 3's codes, ``g_B(200) - g_B(169)``,
    ``g_B(226) - g_B(169)`` and blue's exposure offsets of frames 1-4 (docs/uncertainty.md table)."""
    from derender.core.types import Stack
    from derender.engine.motion.align import shift_into
    from derender.engine.motion.run import MotionOptions
    from derender.hdr.registry import merge
    from derender.hdr.stabilize import filmic
    from derender.io.exif import file_times
    from derender.io.files import expand_image_paths
    from derender.io.images import read_codes

    root = Path(os.environ.get("DERENDER_SHARED_DATA", "../shared/data"))
    paths = expand_image_paths([root / "iphone6-bracket"])
    times = np.asarray(file_times(paths, None, None, False))
    frames = np.stack([read_codes(p)[::step, ::step] for p in paths])
    res = merge(Stack(images=frames.astype(np.float32) / 255.0, times=times), "stabilized",
                motion=MotionOptions(reference=2, align="translation"))
    a = frames.copy()
    for j, (dy, dx) in enumerate(res.info["alignment"]["shifts"]):
        shift_into(a[j], frames[j], int(dy), int(dx))
    sky = np.all((a[2] > 20) & (a[2] < 235), axis=-1) & np.all(a[4] >= 250, axis=-1)
    z3 = a[2][sky].astype(int)
    out = []
    for seed in seeds:
        cur = filmic.unclipped_debevec(lambda j, ys, xs: a[j][ys, xs], a.shape[0], a.shape[1:3], times, seed=seed,
                                       exposure_rounds=exposure_rounds)
        g = cur.log_inverse
        out.append({"seed": seed, "B/G": float(np.median(np.exp(g[z3[:, 2], 2] - g[z3[:, 1], 1]))),
                    "gB200-gB169": float(g[200, 2] - g[169, 2]), "gB226-gB169": float(g[226, 2] - g[169, 2]),
                    "blue_offsets_1_4": np.asarray(cur.params["exposure_offsets"])[:4, 2].round(3).tolist(),
                    "samples": cur.params["n_used"]})
    return {"step": step, "curve_only": out}


def _find(d, key):
    """The first value of ``key`` in a nested dict/list (the curve fit's params sit inside ``info``)."""
    if isinstance(d, dict):
        if key in d:
            return d[key]
        vals = d.values()
    elif isinstance(d, (list, tuple)):
        vals = d
    else:
        return None
    for v in vals:
        r = _find(v, key)
        if r is not None:
            return r
    return None


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, nargs="+", default=[4, 2])
    ap.add_argument("--align", nargs="+", default=["translation"])
    ap.add_argument("--method", default="stabilized")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--options", default="{}", help="JSON options of the method, e.g. '{\"seed\": 1}'")
    ap.add_argument("--bin-min", type=int, default=None,
                    help="derender.hdr.stabilize.curve_samples.CURVE_BIN_MIN for this run (code-stratified curve samples)")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE",
                    help="set constants of derender.hdr.stabilize.filmic (or .curve_samples) for this run, "
                         "e.g. CURVE_SAMPLES=4096")
    ap.add_argument("--curve-only", type=int, nargs="*", metavar="SEED",
                    help="only the reference curve, at these grid seeds (function curve_only)")
    a = ap.parse_args()
    if a.set:
        import derender.hdr.stabilize.curve_samples as curve_samples
        import derender.hdr.stabilize.filmic as filmic
        for item in a.set:
            name, value = item.split("=", 1)
            setattr(curve_samples if hasattr(curve_samples, name) else filmic, name,
                    float(value) if "." in value else int(value))
    if a.curve_only:
        opts = json.loads(a.options)
        for st in a.steps:
            print(json.dumps(curve_only(st, a.curve_only, opts.get("exposure_rounds"))), flush=True)
        raise SystemExit(0)
    if a.bin_min is not None:
        import derender.hdr.stabilize.curve_samples as curve_samples
        curve_samples.CURVE_BIN_MIN = a.bin_min
    rows = []
    for al in a.align:
        for st in a.steps:
            r = run(st, al, a.method, json.loads(a.options))
            rows.append(r)
            print(json.dumps(r), flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
