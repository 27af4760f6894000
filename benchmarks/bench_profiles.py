"""Camera profiles across scenes: a profile saved on one bracket, reused without a spot on another.

Issue 28's done-when line "a profile saved on one bracket, reused without a spot on another
whose aperture and ISO vary: median <= 5 %". Bracket A (spot reading on the smoothest 8x8
patch of the truth, labelled f/5.6 ISO 100 with its true times) is merged with ``--spot`` and
``--save-profile``; bracket B (another scene, frames relabelled f/2.8-16 and ISO 100-1600 at
the same ``t S / N^2``) with ``--profile`` only. Truth in cd/m2: the simulator's radiance per
second times 317 (one scale for one camera). Scores: median and p90 of the relative
luminance error on smooth pixels (as ``tests/photometry/test_spot.py``), B with its own spot
for comparison, and the ratio of the profile's factor to B's own spot factor.

    python benchmarks/bench_profiles.py                       # fixed pipeline, 5 scene pairs
    python benchmarks/bench_profiles.py --families camera,paper,dslr-lut,phone-local,drift

Tuning families: the fixed pipeline (``camera`` style), ``camera``, ``paper``; held out:
``dslr-lut``, ``phone-local``, ``drift``. Results: docs/results-luminance.md.

``--luminance RENDERS`` measures the same line on the luminance-truth family
(:mod:`derender.camera.luminance`, absolute truth in cd/m2 over 1..1e6): bracket A is a time
bracket (f/16, ISO 100) calibrated with ``--spot`` on its grey card (the spot the family
records, the card's exact luminance), bracket B another seed's ``aperture-iso`` bracket (f/4-16,
ISO 100-800 drawn per frame, the times out of order against brightness), merged with the
profile only. Scored on the smooth pixels off the card with truth >= 1 cd/m2 (as
:mod:`derender.evaluation.linearity`). Renderings ``gamma``, ``paper``, ``camera`` tuning;
``dslr-lut``, ``phone-local``, ``drift`` held out::

    python benchmarks/bench_profiles.py --luminance gamma,paper,camera,dslr-lut --methods debevec,stabilized
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

TRUTH_SCALE = 317.0
APERTURES = [16.0, 5.6, 2.8, 8.0, 4.0, 11.0, 5.6]
ISOS = [400, 100, 100, 200, 800, 1600, 200]
PAIRS = [(7, 11, "outdoor", "indoor"), (21, 21, "outdoor", "indoor"), (22, 22, "outdoor", "indoor"),
         (31, 32, "outdoor", "outdoor"), (41, 42, "indoor", "indoor")]


def write_jpeg(path: Path, codes: np.ndarray, t: float, n: float, iso: int) -> Path:
    """A JPEG with EXIF time, f-number and ISO (derender's own writer)."""
    from derender.camera import write_jpeg as write

    return write(path, codes, t, "Test", "Camera", quality=95, fnumber=n, iso=iso)


def bracket(folder: Path, family: str, seed: int, kind: str, vary: bool):
    from derender.camera import simulate_bracket

    opts = {"pipeline": "fixed"} if family == "fixed" else {"family": family}
    b = simulate_bracket(size=(192, 128), exposures=7, seed=seed, kind=kind, **opts)
    folder.mkdir(parents=True)
    files = []
    for j, (codes, t) in enumerate(zip(b.jpeg_codes, b.times)):
        n, s = (APERTURES[j], ISOS[j]) if vary else (5.6, 100)
        files.append(write_jpeg(folder / f"{j:02d}.jpg", codes, float(t) * (n / 5.6) ** 2 * (100 / s), n, s))
    return b, files


def truth_luminance(b):
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    truth = b.truth_linear_srgb.astype(np.float64) * TRUTH_SCALE
    return truth, luminance_cd_m2(truth, SRGB_PRIMARIES)


def spot(b, size: int = 8) -> str:
    from derender.evaluation.linearity import smoothest_window

    _, lum = truth_luminance(b)
    x, y = smoothest_window(lum, size)
    return f"{x},{y},{size},{size}={float(lum[y:y + size, x:x + size].mean()):.6f}"


def score(path: Path, b) -> dict:
    from derender.evaluation.families import smooth_mask
    from derender.io.exr import read_exr
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    truth, lum_true = truth_luminance(b)
    lum = luminance_cd_m2(read_exr(path), SRGB_PRIMARIES)
    ok = (lum_true > 1e-3 * lum_true.max()) & smooth_mask(truth)
    ratio = lum[ok] / lum_true[ok]
    err = np.abs(ratio - 1.0)
    return {"median": float(np.median(err)), "p90": float(np.percentile(err, 90)), "ratio": float(np.median(ratio))}


def merge(args: list) -> None:
    from derender.cli import app

    try:
        app(args=[str(a) for a in args], standalone_mode=False)
    except SystemExit as exc:
        if exc.code:
            raise RuntimeError(f"derender {' '.join(map(str, args))}: exit {exc.code}") from None


def run(family: str, pairs, methods, work: Path) -> list[str]:

    rows = []
    for sa, sb, ka, kb in pairs:
        ba, fa = bracket(work / f"{family}-{sa}a", family, sa, ka, False)
        bb, fb = bracket(work / f"{family}-{sb}b{sa}", family, sb, kb, True)
        rows += profile_rows(f"{family} | {sa}/{sb} {ka}/{kb}", work / f"{family}-{sa}", methods, (fa, ba, spot(ba)),
                             (fb, bb, spot(bb)), score)
    return rows


def profile_rows(label: str, prefix: Path, methods, a_case: tuple, b_case: tuple, score) -> list[str]:
    """One table row per method: bracket A merged with its spot and the profile saved, bracket B
    merged with that profile and, for comparison, with its own spot; ``a_case`` / ``b_case`` are
    ``(files, bracket, spot option)``, ``score(path, bracket)`` the error figures."""
    from derender.io.exr import read_exr

    (fa, ba, spot_a), (fb, bb, spot_b) = a_case, b_case
    rows = []
    for m in methods:
        p, a, bp, bs = (Path(f"{prefix}-{m}{x}") for x in (".json", "a.exr", "b.exr", "bs.exr"))
        merge(["merge", *fa, "-o", a, "--method", m, "--spot", spot_a, "--save-profile", p])
        merge(["merge", *fb, "-o", bp, "--method", m, "--profile", p])
        merge(["merge", *fb, "-o", bs, "--method", m, "--spot", spot_b])
        s_a, s_b, s_bs = score(a, ba), score(bp, bb), score(bs, bb)
        k = float(np.median(read_exr(bp) / np.maximum(read_exr(bs), 1e-30)))
        rows.append(f"| {label} | {m} | {100 * s_a['median']:.1f} % | {100 * s_bs['median']:.1f} % | "
                    f"{100 * s_b['median']:.1f} % | {100 * s_b['p90']:.1f} % | {s_b['ratio']:.3f} | {k:.3f} |")
        print(rows[-1], flush=True)
    return rows


LUMINANCE_PAIRS = [(0, 1), (2, 3), (4, 5)]


def run_luminance(render: str, pairs, methods, work: Path) -> list[str]:
    """The profile line on the luminance family (module docstring)."""
    from derender.camera import bracket_paths, write_bracket
    from derender.camera.luminance import TUNING_RENDERS, simulate_luminance, truth_luminance_cd_m2
    from derender.evaluation.families import smooth_mask
    from derender.io.exr import read_exr
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    role = "tuning" if render in TUNING_RENDERS else "held out"

    def scores(path: Path, b) -> dict:
        lt = truth_luminance_cd_m2(b.truth_linear_srgb)
        ok = smooth_mask(b.truth_linear_srgb) & (lt >= 1.0)
        x, y, w, h = b.params["luminance"]["grey_card"]
        ok[y:y + h, x:x + w] = False
        ratio = luminance_cd_m2(read_exr(path), SRGB_PRIMARIES)[ok] / lt[ok]
        err = np.abs(ratio - 1.0)
        return {"median": float(np.median(err)), "p90": float(np.percentile(err, 90)),
                "ratio": float(np.median(ratio))}

    rows = []
    for sa, sb in pairs:
        ba = simulate_luminance(mode="time", render=render, seed=sa)
        bb = simulate_luminance(mode="aperture-iso", render=render, seed=sb)
        fa_dir, fb_dir = work / f"lum-{render}-{sa}a", work / f"lum-{render}-{sb}b"
        write_bracket(ba, fa_dir)
        write_bracket(bb, fb_dir)
        fa, fb = bracket_paths(fa_dir, "jpeg"), bracket_paths(fb_dir, "jpeg")
        rows += profile_rows(f"luminance `{render}` ({role}) | {sa}/{sb} time/aperture-iso", work / f"lum-{render}-{sa}",
                             methods, (fa, ba, ba.params["luminance"]["spot_option"]),
                             (fb, bb, bb.params["luminance"]["spot_option"]), scores)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default="fixed", help="fixed (fixed pipeline, camera style) and/or simulator "
                                                          "families, comma separated")
    ap.add_argument("--methods", default="debevec,stabilized")
    ap.add_argument("--pairs", type=int, default=None, help="scene pairs per family (default: 5 fixed, 2 families)")
    ap.add_argument("--luminance", default=None, help="luminance-family renderings (gamma, paper, camera, "
                                                      "dslr-lut, phone-local, drift) instead of --families")
    args = ap.parse_args(argv)
    print("| pipeline | seeds A/B, scenes | method | A, spot | B, own spot | B, profile | p90 | ratio | "
          "k profile / k own |\n| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    work = Path(tempfile.mkdtemp(prefix="bench-profiles-"))
    try:
        if args.luminance:
            for render in args.luminance.split(","):
                run_luminance(render, LUMINANCE_PAIRS[:args.pairs or 3], args.methods.split(","), work)
            return 0
        for fam in args.families.split(","):
            n = args.pairs or (5 if fam == "fixed" else 2)
            pairs = PAIRS[:n] if fam == "fixed" else [(s, s, "outdoor", "indoor") for s in (21, 22)][:n]
            run(fam, pairs, args.methods.split(","), work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
