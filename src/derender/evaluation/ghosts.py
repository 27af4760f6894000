"""Ghosts and camera shake: every method on moving brackets, by zone, against their still twins.

Each case is a simulated bracket in which objects move and, for ``handheld``, the camera
shakes (:mod:`derender.camera.motion`), with the exact radiance at the reference frame's
instant; its *still twin* has the same canvas, noise and pipeline and nothing moving, so
the best a merge can do on each zone is measured, not assumed. Per pixel the error is the
relative error of :func:`derender.evaluation.metrics.relative_errors` (``||M r - g|| / ||g||``
after the trimmed 3x3 fit ``M``, fitted on all pixels of that result), and each zone reports
its median:

* ``static``: pixels no object covers in any frame (in scene coordinates);
* ``swept``: covered in some frame but not in the reference (the background must win);
* ``object``: covered in the reference (the object as it was at that instant must win);
* ``object_seen``: the object pixels that the reference frame itself renders unclipped (every
  channel's code within [:data:`SEEN_LOW`, :data:`SEEN_HIGH`]). Elsewhere in the object the
  reference only bounds the radiance, and only a frame in which the object sits somewhere else
  can fill it in (``docs/ghosts.md``, limits; figures in ``docs/results-ghosts.md``).

The ratio ``moving / still`` per zone is what ghost removal must bring towards 1 (the
targets, ``docs/results-ghosts.md``: static <= 1.10, swept <= 1.25, object <= 1.5). A handheld bracket's still twin is the
tripod one (no shake): its ratio also measures what alignment loses.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import numpy as np

from derender.core.errors import InputError

__all__ = ["GHOST_METHODS", "GHOST_SETTINGS", "SEEN_LOW", "SEEN_HIGH", "seen_in_reference", "zone_errors", "ghost_comparison", "summarise_ghosts"]

#: The methods the ghost experiment merges (paper 2's with the camera's chart GP).
GHOST_METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint", "probabilistic")

#: Motion settings: ``tripod`` (objects move) and ``handheld`` (objects move, camera shake).
GHOST_SETTINGS = ("tripod", "handheld")


#: Lowest code (of 255) at which a reference pixel counts as seen (``object_seen``).
SEEN_LOW = 3
#: Highest code (of 255) at which a reference pixel counts as seen unclipped (``object_seen``).
SEEN_HIGH = 250


def seen_in_reference(ref_codes: np.ndarray) -> np.ndarray:
    """(H, W) bool: every channel of the reference frame's 8-bit codes within [SEEN_LOW, SEEN_HIGH]."""
    c = np.asarray(ref_codes)
    return np.all((c >= SEEN_LOW) & (c <= SEEN_HIGH), axis=-1)


def zone_errors(result: np.ndarray, truth: np.ndarray, zones: np.ndarray,
                seen: np.ndarray | None = None) -> dict[str, float]:
    """Median relative error per zone (``static``, ``swept``, ``object``; NaN for an empty zone),
    and ``object_seen`` (the object pixels where ``seen``, (H, W) bool) when ``seen`` is given."""
    from derender.camera.motion import ZONE_NAMES
    from derender.evaluation.metrics import relative_errors

    r = np.asarray(result, dtype=np.float64)
    g = np.asarray(truth, dtype=np.float64)
    m = np.asarray(relative_errors(r, g, fit="matrix")["matrix"])
    n2 = np.sum(g * g, axis=-1)
    ok = n2 > 0
    e = np.full(n2.shape, np.nan)
    e[ok] = np.sqrt(np.sum((r @ m.T - g) ** 2, axis=-1)[ok] / n2[ok])
    out = {}
    for code, name in enumerate(ZONE_NAMES):
        sel = (zones == code) & ok
        out[name] = float(np.median(e[sel])) if sel.any() else float("nan")
    if seen is not None:
        sel = (zones == ZONE_NAMES.index("object")) & ok & np.asarray(seen, dtype=bool)
        out["object_seen"] = float(np.median(e[sel])) if sel.any() else float("nan")
    return out


