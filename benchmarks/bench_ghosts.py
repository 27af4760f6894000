"""Ghost removal against the peer programs, by motion zone (issue 23, item 6).

The same simulated moving brackets as :func:`derender.evaluation.ghosts.ghost_comparison`
(``simulate_bracket(camera, kind, size, exposures, seed, family, motion=MotionSpec(objects,
shake))``, ``.tripod()`` for the tripod setting, ``.still()`` for the still twin; truth at the
reference instant, the middle frame) are merged by

* derender's methods (``dr.merge`` via ``merge_seeded``, ``reference=middle``,
  ``align="translation"``, ``deghost=True``; options a method does not take yet are dropped
  and the row says so), and
* the peers, each through its own command line on lossless files of the very same 8-bit codes
  (TIFF, or PPM for pfstools) with the exposure times given on the command line:
  Luminance HDR (``--autoag``), Hugin (``align_image_stack`` + ``vig_optimize`` + ``nona`` +
  ``hugin_hdrmerge -m khan``, Khan et al. 2006), pfstools (``pfshdrcalibrate --deghosting``)
  and hdrgen (``-g``; built from github.com/radiance-org/hdrgen, see README).

Every output is scored with :func:`derender.evaluation.ghosts.zone_errors` (median relative
error per zone after a trimmed 3x3 fit, so a peer's scale and colour space do not matter):
``static`` (no object in any frame), ``swept`` (an object passed, not at the reference instant),
``object`` (the object at the reference instant). Ratios are moving / still twin, each peer on
its own still-twin run (the same command). Rows are means over seeds.

Tuning families: paper, camera. Held out: dslr-lut, phone-local (and drift).

    PYTHONPATH=src python benchmarks/bench_ghosts.py                     # the issue's grid
    python benchmarks/bench_ghosts.py --families paper --seeds 0 --peers luminance,pfstools
    python benchmarks/bench_ghosts.py --hdrgen /tmp/hdrgen/build/hdrgen --json out.json

A peer whose program is missing is skipped with one line saying which program; it is never a
dependency of derender.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TUNING = ("paper", "camera")
DERENDER_METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint")
PEERS = ("luminance", "hugin-khan", "pfstools", "hdrgen")
#: Peer runs without their ghost removal (same pipeline otherwise): context, not in the default.
BASELINES = ("luminance-noag", "hugin-avg", "pfstools-nodeghost", "hdrgen-nog")

#: The verdict's ratio columns use only rows whose still twin's static median is below this.
STILL_USABLE = 0.5

#: What each peer does about the reference instant (the truth is at the middle frame).
PEER_REFERENCE = {
    "luminance": "auto (h0 = least hue error; not settable)",
    "luminance-noag": "n/a (no deghosting)",
    "hugin-khan": "no reference (Khan); aligned to middle",
    "hugin-avg": "n/a; aligned to middle",
    "pfstools": "auto per pixel (not settable)",
    "pfstools-nodeghost": "n/a (no deghosting)",
    "hdrgen": "auto (best exposure from middle; not settable)",
    "hdrgen-nog": "n/a (no deghosting)",
}


# --------------------------------------------------------------------------- brackets
def brackets(family: str, seed: int, size, exposures: int, objects: int, shake: int | None, camera: str, kind: str):
    """The still twin and the moving brackets ``{setting: bracket}`` (as ghost_comparison)."""
    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec

    shake_px = max(1, int(round(0.02 * size[0]))) if shake is None else int(shake)
    base = MotionSpec(objects=objects, shake=shake_px)
    common = dict(kind=kind, size=size, exposures=exposures, seed=int(seed), family=family)
    still = simulate_bracket(camera, motion=base.still(), **common)
    moving = {"tripod": simulate_bracket(camera, motion=base.tripod(), **common),
              "handheld": simulate_bracket(camera, motion=base, **common)}
    return still, moving


# --------------------------------------------------------------------------- derender
def derender_merge(codes: np.ndarray, times: np.ndarray, method: str, ref: int, seed: int):
    """``dr.merge`` with ``reference=ref, align="translation", deghost=True``, dropping what the
    method does not take yet (``dr.merge`` raises InputError for an unknown option or value).
    Returns (radiance, seconds, options used)."""
    from derender.core.errors import InputError
    from derender.core.types import Stack
    from derender.engine.motion.run import MotionOptions
    from derender.hdr.registry import merge_seeded

    stack = Stack(images=codes.astype(np.float32) / 255, times=times)
    attempts = [{"reference": ref, "align": "translation", "deghost": True}, {"reference": ref, "align": "translation"},
                {"reference": ref}, {}]
    for opts in attempts:
        t0 = time.perf_counter()
        try:
            rad = merge_seeded(stack, method, int(seed), motion=MotionOptions(**opts)).radiance
        except InputError:
            continue
        return rad, time.perf_counter() - t0, opts
    raise RuntimeError(f"derender {method} refused every option set")


def derender_note(opts: dict) -> tuple[str, str]:
    """(name suffix, reference column) for the options a derender merge took."""
    suffix = "" if opts.get("deghost") else " (deghost not yet available)"
    if "reference" in opts and "align" not in opts:
        suffix += " [no align=translation]"
    return suffix, ("middle (told)" if "reference" in opts else "none (method has no reference option)")


# --------------------------------------------------------------------------- peers
class PeerMissing(Exception):
    pass


def _run(cmd, cwd, log, env=None, stdin=None, stdout=None):
    """Run one command; its output goes to ``log``; a failure raises with the log's tail."""
    with open(log, "ab") as fh:
        fh.write(("$ " + " ".join(map(str, cmd)) + "\n").encode())
        fh.flush()
        p = subprocess.run(cmd, cwd=cwd, env=env, stdin=stdin, stdout=stdout or fh, stderr=fh)
    if p.returncode != 0:
        tail = Path(log).read_text(errors="replace").strip().splitlines()[-3:]
        raise RuntimeError(f"{Path(cmd[0]).name} exit {p.returncode}: {' | '.join(tail)}")


