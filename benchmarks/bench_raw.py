"""RAW brackets: the noise-optimal merge against exact truth, paper 1's eq. 11 and HDRutils, and its speed.

Simulated DNG brackets (``derender simulate``'s writer: LibRaw reads them, exact truth, known
noise) for two cameras (nikon-d5100 at 14 bit, sigma-sd-merrill at 12 bit) and three scenes.
RAW merges do not depend on the JPEG rendering family, so there is no tuning/held-out split of
families here: no parameter of the merge was tuned on these brackets (the noise model is
estimated per bracket).

Rows, all on the same DNG files:

* ``raw`` -- ``derender merge --method raw`` (noise estimated from the frames);
* ``raw-oracle`` -- the same merge given the simulator's true gain and read noise;
* ``paper1`` -- paper 1's eq. 11 (``derender groundtruth --method paper1``);
* ``hdrutils`` -- HDRutils 1.2 (PyPI) ``merge(demosaic_first=False, color_space='raw',
  wb=[1, 1, 1], demosaic='malvar')`` with the times given (its EXIF reader needs ISO, which
  the simulated DNGs do not state), if installed.

Scores in camera RGB (no white balance or matrix, so that HDRutils' colour path plays no
part), after one scale factor fitted per result (the project's trimmed fit,
``relative_errors(fit="scale")``; it is ~1 for derender, whose units are exact): median and
p90 relative error, darkest decade and brightest unclipped decade
(:func:`derender.evaluation.raw_merge.raw_scores`), against (a) the demosaiced true mosaic
(the merge's error alone) and (b) the scene's camera RGB (demosaicing error included); and
for derender the coverage of its variance (against (a)).

Speed: LibRaw decoding the frames (``rawpy.imread`` + the mosaic copy) against ``derender
merge --method raw`` in process (read + merge + variance), at ``--speed-size``.

    PYTHONPATH=src python benchmarks/bench_raw.py [--size 384x256] [--speed-size 3000x2000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from derender.engine.options import OutputOptions

CASES = [("nikon-d5100", 14, "outdoor"), ("nikon-d5100", 14, "indoor"), ("nikon-d5100", 14, "night"),
         ("sigma-sd-merrill", 12, "outdoor"), ("sigma-sd-merrill", 12, "indoor"), ("sigma-sd-merrill", 12, "night")]


def _scaled_scores(rad, truth, mask, variance=None):
    from derender.evaluation.metrics import relative_errors
    from derender.evaluation.raw_merge import raw_scores

    k = float(relative_errors(rad[3:-3, 3:-3], truth[3:-3, 3:-3], fit="scale")["matrix"][0][0])
    s = raw_scores(rad * k, truth, mask, None if variance is None else variance * k * k)
    s["scale"] = k
    return s


def _hdrutils(files, times):
    try:
        import HDRutils
    except ImportError:
        return None
    import logging

    logging.getLogger("HDRutils").setLevel(logging.ERROR)
    n = len(files)
    hdr, _ = HDRutils.merge([str(f) for f in files], demosaic_first=False, color_space="raw", wb=[1.0, 1.0, 1.0],
                            demosaic="malvar", exp=np.asarray(times, float), gain=np.ones(n), aperture=np.ones(n))
    return np.asarray(hdr, dtype=np.float64)


def accuracy(size, exposures, seed=3):
    from derender.camera import simulate_bracket, write_bracket
    from derender.camera.sensor import mosaic_signal
    from derender.camera.spectral import load_camera
    from derender.evaluation.raw_merge import true_noise
    from derender.io.raw import read_raw_stack
    from derender.raw.groundtruth import raw_to_camera_rgb
    from derender.raw.mosaic import demosaic_bayer
    from derender.raw.optimal import raw_merge

    rows = []
    for cam_name, bits, kind in CASES:
        with tempfile.TemporaryDirectory() as tmp:
            b = simulate_bracket(load_camera(cam_name).with_bits(bits), kind=kind, size=size, exposures=exposures,
                                 seed=seed, style="simple", pipeline="fixed")
            write_bracket(b, tmp)
            files = sorted((Path(tmp) / "raw").glob("*.dng"))
            frames = read_raw_stack(files)
            g, rn = true_noise(b.camera)
            results = {
                "raw": raw_merge(frames, output_space="camera_rgb", clip_negative=False),
                "raw-oracle": raw_merge(frames, output_space="camera_rgb", gain=g, read_noise=rn,
                                        clip_negative=False),
                "paper1": raw_to_camera_rgb(frames, clip_negative=False),
            }
            hu = _hdrutils(files, b.times)
            mask = results["raw"].mask
            demo_truth = demosaic_bayer(mosaic_signal(b.camera_rgb_per_s), "RGGB").astype(np.float64)
            scene_truth = b.camera_rgb_per_s
            for name, res in list(results.items()) + ([("hdrutils", None)] if hu is not None else []):
                rad = hu if res is None else res.radiance.astype(np.float64)
                var = None if res is None else res.variance
                a = _scaled_scores(rad, demo_truth, mask, var)
                s = _scaled_scores(rad, scene_truth, mask)
                rows.append({"camera": f"{cam_name} {bits}-bit", "scene": kind, "method": name, "demosaiced": a,
                             "scene_truth": s,
                             "noise": None if res is None else res.info.get("noise")})
    return rows


def speed(size, exposures):
    import rawpy

    from derender.camera import simulate_bracket, write_bracket
    from derender.hdr.files import merge_files

    with tempfile.TemporaryDirectory() as tmp:
        b = simulate_bracket("nikon-d5100", kind="outdoor", size=size, exposures=exposures, seed=1, style="simple",
                             pipeline="fixed")
        write_bracket(b, tmp)
        files = sorted((Path(tmp) / "raw").glob("*.dng"))
        best_decode = best_merge = np.inf
        for _ in range(2):
            t0 = time.perf_counter()
            for f in files:
                with rawpy.imread(str(f)) as r:
                    np.array(r.raw_image_visible, copy=True)
            best_decode = min(best_decode, time.perf_counter() - t0)
            t0 = time.perf_counter()
            merge_files(files, method="raw", output=OutputOptions(variance_output=Path(tmp) / "v.exr",
                                                                  output=Path(tmp) / "m.exr"))
            best_merge = min(best_merge, time.perf_counter() - t0)
    return best_decode, best_merge


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="384x256")
    ap.add_argument("--exposures", type=int, default=5)
    ap.add_argument("--speed-size", default="1536x1024")
    ap.add_argument("--speed-exposures", type=int, default=5)
    ap.add_argument("--no-speed", action="store_true")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    rows = accuracy((w, h), args.exposures)
    print(f"## Accuracy: {args.exposures} exposures, {w}x{h}, camera RGB, one fitted scale per result\n")
    print("| camera | scene | method | median | p90 | darkest decade | brightest decade | cov 95 | cov 50 "
          "| median vs scene | darkest vs scene | brightest vs scene |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        a, s = r["demosaiced"], r["scene_truth"]
        cov = (f"{a['coverage95']:.3f} | {a['coverage50']:.3f}" if "coverage95" in a else "- | -")
        print(f"| {r['camera']} | {r['scene']} | {r['method']} | {100 * a['median']:.2f} % | {100 * a['p90']:.2f} % "
              f"| {100 * a['dark_decade']:.2f} % | {100 * a['bright_decade']:.2f} % | {cov} "
              f"| {100 * s['median']:.2f} % | {100 * s['dark_decade']:.2f} % | {100 * s['bright_decade']:.2f} % |")
    print("\nestimated noise / true:")
    from derender.camera.spectral import load_camera
    from derender.evaluation.raw_merge import true_noise

    for r in rows:
        if r["method"] == "raw":
            cam = load_camera(r["camera"].split()[0]).with_bits(int(r["camera"].split()[1].split("-")[0]))
            g, rn = true_noise(cam)
            n = r["noise"]
            print(f"  {r['camera']} {r['scene']}: gain {n['gain_dn_per_electron'] / g:.3f}, "
                  f"read noise {n['read_noise_dn'] / rn:.3f}")
    if not args.no_speed:
        sw, sh = (int(v) for v in args.speed_size.split("x"))
        dec, mer = speed((sw, sh), args.speed_exposures)
        print(f"\n## Speed: {args.speed_exposures} frames of {sw}x{sh}\n")
        print(f"LibRaw decode {dec:.3f} s; derender merge --method raw (read, merge, variance, write) {mer:.3f} s "
              f"= {mer / dec:.1f}x the decode")


if __name__ == "__main__":
    main()
