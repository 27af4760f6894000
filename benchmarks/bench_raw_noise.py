"""RAW brackets: the noise fit against the simulator's true noise, still and with motion, and its merge.

For each camera the RAW benchmark has (nikon-d5100 at 14 bit, sigma-sd-merrill at 12 bit)
and each seed, three brackets of the ghost experiment's protocol
(:mod:`derender.evaluation.ghosts`: outdoor, 192x128, 7 exposures, the ``paper`` family,
``MotionSpec(objects=3, shake=4)``): ``still`` (nothing moves), ``tripod`` (objects move) and
``handheld`` (objects move, the camera shakes). Each is merged as ``derender merge --method raw``
does (``--align translation --deghost`` at the truth's reference for the moving ones, plain for
the still one), once with the noise estimated from the frames and once given the simulator's
true gain and read noise (the oracle). Reported: the estimated gain and read noise over the
truth (:func:`derender.evaluation.raw_merge.true_noise`), and the median and p90 relative error
of the estimated-noise merge over the oracle's (issue 38's "within 1.05x" line), against the
scene at the reference's instant (linear sRGB, :func:`derender.evaluation.raw_merge.raw_scores`,
no fit: the units are exact; the still bracket also against the demosaiced true mosaic, the
merge's error alone). No parameter of the noise fit was tuned on these brackets.

    PYTHONPATH=src python benchmarks/bench_raw_noise.py [--seeds 0,1,2,3,4] [--cameras nikon-d5100,sigma-sd-merrill]

``--coverage``: the coverage of the default variance (``variance_terms="total"``: noise and the
demosaic's interpolation error, :mod:`derender.raw.interpolation`) against the scene, and of
the noise-only variance against the demosaiced true mosaic and against the scene, on still
brackets (``style="simple"``, fixed pipeline, 256x192, 5 exposures) of both cameras and three
scenes, per demosaic. The interpolation weights were fitted on nikon-d5100 ``outdoor`` and
``indoor`` at seed 3 (``tuning`` rows); every other row is held out.

    PYTHONPATH=src python benchmarks/bench_raw_noise.py --coverage [--seeds 3,4] [--demosaics malvar2004]
        [--space camera_rgb,linear_srgb,xyz] [--total-only]

``--correlation``: the channels' correlation at a pixel and whether the variance carries it
into linear sRGB, by Monte Carlo over noise seeds (:func:`correlation_rows`).

    PYTHONPATH=src python benchmarks/bench_raw_noise.py --correlation [--draws 24] [--demosaics malvar2004]

``--interpolation-correlation``: the same question for the interpolation term of the variance
(:func:`interpolation_correlation_rows`), at seed 3.

    PYTHONPATH=src python benchmarks/bench_raw_noise.py --interpolation-correlation [--demosaics malvar2004]

``--colour-texture``: why eq. (1)'s weights fitted on one camera overstate the error on another
(:func:`colour_texture_rows`): on the noise-free mosaic, the scale on eq. (1) that makes its 95 %
and 50 % intervals cover, with the scene as it is and with its colour blurred under its
luminance texture, per camera and scene, at seed 3.

    PYTHONPATH=src python benchmarks/bench_raw_noise.py --colour-texture [--demosaics malvar2004]

(``xyz``: the scene's truth is its linear sRGB through ``LINEAR_SRGB_TO_XYZ``, D65.)
"""

from __future__ import annotations

import argparse

import numpy as np


