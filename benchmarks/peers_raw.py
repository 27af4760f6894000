"""RAW brackets: derender's raw merge against the peer programs, on the same simulated DNG files, in one run.

Issue 38's line: derender's raw merge beats every peer that could be run on median relative
error, on the darkest decade and on the brightest unclipped decade. Each bracket is written
once by the simulator (DNG files LibRaw and dcraw read; exact truth, known noise) and every
program merges those very files, with the exposure times given (the simulated DNGs state no
ISO or f-number, so EXIF readers cannot compute exposures; every peer is given the exact
times, not dcraw's rounded print-out):

* ``derender`` -- ``derender merge --method raw -O output_space=S -O demosaic=D`` (``--derender-space S``,
  default ``camera_rgb``, scored after one scale; ``linear_srgb`` and ``xyz`` are scored after a
  3x3 fit, as the peers in sRGB are; every space demosaics the white-balanced mosaic, as dcraw
  does, and ``camera_rgb`` divides the balance out after the demosaic)
  (:func:`derender.hdr.raw.merge_raw`, noise estimated from the frames; ``--demosaic D``,
  default ``menon2007``; ``ahd``, dcraw's and LibRaw's interpolator, :mod:`derender.raw.ahd`;
  ``malvar2004`` is the merge's default);
* ``hdrutils`` -- HDRutils (PyPI) ``merge(demosaic_first=False, color_space='raw',
  wb=[1, 1, 1], demosaic='malvar', exp=times)``, as docs/raw.md says it runs with today's rawpy;
* ``pfstools`` -- Debian pfstools: ``pfsinhdrgen`` (what ``pfsinme`` runs after
  ``dcraw2hdrgen``; each frame through ``pfsindcraw``: ``dcraw -c -o 1 -4 -w``, linear 16-bit
  sRGB, camera white balance) ``| pfshdrcalibrate -c none -r linear -b 16 | pfsoutexr``: no
  response fitting, Hanji et al.'s Poisson noise-aware merge;
* ``luminance-hdr`` -- ``luminance-hdr-cli`` (LibRaw inside) with its defaults (Debevec model,
  triangular weight, linear response) and ``-e`` EV values ``log2(t_i / t_0)``;
* ``raw2hdr`` -- raw2hdr's pipeline (dcraw + hdrgen): ``dcraw -c -w -W -o 1 -4 -T`` per frame
  (16-bit linear TIFF), then ``hdrgen -r linear.rsp -a -e`` with a linear response file and
  ``-s 1/t_i`` per frame (hdrgen from github.com/radiance-org/hdrgen, ``--hdrgen PATH``). The
  hdrgen of that repository (74b963d, panlib 173fb3a) refuses 16-bit frames ("HDR image
  exposures must be 24-bit RGB", phdrimg.cpp), so this row fails with that line; raw2hdr's own
  script (not in the repository) could not be had to see how it feeds hdrgen.

A missing program is skipped with one line; none is a dependency of derender.

Colour spaces, handled per peer: derender and HDRutils output camera RGB (no white balance, no
matrix) and get **one scale** fitted to the truth (trimmed least squares,
:func:`derender.evaluation.metrics.relative_errors`, ``fit="scale"``; ~1 for derender, whose
units are exact). pfstools, Luminance HDR and raw2hdr output dcraw's / LibRaw's white-balanced
sRGB: they get a **3x3 matrix** fitted to the camera-RGB truth (``fit="matrix"``, the same
trimmed fit). derender is scored with a 3x3 matrix too (row ``derender (3x3 fit)``), so that
the extra freedom is not the difference.

Truths: (a) the scene's camera RGB at every pixel (``bracket.camera_rgb_per_s``): each program
with its own demosaic, the end-to-end error; (b) each program's own merge of the same bracket
simulated **without noise** (same scene, same clipping, noise off; one scale fitted, as a
program may normalise its output): its noise error alone, with its demosaic and colour path
cancelled. Column "noise-free vs scene" is that noise-free merge against (a): the demosaic's
and colour path's share of the end-to-end error. Scores (:func:`derender.evaluation.raw_merge.raw_scores`):
median and p90 relative error, the median in the darkest decade and in the brightest unclipped
decade of the truth's luminance, over the pixels derender's merge measured (mask 0).

Brackets: cameras nikon-d5100 (14 bit) and sigma-sd-merrill (12 bit), scenes outdoor, indoor,
night (the simulator's scene kinds), 5 exposures, seed 3, the fixed rendering pipeline (RAW
merges do not read the JPEG rendering, so the tuning / held-out families do not apply; no
parameter of any merge was tuned on these brackets).

    PYTHONPATH=src python benchmarks/peers_raw.py [--size 384x256] [--hdrgen PATH] [--peers ...]
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

CASES = [("nikon-d5100", 14, "outdoor"), ("nikon-d5100", 14, "indoor"), ("nikon-d5100", 14, "night"),
         ("sigma-sd-merrill", 12, "outdoor"), ("sigma-sd-merrill", 12, "indoor"), ("sigma-sd-merrill", 12, "night")]
PEERS = ("derender", "hdrutils", "pfstools", "luminance-hdr", "raw2hdr")
#: the fit that maps each program's output space onto camera RGB (module docstring)
FITS = {"derender": "scale", "hdrutils": "scale", "pfstools": "matrix", "luminance-hdr": "matrix",
        "raw2hdr": "matrix"}


class PeerMissing(RuntimeError):
    """A peer program is not installed: the row is skipped with this message."""


def _need(prog: str, hint: str) -> str:
    path = prog if os.path.sep in prog else shutil.which(prog)
    if not path or not os.access(path, os.X_OK):
        raise PeerMissing(f"{prog} not found ({hint})")
    return path


def _run(cmd, cwd: Path, **kw) -> None:
    p = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, **kw)
    if p.returncode != 0:
        tail = (p.stderr or b"").decode(errors="replace").strip().splitlines()[-3:]
        raise RuntimeError(f"{Path(str(cmd[0])).name} exit {p.returncode}: {' | '.join(tail)}")


#: Per work folder, the noise model derender estimated on the noisy files: the noise-free twin
#: (:func:`run_case`'s second run) has no noise to estimate, so it is merged with that one.
_NOISE_BY_FOLDER: dict = {}


def run_derender(files, times, work: Path, args):
    from derender.hdr.raw import merge_raw
    from derender.io.raw import read_raw_stack

    opts = {"output_space": args.derender_space, "demosaic": args.demosaic}
    known = _NOISE_BY_FOLDER.get(str(work))
    if known is not None:
        opts.update(gain=known["gain_dn_per_electron"], read_noise=known["read_noise_dn"])
    res = merge_raw(read_raw_stack(files, times=times), opts)
    _NOISE_BY_FOLDER.setdefault(str(work), res.info["noise"])
    return res.radiance.astype(np.float64), res.mask


def run_hdrutils(files, times, work: Path, args):
    try:
        import HDRutils
    except ImportError:
        raise PeerMissing("HDRutils not installed (pip install HDRutils)") from None
    import logging

    logging.getLogger("HDRutils").setLevel(logging.ERROR)
    n = len(files)
    hdr, _ = HDRutils.merge([str(f) for f in files], demosaic_first=False, color_space="raw", wb=[1.0, 1.0, 1.0],
                            demosaic="malvar", exp=np.asarray(times, float), gain=np.ones(n), aperture=np.ones(n))
    return np.asarray(hdr, dtype=np.float64), None


def run_pfstools(files, times, work: Path, args):
    for p in ("pfsinhdrgen", "pfshdrcalibrate", "pfsoutexr", "dcraw"):
        _need(p, "Debian packages pfstools and dcraw")
    script = work / "bracket.hdrgen"
    # pfsinhdrgen's lines: <image> <1/exposure time> <aperture> <iso> 0 (aperture 1, ISO 100: times alone)
    script.write_text("".join(f"{Path(f).resolve()} {1.0 / t!r} 1 100 0\n" for f, t in zip(files, times)))
    out = work / "pfs.exr"
    with open(work / "pfs.log", "wb") as log:
        p1 = subprocess.Popen(["pfsinhdrgen", str(script)], cwd=work, stdout=subprocess.PIPE, stderr=log)
        p2 = subprocess.Popen(["pfshdrcalibrate", "-c", "none", "-r", "linear", "-b", "16"], cwd=work,
                              stdin=p1.stdout, stdout=subprocess.PIPE, stderr=log)
        p1.stdout.close()
        p3 = subprocess.Popen(["pfsoutexr", str(out)], cwd=work, stdin=p2.stdout, stderr=log)
        p2.stdout.close()
        rcs = [p3.wait(), p2.wait(), p1.wait()]
    if any(rcs) or not out.exists():
        raise RuntimeError(f"pfstools exit {rcs}: {(work / 'pfs.log').read_text(errors='replace')[-300:]}")
    from derender.io.rgbe import read_radiance

    return read_radiance(out).astype(np.float64), None


def run_luminance_hdr(files, times, work: Path, args):
    exe = _need("luminance-hdr-cli", "Debian package luminance-hdr")
    ev = ",".join(f"{math.log2(t / times[0]):.6f}" for t in times)
    out = work / "lhdr.exr"
    _run([exe, "-e", ev, "--hdrModel", "debevec", "--hdrWeight", "triangular", "--hdrResponseCurve", "linear",
          "-s", out] + list(files), work, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})
    from derender.io.rgbe import read_radiance

    return read_radiance(out).astype(np.float64), None


def run_raw2hdr(files, times, work: Path, args):
    dcraw = _need("dcraw", "Debian package dcraw")
    exe = _need(args.hdrgen or "hdrgen", "build github.com/radiance-org/hdrgen, pass --hdrgen PATH")
    rsp = work / "linear.rsp"
    rsp.write_text("1 0 1\n1 0 1\n1 0 1\n")        # order 1, c0 = 0, c1 = 1 per channel: a linear response
    cmd = [exe, "-o", work / "raw2hdr.hdr", "-F", "-r", rsp, "-a", "-e"]
    for i, (f, t) in enumerate(zip(files, times)):
        tif = work / f"r{i}.tiff"
        with open(tif, "wb") as fh:
            p = subprocess.run([dcraw, "-c", "-w", "-W", "-o", "1", "-4", "-T", str(f)], stdout=fh,
                               stderr=subprocess.PIPE)
        if p.returncode != 0:
            raise RuntimeError(f"dcraw exit {p.returncode} on {f}")
        cmd += ["-s", f"{1.0 / t:.9g}", tif]
    _run(cmd, work)
    from derender.io.rgbe import read_radiance

    return read_radiance(work / "raw2hdr.hdr").astype(np.float64), None


RUNNERS = {"derender": run_derender, "hdrutils": run_hdrutils, "pfstools": run_pfstools,
           "luminance-hdr": run_luminance_hdr, "raw2hdr": run_raw2hdr}


def _fitted(rad, truth, fit):
    """``rad`` mapped onto ``truth`` by the trimmed fit (interior pixels, positive truth)."""
    from derender.evaluation.metrics import relative_errors

    m = np.asarray(relative_errors(rad[3:-3, 3:-3], truth[3:-3, 3:-3], fit=fit)["matrix"], dtype=np.float64)
    return (rad.reshape(-1, 3) @ m.T).reshape(rad.shape)


def _write(bracket, folder: Path) -> list[Path]:
    from derender.camera import write_bracket

    write_bracket(bracket, folder)
    return sorted((folder / "raw").glob("*.dng"))


def run_case(cam_name, bits, kind, size, exposures, seed, peers, args, work: Path):
    """One bracket, written twice (with and without noise); every peer on both. Returns rows."""
    from derender.camera import simulate_bracket
    from derender.camera.spectral import load_camera
    from derender.evaluation.raw_merge import raw_scores

    cam = load_camera(cam_name).with_bits(bits)
    kw = dict(kind=kind, size=size, exposures=exposures, seed=seed, style="simple", pipeline="fixed")
    b = simulate_bracket(cam, **kw)
    files = _write(b, work / "noisy")
    clean = _write(simulate_bracket(cam, noise=False, **kw), work / "clean")
    times = [float(t) for t in b.times]
    truth = np.asarray(b.camera_rgb_per_s, dtype=np.float64)
    mask = None
    rows = []
    for name in peers:
        pw = work / name
        pw.mkdir(exist_ok=True)
        try:
            t0 = time.perf_counter()
            rad, m = RUNNERS[name](files, times, pw, args)
            secs = time.perf_counter() - t0
            ref, _ = RUNNERS[name](clean, times, pw, args)
        except PeerMissing as exc:
            rows.append({"peer": name, "skipped": str(exc)})
            continue
        except Exception as exc:  # noqa: BLE001 - a peer that fails is reported, not fatal
            rows.append({"peer": name, "skipped": f"failed: {type(exc).__name__}: {exc}"})
            continue
        if m is not None and mask is None:
            mask = m
        fits = [FITS[name]] + (["matrix"] if name == "derender" else [])
        if name == "derender" and args.derender_space != "camera_rgb":
            fits = ["matrix"]             # white-balanced sRGB or XYZ: a 3x3 fit, as pfstools and Luminance HDR get
        for fit in fits:
            a = raw_scores(_fitted(rad, truth, fit), truth, mask)
            own = raw_scores(_fitted(rad, ref, fit), ref, mask)         # same pipeline without noise, same fit
            clean_err = raw_scores(_fitted(ref, truth, fit), truth, mask)   # its demosaic and colour path alone
            label = name if fit == fits[0] else f"{name} (3x3 fit)"
            rows.append({"peer": label, "fit": fit, "scene": a, "noise_free": own, "clean_vs_scene": clean_err,
                         "seconds": secs})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="384x256")
    ap.add_argument("--exposures", type=int, default=5)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--peers", default=",".join(PEERS), help=f"comma-separated, of {', '.join(PEERS)}")
    ap.add_argument("--cases", default="all", help="'all' or indices into CASES, e.g. 0,3")
    ap.add_argument("--hdrgen", default=None, help="path of the hdrgen program (raw2hdr's merger)")
    ap.add_argument("--demosaic", default="menon2007", choices=("menon2007", "malvar2004", "ahd"),
                    help="derender's demosaic (the merge's default is malvar2004)")
    ap.add_argument("--derender-space", default="camera_rgb", choices=("camera_rgb", "linear_srgb", "xyz"),
                    help="derender's output space (linear_srgb, xyz: a 3x3 fit like the peers in sRGB; every "
                         "space demosaics the white-balanced mosaic, as dcraw does)")
    ap.add_argument("--workdir", default=None, help="keep the files here (default: a temporary folder)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    bad = [p for p in peers if p not in RUNNERS]
    if bad:
        ap.error(f"unknown peer(s) {', '.join(bad)}; choose from {', '.join(PEERS)}")
    if "derender" in peers:                      # derender first: its mask selects the scored pixels
        peers = ["derender"] + [p for p in peers if p != "derender"]
    cases = CASES if args.cases == "all" else [CASES[int(i)] for i in args.cases.split(",")]
    print(f"## RAW peers: {args.exposures} exposures, {w}x{h}, seed {args.seed}, camera RGB truth\n")
    print("| camera | scene | program | fit | median | p90 | darkest decade | brightest decade "
          "| median (own noise-free) | darkest (own) | brightest (own) | noise-free vs scene | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    skipped = {}
    base = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="peers-raw-"))
    try:
        for cam_name, bits, kind in cases:
            work = base / f"{cam_name}-{bits}-{kind}"
            work.mkdir(parents=True, exist_ok=True)
            for r in run_case(cam_name, bits, kind, (w, h), args.exposures, args.seed, peers, args, work):
                if "skipped" in r:
                    skipped.setdefault(r["peer"], r["skipped"])
                    continue
                a, o = r["scene"], r["noise_free"]
                print(f"| {cam_name} {bits}-bit | {kind} | {r['peer']} | {r['fit']} | {100 * a['median']:.2f} % "
                      f"| {100 * a['p90']:.2f} % | {100 * a['dark_decade']:.2f} % | {100 * a['bright_decade']:.2f} % "
                      f"| {100 * o['median']:.2f} % | {100 * o['dark_decade']:.2f} % "
                      f"| {100 * o['bright_decade']:.2f} % | {100 * r['clean_vs_scene']['median']:.2f} % "
                      f"| {r['seconds']:.2f} |", flush=True)
    finally:
        if not args.workdir:
            shutil.rmtree(base, ignore_errors=True)
    for peer, why in skipped.items():
        print(f"skipped {peer}: {why}")


if __name__ == "__main__":
    main()