def _need(prog: str, hint: str = "") -> str:
    path = prog if os.path.sep in prog else shutil.which(prog)
    if not path or not os.access(path, os.X_OK):
        raise PeerMissing(f"{prog} not found{hint}")
    return path


def write_frames(codes: np.ndarray, folder: Path, ext: str) -> list[Path]:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, c in enumerate(codes):
        p = folder / f"f{i}.{ext}"
        if not p.exists():
            Image.fromarray(np.ascontiguousarray(c)).save(p)
        out.append(p)
    return out


def run_luminance(codes, times, ref, work: Path, *, deghost: bool, threshold: float):
    exe = _need("luminance-hdr-cli", " (Debian package luminance-hdr)")
    files = write_frames(codes, work.parent / "tif", "tif")
    ev = ",".join(f"{v:.6f}" for v in np.log2(times / times[ref]))
    out = work / "out.exr"
    cmd = [exe, "-e", ev, "--hdrResponseCurve", "srgb", "-a", "MTB"]
    if deghost:
        cmd += ["-t", f"{threshold:g}"]
    cmd += ["-s", str(out)] + [str(f) for f in files]
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    _run(cmd, work, work / "log.txt", env=env)
    from derender.io.exr import read_exr

    return read_exr(out), cmd


def run_hugin(codes, times, ref, work: Path, *, deghost: bool):
    ais = _need("align_image_stack", " (Debian package hugin-tools)")
    for p in ("pto_var", "vig_optimize", "nona", "hugin_hdrmerge"):
        _need(p, " (Debian package hugin-tools)")
    files = write_frames(codes, work.parent / "tif", "tif")
    order = [ref] + [i for i in range(len(files)) if i != ref]    # the first image is the anchor
    log = work / "log.txt"
    cmds = [[ais, "--use-given-order", "-f", "50", "-p", "aligned.pto"] + [str(files[i]) for i in order]]
    _run(cmds[-1], work, log)
    eev = ",".join(f"Eev{k}={np.log2(1.0 / times[i]):.6f}" for k, i in enumerate(order))
    cmds += [["pto_var", f"--set={eev}", "-o", "exposed.pto", "aligned.pto"],
             ["pto_var", "--modify-opt", "--opt=Ra,Rb,Rc,Rd,Re", "-o", "toopt.pto", "exposed.pto"],
             ["vig_optimize", "-p", "2000", "-o", "response.pto", "toopt.pto"],
             ["nona", "-r", "hdr", "-m", "EXR_m", "-o", "remapped_", "response.pto"]]
    for c in cmds[1:]:
        _run(c, work, log)
    remapped = sorted(str(p.name) for p in work.glob("remapped_*.exr"))
    cmds.append(["hugin_hdrmerge", "-m", "khan" if deghost else "avg", "-o", "out.exr"] + remapped)
    _run(cmds[-1], work, log)
    from derender.io.exr import read_exr

    return read_exr(work / "out.exr"), cmds


