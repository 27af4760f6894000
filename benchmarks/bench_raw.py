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

Scores in camera RGB (no matrix, so that HDRutils' colour path plays no part), after one
scale factor fitted per result (the project's trimmed fit, ``relative_errors(fit="scale")``;
it is ~1 for derender, whose units are exact): median and p90 relative error, darkest decade
and brightest unclipped decade (:func:`derender.evaluation.raw_merge.raw_scores`), against (a)
the demosaiced true mosaic, through each merge's own demosaic path (the merge's error alone:
derender demosaics the white-balanced mosaic and divides the balance out,
:func:`derender.evaluation.raw_merge.demosaiced_truth`; paper 1's and HDRutils' Malvar see the
mosaic as it is) and (b) the scene's camera RGB (demosaicing error included); and
for derender the coverage of its noise-only variance (``variance_terms="noise"``, against (a); the
default variance, with the interpolation term, against the scene: ``bench_raw_noise.py --coverage``).

Speed: LibRaw decoding the frames (``rawpy.imread`` + the mosaic copy) against ``derender
merge --method raw`` in process (read + merge + variance), at ``--speed-size``.

    PYTHONPATH=src python benchmarks/bench_raw.py [--size 384x256] [--speed-size 3000x2000]
    PYTHONPATH=src python benchmarks/bench_raw.py --speed-only --speed-exposures 9 --speed-tile 6016x4000
    PYTHONPATH=src python benchmarks/bench_raw.py --coverage-only [--coverage-demosaic menon2007|ahd]
    PYTHONPATH=src python benchmarks/bench_raw.py --demosaic-candidates
    PYTHONPATH=src python benchmarks/bench_raw.py --demosaic-speed 6016x4000 [--with-colour-demosaicing]
    PYTHONPATH=src python benchmarks/bench_raw.py --stages --speed-exposures 9 --speed-tile 6016x4000 [--stages-folder DIR]
    PYTHONPATH=src python benchmarks/bench_raw.py --motion [--motion-seeds 0,1,2]
    PYTHONPATH=src python benchmarks/bench_raw.py --motion-speed 1536x1024 [--motion-speed-folder DIR]

``--demosaic-candidates``: colour_demosaicing's Malvar 2004, bilinear and Menon 2007 (with and
without its refining step) and derender's AHD (:mod:`derender.raw.ahd`) on the noise-free true mosaic and on derender's merged mosaic of
every case, against the scene (one scale fitted): median / darkest / brightest decade.
``--demosaic-speed``: the compiled demosaic passes on a random mosaic of that size.
``--stages``: the merge of the speed bracket stage by stage (:func:`stages`).
``--motion``: issue 38's motion line with the ghost experiment's protocol
(:mod:`derender.evaluation.ghosts`: nikon-d5100, outdoor, 192x128, 7 exposures, the ``paper``
family, ``MotionSpec(objects=3, shake=4)``), ``--align translation --deghost`` at the truth's
reference on the tripod and handheld brackets, each zone's median error (3x3 fit) over the still
twin's, the same on the zones' *measured* pixels only (where the reference or a ghost-free frame
sees the scene unclipped, from the simulator's truth: :func:`derender.evaluation.raw_merge.measured_pixels`;
elsewhere no frame measures the reference's scene), and the shifts found against the simulator's.
Seeds 0 and 2 are tuned on (:data:`TUNING_SEEDS`), the others held out.
``--motion-speed``: the same options on a handheld bracket of that size, stage by stage (:func:`motion_speed`).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from derender.engine.options import OutputOptions

#: ``--motion``: the seeds tuned on (the others are held out).
TUNING_SEEDS = (0, 2)

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
    from derender.evaluation.raw_merge import demosaiced_truth, true_noise
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
                "raw": raw_merge(frames, output_space="camera_rgb", clip_negative=False, variance_terms="noise"),
                "raw-oracle": raw_merge(frames, output_space="camera_rgb", gain=g, read_noise=rn,
                                        clip_negative=False, variance_terms="noise"),
                "paper1": raw_to_camera_rgb(frames, clip_negative=False),
            }
            hu = _hdrutils(files, b.times)
            mask = results["raw"].mask
            demo_truth = demosaic_bayer(mosaic_signal(b.camera_rgb_per_s), "RGGB").astype(np.float64)
            scene_truth = b.camera_rgb_per_s
            for name, res in list(results.items()) + ([("hdrutils", None)] if hu is not None else []):
                rad = hu if res is None else res.radiance.astype(np.float64)
                var = None if res is None else res.variance
                # each merge against its own demosaic of the true mosaic: derender's and paper 1's
                # (raw_to_camera_rgb) demosaic the white-balanced mosaic (the balance divided out
                # after), HDRutils' does not
                own = demo_truth if name == "hdrutils" else demosaiced_truth(b, res.info)
                a = _scaled_scores(rad, own, mask, var)
                s = _scaled_scores(rad, scene_truth, mask)
                rows.append({"camera": f"{cam_name} {bits}-bit", "scene": kind, "method": name, "demosaiced": a,
                             "scene_truth": s,
                             "noise": None if res is None else res.info.get("noise")})
    return rows


