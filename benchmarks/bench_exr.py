#!/usr/bin/env python
"""EXR compression choices for a merged radiance map: size (MB) and write time (s).

Reads one radiance EXR (e.g. ``derender merge``'s output of the 24 MP benchmark bracket)
and writes it with every candidate, rounds alternating, in this process (2 threads unless
``--threads``): our writer (:func:`derender.io.exr.write_exr_fast`: ZIP at deflate levels
1/4/6, every block compressed or only when a probe block saves >= 10 %, no compression,
half float) and the OpenEXR bindings (NONE, ZIPS, ZIP, PIZ, and half float PIZ/ZIP).
Prints median seconds and MB.

    python benchmarks/bench_exr.py /tmp/derender-bench/outputs/derender-debevec-9.exr --rounds 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    import numpy as np
    import OpenEXR

    from derender.io.exr import read_exr, write_exr_fast

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("exr", help="a radiance map to re-write")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--only", default=None, help="comma-separated names of the candidates to run")
    args = ap.parse_args(argv)
    img = read_exr(args.exr)
    h, w = img.shape[:2]
    tmpdir = Path(tempfile.mkdtemp(prefix="bench-exr-"))

    def ours(**kw):
        return lambda p: write_exr_fast(p, img, threads=args.threads, **kw)

    def bindings(comp, half=False):
        def f(p):
            OpenEXR.setGlobalThreadCount(args.threads or 2) if hasattr(OpenEXR, "setGlobalThreadCount") else None
            dt = np.float16 if half else np.float32
            chans = {c: np.ascontiguousarray(img[:, :, i], dtype=dt) for i, c in enumerate("RGB")}
            OpenEXR.File({"compression": comp, "type": OpenEXR.scanlineimage}, chans).write(str(p))
        return f

    cands = {
        "ours zip L1 probe (default)": ours(),
        "ours zip L1 all blocks": ours(probe=1, min_saving=0.0),
        "ours zip L4 all blocks": ours(probe=1, min_saving=0.0, level=4),
        "ours zip L6 all blocks": ours(probe=1, min_saving=0.0, level=6),
        "ours none": ours(compression="none"),
        "ours half zip L1 all blocks": ours(half=True, probe=1, min_saving=0.0),
        "ours half none": ours(half=True, compression="none"),
        "OpenEXR NONE": bindings(OpenEXR.NO_COMPRESSION),
        "OpenEXR ZIPS": bindings(OpenEXR.ZIPS_COMPRESSION),
        "OpenEXR ZIP": bindings(OpenEXR.ZIP_COMPRESSION),
        "OpenEXR PIZ": bindings(OpenEXR.PIZ_COMPRESSION),
        "OpenEXR half PIZ": bindings(OpenEXR.PIZ_COMPRESSION, half=True),
        "OpenEXR half ZIP": bindings(OpenEXR.ZIP_COMPRESSION, half=True),
    }
    if args.only:
        keep = [s.strip() for s in args.only.split(",")]
        cands = {k: v for k, v in cands.items() if k in keep}
    times: dict[str, list[float]] = {k: [] for k in cands}
    sizes: dict[str, float] = {}
    for _ in range(max(1, args.rounds)):
        for i, (name, fn) in enumerate(cands.items()):
            p = tmpdir / f"{i}.exr"
            t0 = time.perf_counter()
            fn(p)
            times[name].append(time.perf_counter() - t0)
            sizes[name] = p.stat().st_size / 1e6
            p.unlink()
    print(f"{w}x{h} float32 RGB ({w * h * 12 / 1e6:.0f} MB raw), median of {args.rounds} alternating rounds\n")
    print("| writer | s | MB |\n|---|---|---|")
    for name in cands:
        print(f"| {name} | {statistics.median(times[name]):.2f} | {sizes[name]:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
