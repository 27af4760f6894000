"""Options of the stabilised merges on the tuning families (paper, camera), then on the held-out ones.

Tuning families: paper, camera. Held out: dslr-lut, phone-local, drift. Each config is a
JSON dict of :func:`derender.hdr.registry.merge_seeded` options.

    PYTHONPATH=src python benchmarks/families_sweep.py --families paper camera \
        --configs '{}' '{"weight": "hat"}' '{"noise_weighting": false}'
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from families_measure import TUNING, bracket, score, stack_of


def main() -> None:
    from derender.hdr.registry import merge_seeded

    ap = argparse.ArgumentParser()
    ap.add_argument("--families", nargs="*", default=list(TUNING))
    ap.add_argument("--kinds", nargs="*", default=["outdoor", "indoor"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    ap.add_argument("--methods", nargs="*", default=["stabilized", "stabilized-joint"])
    ap.add_argument("--configs", nargs="*", default=["{}"])
    a = ap.parse_args()
    configs = [json.loads(c) for c in a.configs]
    brackets = [(f, k, s, bracket(f, k, s)) for f in a.families for k in a.kinds for s in a.seeds]
    for cfg in configs:
        for m in a.methods:
            per_fam: dict = {}
            for f, k, s, b in brackets:
                sc = score(merge_seeded(stack_of(b), m, s, options=cfg).radiance, b)
                per_fam.setdefault(f, []).append(sc)
            cells = " ".join(f"{f}: {np.mean([x['L'] for x in v]):.2f}/{np.mean([x['rel'] for x in v]):.3f}/"
                             f"{np.mean([x['rel4'] for x in v]):.3f}" for f, v in per_fam.items())
            print(f"{m:17s} {json.dumps(cfg):45s} {cells}", flush=True)


if __name__ == "__main__":
    main()
