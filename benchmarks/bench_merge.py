#!/usr/bin/env python
"""Side-by-side HDR merge benchmark: the floor, OpenCV, colour-hdri and ``derender merge``.

Generates (and caches) a bracket of textured simulator JPEGs, runs every tool in a fresh
process on the same files, alternating rounds, and prints median wall time, the tool's
own time, peak RSS (the child's VmHWM), CPU time and EXR size, with same-round ratios to
the floor (decode every frame + write the same EXR), OpenCV and derender's Debevec. See
README.md in this folder.

    python benchmarks/bench_merge.py                         # 9 x 6000x4000, + 18-frame memory run
    python benchmarks/bench_merge.py --size 1200x800 --frames 5 --memory-frames 0   # quick
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    from runner import format_bench, run_bench

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="6000x4000", help="WxH of the generated JPEGs (default 6000x4000, 24 MP)")
    ap.add_argument("--frames", type=int, default=9, help="exposures in the bracket (default 9)")
    ap.add_argument("--memory-frames", type=int, default=18,
                    help="also run derender-debevec on a bracket of this many frames to compare peak RSS (0: skip)")
    ap.add_argument("--entries", default="floor,opencv,derender-debevec,derender-stabilized",
                    help="comma-separated: floor, opencv, opencv-robertson, colour-hdri, derender-<method>, "
                         "derender-<method>+align (--align translation), derender-<method>+deghost "
                         "(--align translation --deghost)")
    ap.add_argument("--workdir", default=None, help="cache folder for brackets and outputs (default: $TMPDIR/derender-bench)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="alternating rounds over all entries; medians and median same-round ratios are reported")
    ap.add_argument("--no-texture", action="store_true",
                    help="the old bracket (upscaled frames + uniform grain, decodes unrealistically fast)")
    ap.add_argument("--scene-texture", action="store_true",
                    help="the physically consistent bracket: the texture in the scene's radiance, rendered by the "
                         "simulated camera (the default bracket multiplies every frame's codes by it)")
    ap.add_argument("--model", default=None, help="de-rendering model for the probabilistic methods "
                    "(default: a GP fitted once on simulated chart pairs, cached in the workdir)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="also write the raw results to this JSON file")
    args = ap.parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size must look like 6000x4000, got {args.size!r}")
    entries = [e.strip() for e in args.entries.split(",") if e.strip()]
    res = run_bench(size=(w, h), frames=args.frames, workdir=args.workdir, entries=entries,
                    memory_frames=args.memory_frames or None, seed=args.seed, repeat=args.repeat,
                    texture="scene" if args.scene_texture else not args.no_texture, model=args.model,
                    progress=lambda msg: print(msg, file=sys.stderr, flush=True))
    print(format_bench(res))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
