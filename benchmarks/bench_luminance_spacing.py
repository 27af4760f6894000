"""Luminance that does not depend on the bracket (issue 36, "Done when"): every 8-bit method on the
luminance family's fixed gamma-2.2 rendering (a tuning rendering) at 1, 1.5 and 2 EV (16 stops
covered: 17, 12, 9 frames), for several cameras, two scenes, a white at 255 and one drawn in
250..254, plain and with ``--deghost``; each map scaled on the grey card's spot
(:func:`derender.evaluation.linearity.spacing_rows`)::

    python benchmarks/bench_luminance_spacing.py --jsonl /tmp/spacing.jsonl
    python benchmarks/bench_luminance_spacing.py --table /tmp/spacing.jsonl

Rows are appended to ``--jsonl`` as they come (a rerun skips the rows already there). ``--table``
prints, per method and white: the largest median abs error, the worst decade ratio (the one
farthest from 1), the brightest 1 % range over the grid and how many brackets meet the line, plain
and with ``--deghost``; then one line per bracket (plain merges). The line is
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


def load_rows(paths: str) -> list[dict]:
    """Rows of one or more JSONL files (comma separated); a later file's row replaces an earlier
    one with the same camera, spacing, scene, white, method and deghost flag."""
    rows: dict = {}
    for path in paths.split(","):
        for line in Path(path).read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                rows[_key(r)] = r
    return list(rows.values())


def _meets(r: dict) -> bool:
    return r["median_abs"] <= 0.03 and bool(np.all(np.abs(np.asarray(r["decades"], float) - 1.0) <= 0.05))


def _figures(r: dict) -> np.ndarray:
    return np.array([r["median_abs"], *r["decades"], r["top"]], float)


ORDER = ("debevec", "robertson", "stabilized", "stabilized-joint")


def table(paths: str) -> str:
    rows = load_rows(paths)
    plain = {_key(r)[:5]: r for r in rows if not r["deghost"]}
    dgh = {_key(r)[:5]: r for r in rows if r["deghost"]}
    out = ["| method | white | brackets | median abs err (largest) | worst decade | decades outside ±5 % | "
           "brightest 1 % | meets the line | `--deghost`: meets / largest change of a figure |",
           "| --- | --- | ---: | ---: | ---: | ---: | --- | --- | --- |"]
    for m in ORDER:
        for white in ("255", "250-254"):
            rs = [r for k, r in plain.items() if k[4] == m and k[3] == white]
            if not rs:
                continue
            worst = [worst_decade(r["decades"]) for r in rs]
            w = worst[int(np.argmax(np.abs(np.asarray(worst) - 1.0)))]
            outside = sum(int(np.sum(np.abs(np.asarray(r["decades"], float) - 1.0) > 0.05)) for r in rs)
            tops = [r["top"] for r in rs]
            pairs = [(r, dgh[_key(r)[:5]]) for r in rs if _key(r)[:5] in dgh]
            if pairs:
                change = max(float(np.max(np.abs(_figures(a) - _figures(b)))) for a, b in pairs)
                dg = f"{sum(_meets(b) for _, b in pairs)} of {len(pairs)} / {change:.4f}"
            else:
                dg = "not run"
            out.append(f"| {m} | {white} | {len(rs)} | {100 * max(r['median_abs'] for r in rs):.1f} % | {w:.3f} | "
                       f"{outside} of {6 * len(rs)} | {min(tops):.3f}-{max(tops):.3f} | "
                       f"{sum(_meets(r) for r in rs)} of {len(rs)} | {dg} |")
    out.append("")
    out.append("| camera | EV | scene | white | " + " | ".join(ORDER) + " |")
    out.append("| --- | ---: | ---: | --- | " + " | ".join("---" for _ in ORDER) + " |")
    cells: dict = {}
    for k, r in plain.items():
        cells.setdefault(k[:4], {})[k[4]] = r
    for (cam, ev, seed, white), c in sorted(cells.items(), key=lambda kv: (kv[0][3] != "255",) + kv[0][:3]):
        txt = []
        for m in ORDER:
            r = c.get(m)
            if r is None:
                txt.append("-")
                continue
            mark = "" if _meets(r) else " **miss**"
            txt.append(f"{100 * r['median_abs']:.1f} %; {worst_decade(r['decades']):.3f}; {r['top']:.3f}{mark}")
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
    ap.add_argument("--table", metavar="JSONL[,JSONL...]",
                    help="Print the tables of finished runs and exit (a later file's rows replace an earlier one's).")
    args = ap.parse_args()
    if args.table:
        print(table(args.table))
        return
    run(args)
    print(table(args.jsonl))


if __name__ == "__main__":
    main()