def noise_rows(cameras, seeds, settings=("still", "tripod", "handheld")):
    """One row per (camera, seed, setting): noise ratios and error ratios (module docstring)."""
    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec
    from derender.camera.spectral import load_camera
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.raw_merge import bracket_raw_frames, demosaiced_truth, raw_scores, true_noise
    from derender.hdr.raw import merge_raw

    base = MotionSpec(objects=3, shake=4)
    rows = []
    for cam_name in cameras:
        cam = load_camera(cam_name)
        g, rn = true_noise(cam)
        for seed in seeds:
            kw = dict(kind="outdoor", size=(192, 128), exposures=7, seed=seed, family="paper")
            specs = {"still": base.still(), "tripod": base.tripod(), "handheld": base}
            for setting in settings:
                b = simulate_bracket(cam, motion=specs[setting], **kw)
                ref = b.params["motion"]["reference"]
                mo = None if setting == "still" else MotionOptions(reference=ref, align="translation", deghost=True)
                frames = bracket_raw_frames(b)
                est = merge_raw(frames, {"variance": True}, motion=mo)
                orc = merge_raw(bracket_raw_frames(b), {"variance": True, "gain": g, "read_noise": rn}, motion=mo)
                n = est.info["noise"]
                se = raw_scores(est.radiance, b.truth_linear_srgb, est.mask)
                so = raw_scores(orc.radiance, b.truth_linear_srgb, est.mask)
                row = {"camera": cam_name, "seed": seed, "setting": setting,
                       "gain": n["gain_dn_per_electron"] / g, "read": n["read_noise_dn"] / rn,
                       "median": se["median"] / so["median"], "p90": se["p90"] / so["p90"],
                       "dark": se["dark_decade"] / so["dark_decade"]}
                if setting == "still":
                    t = demosaiced_truth(b, est.info)
                    de, do = raw_scores(est.radiance, t, est.mask), raw_scores(orc.radiance, t, est.mask)
                    row.update(median_mosaic=de["median"] / do["median"], p90_mosaic=de["p90"] / do["p90"],
                               dark_mosaic=de["dark_decade"] / do["dark_decade"])
                rows.append(row)
                print(_line(row), flush=True)
    return rows


def coverage_rows(cameras, seeds, demosaics, space="camera_rgb", scenes=("outdoor", "indoor", "night"),
                  total_only=False):
    """The ``--coverage`` table's rows (module docstring); ``space`` one output space or several,
    comma-separated (each bracket simulated once); ``total_only`` skips the noise-only columns."""
    from derender.camera import simulate_bracket
    from derender.camera.spectral import load_camera
    from derender.core.colorimetry import LINEAR_SRGB_TO_XYZ
    from derender.evaluation.raw_merge import bracket_raw_frames, demosaiced_truth, raw_scores
    from derender.raw.optimal import raw_merge

    n = 0
    for cam_name in cameras:
        for kind in scenes:
            for seed in seeds:
                b = simulate_bracket(load_camera(cam_name), kind=kind, size=(256, 192), exposures=5, seed=seed,
                                     style="simple", pipeline="fixed")
                frames = bracket_raw_frames(b)
                for sp in space.split(","):
                    truth = {"camera_rgb": b.camera_rgb_per_s, "linear_srgb": b.truth_linear_srgb,
                             "xyz": b.truth_linear_srgb @ np.asarray(LINEAR_SRGB_TO_XYZ).T}[sp]
                    for dm in demosaics:
                        tot = raw_merge(frames, output_space=sp, demosaic=dm, clip_negative=False)
                        st = raw_scores(tot.radiance, truth, tot.mask, tot.variance)
                        tag = "tuning" if (cam_name, kind, seed) in TUNING else "held out"
                        cols = ""
                        if not total_only:
                            noi = raw_merge(frames, output_space=sp, demosaic=dm, clip_negative=False,
                                            variance_terms="noise")
                            sn = raw_scores(noi.radiance, truth, noi.mask, noi.variance)
                            sd = raw_scores(noi.radiance, demosaiced_truth(b, noi.info), noi.mask, noi.variance)
                            cols = (f" {sn['coverage95']:.3f} | {sn['coverage50']:.3f} "
                                    f"| {sd['coverage95']:.3f} | {sd['coverage50']:.3f} |")
                        print(f"| {cam_name} | {kind} | {seed} | {sp} | {dm} | {tag} | **{st['coverage95']:.3f}** "
                              f"| **{st['coverage50']:.3f}** |{cols} "
                              f"{100 * tot.info['variance_sources']['interpolation']:.0f} % |", flush=True)
                        n += 1
    return n


