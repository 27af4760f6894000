"""Luminance maps beside hdrgen (issue 28, item 10): linearity over 5 decades and evalglare.

Brackets of the luminance-truth family (:mod:`derender.camera.luminance`: absolute luminance
1..1e6 cd/m2, EXIF t/N/ISO, a grey card) are merged by derender's methods and by Greg Ward's
hdrgen (github.com/radiance-org/hdrgen, BSD-3; built with its CMake, found as ``--hdrgen``,
``$HDRGEN`` or on PATH), and every map is scaled on the same grey-card spot
(:func:`derender.photometry.calibration.spot_factor`) and scored against the truth by
:func:`derender.evaluation.linearity.linearity_scores` (median and p90 abs error, median ratio
per decade, the brightest decade 1e5..1e6 cd/m2 being the glare sources' bias).

hdrgen runs twice:

* ``hdrgen``: its defaults on the JPEGs (exposures from their EXIF t, N, ISO; the response
  solved on the bracket itself);
* ``hdrgen-rsp``: ``-r cam.rsp`` with a response file hdrgen writes itself (its ``-r`` option
  on a file that does not exist) from a *calibration* bracket of the same camera and rendering
  (the next seed), then reused on the measured bracket, as the luminance-map procedure does.

``--evalglare`` also runs Radiance's ``evalglare`` (pyradiance's) on the fisheye framing: ``-V``
(vertical illuminance Ev) and its default output (DGP, DGI, UGR, VCP, CGI, Lveil) for the
truth map and every map with the same ``VIEW=`` header. The family's fisheye scene gives
Ev of about 41 klx, where DGP = 5.87e-5 Ev + ... + 0.16 saturates at 1 (evalglare clips it):
the table also gives DGP with every map, the truth's included, scaled by ``--dgp-scale``
(default 0.1, Ev about 4 klx) so that the glare probability is not clipped and the maps'
differences show.

A missing hdrgen is skipped with its reason. Run::

    python benchmarks/bench_luminance.py --hdrgen /tmp/hdrgen/build/hdrgen [--renders gamma,camera] \\
        [--evalglare] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint", "probabilistic")


def find_hdrgen(exe: str | None) -> tuple[str | None, str]:
    cand = exe or os.environ.get("HDRGEN") or shutil.which("hdrgen")
    if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
        return cand, ""
    return None, f"hdrgen not found ({cand or 'no --hdrgen, $HDRGEN or PATH'}): build github.com/radiance-org/hdrgen"


def run_hdrgen(exe: str, jpegs: list[Path], out: Path, rsp: Path | None = None) -> np.ndarray:
    from derender.io.rgbe import read_hdr

    cmd = [exe, "-o", str(out), "-F"] + (["-r", str(rsp)] if rsp is not None else []) + [str(p) for p in jpegs]
    run = subprocess.run(cmd, capture_output=True, text=True)
    if not out.is_file():
        tail = " | ".join((run.stderr or run.stdout).strip().splitlines()[-2:])
        raise RuntimeError(f"hdrgen wrote no output (exit {run.returncode}): {tail}")
    return np.asarray(read_hdr(out), dtype=np.float64)


def bracket(render: str, seed: int, size, exposures: int, work: Path, fisheye: bool = False):
    from derender.camera import bracket_paths, write_bracket
    from derender.camera.luminance import simulate_luminance

    b = simulate_luminance(render=render, size=size, exposures=exposures, seed=seed, fisheye=fisheye)
    folder = work / f"{render}-{seed}{'-fisheye' if fisheye else ''}"
    write_bracket(b, folder)
    return b, bracket_paths(folder, "jpeg")


def evaluate(render: str, seed: int, args, work: Path, hdrgen: str | None, why: str) -> list[dict]:
    from derender.camera.luminance import TUNING_RENDERS, truth_luminance_cd_m2
    from derender.core.types import Stack
    from derender.evaluation.families import smooth_mask
    from derender.evaluation.linearity import linearity_scores, render_chart_model
    from derender.hdr.registry import merge_seeded, method_spec

    b, jpegs = bracket(render, seed, args.size, args.exposures, work)
    lt = truth_luminance_cd_m2(b.truth_linear_srgb)
    smooth = smooth_mask(b.truth_linear_srgb)
    spot = b.params["luminance"]["spot"]
    stack = Stack(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
    role = "tuning" if render in TUNING_RENDERS else "held-out"
    rows, mask = [], None
    for m in args.methods:
        opts = ({"model": render_chart_model("nikon-d5100", render, args.n_train)}
                if method_spec(m).needs_model else {})
        res = merge_seeded(stack, m, seed, options=opts)
        mask = res.mask if mask is None else mask
        rows.append({"render": render, "role": role, "seed": seed, "method": m}
                    | linearity_scores(res.radiance, lt, spot, score_mask=smooth, merge_mask=res.mask))
    peers = {"hdrgen": None, "hdrgen-rsp": None}
    if hdrgen is None:
        for name in peers:
            rows.append({"render": render, "role": role, "seed": seed, "method": name, "skipped": why})
        return rows
    out = work / f"{render}-{seed}-hdrgen"
    out.mkdir(exist_ok=True)
    try:
        peers["hdrgen"] = run_hdrgen(hdrgen, jpegs, out / "default.hdr")
    except RuntimeError as e:
        peers["hdrgen"] = str(e)
    try:
        _, cal = bracket(render, seed + 1, args.size, args.exposures, work)
        rsp = out / "cam.rsp"
        rsp.unlink(missing_ok=True)
        run_hdrgen(hdrgen, cal, out / "calibration.hdr", rsp)
        if not rsp.is_file():
            raise RuntimeError("hdrgen -r wrote no response file on the calibration bracket")
        peers["hdrgen-rsp"] = run_hdrgen(hdrgen, jpegs, out / "rsp.hdr", rsp)
    except RuntimeError as e:
        peers["hdrgen-rsp"] = str(e)
    for name, rad in peers.items():
        row = {"render": render, "role": role, "seed": seed, "method": name}
        if isinstance(rad, str):
            row["skipped"] = rad
        elif rad.shape[:2] != lt.shape:
            row["skipped"] = f"hdrgen wrote {rad.shape[1]}x{rad.shape[0]}, not {lt.shape[1]}x{lt.shape[0]}"
        else:
            row |= linearity_scores(np.maximum(rad, 0.0), lt, spot, score_mask=smooth, merge_mask=mask)
        rows.append(row)
    return rows


def glare(args, work: Path, hdrgen: str | None) -> list[dict]:
    """evalglare -V (pyradiance's) on the fisheye framing: truth, our methods, hdrgen."""
    from derender.camera.luminance import SATURATION_EXPOSURE
    from derender.evaluation.linearity import FISHEYE_VIEW, fisheye_maps
    from derender.io.rgbe import write_hdr
    from derender.photometry.calibration import Spot, spot_factor

    try:
        import pyradiance
    except ImportError:
        return [{"map": "all", "skipped": "pyradiance not installed (pip install pyradiance)"}]
    evalglare = Path(pyradiance.__file__).parent / "bin" / "evalglare"
    maps = fisheye_maps(["debevec", "stabilized"], size=args.fisheye_size, n_train=args.n_train)
    if hdrgen is not None:
        b, jpegs = bracket("gamma", 0, (args.fisheye_size, args.fisheye_size), args.exposures, work, fisheye=True)
        assert np.allclose(b.truth_linear_srgb * (SATURATION_EXPOSURE / 179.0), maps["truth"], rtol=1e-5)
        from derender.io.rgbe import SRGB_PRIMARIES

        lum = b.params["luminance"]
        spot = Spot(*lum["spot"], lum["spot_cd_m2"])
        _, cal = bracket("gamma", 1, args.size, args.exposures, work)   # the response once, on a plain framing
        rsp = work / "fisheye-cam.rsp"
        rsp.unlink(missing_ok=True)
        for name, opt in (("hdrgen", None), ("hdrgen-rsp", rsp)):
            try:
                if opt is not None:
                    run_hdrgen(hdrgen, cal, work / "fisheye-cal.hdr", rsp)
                rad = np.maximum(run_hdrgen(hdrgen, jpegs, work / f"fisheye-{name}-out.hdr", opt), 0.0)
                maps[name] = rad * spot_factor(rad, spot, SRGB_PRIMARIES).factor
            except RuntimeError as e:
                print(f"{name} on the fisheye bracket: {e}", file=sys.stderr)
    rows = []
    for name, img in maps.items():
        path = work / f"fisheye-{name}.hdr"
        write_hdr(path, img, view=FISHEYE_VIEW)
        run = subprocess.run([str(evalglare), "-V", str(path)], capture_output=True, text=True)
        row = {"map": name, "ev_lx": float(run.stdout.split()[0])} | evalglare_indices(evalglare, path)
        scaled = work / f"fisheye-{name}-scaled.hdr"
        write_hdr(scaled, img * args.dgp_scale, view=FISHEYE_VIEW)
        row["dgp_scaled"] = evalglare_indices(evalglare, scaled).get("dgp", float("nan"))
        rows.append(row)
    ref = rows[0]
    for r in rows:
        r["ev_error"] = r["ev_lx"] / ref["ev_lx"] - 1.0
        r["dgp_scaled_diff"] = r["dgp_scaled"] - ref["dgp_scaled"]
    return rows


def evalglare_indices(evalglare, path) -> dict:
    """evalglare's default output on a fisheye map with a VIEW= header, ``dgp,dgi,ugr,vcp,cgi,Lveil:
    v1 v2 ...``, as a dict (lower-case names); empty when evalglare printed no such line."""
    run = subprocess.run([str(evalglare), str(path)], capture_output=True, text=True)
    for line in run.stdout.splitlines():
        if ":" in line and line.lower().startswith("dgp"):
            names, values = line.split(":", 1)
            return {n.strip().lower(): float(v) for n, v in zip(names.split(","), values.split())}
    return {}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--hdrgen", default=None, help="hdrgen executable (default: $HDRGEN or PATH)")
    p.add_argument("--renders", default="gamma,camera,dslr-lut", help="luminance-family renderings")
    p.add_argument("--seeds", default="0")
    p.add_argument("--size", default="192x128")
    p.add_argument("--exposures", type=int, default=9)
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--n-train", type=int, default=3000)
    p.add_argument("--evalglare", action="store_true", help="also evalglare -V on the fisheye framing")
    p.add_argument("--fisheye-size", type=int, default=160)
    p.add_argument("--dgp-scale", type=float, default=0.1,
                   help="DGP also on every map scaled by this (the family's Ev ~41 klx clips DGP at 1)")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    args.size = tuple(int(v) for v in args.size.lower().split("x"))
    args.methods = [m for m in args.methods.split(",") if m]
    hdrgen, why = find_hdrgen(args.hdrgen)
    if hdrgen is None:
        print(f"skipping hdrgen: {why}", file=sys.stderr)
    from derender.evaluation.linearity import format_decades

    rows, glare_rows = [], []
    with tempfile.TemporaryDirectory(prefix="bench-luminance-") as tmp:
        work = Path(tmp)
        for render in [r for r in args.renders.split(",") if r]:
            for seed in [int(s) for s in args.seeds.split(",") if s]:
                rows += evaluate(render, seed, args, work, hdrgen, why)
        if args.evalglare:
            glare_rows = glare(args, work, hdrgen)
    print("| render | role | method | median abs err | p90 | brightest decade (1e5..1e6) | median ratio per decade |")
    print("| --- | --- | --- | ---: | ---: | ---: | --- |")
    for r in rows:
        if "skipped" in r:
            print(f"| {r['render']} | {r['role']} | {r['method']} | skipped: {r['skipped']} | | | |")
            continue
        print(f"| {r['render']} | {r['role']} | {r['method']} | {r['median_abs']:.1%} | {r['p90_abs']:.1%} | "
              f"{r['decades'][-1]:.3f} | {format_decades(r['decades'])} |")
    if glare_rows:
        print(f"\n| map (fisheye, gamma camera, tuning) | evalglare -V Ev (lx) | vs truth | DGP | UGR | "
              f"DGP, maps x {args.dgp_scale:g} | vs truth |")
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
        for r in glare_rows:
            if "skipped" in r:
                print(f"| {r['map']} | skipped: {r['skipped']} | | | | | |")
            else:
                print(f"| {r['map']} | {r['ev_lx']:.0f} | {r['ev_error']:+.1%} | {r.get('dgp', float('nan')):.3f} | "
                      f"{r.get('ugr', float('nan')):.1f} | {r['dgp_scaled']:.3f} | {r['dgp_scaled_diff']:+.3f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"linearity": rows, "evalglare": glare_rows}, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
