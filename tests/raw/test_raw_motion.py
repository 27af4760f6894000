"""Motion on RAW brackets (derender.hdr.raw.raw_motion): alignment by Ward's MTB on a grey rendering
refined to a fraction of a photosite (derender.raw.register), ghost removal by the Poisson-Gaussian
model against the reference; simulated DNG
mosaics with camera shake and moving discs (derender.camera.motion), scored per motion zone
against the scene at the reference instant."""

import numpy as np
import pytest

from derender.camera import simulate_bracket
from derender.camera.motion import ZONE_OBJECT, ZONE_STATIC, MotionSpec
from derender.core.errors import InputError
from derender.engine.motion.run import MotionOptions
from derender.evaluation.raw_merge import bracket_raw_frames, raw_scores
from derender.hdr.raw import merge_raw


def _zone_median(res, bracket, zone):
    mask = res.mask.copy()
    mask[bracket.motion_zones != zone] = 1
    return raw_scores(res.radiance, bracket.camera_rgb_per_s, mask)["median"]


@pytest.fixture(scope="module")
def moving():
    return simulate_bracket("nikon-d5100", kind="outdoor", size=(192, 128), exposures=5, seed=4, style="simple",
                            pipeline="fixed", motion=MotionSpec(objects=3, shake=3))


def test_alignment_finds_the_shifts(moving):
    """The simulator's shifts (dy, dx) per frame are [2, 2], [2, 2], [0, 0], [0, 1], [1, 0]: found to
    0.05 photosite (measured: exactly, after the 0.1-photosite snap), odd ones included (the sign is
    the engine's: content of the reference at (y, x) is at (y + dy, x + dx) in the frame;
    derender.raw.register; the 2x2-block MTB alone kept only the even part). Static-zone median
    error against the scene: measured 7.30 % without, 3.85 % aligned (4.01 % before the resampling's
    demosaic saw the balanced mosaic; the 2x2-block MTB alone, even shifts only: 6.51 %; the same
    scene without shake: 4.05 %)."""
    frames = bracket_raw_frames(moving)
    ref = moving.params["motion"]["reference"]
    plain = merge_raw(frames, {"output_space": "camera_rgb"})
    res = merge_raw(frames, {"output_space": "camera_rgb"}, motion=MotionOptions(reference=ref, align="translation"))
    true = -np.array(moving.params["motion"]["shifts_dy_dx"], float)
    found = np.array(res.info["raw_motion"]["shifts"], float)
    assert np.max(np.abs(found - true)) <= 0.05, (true, found)
    assert _zone_median(res, moving, ZONE_STATIC) < 0.65 * _zone_median(plain, moving, ZONE_STATIC)


def test_ghost_removal_keeps_the_reference_where_things_move(moving):
    """Where a disc is at the reference instant the plain merge is wrong by 59 % (median), aligned and
    ghost-free by 9.9 % (measured; 10.2 % before the resampling's demosaic saw the balanced mosaic;
    even shifts only: 10.5 %); the variance stays finite and the
    reference frame is never rejected."""
    frames = bracket_raw_frames(moving)
    ref = moving.params["motion"]["reference"]
    plain = merge_raw(frames, {"output_space": "camera_rgb"})
    res = merge_raw(frames, {"output_space": "camera_rgb", "variance": True},
                    motion=MotionOptions(reference=ref, align="translation", deghost=True))
    assert _zone_median(plain, moving, ZONE_OBJECT) > 0.4
    assert _zone_median(res, moving, ZONE_OBJECT) < 0.2
    assert _zone_median(res, moving, ZONE_STATIC) < 1.05 * _zone_median(plain, moving, ZONE_STATIC)
    info = res.info["raw_motion"]
    assert info["reference"] == ref and info["rejected"][ref] == 0.0 and max(info["rejected"]) > 0.01
    assert np.all(np.isfinite(res.variance)) and res.variance.min() >= 0


