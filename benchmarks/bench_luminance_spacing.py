"""Luminance that does not depend on the bracket (issue 36, "Done when"): every 8-bit method on the
luminance family's fixed gamma-2.2 rendering (a tuning rendering) at 1, 1.5 and 2 EV (16 stops
covered: 17, 12, 9 frames), for several cameras, two scenes, a white at 255 and one drawn in
250..254, plain and with ``--deghost``; each map scaled on the grey card's spot
(:func:`derender.evaluation.linearity.spacing_rows`)::

    python benchmarks/bench_luminance_spacing.py --jsonl /tmp/spacing.jsonl
    python benchmarks/bench_luminance_spacing.py --table /tmp/spacing.jsonl

Rows are appended to ``--jsonl`` as they come (a rerun skips the rows already there). ``--table``
prints, per method, white and deghost: the largest median abs error, the worst decade ratio (the
one farthest from 1) and the brightest 1 % range over the grid, and a line per camera. The line is
a median <= 3 % and every decade within +-5 %. Results: docs/results-luminance.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _key(r: dict) -> tuple:
    return (r["camera"], float(r["stops"]), int(r["seed"]), r["white"], r["method"], bool(r["deghost"]))


def run(args) -> None:
    from derender.evaluation.linearity import spacing_rows

    path = Path(args.jsonl)
    done = set()
    if path.exists():
        done = {_key(json.loads(line)) for line in path.read_text().splitlines() if line.strip()}
    split = lambda s: [v.strip() for v in s.split(",") if v.strip()]
    for cam in split(args.cameras):
        for ev in [float(v) for v in split(args.stops)]:
            for seed in [int(v) for v in split(args.seeds)]:
                for white in split(args.whites):
                    flags = (False, True) if args.deghost == "both" else (args.deghost == "only",)
                    todo = [m for m in split(args.methods)
                            if any((cam, ev, seed, white, m, dg) not in done for dg in flags)]
                    if not todo:
                        continue
                    for row in spacing_rows([cam], [ev], [seed], [white], todo, flags,
                                            progress=lambda s: print(s, file=sys.stderr, flush=True)):
                        with path.open("a") as f:
                            f.write(json.dumps(row, default=float) + "\n")


def worst_decade(decades) -> float:
    d = np.asarray(decades, float)
    d = d[np.isfinite(d)]
    return float(d[np.argmax(np.abs(d - 1.0))])


def table(path: str) -> str:
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    out = ["| method | white | deghost | brackets | median abs err (max) | worst decade | decades outside ±5 % | "
           "brightest 1 % | meets the line |", "| --- | --- | --- | ---: | ---: | ---: | ---: | --- | --- |"]
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["method"], r["white"], r["deghost"]), []).append(r)
    order = ["debevec", "robertson", "stabilized", "stabilized-joint"]
    for (m, white, dg), rs in sorted(groups.items(), key=lambda kv: (order.index(kv[0][0]) if kv[0][0] in order else 9,
                                                                      kv[0][1] != "255", kv[0][2])):
        med = max(r["median_abs"] for r in rs)
        worst = [worst_decade(r["decades"]) for r in rs]
        w = worst[int(np.argmax(np.abs(np.asarray(worst) - 1.0)))]
        outside = sum(int(np.sum(np.abs(np.asarray(r["decades"], float) - 1.0) > 0.05)) for r in rs)
        tops = [r["top"] for r in rs]
        ok = sum(1 for r in rs if r["median_abs"] <= 0.03 and np.all(np.abs(np.asarray(r["decades"]) - 1.0) <= 0.05))
        out.append(f"| {m} | {white} | {'yes' if dg else 'no'} | {len(rs)} | {100 * med:.1f} % | {w:.3f} | "
                   f"{outside} of {6 * len(rs)} | {min(tops):.3f}-{max(tops):.3f} | {ok} of {len(rs)} |")
    out.append("")
    out.append("| camera | EV | scene | white | " + " | ".join(order) + " |")
    out.append("| --- | ---: | ---: | --- | " + " | ".join("---" for _ in order) + " |")
    cells: dict = {}
    for r in rows:
        cells.setdefault((r["camera"], r["stops"], r["seed"], r["white"]), {})[(r["method"], r["deghost"])] = r
    for (cam, ev, seed, white), c in cells.items():
        txt = []
        for m in order:
            p, d = c.get((m, False)), c.get((m, True))
            if p is None:
                txt.append("-")
                continue
            s = f"{100 * p['median_abs']:.1f} % {worst_decade(p['decades']):.3f} {p['top']:.3f}"
            if d is not None:
                s += f" / {100 * d['median_abs']:.1f} % {worst_decade(d['decades']):.3f} {d['top']:.3f}"
            txt.append(s)
        out.append(f"| {cam} | {ev:g} | {seed} | {white} | " + " | ".join(txt) + " |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jsonl", default="spacing.jsonl")
    ap.add_argument("--cameras", default="nikon-d5100,canon-eos-5d-mark-iii,sony-ilce-7m3,fujifilm-x-t3")
    ap.add_argument("--stops", default="1,1.5,2")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--whites", default="255,250-254")
    ap.add_argument("--methods", default="debevec,robertson,stabilized,stabilized-joint")
    ap.add_argument("--deghost", choices=("both", "plain", "only"), default="both",
                    help="Merge plain and with --deghost (both), or one of them.")
    ap.add_argument("--table", metavar="JSONL", help="Print the tables of a finished run and exit.")
    args = ap.parse_args()
    if args.table:
        print(table(args.table))
        return
    run(args)
    print(table(args.jsonl))


if __name__ == "__main__":
    main()
