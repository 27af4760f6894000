"""Why the brightest decades miss on the auto-pipeline renderings (issue 28, linearity on ``camera``).

The ``paper`` and ``camera`` renderings of the luminance family draw every frame's rendering
afresh (:func:`derender.camera.rendering.pipeline_settings`, the ``auto`` pipeline): a digital
gain ``exp(U(0, 0.3))``, a display gamma ``U(1.8, 2.6)``, a white-balance drift and a saturation
``U(0.85, 1.15)``. The brightest decades (lamps, 1e5..1e6 cd/m2) are seen only by the 1-3
shortest frames, the grey card that sets the scale by the middle ones, so whatever differs
between those frames' renderings lands on the top decades' ratio. This script takes the
per-frame draws away one at a time (a diagnostic intervention: it wraps
``pipeline_settings`` so the drawn settings are replaced by the fixed pipeline's, gain 1,
gamma 2.2, the scene's white balance, saturation 1) and scores every method as
:func:`derender.evaluation.linearity.linearity_scores` does (spot on the grey card)::

    python benchmarks/bench_linearity_causes.py --render camera --seeds 0,1 --methods debevec,stabilized

Variants: ``none`` (the family as it is), ``nogain``, ``nogamma``, ``nogain-nogamma``,
``fixed`` (no per-frame draw at all: the ``camera`` style's Hable shoulder, toe and gamut
compression remain). ``camera`` and ``paper`` are tuning renderings. Results: docs/results-luminance.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

VARIANTS = {"none": {}, "nogain": {"gain"}, "nogamma": {"gamma"}, "nogain-nogamma": {"gain", "gamma"},
            "fixed": {"gain", "gamma", "wb", "saturation"}}


def frozen_settings(orig, frozen: set):
    """``pipeline_settings`` whose per-frame draws in ``frozen`` are replaced by the fixed pipeline's."""
    def patched(pipeline, n, wb_true, style, rng, tone_curve=False):
        out = orig(pipeline, n, wb_true, style, rng, tone_curve)   # the same draws (same rng use)
        rep = {"gain": 1.0, "gamma": 2.2, "wb": [float(v) for v in wb_true], "saturation": 1.0}
        return [dataclasses.replace(s, **{k: v for k, v in rep.items() if k in frozen}) for s in out]
    return patched


def main(argv=None) -> int:
    import derender.camera.rendering as rendering
    from derender.camera.luminance import simulate_luminance, truth_luminance_cd_m2
    from derender.core.types import Stack
    from derender.evaluation.families import smooth_mask
    from derender.evaluation.linearity import format_decades, linearity_scores
    from derender.hdr.registry import merge_seeded

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--render", default="camera", help="paper or camera (the auto-pipeline renderings)")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--methods", default="debevec,stabilized")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args(argv)
    orig = rendering.pipeline_settings
    print(f"| variant ({args.render}, tuning) | seed | method | median abs err | p90 | median ratio per decade 1..1e6 |")
    print("| --- | ---: | --- | ---: | ---: | --- |")
    try:
        for v in args.variants.split(","):
            rendering.pipeline_settings = frozen_settings(orig, VARIANTS[v])
            for seed in (int(s) for s in args.seeds.split(",")):
                b = simulate_luminance(render=args.render, seed=seed)
                stack = Stack(images=b.jpeg_codes.astype(np.float32) / 255, times=b.times)
                lt, sm = truth_luminance_cd_m2(b.truth_linear_srgb), smooth_mask(b.truth_linear_srgb)
                for m in args.methods.split(","):
                    res = merge_seeded(stack, m, seed)
                    sc = linearity_scores(res.radiance, lt, b.params["luminance"]["spot"], score_mask=sm,
                                          merge_mask=res.mask)
                    print(f"| {v} | {seed} | {m} | {sc['median_abs']:.1%} | {sc['p90_abs']:.1%} | "
                          f"{format_decades(sc['decades'])} |", flush=True)
    finally:
        rendering.pipeline_settings = orig
    return 0


if __name__ == "__main__":
    sys.exit(main())