def run_pfstools(codes, times, ref, work: Path, *, deghost: bool, sigmas: float):
    for p in ("pfsinhdrgen", "pfshdrcalibrate", "pfsoutrgbe"):
        _need(p, " (Debian package pfstools)")
    files = write_frames(codes, work.parent / "ppm", "ppm")
    script = work / "bracket.hdrgen"
    # pfsinhdrgen's script: <image> <1/exposure time> <aperture> <iso> 0
    script.write_text("".join(f"{f.resolve()} {1.0 / t:.9g} 1 100 0\n" for f, t in zip(files, times)))
    cal = ["pfshdrcalibrate", "-r", "gamma"] + (["-d", f"{sigmas:g}"] if deghost else [])
    cmds = [["pfsinhdrgen", str(script)], cal, ["pfsoutrgbe", "out.hdr"]]
    log = work / "log.txt"
    with open(log, "ab") as fh:
        fh.write(("$ " + " | ".join(" ".join(c) for c in cmds) + "\n").encode())
        p1 = subprocess.Popen(cmds[0], cwd=work, stdout=subprocess.PIPE, stderr=fh)
        p2 = subprocess.Popen(cmds[1], cwd=work, stdin=p1.stdout, stdout=subprocess.PIPE, stderr=fh)
        p1.stdout.close()
        p3 = subprocess.Popen(cmds[2], cwd=work, stdin=p2.stdout, stderr=fh)
        p2.stdout.close()
        rcs = [p3.wait(), p2.wait(), p1.wait()]
    if any(rcs):
        tail = log.read_text(errors="replace").strip().splitlines()[-3:]
        raise RuntimeError(f"pfstools pipeline exit {rcs}: {' | '.join(tail)}")
    from derender.io.rgbe import read_hdr

    return read_hdr(work / "out.hdr"), cmds