def test_still_bracket_unchanged_and_homography_refused():
    b = simulate_bracket("nikon-d5100", kind="indoor", size=(96, 64), exposures=3, seed=2, style="simple",
                         pipeline="fixed")
    frames = bracket_raw_frames(b)
    plain = merge_raw(frames, {"output_space": "camera_rgb"})
    res = merge_raw(frames, {"output_space": "camera_rgb"}, motion=MotionOptions(align="translation", deghost=True))
    assert res.info["raw_motion"]["shifts"] == [(0, 0)] * 3
    assert max(res.info["raw_motion"]["rejected"]) < 0.01            # measured 0
    assert raw_scores(res.radiance, b.camera_rgb_per_s, plain.mask)["median"] \
        <= 1.01 * raw_scores(plain.radiance, b.camera_rgb_per_s, plain.mask)["median"]
    with pytest.raises(InputError, match="homography"):
        merge_raw(frames, motion=MotionOptions(align="homography"))


@pytest.mark.parametrize("seed", [0, 2])
def test_tripod_raw_bracket_with_moving_things_against_its_still_twin(seed):
    """Issue 38's motion line, the ghost experiment's protocol (derender.evaluation.ghosts: 192x128,
    7 exposures, 3 moving objects, tripod, the `paper` family (a RAW merge never sees its rendering); scored per zone against the still twin, whose truth is
    the same with nothing moving): with --align translation --deghost the static zone is within
    issue 23's 1.10 of the still twin and no frame is shifted. Before the RAW path used the engine's
    chained registration, its own pairwise MTB shifted the two longest frames by (16, 32) and
    (-20, 4) photosites (seeds 0, 2; static 1.82 and 2.19). Measured now: static 1.003-1.008,
    swept 1.10-1.66, object 1.50-2.46 (seeds 0-2; the JPEG methods' object zone is 1.44-2.17)."""
    from derender.camera.motion import MotionSpec
    from derender.evaluation.ghosts import zone_errors

    base = MotionSpec(objects=3, shake=4)
    kw = dict(kind="outdoor", size=(192, 128), exposures=7, seed=seed, family="paper")
    still = simulate_bracket("nikon-d5100", motion=base.still(), **kw)
    moving = simulate_bracket("nikon-d5100", motion=base.tripod(), **kw)
    mo = MotionOptions(reference=still.params["motion"]["reference"], align="translation", deghost=True)
    rs = merge_raw(bracket_raw_frames(still), motion=mo)
    rm = merge_raw(bracket_raw_frames(moving), motion=mo)
    assert all(s == (0, 0) for s in rm.info["raw_motion"]["shifts"])
    m = zone_errors(rm.radiance, moving.truth_linear_srgb, moving.motion_zones)
    s = zone_errors(rs.radiance, still.truth_linear_srgb, moving.motion_zones)
    assert m["static"] <= 1.10 * s["static"]
    assert m["object"] < 3.0 * s["object"]


