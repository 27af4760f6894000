"""Time `derender derender` on a full-resolution JPEG (issues 6 and 8: 24 MP with variance under 5 s).

Generates (once, cached in --workdir) a GP model fitted on 5000 simulated chart pairs of
the Nikon D5100 and a JPEG of --size: a simulator frame upscaled with bicubic
interpolation plus +-2 codes of deterministic grain (so it has photograph-like numbers of
distinct colours). Then runs, each in a fresh process and in the same session:

* ``derender``: the CLI, ``derender derender IMG -m MODEL -o mean.exr --variance var.exr``
  (streamed per-colour tables, uncompressed EXR; ``--compression zip`` as a second entry);
* ``in-memory``: the library's plain path, ``DerenderModel.predict`` on the whole image
  (one prediction per distinct colour, then full-size gathers) and ``derender.io.write_exr``
  (OpenEXR) for both outputs -- what a user scripting the API without the streaming
  writer would do.

Prints wall time (interpreter start included), peak RSS and the ratio to the in-memory
path.

    python benchmarks/bench_derender.py                  # 6000x4000
    python benchmarks/bench_derender.py --size 1200x800  # a few seconds
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from runner import _run_measured

IN_MEMORY = """
import sys, time
t0 = time.perf_counter()
from derender.derendering.apply import check_8bit_rgb
from derender.derendering.base import load_model
from derender.io.exr import write_exr
codes = check_8bit_rgb(sys.argv[1])
mean, var = load_model(sys.argv[2]).predict(codes)
write_exr(sys.argv[3], mean)
write_exr(sys.argv[4], var)
print(f"in-memory {time.perf_counter() - t0:.2f} s")
"""


def prepare(workdir: Path, size: tuple[int, int], seed: int = 0) -> tuple[Path, Path]:
    import cv2

    from derender.camera import simulate_bracket
    from derender.camera.chart import chart_pairs
    from derender.derendering.base import fit_model

    workdir.mkdir(parents=True, exist_ok=True)
    from derender.core.errors import DerenderError
    from derender.derendering.base import load_model

    model = workdir / "nikon-d5100-gp.npz"
    try:
        load_model(model)
        fresh = False
    except DerenderError:          # missing, or written by another model-file version
        fresh = True
    if fresh:
        model.unlink(missing_ok=True)
        pairs = chart_pairs("nikon-d5100")
        train = np.random.default_rng(seed).permutation(len(pairs.jpeg))[:5000]
        fit_model("gp", pairs.jpeg[train], pairs.raw[train], seed=seed).save(model)
    image = workdir / f"shot-{size[0]}x{size[1]}.jpg"
    if not image.exists():
        b = simulate_bracket(size=(768, 512), exposures=3, pipeline="fixed", wb_preset="D65", seed=seed + 1)
        img = cv2.resize(b.jpeg_codes[1], size, interpolation=cv2.INTER_CUBIC)
        rng = np.random.default_rng(seed)
        img = np.clip(img.astype(np.int16) + rng.integers(-2, 3, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(image), img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    return image, model


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="6000x4000", help="W x H of the JPEG")
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "derender-bench-derender")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--prepare-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.prepare_only:
        prepare(args.workdir, (w, h))
        return 0
    # inputs are made in a child: a child's peak RSS (wait4) starts from its parent's at fork
    import subprocess

    subprocess.run([sys.executable, __file__, "--prepare-only", "--size", args.size, "--workdir", str(args.workdir)],
                   check=True)
    image, model = prepare(args.workdir, (w, h))
    out = args.workdir / "outputs"
    out.mkdir(exist_ok=True)
    py = sys.executable
    entries = {
        "derender": [py, "-m", "derender.cli", "derender", str(image), "-m", str(model),
                     "-o", str(out / "m.exr"), "--variance", str(out / "v.exr")],
        "derender --compression zip": [py, "-m", "derender.cli", "derender", str(image), "-m", str(model),
                                       "-o", str(out / "mz.exr"), "--variance", str(out / "vz.exr"),
                                       "--compression", "zip"],
        "in-memory": [py, "-c", IN_MEMORY, str(image), str(model), str(out / "mi.exr"), str(out / "vi.exr")],
    }
    rows = []
    for _ in range(max(1, args.repeat)):
        for name, cmd in entries.items():
            for f in out.glob("*.exr"):
                f.unlink()
            r = _run_measured(cmd)
            if r["returncode"] != 0:
                print(f"{name} failed: {r['stderr']}", file=sys.stderr)
                return 1
            rows.append((name, r))
    base = {name: r["wall_s"] for name, r in rows if name == "in-memory"}
    ref = sum(base.values()) / max(len(base), 1) if base else float("nan")
    print(f"{w}x{h} JPEG ({image.stat().st_size / 1e6:.1f} MB), GP model {model.name}")
    print("| tool | wall s | peak RSS MB | CPU s | vs in-memory |")
    print("|---|---|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['wall_s']:.2f} | {r['peak_rss_mb']:.0f} | {r['cpu_s']:.1f} | {r['wall_s'] / ref:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
