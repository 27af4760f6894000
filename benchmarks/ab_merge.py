#!/usr/bin/env python
"""Same-run A/B timing of ``derender merge`` from two source trees (e.g. before and after a refactor).

Alternates the two trees run by run (A, B, A, B, ...) on the same bracket, each run a fresh
process (``python -m derender.cli merge``) with the tree's ``src`` first on ``PYTHONPATH``;
reports per method the median wall time, the median ratio B/A over the pairs (wall and CPU
time, the latter steadier on a shared machine) and the peak
RSS measured in the child itself (``runner._run_measured``). Outputs of the last runs are
compared (max relative difference of the radiance).

    python benchmarks/ab_merge.py --a /tmp/before/src --b src --bracket DIR \\
        --methods debevec,stabilized,probabilistic --model gp.npz --runs 3

A method may carry ``+align`` (``--align translation``) or ``+deghost`` (``--align translation
--deghost``), as in ``bench_merge.py``'s entries: ``--methods debevec,debevec+deghost``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from runner import _run_measured  # noqa: E402


def _cmd(entry: str, files: list[str], out: Path, model: str | None) -> list[str]:
    method, *extras = entry.split("+")
    cmd = [sys.executable, "-m", "derender.cli", "merge", *files, "-o", str(out / f"{entry}.exr"), "--method", method]
    for extra in extras:            # METHOD+align, METHOD+deghost: the engine's motion steps (as bench_merge.py)
        if extra == "align":
            cmd += ["--align", "translation"]
        elif extra == "deghost":
            cmd += ["--align", "translation", "--deghost"]
        else:
            raise SystemExit(f"unknown suffix +{extra} (use +align or +deghost)")
    if method in ("probabilistic", "stabilized-probabilistic"):
        if not model:
            raise SystemExit(f"--model is needed for {method}")
        cmd += ["-m", model]
        if method == "probabilistic":
            cmd += ["--variance", str(out / f"{method}-var.exr")]
    return cmd


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, help="source tree A (the folder holding the derender package)")
    ap.add_argument("--b", required=True, help="source tree B")
    ap.add_argument("--bracket", required=True, help="folder of JPEGs with EXIF times")
    ap.add_argument("--methods", default="debevec,stabilized,probabilistic")
    ap.add_argument("--model", default=None, help="de-rendering model (.npz) for the probabilistic methods")
    ap.add_argument("--runs", type=int, default=3, help="pairs of runs per method")
    ap.add_argument("--json", default=None, help="write the raw results here")
    args = ap.parse_args(argv)
    files = sorted(str(p) for p in Path(args.bracket).iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
    trees = {"A": str(Path(args.a).resolve()), "B": str(Path(args.b).resolve())}
    rows: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        outs = {k: Path(tmp) / k for k in trees}
        for d in outs.values():
            d.mkdir()
        for method in [m.strip() for m in args.methods.split(",") if m.strip()]:
            runs: dict = {"A": [], "B": []}
            for i in range(args.runs):
                for key in (("A", "B") if i % 2 == 0 else ("B", "A")):
                    env = {**os.environ, "PYTHONPATH": trees[key]}
                    r = _run_measured(_cmd(method, files, outs[key], args.model), env=env)
                    if r["returncode"] != 0:
                        raise SystemExit(f"{key} {method} failed: {r['stderr'][-500:]}")
                    runs[key].append(r)
                    print(f"{method} {key} run {i + 1}: {r['wall_s']:.2f} s, {r['peak_rss_mb']:.0f} MB",
                          file=sys.stderr, flush=True)
            import numpy as np

            from derender.io.exr import read_exr

            ra, rb = read_exr(outs["A"] / f"{method}.exr"), read_exr(outs["B"] / f"{method}.exr")
            scale = np.maximum(np.abs(ra).max(axis=-1, keepdims=True), 1e-30)
            rel = float(np.max(np.abs(rb.astype(np.float64) - ra) / scale))
            wa = [r["wall_s"] for r in runs["A"]]
            wb = [r["wall_s"] for r in runs["B"]]
            rows[method] = {
                "A_wall_s": wa, "B_wall_s": wb, "A_median_s": statistics.median(wa), "B_median_s": statistics.median(wb),
                "B_over_A_pairs": [b / a for a, b in zip(wa, wb)],
                "B_over_A_median": statistics.median([b / a for a, b in zip(wa, wb)]),
                "A_peak_mb": max(r["peak_rss_mb"] for r in runs["A"]),
                "B_peak_mb": max(r["peak_rss_mb"] for r in runs["B"]),
                "B_over_A_cpu_median": statistics.median([b["cpu_s"] / a["cpu_s"] for a, b in zip(runs["A"], runs["B"])]),
                "max_rel_diff": rel, "bit_identical": bool(np.array_equal(ra, rb)),
            }
    print("| method | A median s | B median s | B/A (median of pairs) | B/A CPU time | A peak MB | B peak MB | outputs |")
    print("|---|---|---|---|---|---|---|---|")
    for m, r in rows.items():
        same = "identical" if r["bit_identical"] else f"max rel diff {r['max_rel_diff']:.2g}"
        print(f"| {m} | {r['A_median_s']:.2f} | {r['B_median_s']:.2f} | {r['B_over_A_median']:.3f} | {r['B_over_A_cpu_median']:.3f} | "
              f"{r['A_peak_mb']:.0f} | {r['B_peak_mb']:.0f} | {same} |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
