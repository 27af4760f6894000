"""Linearity over 5 decades: per-decade ratio of a spot-calibrated map to the absolute truth.

On a bracket of the luminance family (:mod:`derender.camera.luminance`) the truth is in cd/m2.
A merged map (relative linear sRGB) is scaled on the grey card as a luminance meter's spot
reading would (:func:`derender.photometry.calibration.spot_factor`: ``k = L_card / mean_card
(179 w . RGB)``), and at every scored pixel

    rho = k 179 (w . RGB) / L_true,

``w`` the Rec. 709 row. Reported: the median and 90th percentile of
``|rho - 1|`` over all scored pixels, and the median ``rho`` in each decade of the true
luminance 1..10, ..., 1e5..1e6 cd/m2. Scored pixels are those where the in-camera demosaicing
and chroma denoising keep the truth (:func:`derender.evaluation.families.smooth_mask`), off the
grey card itself, and not over-exposed in every frame (the merge's mask: a bound, not a value).

``readback="pvalue"`` scores the file a user would get instead of the array: the spot-scaled
map is written as a Radiance ``.hdr`` (:func:`derender.io.rgbe.write_hdr`, ``EXPOSURE=`` as
given) and read back by Radiance's own ``pvalue -h -H -o -d`` (``-o``: ``EXPOSURE`` undone,
mantissa + 0.5 as Radiance decodes), found on ``PATH`` or in the ``pyradiance`` wheel
(:func:`radiance_program`); the scores are then computed from those numbers. They agree with the
array's to RGBE precision (one mantissa step, ``2^-8`` relative at worst): a check that the
written file carries the measured linearity.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from derender.core.errors import InputError

__all__ = ["DECADES", "LINEARITY_METHODS", "linearity_scores", "linearity_experiment", "render_chart_model",
           "format_decades", "fisheye_maps", "FISHEYE_VIEW", "radiance_program", "pvalue_rgb", "smoothest_window",
           "SPACING_METHODS", "SPACING_CAMERAS", "COVERED_STOPS", "saturate_below", "brightest_ratio", "spacing_rows"]

#: Decade edges of the true luminance (cd/m2).
DECADES = tuple(10.0 ** k for k in range(7))
#: Methods scored by :func:`linearity_experiment`.
LINEARITY_METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint", "probabilistic")


def radiance_program(name: str) -> str | None:
    """Path of Radiance's program ``name`` (``pvalue``, ``getinfo``, ``evalglare``): on ``PATH``,
    else inside the ``pyradiance`` wheel (PyPI); None when neither has it."""
    import shutil
    from pathlib import Path

    found = shutil.which(name)
    if found:
        return found
    try:
        import pyradiance
    except ImportError:
        return None
    path = Path(pyradiance.__file__).parent / "bin" / name
    return str(path) if path.is_file() else None


def pvalue_rgb(path: Any, *, pvalue: str | None = None) -> np.ndarray:
    """(H, W, 3) float64 of a Radiance picture as ``pvalue -h -H -o -d`` prints it (no header, no
    resolution line, original units: ``EXPOSURE`` undone; one ``R G B`` line per pixel in
    scanline order), the size from the file's resolution line. ``InputError`` without pvalue."""
    import subprocess

    exe = pvalue or radiance_program("pvalue")
    if exe is None:
        raise InputError("Radiance's pvalue not found (PATH or pip install pyradiance)")
    with open(path, "rb") as f:
        head = f.read(65536)
    end = head.find(b"\n\n")
    res = head[end + 2:head.find(b"\n", end + 2)].split()
    if end < 0 or len(res) != 4 or res[0] != b"-Y" or res[2] != b"+X":
        raise InputError(f"{path}: not a standard-orientation (-Y H +X W) Radiance picture")
    h, w = int(res[1]), int(res[3])
    run = subprocess.run([exe, "-h", "-H", "-o", "-d", str(path)], capture_output=True, text=True)
    if run.returncode != 0:
        raise InputError(f"pvalue failed on {path}: {run.stderr.strip()}")
    vals = np.array(run.stdout.split(), dtype=np.float64)
    if vals.size != h * w * 3:
        raise InputError(f"pvalue printed {vals.size} numbers for a {w}x{h} picture")
    return vals.reshape(h, w, 3)


def smoothest_window(luminance: np.ndarray, size: int = 8) -> tuple[int, int]:
    """Top-left ``(x, y)`` of the ``size`` x ``size`` window of a truth luminance map (H, W) with the
    smallest relative spread, among windows 8 pixels in from the border on a 4-pixel grid whose mean
    lies between 1e-3 and 0.05 of the map's maximum: where a meter reading is taken in the spot
    tests and benchmarks (a uniform, well-exposed surface)."""
    lum = np.asarray(luminance)
    best, where = np.inf, (0, 0)
    for y in range(8, lum.shape[0] - size - 8, 4):
        for x in range(8, lum.shape[1] - size - 8, 4):
            win = lum[y:y + size, x:x + size]
            spread = win.std() / win.mean()
            if spread < best and 0.05 * lum.max() > win.mean() > 1e-3 * lum.max():
                best, where = spread, (x, y)
    return where