def ghost_comparison(families: Sequence[str] = ("paper", "camera", "dslr-lut"), *, settings: Sequence[str] = GHOST_SETTINGS,
                     seeds: Sequence[int] = (0,), size: tuple[int, int] = (192, 128), exposures: int = 7,
                     objects: int = 3, shake: int | None = None, methods: Sequence[str] = GHOST_METHODS,
                     camera: str = "nikon-d5100", kind: str = "outdoor", motion: Any = None,
                     progress: Callable[[str], None] | None = None, model: Any = None) -> list[dict[str, Any]]:
    """One row per (family, setting, seed, method): zone medians on the moving bracket and on
    its still twin, and their ratios. ``shake`` defaults to 2 % of the width (a handheld
    bracket); ``motion`` (a :class:`~derender.engine.motion.run.MotionOptions`, e.g.
    ``deghost=True, align="translation"``) goes to every merge, with the truth's reference
    frame (the middle frame, an engine option of every method), so that the table measures
    ghosts and alignment, not the choice of instant. Paper 2's
    methods get ``model`` (default: the GP of :func:`derender.evaluation.uncertainty.chart_model`)."""


    from derender.camera import simulate_bracket
    from derender.camera.families import FAMILIES, check_family
    from derender.camera.motion import MotionSpec
    from derender.core.types import Stack
    from derender.engine.motion.run import MotionOptions
    from derender.evaluation.families import TUNING_FAMILIES
    from derender.hdr.registry import merge_seeded, method_spec

    for s in settings:
        if s not in GHOST_SETTINGS:
            raise InputError(f"unknown motion setting {s!r}: use {', '.join(GHOST_SETTINGS)}")
    families = [check_family(f) for f in families] if families else list(FAMILIES)
    if model is None and any(method_spec(m).needs_model for m in methods):
        from derender.evaluation.uncertainty import chart_model

        model = chart_model(camera)
    shake_px = max(1, int(round(0.02 * size[0]))) if shake is None else int(shake)
    rows: list[dict[str, Any]] = []
    for family in families:
        for seed in seeds:
            base = MotionSpec(objects=objects, shake=shake_px)
            still_b = simulate_bracket(camera, kind=kind, size=size, exposures=exposures, seed=int(seed),
                                       family=family, motion=base.still())
            ref = still_b.params["motion"]["reference"]

            at_ref = dataclasses.replace(motion or MotionOptions(), reference=ref)

            def opts(m: str) -> dict:
                return {"model": model} if method_spec(m).needs_model else {}

            still_results = {m: merge_seeded(_stack(still_b, Stack), m, int(seed), opts(m), motion=at_ref).radiance
                             for m in methods}
            for setting in settings:
                spec = base if setting == "handheld" else base.tripod()
                if progress is not None:
                    progress(f"{family} {setting} seed {seed}")
                b = simulate_bracket(camera, kind=kind, size=size, exposures=exposures, seed=int(seed),
                                     family=family, motion=spec)
                seen = seen_in_reference(b.jpeg_codes[ref])
                for m in methods:
                    moving = zone_errors(merge_seeded(_stack(b, Stack), m, int(seed), opts(m), motion=at_ref).radiance,
                                         b.truth_linear_srgb, b.motion_zones, seen)
                    still = zone_errors(still_results[m], still_b.truth_linear_srgb, b.motion_zones, seen)
                    row = {"family": family, "held_out": family not in TUNING_FAMILIES, "setting": setting, "seed": int(seed),
                           "method": m, "shake_px": spec.shake,
                           "zone_pixels": [int(np.sum(b.motion_zones == z)) for z in range(3)],
                           "object_seen_pixels": int(np.sum((b.motion_zones == 2) & seen))}
                    for zone in ("static", "swept", "object", "object_seen"):
                        row[f"{zone}_moving"] = moving[zone]
                        row[f"{zone}_still"] = still[zone]
                        row[f"{zone}_ratio"] = (moving[zone] / still[zone] if still[zone] > 0 else float("nan"))
                    rows.append(row)
    return rows


def _stack(b, stack_cls):
    return stack_cls(images=b.jpeg_codes.astype(np.float32) * np.float32(1 / 255), times=b.times)


def summarise_ghosts(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean over seeds per (family, setting, method)."""
    keys: dict[tuple, list[dict]] = {}
    for r in rows:
        keys.setdefault((r["family"], r["setting"], r["method"]), []).append(r)
    out = []
    for (family, setting, method), rs in keys.items():
        s = {"family": family, "held_out": rs[0]["held_out"], "setting": setting, "method": method, "n": len(rs)}
        for k in rs[0]:
            if k.endswith(("_moving", "_still", "_ratio")):
                s[k] = float(np.nanmean([r[k] for r in rs]))
        out.append(s)
    return out