@pytest.mark.parametrize("camera", ["nikon-d5100", "sigma-sd-merrill"])
def test_noise_fit_is_the_sensors_when_things_move(camera):
    """Gain and read noise estimated from a tripod bracket with three moving objects (the ghost
    experiment's protocol, seed 1), as ``--align translation --deghost`` merges it, against the
    simulator's: within 8 % and 5 % (measured on seeds 0-4 and both cameras: gain 0.981-1.060,
    read noise 1.009-1.045 of the truth; before the robust start, gain 9.3-32.7x and read noise
    up to 12.5x: the moving objects' frame differences entered the least-squares start and no
    clipping drawn from it left them out). The still twin's stays within 1 %. The handheld twin
    (the camera shakes too, frames resampled) is fitted on the frame pairs whose relative shift
    is whole and even (derender.raw.noise.estimate_noise_shifted): within 5 % and 3 % (measured
    on seeds 0-4 and both cameras: gain 0.984-1.016, read noise 0.988-1.008; when the fit took
    adjacent frames rounded to even shifts on their smooth photosites, gain 1.27-2.12x)."""
    from derender.camera.spectral import load_camera
    from derender.evaluation.raw_merge import true_noise

    base = MotionSpec(objects=3, shake=4)
    kw = dict(kind="outdoor", size=(192, 128), exposures=7, seed=1, family="paper")
    g, rn = true_noise(load_camera(camera))
    for spec, tol_g, tol_r in ((base.tripod(), 0.08, 0.05), (base.still(), 0.01, 0.01), (base, 0.05, 0.03)):
        b = simulate_bracket(camera, motion=spec, **kw)
        mo = MotionOptions(reference=b.params["motion"]["reference"], align="translation", deghost=True)
        n = merge_raw(bracket_raw_frames(b), motion=mo).info["noise"]
        assert abs(n["gain_dn_per_electron"] / g - 1) < tol_g, n
        assert abs(n["read_noise_dn"] / rn - 1) < tol_r, n
        assert (n["source"] == "exact-pairs") == (spec.shake > 0), n


def test_alignment_leaves_a_tripod_bracket_bit_for_bit():
    """A tripod bracket (moving discs, no shake): `--align translation` finds no shift, so the merge
    with it is bit for bit the merge without it, with and without ghost removal (radiance, variance,
    mask and ghost map); the registration's compiled loops and the resampling never run on it."""
    b = simulate_bracket("nikon-d5100", kind="outdoor", size=(96, 64), exposures=5, seed=0, family="paper",
                         motion=MotionSpec(objects=3, shake=4).tripod())
    frames = bracket_raw_frames(b)
    ref = b.params["motion"]["reference"]
    opts = {"output_space": "camera_rgb", "variance": True}
    for deghost in (False, True):
        a = merge_raw(frames, opts, motion=MotionOptions(reference=ref, align="translation", deghost=deghost))
        n = merge_raw(frames, opts, motion=MotionOptions(reference=ref, deghost=deghost))
        assert a.info["raw_motion"]["shifts"] == [(0, 0)] * len(frames) and not a.info["raw_motion"]["resampled"]
        assert np.array_equal(a.radiance, n.radiance) and np.array_equal(a.variance, n.variance)
        assert np.array_equal(a.mask, n.mask) and np.array_equal(a.ghosts, n.ghosts)
    assert np.any(a.ghosts)                                          # ghost removal did act


def test_measured_pixels_follow_the_truth():
    """derender.evaluation.raw_merge.measured_pixels (bench_raw.py --motion's measured zones): on a
    still twin (nothing moves) every frame is ghost-free, so a pixel is measured wherever some
    frame's noise-free signal is unclipped: everywhere on this bracket, whose shortest frame holds
    the scene below white; on the moving bracket an object pixel is measured only where the
    reference itself is unclipped (every other frame sees the object elsewhere: 102 of its 428
    object pixels are clipped there), and most static pixels are (measured 98 %)."""
    from derender.evaluation.raw_merge import measured_pixels

    kw = dict(kind="outdoor", size=(96, 64), exposures=5, seed=1, family="paper")
    base = MotionSpec(objects=3, shake=2)
    still = simulate_bracket("nikon-d5100", motion=base.still(), **kw)
    moving = simulate_bracket("nikon-d5100", motion=base, **kw)
    assert measured_pixels(still).all()
    m = measured_pixels(moving)
    ref = moving.params["motion"]["reference"]
    peak = moving.camera_rgb_per_s.max(axis=-1) * moving.times[ref]
    obj = moving.motion_zones == ZONE_OBJECT
    assert obj.any() and (obj & (peak >= 1.0)).any()
    assert not np.any(m & obj & (peak >= 1.0))
    static = moving.motion_zones == ZONE_STATIC
    assert m[static].mean() > 0.95 and 0 < m[obj].mean() < 1