def linearity_scores(radiance_srgb: Any, truth_cd_m2: Any, card: Sequence[int], *,
                     score_mask: np.ndarray | None = None, merge_mask: np.ndarray | None = None,
                     readback: str | None = None, hdr_exposure: float = 1.0) -> dict[str, Any]:
    """Spot-calibrate ``radiance_srgb`` (H, W, 3, linear sRGB, relative) on ``card`` ``[x, y, w, h]`` (the
    meter's spot: ``scene.json``'s ``luminance.spot``)
    against ``truth_cd_m2`` (H, W) and score it (module docstring). ``score_mask`` (H, W bool)
    selects pixels; ``merge_mask`` (``HDRResult.mask``, 1 = over-exposed in every frame) drops
    those. Returns ``median_abs``, ``p90_abs``, ``median_ratio``, ``decades`` (median ratio per
    decade, NaN for an empty one), ``counts`` and the ``factor``. ``readback="pvalue"``: the
    spot-scaled map goes through a ``.hdr`` (``EXPOSURE=hdr_exposure``) and Radiance's ``pvalue``
    before it is scored (module docstring); ``factor`` is then the spot factor of the array times
    the (near 1) factor of the read-back map."""
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.calibration import Spot, spot_factor
    from derender.photometry.illuminance import luminance_cd_m2

    rad = np.asarray(radiance_srgb, dtype=np.float64)
    lt = np.asarray(truth_cd_m2, dtype=np.float64)
    if rad.shape[:2] != lt.shape or rad.ndim != 3:
        raise InputError(f"map {rad.shape} and truth {lt.shape} differ in size")
    x, y, w, h = (int(v) for v in card)
    spot = Spot(x, y, w, h, float(lt[y:y + h, x:x + w].mean()))
    cal = spot_factor(rad, spot, SRGB_PRIMARIES, mask=merge_mask)
    factor = float(cal.factor)
    if readback == "pvalue":
        import tempfile
        from pathlib import Path

        from derender.io.rgbe import write_hdr

        with tempfile.TemporaryDirectory(prefix="derender-readback-") as tmp:
            path = Path(tmp) / "map.hdr"
            write_hdr(path, rad * factor, exposure=hdr_exposure, software="derender linearity readback")
            rad = pvalue_rgb(path)
        cal = spot_factor(rad, spot, SRGB_PRIMARIES, mask=merge_mask)
        factor *= float(cal.factor)
    elif readback is not None:
        raise InputError(f"readback must be None or 'pvalue', got {readback!r}")
    lum = cal.factor * luminance_cd_m2(rad, SRGB_PRIMARIES)
    sel = np.ones(lt.shape, bool) if score_mask is None else np.asarray(score_mask, bool).copy()
    sel[y:y + h, x:x + w] = False
    if merge_mask is not None:
        sel &= np.asarray(merge_mask) != 1
    sel &= lt >= DECADES[0]
    ratio = lum[sel] / lt[sel]
    lsel = lt[sel]
    decades, counts = [], []
    for lo, hi in zip(DECADES[:-1], DECADES[1:]):
        d = (lsel >= lo) & (lsel < hi)
        counts.append(int(d.sum()))
        decades.append(float(np.median(ratio[d])) if d.any() else float("nan"))
    err = np.abs(ratio - 1.0)
    return {"median_abs": float(np.median(err)), "p90_abs": float(np.percentile(err, 90)),
            "median_ratio": float(np.median(ratio)), "decades": decades, "counts": counts,
            "factor": factor, "n": int(ratio.size), "readback": readback or "array"}


#: Methods of the bracket-independence grid (:func:`spacing_rows`): every method that merges an 8-bit
#: bracket without a calibration (``probabilistic`` and ``stabilized-probabilistic`` need paper 2's
#: de-rendering model, ``-m MODEL.npz``, fitted on a chart session of the camera; ``raw`` merges RAW frames).
SPACING_METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint")
#: Cameras of the grid: the built-in Nikon D5100 (colour-science) and three ``rawtoaces-spectral`` cameras
#: (the Fujifilm X-T3 is the one no method was looked at on while choosing).
SPACING_CAMERAS = ("nikon-d5100", "canon-eos-5d-mark-iii", "sony-ilce-7m3", "fujifilm-x-t3")
#: Stops covered by every bracket of the grid, whatever its spacing (1, 1.5, 2 EV: 17, 12, 9 frames).
COVERED_STOPS = 16.0