def coverage(size, exposures, seed=3, demosaic="malvar2004"):
    """Coverage of derender's sigma (estimated noise, camera RGB) on the mosaic (merged photosite
    against the true one, before the demosaic), against the demosaiced truth and against the
    scene (demosaicing error included), for every case of :data:`CASES`."""
    from derender.camera import simulate_bracket
    from derender.camera.sensor import mosaic_signal
    from derender.camera.spectral import load_camera
    from derender.evaluation.raw_merge import bracket_raw_frames, demosaiced_truth, raw_scores
    from derender.raw.mosaic import sorted_raw_frames
    from derender.raw.noise import estimate_noise_frames
    from derender.raw.optimal import compiled_frames, interleave, merge_compiled, raw_merge

    print(f"## Coverage of sigma: {exposures} exposures, {size[0]}x{size[1]}, seed {seed}, demosaic {demosaic}\n")
    print("| camera | scene | mosaic 95 % | mosaic 50 % | demosaiced truth 95 % | 50 % | scene 95 % | 50 % |")
    print("|---|---|---|---|---|---|---|---|")
    for cam_name, bits, kind in CASES:
        b = simulate_bracket(load_camera(cam_name).with_bits(bits), kind=kind, size=size, exposures=exposures,
                             seed=seed, style="simple", pipeline="fixed")
        frames = bracket_raw_frames(b)
        res = raw_merge(frames, output_space="camera_rgb", clip_negative=False, demosaic=demosaic,
                        variance_terms="noise")
        ordered, times = sorted_raw_frames(frames)
        mosaics, black, white = compiled_frames(ordered)
        noise = estimate_noise_frames(mosaics, black, white, times)
        x, v, m = merge_compiled(mosaics, black, white, times, noise, scale=1.0 / (white[0] - black[0]))
        x, v = interleave(x, m.shape), interleave(v, m.shape)
        sl = (slice(3, -3), slice(3, -3))
        z = (np.abs(x - mosaic_signal(b.camera_rgb_per_s)) / np.sqrt(v))[sl][(m == 0)[sl]]
        a = raw_scores(res.radiance, demosaiced_truth(b, res.info), res.mask, res.variance)
        sc = raw_scores(res.radiance, b.camera_rgb_per_s, res.mask, res.variance)
        print(f"| {cam_name} {bits}-bit | {kind} | {np.mean(z <= 1.959964):.3f} | {np.mean(z <= 0.674490):.3f} "
              f"| {a['coverage95']:.3f} | {a['coverage50']:.3f} | {sc['coverage95']:.3f} | {sc['coverage50']:.3f} |")


