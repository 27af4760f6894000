"""Robertson against Debevec per bracket and family, with the curve and the merge swapped (issue 16).

Tuning families: paper, camera. Held out: dslr-lut, phone-local, drift. For every bracket it
prints PSNR L of ``debevec``, ``robertson``, Robertson's curve with Debevec's merge
(``robC_debM``) and Debevec's curve with Robertson's merge (``debC_robM``), so that a gap can
be put on the curve or on the merge; then the per-family means (all seeds, and seeds 0-1 as
in ``derender experiment families``).

    PYTHONPATH=src python benchmarks/robertson_families.py --families paper camera --seeds 0 1 2 3 4 5
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from families_measure import HELD_OUT, TUNING, bracket, score, stack_of


def main() -> None:
    from derender.hdr.classic import merge_debevec, merge_robertson

    ap = argparse.ArgumentParser()
    ap.add_argument("--families", nargs="*", default=list(TUNING))
    ap.add_argument("--kinds", nargs="*", default=["outdoor", "indoor"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    a = ap.parse_args()
    keys = ("debevec", "robertson", "robC_debM", "debC_robM")
    rows = []
    for fam in a.families:
        for kind in a.kinds:
            for seed in a.seeds:
                b = bracket(fam, kind, seed)
                st = stack_of(b)
                rd, rr = merge_debevec(st, options={"seed": seed}), merge_robertson(st, options={"seed": seed})
                row = {"family": fam, "scene": f"{kind}-{seed}", "seed": seed,
                       "debevec": score(rd.radiance, b)["L"], "robertson": score(rr.radiance, b)["L"],
                       "robC_debM": score(merge_debevec(st, options={"curves": rr.info["curves"]}).radiance, b)["L"],
                       "debC_robM": score(merge_robertson(st, options={"curves": rd.info["curves"]}).radiance, b)["L"]}
                rows.append(row)
                print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    print("| family | split | brackets | " + " | ".join(keys) + " | robertson - debevec | (seeds 0-1) |")
    print("|---|---|---|" + "---|" * (len(keys) + 2))
    for fam in a.families:
        rs = [r for r in rows if r["family"] == fam]
        m = {k: float(np.mean([r[k] for r in rs])) for k in keys}
        off = [r for r in rs if r["seed"] in (0, 1)]
        d01 = (float(np.mean([r["robertson"] - r["debevec"] for r in off])) if off else float("nan"))
        split = "tuning" if fam in TUNING else ("held-out" if fam in HELD_OUT else "?")
        print(f"| {fam} | {split} | {len(rs)} | " + " | ".join(f"{m[k]:.2f}" for k in keys)
              + f" | {m['robertson'] - m['debevec']:+.2f} | {d01:+.2f} |")


if __name__ == "__main__":
    main()