def correlation_rows(cameras, demosaics, draws=24, kind="outdoor", seed=3):
    """``--correlation``: is the noise variance carried into linear sRGB with the channels'
    correlation? Per camera and demosaic, ``draws`` noise realisations of one still bracket
    (the simulator's scene and true mosaic, :func:`derender.camera.sensor.expose_mosaic` with
    seeds ``[seed, k, j]``) merged with the true noise in camera RGB and linear sRGB
    (``variance_terms="noise"``). Printed: the median over pixels of the per-pixel channel
    correlation; the median ratio of the draws' variance to the merge's variance (``draws - 1``
    degrees of freedom: 0.971 for 24 draws when exact); and the median ratio of the variance a
    propagation as if the camera channels were independent (``sum_c F_oc^2 Var[cam_c]``,
    ``F = M diag(w)`` from the camera-RGB output) would give, to the draws' variance."""
    from derender.camera import simulate_bracket
    from derender.camera.sensor import expose_mosaic, mosaic_signal
    from derender.camera.spectral import load_camera
    from derender.evaluation.raw_merge import bracket_raw_frames, true_noise
    from derender.raw.optimal import raw_merge

    for cam_name in cameras:
        cam = load_camera(cam_name)
        b = simulate_bracket(cam, kind=kind, size=(256, 192), exposures=5, seed=seed, style="simple",
                             pipeline="fixed")
        g, rn = true_noise(cam)
        frames = bracket_raw_frames(b)
        sig = mosaic_signal(b.camera_rgb_per_s)
        for dm in demosaics:
            outs = {"camera_rgb": [], "linear_srgb": []}
            var, info = {}, {}
            for k in range(draws):
                for j, f in enumerate(frames):
                    f.mosaic = expose_mosaic(sig, cam, float(f.exposure_time), np.random.default_rng([seed, k, j]))
                for sp in outs:
                    r = raw_merge(frames, output_space=sp, gain=g, read_noise=rn, demosaic=dm, clip_negative=False,
                                  variance_terms="noise")
                    outs[sp].append(r.radiance[4:-4, 4:-4].astype(np.float64))
                    if k == 0:
                        var[sp], info[sp], ok = r.variance[4:-4, 4:-4].astype(np.float64), r.info, r.mask[4:-4, 4:-4] == 0
            for sp, stack in outs.items():
                a = np.stack(stack)
                d = a - a.mean(0)
                cov = np.einsum("khwi,khwj->hwij", d, d) / (draws - 1)
                v = np.einsum("hwii->hwi", cov)
                sd = np.sqrt(np.maximum(v, 1e-300))
                corr = [float(np.median((cov[..., i, j] / (sd[..., i] * sd[..., j]))[ok])) for i, j in ((0, 1), (0, 2), (1, 2))]
                ratio = np.median((v / var[sp])[ok], axis=0)
                line = (f"| {cam_name} | {dm} | {sp} | {corr[0]:.2f} / {corr[1]:.2f} / {corr[2]:.2f} "
                        f"| {' / '.join(f'{x:.3f}' for x in ratio)} |")
                if sp == "linear_srgb":
                    f_ = np.asarray(info[sp]["output_matrix"]) @ np.diag(info[sp]["wb_multipliers"])
                    indep = np.einsum("oc,hwc->hwo", f_ ** 2, var["camera_rgb"])
                    line += f" {' / '.join(f'{x:.2f}' for x in np.median((indep / v)[ok], axis=0))} |"
                else:
                    line += " - |"
                print(line, flush=True)