def saturate_below(codes: np.ndarray, seed: int) -> np.ndarray:
    """A camera whose white is 250..254, drawn per observation with ``seed`` (noise after clipping):
    ``min(codes, 250 + U{0..4})``, uint8 (many cameras clip their JPEGs below 255)."""
    white = 250 + np.random.default_rng(seed).integers(0, 5, size=np.shape(codes))
    return np.minimum(codes, white).astype(np.uint8)


def brightest_ratio(radiance_srgb: Any, truth_cd_m2: Any, card: Sequence[int]) -> float:
    """The brightest 1 % of the truth read by the map, relative to the grey card: the median over
    those pixels of ``(w . RGB) / L`` divided by the median over the card (``card`` ``[x, y, w, h]``,
    ``w`` the Rec. 709 row); 1 for a map linear up to the lamps."""
    from derender.core.colorimetry import LUMINANCE_WEIGHTS_REC709

    lum = np.asarray(radiance_srgb, np.float64) @ np.asarray(LUMINANCE_WEIGHTS_REC709, np.float64)
    lt = np.asarray(truth_cd_m2, np.float64)
    x, y, w, h = (int(v) for v in card)
    ref = np.median(lum[y:y + h, x:x + w] / lt[y:y + h, x:x + w])
    top = lt >= np.percentile(lt, 99)
    return float(np.median(lum[top] / lt[top]) / ref)


