#!/usr/bin/env python
"""The variance kernels against the plain merge kernels on a crop of rows, in one process.

Runs ``merge_files(paths, method=M, variance=True)`` once on the bracket (default: the
9 x 24 MP bracket of ``bench_merge.py``) to capture the compiled variance kernel's arguments,
then times, alternating, the plain kernel (:func:`derender.engine.kernels.table_merge_rows` or
``stabilized_merge_rows``) and the variance kernel (:mod:`derender.engine.variance_kernels`)
on ``--rows`` rows from the middle, output buffers allocated once; reports the median CPU time
(``time.process_time``: both numba threads) of each and their ratio, and checks the radiance
and mask are byte-identical.

    python benchmarks/bench_variance_kernel.py --methods debevec,stabilized --rows 512 --reps 7
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    import derender.engine.kernels as kernels
    import derender.engine.variance_kernels as vk
    from derender.hdr.files import merge_files

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bracket", default="/tmp/derender-bench/bracket-6000x4000-9-s0-tex")
    ap.add_argument("--methods", default="debevec,stabilized")
    ap.add_argument("--rows", type=int, default=512)
    ap.add_argument("--reps", type=int, default=7)
    args = ap.parse_args(argv)
    paths = sorted(str(p) for p in Path(args.bracket).iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
    for method in [m.strip() for m in args.methods.split(",") if m.strip()]:
        table = method in ("debevec", "robertson")
        name = "table_merge_var_rows" if table else "stabilized_merge_var_rows"
        orig = getattr(vk, name)
        cap: dict = {}

        def capture(*a, _orig=orig):
            cap.setdefault("args", a)
            return _orig(*a)

        setattr(vk, name, capture)
        try:
            merge_files(paths, options={"variance": True}, method=method)
        finally:
            setattr(vk, name, orig)
        a = cap["args"]
        npre = 13 if table else 16
        pre = a[:npre]
        h, w = pre[0].shape[1:3]
        y0 = max(0, (h - args.rows) // 2)
        y1 = min(h, y0 + args.rows)
        tn, tq, k, stride = a[npre + 5], a[npre + 6], a[npre + 7], a[-1]
        out_p, mask_p = np.zeros((3, y1 - y0, w), np.float32), np.zeros((h, w), np.uint8)
        out_v, mask_v = np.zeros_like(out_p), np.zeros_like(mask_p)
        var, parts = np.zeros_like(out_p), np.zeros((5, -(-h // stride), w, 3), np.float32)
        plain = getattr(kernels, name.replace("_var", ""))
        fns = {"plain": lambda: plain(*pre, y0, y1, y0, out_p, mask_p),
               "variance": lambda: orig(*pre, y0, y1, y0, out_v, mask_v, tn, tq, k, var, parts, stride)}
        for f in fns.values():
            f()
        times: dict = {key: [] for key in fns}
        for i in range(args.reps):
            for key in (list(fns) if i % 2 == 0 else list(fns)[::-1]):
                c0 = time.process_time()
                fns[key]()
                times[key].append(time.process_time() - c0)
        p, v = statistics.median(times["plain"]), statistics.median(times["variance"])
        same = np.array_equal(out_p, out_v) and np.array_equal(mask_p, mask_v)
        print(f"{method:11s} {y1 - y0} rows x {w}: plain kernel {p:.3f} s CPU, variance kernel {v:.3f} s CPU, "
              f"ratio {v / p:.2f}; radiance byte-identical: {same}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