def interpolation_correlation_rows(cameras, demosaics, specs=(("outdoor", 3), ("indoor", 3), ("night", 3))):
    """``--interpolation-correlation``: the channels' correlation of the demosaic's interpolation
    error, and how the interpolation term of the variance is carried into linear sRGB and XYZ.
    Per bracket (256x192, 5 exposures, noise estimated) and demosaic: over the measured pixels,
    the correlation between the white-balanced camera-RGB channels of the true error (merge
    minus scene) and of the disagreements the term is made of
    (:func:`derender.raw.interpolation.interpolation_variance`); then the coverage against the
    scene in linear sRGB and XYZ of the noise variance plus the term carried by the output
    matrix ``F`` four ways: ``per pixel`` (the default: each disagreement through ``F``, then
    squared, i.e. its own per-pixel correlation; with the colour-texture term of eq. (2) since
    it was added, which the three other columns leave out: they are eq. (1)'s disagreements only), ``independent`` (``sum_c F_oc^2 s_c^2`` with
    ``s_c^2 = sum_a k_a e_a,c^2`` in balanced camera RGB), ``rho`` (``sum_cd F_oc F_od rho_cd
    s_c s_d``, ``rho`` the true error's correlation of that bracket) and ``rho = 1``."""
    from derender.camera import simulate_bracket
    from derender.camera.spectral import load_camera
    from derender.core.colorimetry import LINEAR_SRGB_TO_XYZ
    from derender.evaluation.raw_merge import bracket_raw_frames
    from derender.raw.interpolation import INTERPOLATION_ESTIMATES
    from derender.raw.optimal import raw_merge

    z50, z95 = 0.6744897501960817, 1.959963984540054
    sl = (slice(3, -3), slice(3, -3))

    def cover(v, e):
        z = np.abs(e) / np.sqrt(np.maximum(v, 1e-300))
        return f"{np.mean(z <= z95):.3f} / {np.mean(z <= z50):.3f}"

    def corr(e):
        c = e.T @ e / len(e)
        d = np.sqrt(np.diag(c))
        r = c / np.outer(d, d)
        return r, f"{r[0, 1]:.2f} / {r[0, 2]:.2f} / {r[1, 2]:.2f}"

    for cam_name in cameras:
        for kind, seed in specs:
            b = simulate_bracket(load_camera(cam_name), kind=kind, size=(256, 192), exposures=5, seed=seed,
                                 style="simple", pipeline="fixed")
            frames = bracket_raw_frames(b)
            tag = "tuning" if (cam_name, kind, seed) in TUNING else "held out"
            for dm in demosaics:
                rc = raw_merge(frames, output_space="camera_rgb", clip_negative=False, variance_terms="noise",
                               demosaic=dm)
                w = np.asarray(rc.info["wb_multipliers"])
                ok = rc.mask[sl] == 0
                bal = rc.radiance[sl].astype(np.float64) * w
                rho, rho_text = corr((bal - b.camera_rgb_per_s[sl] * w)[ok])
                s2 = np.zeros(bal.shape)
                dis = []
                for a, k in INTERPOLATION_ESTIMATES[dm]:
                    oa = raw_merge(frames, output_space="camera_rgb", clip_negative=False, variance=False,
                                   demosaic=a).radiance[sl].astype(np.float64) * w
                    s2 += k * (bal - oa) ** 2
                    dis.append((bal - oa)[ok])
                _, dis_text = corr(np.concatenate(dis))
                s = np.sqrt(s2[ok])
                cells = []
                for space in ("linear_srgb", "xyz"):
                    r = raw_merge(frames, output_space=space, clip_negative=False, demosaic=dm)
                    rn = raw_merge(frames, output_space=space, clip_negative=False, demosaic=dm, variance_terms="noise")
                    f = np.asarray(r.info["output_matrix"])
                    truth = b.truth_linear_srgb[sl] if space == "linear_srgb" else \
                        b.truth_linear_srgb[sl] @ np.asarray(LINEAR_SRGB_TO_XYZ).T
                    err = (r.radiance[sl] - truth)[ok]
                    vn = rn.variance[sl][ok].astype(np.float64)
                    cells.append(cover(r.variance[sl][ok], err))
                    for model in (np.eye(3), rho, np.ones((3, 3))):
                        cells.append(cover(vn + np.einsum("oi,oj,ij,ni,nj->no", f, f, model, s, s), err))
                print(f"| {cam_name} | {kind} | {seed} | {tag} | {dm} | {rho_text} | {dis_text} | "
                      + " | ".join(cells) + " |", flush=True)