def run_hdrgen(codes, times, ref, work: Path, *, deghost: bool, exe: str | None):
    """hdrgen cannot solve its response on the whole 7-frame bracket ("Cannot solve for response
    function": the darkest and brightest frames, ~3 stops apart); its man page's remedy: solve on
    the frames without the extremes into a response file (``-r``), then merge all with it."""
    exe = _need(exe or "hdrgen", " (build github.com/radiance-org/hdrgen, pass --hdrgen PATH)")
    files = write_frames(codes, work.parent / "tif", "tif")
    log = work / "log.txt"

    def images(idx):
        # -s: sample-to-nits factor of the next image; only ratios matter: 1/t
        return [a for i in idx for a in ("-s", f"{1.0 / times[i]:.9g}", str(files[i]))]

    n = len(files)
    rsp = work / "camera.rsp"
    rsp.unlink(missing_ok=True)
    cmds = []
    for k in range(1, n // 2):
        cmds.append([exe, "-o", "calibration.hdr", "-F", "-r", str(rsp)] + images(range(k, n - k)))
        try:
            _run(cmds[-1], work, log)
        except RuntimeError:            # no solution on this subset: drop one more frame each end
            rsp.unlink(missing_ok=True)
            continue
        if rsp.exists():
            break
    if not rsp.exists():
        raise RuntimeError("hdrgen: cannot solve for the response on any centred subset")
    (work / "out.hdr").unlink(missing_ok=True)
    cmds.append([exe, "-o", "out.hdr", "-F", "-r", str(rsp)] + (["-g"] if deghost else []) + images(range(n)))
    _run(cmds[-1], work, log)
    if not (work / "out.hdr").exists():
        tail = log.read_text(errors="replace").strip().splitlines()[-2:]
        raise RuntimeError(f"hdrgen wrote no output: {' | '.join(tail)}")
    from derender.io.rgbe import read_hdr

    return read_hdr(work / "out.hdr"), cmds


def run_peer(name, codes, times, ref, work: Path, args):
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if name.startswith("luminance"):
        rad, cmd = run_luminance(codes, times, ref, work, deghost=name == "luminance", threshold=args.luminance_threshold)
    elif name.startswith("hugin"):
        rad, cmd = run_hugin(codes, times, ref, work, deghost=name == "hugin-khan")
    elif name.startswith("pfstools"):
        rad, cmd = run_pfstools(codes, times, ref, work, deghost=name == "pfstools", sigmas=args.pfs_sigmas)
    elif name.startswith("hdrgen"):
        rad, cmd = run_hdrgen(codes, times, ref, work, deghost=name == "hdrgen", exe=args.hdrgen)
    else:
        raise ValueError(name)
    dt = time.perf_counter() - t0
    rad = np.asarray(rad, dtype=np.float64)[..., :3]
    bad = int(np.sum(~np.isfinite(rad)))
    rad = np.clip(np.nan_to_num(rad, nan=0.0, posinf=0.0, neginf=0.0), 0, None)
    return rad, dt, ("(non-finite values set to 0)" if bad else ""), cmd


# --------------------------------------------------------------------------- run + table
def run(args) -> list[dict]:
    from derender.evaluation.ghosts import zone_errors

    rows: list[dict] = []
    missing: dict[str, str] = {}
    failures: list[str] = []
    commands: dict[str, object] = {}
    root = Path(args.workdir or tempfile.mkdtemp(prefix="derender-ghost-peers-"))
    for family in args.families:
        for seed in args.seeds:
            still, moving = brackets(family, seed, args.size, args.exposures, args.objects, args.shake,
                                     args.camera, args.kind)
            ref = int(still.params["motion"]["reference"])
            cases = {"still": still, **{s: moving[s] for s in args.settings}}
            for entry in list(args.methods) + list(args.peers):
                if entry in missing:
                    continue
                errs, secs, notes, ref_col = {}, [], set(), PEER_REFERENCE.get(entry, "")
                nan = {"static": float("nan"), "swept": float("nan"), "object": float("nan")}
                try:
                    for case, b in cases.items():
                        try:
                            if entry in args.methods:
                                rad, dt, used = derender_merge(b.jpeg_codes, b.times, entry, ref, seed)
                                note, ref_col = derender_note(used)
                            else:
                                work = root / f"{family}-s{seed}-{case}" / entry
                                rad, dt, note, cmd = run_peer(entry, b.jpeg_codes, b.times, ref, work, args)
                                commands.setdefault(entry, cmd)
                        except RuntimeError as exc:      # a peer that fails on one case: NaN + the reason
                            print(f"failed {entry} on {family} seed {seed} {case}: {exc}", file=sys.stderr, flush=True)
                            failures.append(f"{entry} on {family} seed {seed} {case}: {exc}")
                            errs.update({("still", s): nan for s in args.settings} if case == "still" else {case: nan})
                            continue
                        secs.append(dt)
                        if note:
                            notes.add(note)
                        if case == "still":
                            # scored on each moving bracket's zones below (as ghost_comparison)
                            errs.update({("still", s): zone_errors(rad, b.truth_linear_srgb, moving[s].motion_zones)
                                         for s in args.settings})
                        else:
                            errs[case] = zone_errors(rad, b.truth_linear_srgb, b.motion_zones)
                except PeerMissing as exc:
                    missing[entry] = str(exc)
                    print(f"skipped {entry}: {exc}", file=sys.stderr, flush=True)
                    continue
                for setting in args.settings:
                    if setting not in errs or ("still", setting) not in errs:
                        continue
                    still_z = errs[("still", setting)]
                    row = {"family": family, "held_out": family not in TUNING, "setting": setting, "seed": int(seed),
                           "method": entry if entry in args.peers else f"derender {entry}",
                           "peer": entry in args.peers, "note": "; ".join(sorted(notes)), "reference": ref_col,
                           "seconds": statistics.median(secs) if secs else float("nan")}
                    for zone in ("static", "swept", "object"):
                        mv, st = errs[setting][zone], still_z[zone]
                        row[f"{zone}_moving"], row[f"{zone}_still"] = mv, st
                        row[f"{zone}_ratio"] = mv / st if st > 0 and np.isfinite(mv) else float("nan")
                    rows.append(row)
                    print(json.dumps(row), file=sys.stderr, flush=True)
    for entry, why in missing.items():
        print(f"skipped {entry}: {why}")
    run.commands = commands        # for the README: the exact command lines used
    run.failures = failures
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["family"], r["setting"], r["method"]), []).append(r)
    out = []
    for (family, setting, method), rs in groups.items():
        s = {k: rs[0][k] for k in ("family", "held_out", "setting", "method", "peer", "reference")}
        s["note"] = "; ".join(sorted({r["note"] for r in rs if r["note"]}))
        s["n"] = sum(bool(np.isfinite(r["static_ratio"])) for r in rs)
        s["n_all"] = len(rs)
        for k in rs[0]:
            if k.endswith(("_moving", "_still", "_ratio")) or k == "seconds":
                v = [r[k] for r in rs if np.isfinite(r[k])]
                s[k] = float(np.mean(v)) if v else float("nan")
        out.append(s)
    return out