def spacing_rows(cameras: Sequence[str] = SPACING_CAMERAS[:3], stops: Sequence[float] = (1.0, 1.5, 2.0),
                 seeds: Sequence[int] = (0, 1), whites: Sequence[str] = ("255", "250-254"),
                 methods: Sequence[str] = SPACING_METHODS, deghost: Sequence[bool] = (False, True), *,
                 size: tuple[int, int] = (192, 128), progress: Callable[[str], None] | None = None):
    """Issue 36's "luminance that does not depend on the bracket": the luminance family's fixed
    gamma-2.2 rendering (a tuning rendering) for each camera, stop spacing (``COVERED_STOPS`` covered:
    17, 12, 9 frames at 1, 1.5, 2 EV), scene seed and white (``"255"``: as simulated;
    ``"250-254"``: :func:`saturate_below` with the scene's seed), merged by each method plain and with
    ``deghost`` (the engine's ghost removal), scored by :func:`linearity_scores` (``--spot`` on the
    grey card) and :func:`brightest_ratio`. Yields one row per merge: camera, stops, frames, seed,
    white, method, deghost and the scores (``top``: the brightest 1 %)."""
    import math

    from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2
    from derender.core.types import Stack
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.families import smooth_mask
    from derender.hdr.registry import merge_seeded

    for cam in cameras:
        for ev in stops:
            n = int(math.ceil(COVERED_STOPS / float(ev) - 1e-9)) + 1
            for seed in seeds:
                b = simulate_luminance(render="gamma", size=size, exposures=n, stops=float(ev), seed=int(seed),
                                       camera=cam)
                lt = truth_luminance_cd_m2(b.truth_linear_srgb)
                smooth = smooth_mask(b.truth_linear_srgb)
                card = b.params["luminance"]["spot"]
                for white in whites:
                    if white not in ("255", "250-254"):
                        raise InputError(f"white must be '255' or '250-254', got {white!r}")
                    codes = b.jpeg_codes if white == "255" else saturate_below(b.jpeg_codes, int(seed))
                    stack = Stack(images=codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
                    for m in methods:
                        for dg in deghost:
                            if progress is not None:
                                progress(f"{cam} {ev} EV seed {seed} white {white} {m}{' deghost' if dg else ''}")
                            res = merge_seeded(stack, m, 0, motion=MotionOptions(deghost=True) if dg else None)
                            sc = linearity_scores(res.radiance, lt, card, score_mask=smooth, merge_mask=res.mask)
                            yield {"camera": cam, "stops": float(ev), "frames": n, "seed": int(seed), "white": white,
                                   "method": m, "deghost": bool(dg),
                                   "top": brightest_ratio(res.radiance, lt, card)} | sc


def linearity_experiment(renders: Sequence[str] = ("gamma", "paper", "camera", "dslr-lut", "phone-local", "drift"),
                         *, modes: Sequence[str] = ("time",), seeds: Sequence[int] = (0,),
                         size: tuple[int, int] = (192, 128), exposures: int = 9,
                         methods: Sequence[str] = LINEARITY_METHODS, camera: str = "nikon-d5100",
                         n_train: int = 5000, readback: str | None = None,
                         progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """``derender experiment linearity``: every method on luminance-family brackets of every
    rendering, scored by :func:`linearity_scores`. ``probabilistic`` uses paper 2's GP from the
    camera's chart session (:func:`derender.evaluation.uncertainty.chart_model`), as
    ``derender experiment uncertainty`` does. Rows: render, role (tuning / held-out), mode,
    seed, method and the scores (``readback="pvalue"``: read back through Radiance's pvalue)."""
    from derender.camera.luminance import TUNING_RENDERS, simulate_luminance, truth_luminance_cd_m2
    from derender.core.types import Stack
    from derender.evaluation.families import smooth_mask
    from derender.hdr.registry import merge_seeded, method_spec

    models: dict[str, Any] = {}
    rows: list[dict[str, Any]] = []
    for render in renders:
        for mode in modes:
            for seed in seeds:
                if progress is not None:
                    progress(f"{render} {mode} seed {seed}")
                b = simulate_luminance(mode=mode, render=render, size=size, exposures=exposures, seed=int(seed),
                                       camera=camera)
                stack = Stack(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
                lt = truth_luminance_cd_m2(b.truth_linear_srgb)
                smooth = smooth_mask(b.truth_linear_srgb)
                card = b.params["luminance"]["spot"]
                for m in methods:
                    opts: dict[str, Any] = {}
                    if method_spec(m).needs_model:
                        if render not in models:
                            models[render] = render_chart_model(camera, render, n_train)
                        opts["model"] = models[render]
                    res = merge_seeded(stack, m, int(seed), opts)
                    sc = linearity_scores(res.radiance, lt, card, score_mask=smooth, merge_mask=res.mask,
                                          readback=readback)
                    rows.append({"render": render, "role": "tuning" if render in TUNING_RENDERS else "held-out",
                                 "mode": mode, "seed": int(seed), "method": m} | sc)
    return rows


#: Radiance view of the family's fisheye framing (:func:`fisheye_maps`).
FISHEYE_VIEW = "-vta -vh 180 -vv 180"


def fisheye_maps(methods: Sequence[str] = ("debevec", "stabilized"), *, render: str = "gamma", size: int = 160,
                 exposures: int = 9, seed: int = 0, camera: str = "nikon-d5100", n_train: int = 5000
                 ) -> dict[str, np.ndarray]:
    """The glare check of the luminance maps: the luminance family framed as a 180-degree circular fisheye
    (``size`` x ``size``, :data:`FISHEYE_VIEW`), merged by each method and scaled on the grey
    card's spot, with the truth: ``{"truth": ..., method: ...}`` (H, W, 3) in Radiance units
    (``179 w·RGB`` = cd/m2), ready for ``write_hdr(..., view=FISHEYE_VIEW)`` and ``evalglare -V``."""
    from derender.camera.luminance import SATURATION_EXPOSURE, simulate_luminance
    from derender.core.types import Stack
    from derender.hdr.registry import merge_seeded, method_spec
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.calibration import Spot, spot_factor

    b = simulate_luminance(render=render, size=(size, size), exposures=exposures, seed=seed, camera=camera,
                           fisheye=True)
    lum = b.params["luminance"]
    spot = Spot(*lum["spot"], lum["spot_cd_m2"])
    out = {"truth": b.truth_linear_srgb.astype(np.float64) * (SATURATION_EXPOSURE / 179.0)}
    stack = Stack(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)
    for m in methods:
        opts = ({"model": render_chart_model(camera, render, n_train)}
                if method_spec(m).needs_model else {})
        res = merge_seeded(stack, m, seed, opts)
        k = spot_factor(res.radiance, spot, SRGB_PRIMARIES, mask=res.mask).factor
        out[m] = np.asarray(res.radiance, dtype=np.float64) * k
    return out


def render_chart_model(camera: str, render: str, n_train: int = 5000, seed: int = 0):
    """Paper 2's GP for ``camera`` rendering as ``render`` (``gamma``: the fixed gamma-2.2 ``simple``
    style; otherwise that pipeline family), calibrated on its simulated chart session (fixed white
    balance), ``n_train`` pairs drawn with ``seed``, as :func:`derender.evaluation.uncertainty.chart_model`."""
    from derender.camera.chart import chart_pairs
    from derender.derendering.base import fit_model, model_metadata

    pairs = (chart_pairs(camera, style="simple", seed=seed) if render == "gamma"
             else chart_pairs(camera, seed=seed, family=render))
    rng = np.random.default_rng(seed)
    sel = rng.choice(pairs.jpeg.shape[0], size=min(n_train, pairs.jpeg.shape[0]), replace=False)
    model = fit_model("gp", pairs.jpeg[sel], pairs.raw[sel], seed=seed, n_train=n_train)
    model.metadata.update(model_metadata(pairs))
    return model


def format_decades(values: Sequence[float]) -> str:
    """Per-decade median ratios as text: three decimals each, a dash for an empty decade."""
    return ", ".join("-" if not np.isfinite(v) else f"{v:.3f}" for v in values)