def colour_texture_rows(cameras, demosaics, scenes=("outdoor", "indoor", "night"), seed=3, blur=3.0):
    """``--colour-texture``: per camera, scene and demosaic, on the noise-free true mosaic
    (white-balanced camera RGB, no noise, so only the interpolation error is left), the factor on
    eq. (1) of :mod:`derender.raw.interpolation` (its disagreements and weights only) that makes
    the 95 % and the 50 % interval cover exactly, over the interpolated pixel-channels; first
    for the scene as it is, then for the scene with its colour (each channel minus the channels'
    mean) blurred by a Gaussian of ``blur`` pixels and its luminance (the mean) unchanged. Also
    the median, over pixels, of ``(|L(R - G)| + |L(B - G)|) / |L(mean)|`` (``L`` the 3x3
    Laplacian) of the true balanced image: the scene's colour texture in camera RGB."""
    from scipy.ndimage import gaussian_filter, laplace

    from derender.camera import simulate_bracket
    from derender.camera.sensor import mosaic_signal
    from derender.camera.spectral import load_camera
    from derender.raw.interpolation import INTERPOLATION_ESTIMATES
    from derender.raw.mosaic import demosaic_bayer

    z50, z95 = 0.6744897501960817, 1.959963984540054
    sl = (slice(3, -3), slice(3, -3))

    def scale(vi, e, z, target):
        lo, hi = 0.01, 100.0
        for _ in range(50):
            m = np.sqrt(lo * hi)
            lo, hi = (lo, m) if np.mean(np.abs(e) <= z * np.sqrt(m * vi)) > target else (m, hi)
        return np.sqrt(lo * hi)

    for cam_name in cameras:
        for kind in scenes:
            b = simulate_bracket(load_camera(cam_name), kind=kind, size=(256, 192), exposures=5, seed=seed,
                                 style="simple", pipeline="fixed")
            t = b.camera_rgb_per_s * np.asarray(b.wb_true)
            lap = np.stack([laplace(t[..., c]) for c in range(3)], -1)[sl]
            y = np.abs(lap.mean(-1))
            colour = np.median((np.abs(lap[..., 0] - lap[..., 1]) + np.abs(lap[..., 2] - lap[..., 1]))
                               / np.maximum(y, 1e-12))
            mean = t.mean(-1, keepdims=True)
            blurred = mean + np.stack([gaussian_filter((t - mean)[..., c], blur) for c in range(3)], -1)
            for dm in demosaics:
                cells = []
                for img in (t, blurred):
                    x = mosaic_signal(img)
                    names = {dm} | {a for a, _ in INTERPOLATION_ESTIMATES[dm]}
                    o = {m: demosaic_bayer(x, "RGGB", m).astype(np.float64)[sl] for m in names}
                    vi = sum(k * (o[dm] - o[a]) ** 2 for a, k in INTERPOLATION_ESTIMATES[dm])
                    e = o[dm] - img[sl]
                    ok = vi > 0
                    cells.append(f"{scale(vi[ok], e[ok], z95, 0.95):.2f} / {scale(vi[ok], e[ok], z50, 0.5):.2f}")
                print(f"| {cam_name} | {kind} | {dm} | {colour:.2f} | {cells[0]} | {cells[1]} |", flush=True)


#: The brackets the interpolation weights were fitted on (camera, scene, seed).
TUNING = {("nikon-d5100", "outdoor", 3), ("nikon-d5100", "indoor", 3)}