def demosaic_candidates(size, exposures, seed=3, white_balanced=False):
    """The demosaic candidates' table (module docstring) for every case of :data:`CASES`; with
    ``white_balanced`` each mosaic is multiplied by the bracket's as-shot white balance before
    the demosaic and divided by it after (as dcraw and the merge's ``linear_srgb`` output do),
    so that the result is camera RGB still."""
    import colour_demosaicing as cd

    from derender.camera import simulate_bracket
    from derender.camera.sensor import mosaic_signal
    from derender.camera.spectral import load_camera
    from derender.evaluation.raw_merge import bracket_raw_frames
    from derender.raw.ahd import ahd_demosaic
    from derender.raw.mosaic import cfa_channel_index, sorted_raw_frames, spread_mask
    from derender.raw.noise import estimate_noise_frames
    from derender.raw.optimal import compiled_frames, interleave, merge_compiled

    cands = {"Malvar 2004": lambda m: cd.demosaicing_CFA_Bayer_Malvar2004(m, "RGGB"),
             "bilinear": lambda m: cd.demosaicing_CFA_Bayer_bilinear(m, "RGGB"),
             "Menon 2007": lambda m: cd.demosaicing_CFA_Bayer_Menon2007(m, "RGGB", refining_step=False),
             "Menon 2007 + refining": lambda m: cd.demosaicing_CFA_Bayer_Menon2007(m, "RGGB", refining_step=True),
             "AHD 2005": lambda m: ahd_demosaic(m, "RGGB")[0]}
    print(f"## Demosaic candidates: {exposures} exposures, {size[0]}x{size[1]}, seed {seed}"
          f"{', white-balanced first' if white_balanced else ''}\n")
    print("| camera | scene | mosaic | " + " | ".join(cands) + " |")
    print("|---|---|---|" + "---|" * len(cands))
    for cam_name, bits, kind in CASES:
        b = simulate_bracket(load_camera(cam_name).with_bits(bits), kind=kind, size=size, exposures=exposures,
                             seed=seed, style="simple", pipeline="fixed")
        ordered, times = sorted_raw_frames(bracket_raw_frames(b))
        mosaics, black, white = compiled_frames(ordered)
        noise = estimate_noise_frames(mosaics, black, white, times)
        x, _, m = merge_compiled(mosaics, black, white, times, noise, scale=1.0 / (white[0] - black[0]))
        truth = np.asarray(b.camera_rgb_per_s, np.float64)
        wb = np.asarray(ordered[len(ordered) // 2].as_shot_wb, np.float64) if white_balanced else np.ones(3)
        gains = wb[cfa_channel_index(m.shape, "RGGB")]
        for label, mos in (("true", mosaic_signal(b.camera_rgb_per_s).astype(np.float64)),
                           ("merged", interleave(x, m.shape).astype(np.float64))):
            cells = []
            for fn in cands.values():
                sc = _scaled_scores(np.asarray(fn(mos * gains), np.float64) / wb, truth, spread_mask(m))
                cells.append(f"{100 * sc['median']:.2f} / {100 * sc['dark_decade']:.2f} / "
                             f"{100 * sc['bright_decade']:.2f}")
            print(f"| {cam_name} | {kind} | {label} | " + " | ".join(cells) + " |", flush=True)


def demosaic_speed(size, with_colour_demosaicing=False, skip=()):
    """Wall and CPU seconds (best of 2) of the compiled demosaic passes on a random mosaic of ``size``
    (the passes whose name contains one of ``skip`` left out)."""
    from derender.raw.optimal import demosaic_compiled

    w, h = size
    rng = np.random.default_rng(0)
    m = (rng.random((h, w)) ** 2).astype(np.float32)
    x = np.zeros((2, 2, h // 2, w // 2), np.float32)
    for a in range(2):
        for c in range(2):
            x[a, c] = m[a::2, c::2]
    v = x * 0.01 + 1e-4
    mat = np.array([[1.8, -0.6, -0.2], [-0.2, 1.5, -0.3], [0.0, -0.5, 1.5]])
    mult = np.array([2.0, 1.0, 1.5])

    def timed(name, fn, repeats=2):
        if any(k in name for k in skip):
            return
        fn()
        wall = cpu = float("inf")
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
        print(f"| {name} | {wall:.3f} | {cpu:.3f} |", flush=True)

    print(f"## Demosaic passes on a {w}x{h} mosaic\n\n| pass | wall s | CPU s |\n|---|---|---|")
    timed("compiled Malvar 2004 + variance", lambda: demosaic_compiled(x, v, (h, w), "RGGB", mult, mat, "malvar2004"))
    timed("compiled Menon 2007, no variance", lambda: demosaic_compiled(x, None, (h, w), "RGGB", mult, mat,
                                                                          "menon2007"))
    timed("compiled Menon 2007 + variance", lambda: demosaic_compiled(x, v, (h, w), "RGGB", mult, mat, "menon2007"))
    timed("compiled AHD 2005, no variance", lambda: demosaic_compiled(x, None, (h, w), "RGGB", mult, mat, "ahd"))
    timed("compiled AHD 2005 + variance", lambda: demosaic_compiled(x, v, (h, w), "RGGB", mult, mat, "ahd"))
    if with_colour_demosaicing:
        import colour_demosaicing as cd

        m64 = m.astype(np.float64)
        timed("colour_demosaicing Menon 2007 (no refining, float64)",
              lambda: cd.demosaicing_CFA_Bayer_Menon2007(m64, "RGGB", refining_step=False), 1)
        timed("colour_demosaicing Malvar 2004 (float64)", lambda: cd.demosaicing_CFA_Bayer_Malvar2004(m64, "RGGB"), 1)


def _tiled_dngs(size, exposures, tile, folder):
    """A simulated bracket of ``size`` (nikon-d5100, outdoor, seed 1) written as DNG files, each
    mosaic tiled to ``tile`` photosites (``WxH``; the CFA phase kept): the simulator's noise,
    levels and metadata at a size it would take minutes to simulate."""
    from derender.camera import simulate_bracket
    from derender.camera.dng import write_dng

    b = simulate_bracket("nikon-d5100", kind="outdoor", size=size, exposures=exposures, seed=1, style="simple",
                         pipeline="fixed")
    cam = b.camera
    tw, th = tile
    span = float(cam.white_level - cam.black_level)
    files = []
    for j, t in enumerate(b.times):
        m = np.asarray(b.mosaics[j])
        m = np.tile(m, (-(-th // m.shape[0]), -(-tw // m.shape[1])))[:th, :tw]
        files.append(write_dng(Path(folder) / f"{j:02d}.dng", np.ascontiguousarray(m), cfa_pattern="RGGB",
                               black_level=cam.black_level, white_level=cam.white_level,
                               xyz_to_camera=b.xyz_to_camera, as_shot_neutral=1.0 / np.asarray(b.wb_true),
                               exposure_time=float(t), make=cam.make, model=cam.model, bits=cam.bits,
                               noise_profile=(1.0 / cam.full_well, (cam.read_noise ** 2 + 1.0 / 12.0) / span ** 2)))
    return files, b.times


def speed(size, exposures, tile=None, repeats=3, hdrutils=True):
    """Best of ``repeats`` (wall and CPU seconds, interleaved so that load on the machine hits
    every row alike): LibRaw decoding the frames one after the other (``rawpy.imread`` + the
    mosaic copy: the floor), derender's read (LibRaw in threads, the DNG tags), the merge in
    memory (read + noise fit + merge + variance + demosaic), the same writing both EXR files
    (zip), and HDRutils' merge of the same files."""
    import rawpy

    from derender.hdr.files import merge_files

    rows = {}

    def timed(name, fn):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        w, c = time.perf_counter() - w0, time.process_time() - c0
        bw, bc = rows.get(name, (np.inf, np.inf))
        rows[name] = (min(bw, w), min(bc, c))

    with tempfile.TemporaryDirectory() as tmp:
        if tile is None:
            from derender.camera import simulate_bracket, write_bracket

            b = simulate_bracket("nikon-d5100", kind="outdoor", size=size, exposures=exposures, seed=1,
                                 style="simple", pipeline="fixed")
            write_bracket(b, tmp)
            files, times = sorted((Path(tmp) / "raw").glob("*.dng")), b.times
        else:
            files, times = _tiled_dngs(size, exposures, tile, tmp)

        def decode():
            for f in files:
                with rawpy.imread(str(f)) as r:
                    np.array(r.raw_image_visible, copy=True)

        def read():
            from derender.io.raw import read_raw_bracket

            read_raw_bracket(files)

        merge_files(files[:2], method="raw")                  # numba's cache loaded once
        for _ in range(repeats):
            timed("LibRaw decode (floor)", decode)
            timed("derender read (threads)", read)
            timed("merge in memory (read, noise, merge, variance, demosaic)",
                  lambda: merge_files(files, method="raw", options={"variance": True}))
            timed("merge + radiance and variance EXR (zip)",
                  lambda: merge_files(files, method="raw", output=OutputOptions(variance_output=Path(tmp) / "v.exr",
                                                                                output=Path(tmp) / "m.exr")))
        if hdrutils and _hdrutils(files[:2], times[:2]) is not None:
            for _ in range(max(1, repeats - 1)):
                timed("HDRutils 1.2 merge (no variance)", lambda: _hdrutils(files, times))
    return rows


def stages(size, exposures, tile=None, repeats=3, folder=None):
    """Best of ``repeats`` (wall and CPU seconds, the stages interleaved) of the RAW merge stage by
    stage on the bracket of :func:`speed`: LibRaw decoding (the floor), derender's read, the
    noise fit, the merge (black and white levels, pooled start, two reweighted rounds, the
    censored Newton steps; and without censoring, so that the Newton steps' share shows), the
    demosaic with and without its variance, the two other demosaics of the default variance's
    interpolation term (:mod:`derender.raw.interpolation`), the mask, the EXR writing, and the
    whole merge in memory (the default variance, the noise-only variance, no variance). ``folder``: keep the DNG files there (written once) instead of a temporary folder."""
    import rawpy

    from derender.engine.outputs import write_outputs
    from derender.hdr.files import merge_files
    from derender.io.raw import read_raw_bracket
    from derender.raw.mosaic import sorted_raw_frames, spread_mask
    from derender.raw.noise import estimate_noise_frames
    from derender.raw.optimal import compiled_frames, demosaic_compiled, merge_compiled, output_matrix

    rows = {}

    def timed(name, fn):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        w, c = time.perf_counter() - w0, time.process_time() - c0
        bw, bc = rows.get(name, (np.inf, np.inf))
        rows[name] = (min(bw, w), min(bc, c))
        return out

    with tempfile.TemporaryDirectory() as tmp:
        where = Path(folder or tmp)
        where.mkdir(parents=True, exist_ok=True)
        files = sorted(where.glob("*.dng"))
        if len(files) != exposures:
            files, _ = _tiled_dngs(size, exposures, tile or size, where)

        def decode():
            for f in files:
                with rawpy.imread(str(f)) as r:
                    np.array(r.raw_image_visible, copy=True)

        merge_files(files[:2], method="raw", options={"variance": True})      # numba's cache loaded once
        for _ in range(repeats):
            timed("LibRaw decode, frame after frame (the floor)", decode)
            frames = timed("derender read (LibRaw in threads, DNG tags)", lambda: read_raw_bracket(files))
            ordered, times = sorted_raw_frames(frames)
            mosaics, black, white = compiled_frames(ordered)
            noise = timed("noise fit (frame pairs)", lambda: estimate_noise_frames(mosaics, black, white, times))
            inv = 1.0 / (white[0] - black[0])
            x, v, m = timed("merge: levels, pooled start, 2 reweighted rounds, censored Newton steps",
                            lambda: merge_compiled(mosaics, black, white, times, noise, scale=inv))
            timed("merge without censoring (no Newton steps)",
                  lambda: merge_compiled(mosaics, black, white, times, noise, censored=False, scale=inv))
            mat = output_matrix(ordered[len(ordered) // 2], "linear_srgb")
            wb = ordered[len(ordered) // 2].as_shot_wb
            res = timed("demosaic (Malvar) + colour matrix + variance",
                        lambda: demosaic_compiled(x, v, m.shape, "RGGB", wb, mat))
            timed("demosaic (Malvar) + colour matrix, no variance",
                  lambda: demosaic_compiled(x, None, m.shape, "RGGB", wb, mat))
            timed("interpolation term: bilinear demosaic", lambda: demosaic_compiled(x, None, m.shape, "RGGB", wb, mat,
                                                                                      "bilinear"))
            timed("interpolation term: Menon demosaic (raw/menon.py)",
                  lambda: demosaic_compiled(x, None, m.shape, "RGGB", wb, mat, "menon2007"))
            timed("mask spread", lambda: spread_mask(m, 2))
            from derender.core.types import HDRResult

            hdr = HDRResult(radiance=res[0], variance=res[1], mask=spread_mask(m, 2), info={})
            timed("write radiance + variance EXR (zip)",
                  lambda: write_outputs(hdr, where / "m.exr", where / "v.exr", name="raw"))
            frames = ordered = mosaics = x = v = m = res = hdr = None     # freed before the whole merge
            timed("merge_files in memory (read, noise, merge, variance, demosaic)",
                  lambda: merge_files(files, method="raw", options={"variance": True}))
            timed("the same, variance_terms=noise (no interpolation term)",
                  lambda: merge_files(files, method="raw", options={"variance": True, "variance_terms": "noise"}))
            timed("the same, no variance", lambda: merge_files(files, method="raw"))
        for name in ("m.exr", "v.exr"):
            (where / name).unlink(missing_ok=True)
    return rows


def motion(seeds) -> None:
    """Issue 38's motion line (module docstring, ``--motion``)."""
    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.ghosts import zone_errors
    from derender.evaluation.raw_merge import bracket_raw_frames, measured_pixels
    from derender.hdr.raw import merge_raw

    base = MotionSpec(objects=3, shake=4)
    print("| seed | set | setting | static / still | swept / still | object / still | measured: static / still "
          "| swept / still | object / still | measured swept, object px | largest shift error (photosites) "
          "| s per merge |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for seed in seeds:
        kw = dict(kind="outdoor", size=(192, 128), exposures=7, seed=seed, family="paper")
        still = simulate_bracket("nikon-d5100", motion=base.still(), **kw)
        mo = MotionOptions(reference=still.params["motion"]["reference"], align="translation", deghost=True)
        rs = merge_raw(bracket_raw_frames(still), motion=mo)
        for name, spec in (("tripod", base.tripod()), ("handheld", base)):
            b = simulate_bracket("nikon-d5100", motion=spec, **kw)
            t0 = time.perf_counter()
            rm = merge_raw(bracket_raw_frames(b), motion=mo)
            dt = time.perf_counter() - t0
            m = zone_errors(rm.radiance, b.truth_linear_srgb, b.motion_zones)
            z = zone_errors(rs.radiance, still.truth_linear_srgb, b.motion_zones)
            # the zones where the reference or a ghost-free frame measures the scene unclipped
            # (derender.evaluation.raw_merge.measured_pixels, from the simulator's truth)
            measured = measured_pixels(b)
            zm = np.where(measured, b.motion_zones, 255)
            mm = zone_errors(rm.radiance, b.truth_linear_srgb, zm)
            sm = zone_errors(rs.radiance, still.truth_linear_srgb, zm)
            err = np.max(np.abs(np.array(rm.info["raw_motion"]["shifts"], float)
                                + np.array(b.params["motion"]["shifts_dy_dx"], float)))
            part = "tuning" if seed in TUNING_SEEDS else "held out"
            print(f"| {seed} | {part} | {name} | {m['static'] / z['static']:.3f} | {m['swept'] / z['swept']:.3f} "
                  f"| {m['object'] / z['object']:.3f} | {mm['static'] / sm['static']:.3f} "
                  f"| {mm['swept'] / sm['swept']:.3f} | {mm['object'] / sm['object']:.3f} "
                  f"| {int(np.sum(zm == 1))} of {int(np.sum(b.motion_zones == 1))}, "
                  f"{int(np.sum(zm == 2))} of {int(np.sum(b.motion_zones == 2))} | {err:.2f} | {dt:.2f} |", flush=True)


def motion_speed(size, exposures=7, seed=0, repeats=2, folder=None) -> None:
    """``--motion-speed WxH``: ``--align translation --deghost`` on a handheld RAW bracket
    (``MotionSpec(objects=3, shake=4)``, outdoor, the ``paper`` family, nikon-d5100) stage by
    stage, best of ``repeats`` after one untimed run (numba's compilation), wall and CPU time
    (the process's, threads included: steadier on a shared machine): registration
    (:func:`derender.hdr.raw.raw_motion` without ghost removal), registration + ghost removal,
    the merge in colour (:func:`derender.raw.register.raw_merge_shifted`), the whole
    :func:`derender.hdr.raw.merge_raw`, and the same merge without motion options. The frames are
    kept in ``folder`` (a pickle) to run the same bracket on two checkouts."""
    import pickle

    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.raw_merge import bracket_raw_frames
    from derender.hdr.raw import merge_raw, raw_motion
    from derender.raw.register import raw_merge_shifted

    w, h = size
    path = Path(folder) / f"motion_{w}x{h}_{exposures}_{seed}.pkl" if folder else None
    if path is not None and path.exists():
        frames, ref = pickle.loads(path.read_bytes())
    else:
        b = simulate_bracket("nikon-d5100", motion=MotionSpec(objects=3, shake=4), kind="outdoor", size=(w, h),
                             exposures=exposures, seed=seed, family="paper")
        frames, ref = bracket_raw_frames(b), b.params["motion"]["reference"]
        if path is not None:
            path.write_bytes(pickle.dumps((frames, ref)))
    mo = MotionOptions(reference=ref, align="translation", deghost=True)
    mo_align = MotionOptions(reference=ref, align="translation", deghost=False)
    info = raw_motion(frames, mo)[2]

    def best(fn):
        fn()
        times = []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            times.append((time.perf_counter() - t0, time.process_time() - c0))
        return min(t for t, _ in times), min(c for _, c in times)

    rows = [("registration (raw_motion, no ghost removal)", best(lambda: raw_motion(frames, mo_align))),
            ("registration + ghost removal (raw_motion)", best(lambda: raw_motion(frames, mo))),
            ("merge in colour (raw_merge_shifted)",
             best(lambda: raw_merge_shifted(frames, info["shifts"], info["noise"], valid=info["kept"]))),
            ("merge_raw --align translation --deghost", best(lambda: merge_raw(frames, motion=mo))),
            ("merge_raw, no motion options", best(lambda: merge_raw(frames)))]
    print(f"## --align translation --deghost, {exposures} frames of {w}x{h}, seed {seed}, shifts {info['shifts']}\n")
    print("| stage | wall s (best of %d) | CPU s (best of %d) |" % (repeats, repeats))
    print("|---|---|---|")
    for name, (t, c) in rows:
        print(f"| {name} | {t:.2f} | {c:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="384x256")
    ap.add_argument("--exposures", type=int, default=5)
    ap.add_argument("--speed-size", default="1536x1024")
    ap.add_argument("--speed-exposures", type=int, default=5)
    ap.add_argument("--speed-tile", default=None, help="WxH: tile the speed bracket's mosaics to this size "
                    "(e.g. 6016x4000, 24 MP)")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--speed-only", action="store_true")
    ap.add_argument("--no-hdrutils-speed", action="store_true")
    ap.add_argument("--coverage-only", action="store_true")
    ap.add_argument("--coverage-demosaic", default="malvar2004", choices=("malvar2004", "menon2007", "ahd"),
                    help="the demosaic of --coverage-only")
    ap.add_argument("--demosaic-candidates", action="store_true")
    ap.add_argument("--white-balanced", action="store_true",
                    help="--demosaic-candidates on the mosaics white-balanced first (as-shot), undone after")
    ap.add_argument("--demosaic-speed", default=None, help="WxH: time the compiled demosaic passes")
    ap.add_argument("--with-colour-demosaicing", action="store_true")
    ap.add_argument("--skip-passes", default="", help="comma-separated: --demosaic-speed leaves out the passes "
                                                       "whose name contains one, e.g. 'Menon 2007 + variance'")
    ap.add_argument("--stages", action="store_true", help="the merge stage by stage at --speed-size/--speed-tile")
    ap.add_argument("--stages-folder", default=None, help="keep the speed bracket's DNG files in this folder")
    ap.add_argument("--motion", action="store_true", help="issue 38's motion line (module docstring)")
    ap.add_argument("--motion-seeds", default="0,1,2")
    ap.add_argument("--motion-speed", default=None, help="WxH: --align --deghost on a handheld bracket, stage by stage")
    ap.add_argument("--motion-speed-folder", default=None, help="keep that bracket's frames in this folder")
    args = ap.parse_args()
    if args.motion:
        motion([int(v) for v in args.motion_seeds.split(",")])
        return
    if args.motion_speed:
        motion_speed(tuple(int(v) for v in args.motion_speed.split("x")), folder=args.motion_speed_folder)
        return
    w, h = (int(v) for v in args.size.split("x"))
    if args.demosaic_candidates:
        demosaic_candidates((w, h), args.exposures, white_balanced=args.white_balanced)
        return
    if args.demosaic_speed:
        demosaic_speed(tuple(int(v) for v in args.demosaic_speed.split("x")), args.with_colour_demosaicing,
                       tuple(k for k in args.skip_passes.split(",") if k))
        return
    if args.stages:
        _print_stages(args)
        return
    if args.coverage_only:
        coverage((w, h), args.exposures, demosaic=args.coverage_demosaic)
        return
    if args.speed_only:
        _print_speed(args)
        return
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
        _print_speed(args)


def _print_speed(args) -> None:
    import os

    sw, sh = (int(v) for v in args.speed_size.split("x"))
    tile = None if args.speed_tile is None else tuple(int(v) for v in args.speed_tile.split("x"))
    rows = speed((sw, sh), args.speed_exposures, tile, hdrutils=not args.no_hdrutils_speed)
    fw, fh = tile or (sw, sh)
    print(f"\n## Speed: {args.speed_exposures} frames of {fw}x{fh} ({fw * fh / 1e6:.1f} MP"
          + (f", tiled from {sw}x{sh}" if tile else "") + f"), {os.cpu_count()} CPUs, best of 3\n")
    dec_w, dec_c = rows["LibRaw decode (floor)"]
    print("| step | wall s | x floor | CPU s |")
    print("|---|---|---|---|")
    for name, (wall, cpu) in rows.items():
        print(f"| {name} | {wall:.3f} | {wall / dec_w:.2f}x | {cpu:.3f} |")


def _print_stages(args) -> None:
    import os

    sw, sh = (int(v) for v in args.speed_size.split("x"))
    tile = None if args.speed_tile is None else tuple(int(v) for v in args.speed_tile.split("x"))
    rows = stages((sw, sh), args.speed_exposures, tile, folder=args.stages_folder)
    fw, fh = tile or (sw, sh)
    print(f"\n## Stages: {args.speed_exposures} frames of {fw}x{fh} ({fw * fh / 1e6:.1f} MP), {len(os.sched_getaffinity(0))} CPUs "
          f"(of {os.cpu_count()}), load average {os.getloadavg()[0]:.1f}, best of 3\n")
    dec_w, dec_c = rows["LibRaw decode, frame after frame (the floor)"]
    print("| stage | wall s | x floor (wall) | CPU s | x floor (CPU) |")
    print("|---|---|---|---|---|")
    for name, (wall, cpu) in rows.items():
        print(f"| {name} | {wall:.3f} | {wall / dec_w:.2f}x | {cpu:.3f} | {cpu / dec_c:.2f}x |")


if __name__ == "__main__":
    main()