def table(summary: list[dict]) -> str:
    head = ("| family | held out | setting | method / peer | reference frame | static | swept | object | "
            "static / still | swept / still | object / still | s per merge | seeds |")
    lines = [head, "|" + "---|" * 13]
    for s in summary:
        name = (s["method"] + (f" {s['note'].strip()}" if s["note"] else "")).replace("|", "/")
        lines.append(f"| {s['family']} | {'yes' if s['held_out'] else 'no (tuning)'} | {s['setting']} | {name} | "
                     f"{s['reference']} | {s['static_moving']:.3f} | {s['swept_moving']:.3f} | {s['object_moving']:.3f} | "
                     f"{s['static_ratio']:.2f} | {s['swept_ratio']:.2f} | {s['object_ratio']:.2f} | {s['seconds']:.2f} | "
                     f"{s['n']}/{s['n_all']} |")
    return "\n".join(lines)


def verdict(summary: list[dict]) -> str:
    """Per family, setting and zone (swept, object): the best derender row and the best peer row,
    by the moving median and by the ratio to the still twin; "yes" when derender's best is lower
    than every peer's (rows without a finite value are left out). A row whose still twin's static
    median is >= ``STILL_USABLE`` is left out of the ratio columns: a ratio to a still-twin merge
    that is itself wrong (Luminance's --autoag output, ~0.9) says nothing about ghosts."""
    lines = ["| family | held out | setting | zone | best derender: median (ratio) | best peer: median (ratio) | "
             "derender lower median? | derender lower ratio? |", "|" + "---|" * 8]
    keys = []
    for s in summary:
        if (s["family"], s["setting"]) not in keys:
            keys.append((s["family"], s["setting"]))
    for family, setting in keys:
        group = [s for s in summary if s["family"] == family and s["setting"] == setting]
        for zone in ("swept", "object"):
            def best(rows, k):
                rows = [r for r in rows if np.isfinite(r[k])]
                return min(rows, key=lambda r: r[k]) if rows else None
            ours = [s for s in group if not s["peer"]]
            peers = [s for s in group if s["peer"]]
            om, pm = best(ours, f"{zone}_moving"), best(peers, f"{zone}_moving")
            usable = [r for r in peers if r["static_still"] < STILL_USABLE]
            orat, prat = best(ours, f"{zone}_ratio"), best(usable, f"{zone}_ratio")
            if not (om and pm and orat and prat):
                continue

            def cell(a, b):
                return f"{a['method'].replace('derender ', '')} {a[f'{zone}_moving']:.3f} ({a[f'{zone}_ratio']:.2f})" + (
                    "" if a is b else f"; {b['method'].replace('derender ', '')} ({b[f'{zone}_ratio']:.2f})")
            lines.append(f"| {family} | {'yes' if group[0]['held_out'] else 'no (tuning)'} | {setting} | {zone} | "
                         f"{cell(om, orat)} | {cell(pm, prat)} | "
                         f"{'yes' if om[f'{zone}_moving'] < pm[f'{zone}_moving'] else 'no'} | "
                         f"{'yes' if orat[f'{zone}_ratio'] < prat[f'{zone}_ratio'] else 'no'} |")
    return "\n".join(lines)


