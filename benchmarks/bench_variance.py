#!/usr/bin/env python
"""What ``--variance`` costs the classic and stabilised merges, apart from writing its EXR.

In one process, on a bracket of JPEGs (default: the 9 x 24 MP bracket of ``bench_merge.py``),
runs ``merge_files(paths, method=M)`` and ``merge_files(paths, method=M, variance=True)``
(outputs held in memory, nothing written) in alternating pairs (plain, variance; then
variance, plain; ...) after one warm-up run each, and reports per configuration the median
wall time and CPU time (``time.process_time``: every thread of the process, so other jobs on
a shared machine count less) of the whole merge and of the compiled kernel calls alone
(the kernels are wrapped by timers; the edge term's CPU also counts numba's worker threads
spinning after the kernel, measured alone it is ~0.2 s per 24 MP), and the median pair ratios.
The radiance of the last two runs is compared byte for byte.

``--cli``: instead, ``derender merge BRACKET -o out.exr --method M`` against the same with
``--variance var.exr`` (the second EXR written too), each a fresh process, in alternating
pairs; wall and CPU time (``wait4``) of the whole command.

    python benchmarks/bench_variance.py --methods debevec,stabilized --pairs 3
    python benchmarks/bench_variance.py --cli --methods debevec,stabilized --pairs 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from derender.engine.options import EngineOptions


class _Timer:
    def __init__(self) -> None:
        self.wall = 0.0
        self.cpu = 0.0
        self.edge_cpu = 0.0

    def wrap(self, fn, edge: bool = False):
        def timed(*a, **k):
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                self.wall += time.perf_counter() - w0
                dc = time.process_time() - c0
                self.cpu += dc
                if edge:
                    self.edge_cpu += dc
        return timed


def _cli(args, paths) -> int:
    import tempfile

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from runner import _run_measured

    print(f"derender merge, fresh process per run, bracket {args.bracket} ({len(paths)} frames), "
          f"pairs {args.pairs}, alternating order")
    with tempfile.TemporaryDirectory(dir=Path(args.bracket).parent) as tmp:
        for method in [m.strip() for m in args.methods.split(",") if m.strip()]:
            runs: dict = {False: [], True: []}
            for i in range(args.pairs + 1):          # the first pair warms the caches and is not counted
                for var in ((False, True) if i % 2 == 0 else (True, False)):
                    cmd = [sys.executable, "-m", "derender.cli", "merge", *paths, "-o", f"{tmp}/{method}.exr",
                           "--method", method] + (["--variance", f"{tmp}/{method}-var.exr"] if var else [])
                    r = _run_measured(cmd)
                    if r["returncode"] != 0:
                        raise SystemExit(r["stderr"])
                    if i:
                        runs[var].append((r["wall_s"], r["cpu_s"]))
                    print(f"  {method} {'variance' if var else 'plain   '} wall {r['wall_s']:6.2f} s "
                          f"cpu {r['cpu_s']:6.2f} s{'' if i else ' (warm-up)'}", flush=True)
            for k, lab in enumerate(("wall", "cpu")):
                a = statistics.median(r[k] for r in runs[False])
                b = statistics.median(r[k] for r in runs[True])
                ratios = [rv[k] / rp[k] for rp, rv in zip(runs[False], runs[True])]
                print(f"{method:11s} {lab:5s} plain {a:6.2f} s  --variance {b:6.2f} s  median pair ratio "
                      f"{statistics.median(ratios):.2f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    import derender.engine.kernels as kernels
    import derender.engine.variance as variance
    import derender.engine.variance_kernels as variance_kernels
    from derender.hdr.files import merge_files

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bracket", default="/tmp/derender-bench/bracket-6000x4000-9-s0-tex")
    ap.add_argument("--methods", default="debevec,stabilized")
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--cli", action="store_true", help="time 'derender merge' with and without --variance instead")
    args = ap.parse_args(argv)
    paths = sorted(str(p) for p in Path(args.bracket).iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
    if args.cli:
        return _cli(args, paths)
    timer = _Timer()
    for mod, names in ((kernels, ("table_merge_rows", "stabilized_merge_rows")),
                       (variance_kernels, ("table_merge_var_rows", "stabilized_merge_var_rows")),
                       (variance, ("add_edge_term",))):
        for name in names:
            setattr(mod, name, timer.wrap(getattr(mod, name), edge=name == "add_edge_term"))

    def once(method: str, var: bool):
        timer.wall = timer.cpu = timer.edge_cpu = 0.0
        w0, c0 = time.perf_counter(), time.process_time()
        res = merge_files(paths, options={"variance": True} if var else {}, method=method,
                          engine=EngineOptions(threads=args.threads))
        return (time.perf_counter() - w0, time.process_time() - c0, timer.wall, timer.cpu, timer.edge_cpu), res

    print(f"bracket {args.bracket} ({len(paths)} frames), pairs {args.pairs}, alternating order")
    for method in [m.strip() for m in args.methods.split(",") if m.strip()]:
        once(method, False)
        once(method, True)       # warm-up (compilation, page cache)
        runs: dict = {False: [], True: []}
        last = {}
        for i in range(args.pairs):
            for var in ((False, True) if i % 2 == 0 else (True, False)):
                t, res = once(method, var)
                runs[var].append(t)
                last[var] = res
                print(f"  {method} {'variance' if var else 'plain   '} wall {t[0]:6.2f} s cpu {t[1]:6.2f} s "
                      f"kernel wall {t[2]:6.2f} s cpu {t[3]:6.2f} s (of which edge term cpu {t[4]:5.2f} s)", flush=True)
        same = np.array_equal(np.asarray(last[False].radiance), np.asarray(last[True].radiance))
        last.clear()
        labels = ("wall", "cpu", "kernel wall", "kernel cpu", "edge cpu")
        for k, lab in enumerate(labels):
            a = statistics.median(r[k] for r in runs[False])
            b = statistics.median(r[k] for r in runs[True])
            ratios = [rv[k] / rp[k] for rp, rv in zip(runs[False], runs[True]) if rp[k] > 0]
            print(f"{method:11s} {lab:12s} plain {a:6.2f} s  variance {b:6.2f} s"
                  + (f"  median pair ratio {statistics.median(ratios):.2f}" if ratios else ""))
        print(f"{method:11s} radiance byte-identical with and without variance: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
