"""Record the merged radiance of every method before the package restructuring (issue 14).

Run once, on the commit *before* the move (``git show 'HEAD^{/reference outputs}'``), from the
repository root::

    python tests/data/make_reference_outputs.py

It writes ``tests/data/reference_outputs.npz``: the arrays, and the predictions of the small GP model
the probabilistic methods use (fitted here and in the test from the same seeded chart session, as
``derender calibrate`` does). ``tests/test_reference_outputs.py`` recomputes the same cases with the current code and
compares them: every array must be bit-identical or within 1e-6 relative.

The cases use only the public entry points of the time (``merge_files_fast`` is the product path of
``derender merge``, ``merge`` the in-memory API), so the script documents what was recorded.
Large outputs are stored subsampled (``STEP``) to keep the file small.

**Re-recording some methods** after a deliberate change of their output (the rest of the file stays
as recorded)::

    PYTHONPATH=src python tests/data/make_reference_outputs.py --update stabilized stabilized-joint

(``model``: the reference GP's own predictions) recomputes only those methods' keys with the current package (the entry points
``tests/test_reference_outputs.py`` uses), prints each key's largest relative change, and rewrites
the file. Re-recorded so far (issue 15 item 6): ``stabilized-joint`` (its noise weights floored on
flat response-table segments: sim-camera moved by 0.4 %), then ``stabilized``,
``stabilized-joint`` and ``stabilized-probabilistic`` (each frame's estimate projected onto the
non-negative orthant: the pixels that had a negative channel, e.g. 316 of 6144 on sim-camera,
and on Memorial up to 1.2 % relative where a frame's dark channel went below 0); issue 16 items 5-6:
``debevec`` (curves offset so that neutral colours stay neutral: up to 57 % relative per channel
on sim-camera) and ``robertson`` (leave-one-out log-domain update, smooth monotone curve, weights
``w / g'^2``, the same colour balance: a different curve and merge altogether); then ``model``,
``probabilistic`` and ``stabilized-probabilistic`` (issue 17 item 4: faster GP calibration, ML search
tolerance 1e-6 and a 250-point first search, then the compiled ML objective: rounding-level
changes, up to 1.5e-4 in a variance; changes printed by ``--update``); issue 16 item 4 (third
session): ``stabilized``, ``stabilized-joint``, ``stabilized-probabilistic`` (the curve model's
per-frame exposure offsets on by default: sim-camera, a filmic auto-pipeline bracket, moved by up
to 1.2 relative per pixel; Memorial and Frobisher unchanged; sim-simple within 3.6e-7); then ``robertson`` (issue 16:
the calibration's leave-one-out radiance is the geometric mean of the other frames weighted by
``w`` instead of the linear mean weighted by ``w / g'^2``, and the smoother's data weighted by
their inverse variance: a different curve; changes printed by ``--update``); then
``probabilistic`` (issue 27 part 4: the linear-sRGB mean projected onto the non-negative orthant,
a projected channel's variance plus its squared distance: the pixels that had a negative channel
moved, up to 0.37 relative in radiance and 38x in variance, on sim-camera and sim-simple); then
``model``, ``probabilistic`` and ``stabilized-probabilistic`` (issue 27 part 1: each cluster GP's
latent variance capped at its cluster target's variance; the reference GP, 800 pairs of 4
illuminants, extrapolates on much of the code cube, so its probe predictions moved by up to 0.97
(mean) relative and the probabilistic merges by up to 1.39 relative on single pixels; re-recorded
after both changes were merged); then issue 27 part 3:
``debevec``, ``robertson``, ``stabilized``, ``stabilized-joint``, ``stabilized-probabilistic`` (the
three channel curves solved as one system whose curves share their shape, and the classic merges
balanced along the grey axis, so that greys stay grey at every level: up to 0.9 relative on
sim-simple (debevec), 2.2 on Memorial (robertson), 1.3 on sim-camera (stabilized); sim-simple's
stabilised merges, on the power law, unchanged); then ``debevec`` (issue 28: its grid samples
leave out pixels that see a clipped neighbour while unclipped themselves, 3x3 clusters on a 4x
denser grid: other samples, another curve; max relative change per pixel 0.39 sim-camera, 0.57
sim-simple, 0.18 Memorial, 0.022 Frobisher); then issue 29
(probabilistic merges' variance): ``probabilistic`` and ``stabilized-probabilistic`` (the model's error
kept shared across frames, the frames' excess spread and the spatial-mixing term added: every radiance
unchanged (max relative change 0), the probabilistic variance up to 880x (sim-camera) and 1270x
(sim-simple) on single pixels; ``stabilized-probabilistic`` gives a variance only when asked, so none is
recorded); then issue 27 part 3 (grey balance, ``derender.hdr.stabilize.grey_balance``):
``stabilized``, ``stabilized-joint``, ``stabilized-probabilistic`` (one gain per output channel
from the frames' neutral blocks folded into every matrix: max relative change per pixel 0.18
sim-camera, 0.075 sim-simple, 0.11 Memorial, 0.16 Frobisher);
then ``debevec`` (issue 28, linearity: the Debevec merge's smoothness lambda 60 instead of
30, ``derender.hdr.classic.MERGE_LAMBDA``: a smoother curve; max relative change per pixel 0.266
sim-camera, 0.151 sim-simple, 0.552 Memorial, 0.087 Frobisher); then ``debevec`` (issues 36/37: the
bound-aware top of its calibration, ``censor=True``: codes that stopped following the exposure are
bounds, not data rows, and codes at or above a detected white get no merge weight; max relative
change per pixel 0.222 sim-camera, 0.343 sim-simple, 0.0114 Memorial, 0.0102 Frobisher); then issue 36 item 2
(reference invariance): ``stabilized``, ``stabilized-joint``, ``stabilized-probabilistic`` (brackets whose frames
differ by per-channel gains only take gains consistent over the whole pair graph; response-table
weights floored: Memorial 0.765 / 0.455 and Frobisher 0.076 / 0.018 max relative change per pixel
(stabilized / stabilized-joint); both simulated auto-pipeline brackets unchanged, max relative
change 0); then issue 36 (cross-method agreement): ``debevec`` and ``robertson`` (no merge weight at
or below the bracket's black floor, ``derender.engine.weights.black_codes``: Memorial's film base
at codes R 15, G 20, B 19; max relative change per pixel 0.933 / 1.4e6 on Memorial, the latter on
column 0's padding (codes 0, 0, 255), 0.5 or more on 2925 / 15506 pixels, its dark ceiling; the
simulated brackets and Frobisher unchanged, max relative change 0); then ``robertson`` (issue 36,
luminance that does not depend on the bracket: its calibration's observations that stopped
following the exposure, a channel stuck or at its white, the rim of a clipped region, are bounds,
not data, and codes at or above a detected white get no merge weight,
``derender.response.robertson2003.calibration_bounds``: another curve; max relative change per
pixel 0.967 sim-camera, 0.969 sim-simple, 0.242 Memorial, 0.782 Frobisher, measured before the
black floor was merged with it).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: The real brackets: ``$DERENDER_SHARED_DATA`` (as the tests read it), else the checkout's sibling.
SHARED = Path(os.environ.get("DERENDER_SHARED_DATA") or HERE.parents[2] / "shared" / "data")

#: (case, pixel step of the stored arrays)
STEP = {"sim-camera": 1, "sim-simple": 1, "memorial": 8, "frobisher": 8}
METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint")
MODEL_METHODS = ("probabilistic", "stabilized-probabilistic")


def _sim_paths(tmp: Path):
    from derender.camera import bracket_paths, simulate_bracket, write_bracket

    out = {}
    b = simulate_bracket(size=(96, 64), exposures=5, pipeline="auto", style="camera", seed=1)
    write_bracket(b, tmp / "camera")
    out["sim-camera"] = (bracket_paths(tmp / "camera", "jpeg"), {})
    b = simulate_bracket(kind="indoor", size=(96, 64), exposures=5, pipeline="auto", style="simple", seed=2)
    write_bracket(b, tmp / "simple")
    out["sim-simple"] = (bracket_paths(tmp / "simple", "jpeg"), {})
    return out


def _real_paths():
    mem = SHARED / "debevec-memorial"
    frob = SHARED / "colour-hdri-frobisher"
    return {
        "memorial": (sorted(mem.glob("memorial00*.png")),
                     {"times_file": mem / "memorial.hdr_image_list.txt", "times_file_inverse": True}),
        "frobisher": (sorted(frob.glob("IMG_*.jpg")), {}),
    }


def cases(tmp: Path):
    """Yield (name, paths, time options, methods) for every recorded case."""
    for name, (paths, topts) in {**_sim_paths(tmp), **_real_paths()}.items():
        methods = METHODS + (MODEL_METHODS if name.startswith("sim") else ())
        yield name, paths, topts, methods


def reference_model(fit_model, model_metadata):
    """The GP of the probabilistic cases: a small seeded chart session, camera metadata as `calibrate`."""
    try:
        from derender.chart import chart_pairs
    except ImportError:                 # the package as restructured (issue 14)
        from derender.camera.chart import chart_pairs

    pairs = chart_pairs("nikon-d5100", n_illuminants=4, n_exposures=10, seed=0)
    model = fit_model("gp", pairs.jpeg, pairs.raw, seed=0, n_train=800)
    model.metadata.update(model_metadata(pairs))
    return model


def main() -> int:
    from derender.benchmark import merge_seeded
    from derender.derendering import fit_model
    from derender.experiments import model_metadata
    from derender.fastmerge import merge_files_fast
    from derender.io import read_stack

    model = reference_model(fit_model, model_metadata)
    rec: dict[str, np.ndarray] = {}
    probe = np.stack(np.meshgrid(np.arange(0, 256, 15), np.arange(0, 256, 15), np.arange(0, 256, 15),
                                 indexing="ij"), -1).reshape(-1, 3).astype(np.uint8)
    mean, var = model.predict(probe / 255.0)
    rec["model/predict_mean"], rec["model/predict_var"] = mean, var
    with tempfile.TemporaryDirectory() as d:
        for name, paths, topts, methods in cases(Path(d)):
            s = STEP[name]
            stack = read_stack(paths, **topts)
            for method in methods:
                opts = {"model": model} if method in MODEL_METHODS else {}
                streamed = merge_files_fast(paths, method=method, options=opts, **topts)
                mem = merge_seeded(stack, method, 0, options=opts)
                for tag, res in (("files", streamed), ("stack", mem)):
                    for what in ("radiance", "variance"):
                        arr = getattr(res, what)
                        if arr is None:
                            continue
                        arr = np.ascontiguousarray(arr[::s, ::s])
                        same = rec.get(f"{name}/{method}/files/{what}")
                        if tag == "stack" and same is not None and np.array_equal(same, arr):
                            rec[f"{name}/{method}/stack/{what}"] = np.array("same as files")
                        else:
                            rec[f"{name}/{method}/{tag}/{what}"] = arr
                print(name, method, "engine_path", streamed.info.get("engine_path"), flush=True)
    np.savez_compressed(HERE / "reference_outputs.npz", **rec)
    print(f"{len(rec)} arrays -> {HERE / 'reference_outputs.npz'}")
    return 0


def update(methods: list[str]) -> int:
    """Recompute the keys of ``methods`` with the current package; keep every other key."""
    from derender.derendering.base import fit_model, model_metadata
    from derender.hdr.files import merge_files
    from derender.hdr.registry import merge_seeded
    from derender.io.images import read_stack

    with np.load(HERE / "reference_outputs.npz") as z:
        rec = {k: z[k] for k in z.files}
    recorded = dict(rec)
    model = reference_model(fit_model, model_metadata) if set(methods) & {*MODEL_METHODS, "model"} else None
    if "model" in methods:              # the GP's own predictions (``model/predict_*``)
        probe = np.stack(np.meshgrid(np.arange(0, 256, 15), np.arange(0, 256, 15), np.arange(0, 256, 15),
                                     indexing="ij"), -1).reshape(-1, 3).astype(np.uint8)
        for key, arr in zip(("model/predict_mean", "model/predict_var"), model.predict(probe / 255.0)):
            old = recorded[key]
            scale = np.maximum(np.abs(old).max(axis=-1, keepdims=True), 1e-30)
            print(f"{key}: max relative change {float(np.max(np.abs(arr.astype(np.float64) - old) / scale)):.3g}")
            rec[key] = arr
    with tempfile.TemporaryDirectory() as d:
        for name, paths, topts, case_methods in cases(Path(d)):
            s = STEP[name]
            stack = read_stack(paths, **topts)
            for method in (m for m in case_methods if m in methods):
                opts = {"model": model} if method in MODEL_METHODS else {}
                res = {"files": merge_files(paths, method=method, options=opts, **topts),
                       "stack": merge_seeded(stack, method, 0, options=opts)}
                for tag in ("files", "stack"):
                    for what in ("radiance", "variance"):
                        key = f"{name}/{method}/{tag}/{what}"
                        arr = getattr(res[tag], what)
                        if arr is None:
                            continue
                        arr = np.ascontiguousarray(arr[::s, ::s])
                        old = recorded.get(key)
                        if old is not None and old.dtype.kind == "U":
                            old = recorded[f"{name}/{method}/files/{what}"]
                        if old is not None:
                            scale = np.maximum(np.abs(old).max(axis=-1, keepdims=True), 1e-30)
                            rel = float(np.max(np.abs(arr.astype(np.float64) - old) / scale))
                            print(f"{key}: max relative change {rel:.3g}", flush=True)
                        same = rec.get(f"{name}/{method}/files/{what}")
                        if tag == "stack" and same is not None and np.array_equal(same, arr):
                            rec[key] = np.array("same as files")
                        else:
                            rec[key] = arr
    np.savez_compressed(HERE / "reference_outputs.npz", **rec)
    print(f"{len(rec)} arrays -> {HERE / 'reference_outputs.npz'}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--update":
        sys.exit(update(sys.argv[2:]))
    sys.exit(main())