def _line(r) -> str:
    extra = (f" | {r['median_mosaic']:.3f} | {r['p90_mosaic']:.3f} | {r['dark_mosaic']:.3f}"
             if "median_mosaic" in r else " | - | - | -")
    return (f"| {r['camera']} | {r['seed']} | {r['setting']} | {r['gain']:.3f} | {r['read']:.3f} "
            f"| {r['median']:.3f} | {r['p90']:.3f} | {r['dark']:.3f}{extra} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--cameras", default="nikon-d5100,sigma-sd-merrill")
    ap.add_argument("--settings", default="still,tripod,handheld")
    ap.add_argument("--coverage", action="store_true", help="coverage of the variance against the scene")
    ap.add_argument("--demosaics", default="malvar2004,menon2007,ahd")
    ap.add_argument("--space", default="camera_rgb", help="output space(s), comma-separated")
    ap.add_argument("--total-only", action="store_true", help="--coverage: the default variance's columns only")
    ap.add_argument("--correlation", action="store_true", help="the channels' correlation, Monte Carlo over noise")
    ap.add_argument("--draws", type=int, default=24)
    ap.add_argument("--interpolation-correlation", action="store_true",
                    help="the interpolation error's channel correlation and its propagation to sRGB / XYZ")
    ap.add_argument("--colour-texture", action="store_true",
                    help="eq. (1)'s scale to cover, noise-free, with the scene's colour texture and without")
    args = ap.parse_args()
    if args.colour_texture:
        print("| camera | scene | demosaic | colour / luminance texture (median) | eq. (1)'s scale to cover 95 % / 50 %: "
              "scene | colour blurred |")
        print("|---|---|---|---|---|---|")
        colour_texture_rows(args.cameras.split(","), args.demosaics.split(","))
        return
    if args.interpolation_correlation:
        print("| camera | scene | seed | split | demosaic | true error's channel correlation (0,1) / (0,2) / (1,2) "
              "| disagreements' | linear sRGB 95 % / 50 %: per pixel (default) | independent | rho | rho = 1 "
              "| XYZ: per pixel (default) | independent | rho | rho = 1 |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        interpolation_correlation_rows(args.cameras.split(","), args.demosaics.split(","))
        return
    if args.correlation:
        print("| camera | demosaic | space | channel correlation (0,1) / (0,2) / (1,2), median | draws' variance / "
              "merge's variance, median per channel | independent-channel propagation / draws' variance |")
        print("|---|---|---|---|---|---|")
        correlation_rows(args.cameras.split(","), args.demosaics.split(","), args.draws)
        return
    if args.coverage:
        print(f"## Coverage ({args.space}): total variance vs scene, noise-only vs scene, noise-only vs demosaiced "
              "truth\n")
        noise_cols = "" if args.total_only else (" noise-only vs scene 95 % | 50 % | noise-only vs demosaiced "
                                                 "truth 95 % | 50 % |")
        print(f"| camera | scene | seed | space | demosaic | split | total vs scene 95 % | 50 % |{noise_cols} "
              "interpolation's median share |")
        print("|---|---|---|---|---|---|---|---|" + ("" if args.total_only else "---|---|---|---|") + "---|")
        coverage_rows(args.cameras.split(","), [int(s) for s in args.seeds.split(",")], args.demosaics.split(","),
                      args.space, total_only=args.total_only)
        return
    print("| camera | seed | setting | gain / true | read noise / true | median / oracle | p90 / oracle "
          "| darkest decade / oracle | median / oracle (mosaic truth) | p90 / oracle (mosaic truth) "
          "| darkest / oracle (mosaic truth) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rows = noise_rows(args.cameras.split(","), [int(s) for s in args.seeds.split(",")],
                      tuple(args.settings.split(",")))
    for key in ("gain", "read", "median", "p90"):
        for s in sorted({r["setting"] for r in rows}):
            v = np.array([r[key] for r in rows if r["setting"] == s])
            print(f"{key} {s}: {v.min():.3f}-{v.max():.3f}")


if __name__ == "__main__":
    main()