def peer_times(rows: list[dict]) -> str:
    by: dict[str, list[float]] = {}
    for r in rows:
        by.setdefault(r["method"], []).append(r["seconds"])
    lines = ["| method / peer | median s per merge (192x128 x 7 unless changed) |", "|---|---|"]
    lines += [f"| {m} | {statistics.median([x for x in v if np.isfinite(x)] or [float('nan')]):.2f} |"
              for m, v in by.items()]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--families", nargs="+", default=["paper", "camera", "dslr-lut", "phone-local"])
    p.add_argument("--settings", nargs="+", default=["tripod", "handheld"], choices=["tripod", "handheld"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    p.add_argument("--size", default="192x128", help="WxH")
    p.add_argument("--exposures", type=int, default=7)
    p.add_argument("--objects", type=int, default=3)
    p.add_argument("--shake", type=int, default=None, help="px per frame (default 2%% of the width)")
    p.add_argument("--camera", default="nikon-d5100")
    p.add_argument("--kind", default="outdoor")
    p.add_argument("--methods", default=",".join(DERENDER_METHODS), help="derender methods ('' for none)")
    p.add_argument("--peers", default=",".join(PEERS),
                   help=f"comma list of {', '.join(PEERS + BASELINES)} ('' for none)")
    p.add_argument("--hdrgen", default=os.environ.get("HDRGEN"), help="hdrgen executable (default: $HDRGEN or PATH)")
    p.add_argument("--luminance-threshold", type=float, default=0.5, help="luminance-hdr-cli --autoag threshold")
    p.add_argument("--pfs-sigmas", type=float, default=2.0, help="pfshdrcalibrate --deghosting value")
    p.add_argument("--workdir", default=None, help="peer files and logs (default: a new temp folder)")
    p.add_argument("--json", default=None, help="write the per-seed rows here")
    args = p.parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"error: --size must be WxH, got {args.size!r}", file=sys.stderr)
        return 2
    args.size = (w, h)
    args.methods = [m for m in args.methods.split(",") if m]
    args.peers = [m for m in args.peers.split(",") if m]
    bad = [m for m in args.peers if m not in PEERS + BASELINES]
    if bad:
        print(f"error: unknown peer(s) {', '.join(bad)}; known: {', '.join(PEERS + BASELINES)}", file=sys.stderr)
        return 2
    from derender.camera.families import check_family
    from derender.core.errors import InputError

    try:
        args.families = [check_family(f) for f in args.families]
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    rows = run(args)
    summary = summarise(rows)
    print(f"\nZone medians (moving) and moving / still-twin ratios; mean over seeds {args.seeds}; "
          f"{args.size[0]}x{args.size[1]}, {args.exposures} exposures. Tuning families: paper, camera; "
          f"held out: the others.\n")
    print(table(summary))
    if args.methods and args.peers:
        print(f"\nDoes derender beat every peer? (best of each side; a second name is the side's best ratio; "
              f"ratios only from rows whose still twin's static median < {STILL_USABLE})\n")
        print(verdict(summary))
    print("\nTime per merge (median over cases):\n")
    print(peer_times(rows))
    print("\nPeer commands (first case):")
    for k, v in getattr(run, "commands", {}).items():
        cmds = v if isinstance(v[0], list) else [v]
        for c in cmds:
            print(f"  {k}: {' '.join(map(str, c))}")
    fails = getattr(run, "failures", [])
    if fails:
        print(f"\nFailed runs ({len(fails)}; those seeds are left out of the row's mean, see 'seeds'):")
        for f in fails:
            print(f"  {f}")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
