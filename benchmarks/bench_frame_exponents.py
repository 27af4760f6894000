"""Per-frame exponents in the curve model (:mod:`derender.hdr.stabilize.frame_exponents`): searched vs oracle.

For each bracket of a family the stabilised merges run with ``exponent_rounds`` 0 (one table for
every frame, the default before), the searched ``rho_j`` (``--rounds``), and the *oracle*
exponents ``rho_j = gamma_j / geomean(gamma)`` from the simulator's per-frame display gammas
(``exponents=`` of :func:`~derender.hdr.stabilize.filmic.unclipped_debevec`; the oracle tells
whether an exact per-frame exponent reaches the truth); "grey": the largest per-decade deviation of
the truly neutral pixels from neutral (:func:`derender.evaluation.neutral.neutral_axis_truth`,
issue 27). Tuning families: paper, camera; held
out: dslr-lut, phone-local, drift. Scores as ``benchmarks/families_measure.py``::

    PYTHONPATH=src python benchmarks/bench_frame_exponents.py --families camera --seeds 0 1
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from families_measure import TUNING, bracket, score, stack_of


def true_rho(b) -> np.ndarray | None:
    g = np.array([f.gamma for f in b.frames], dtype=np.float64)
    return g / np.exp(np.mean(np.log(g)))


def run_oracle(st, method, seed, rho):
    """The merge with ``unclipped_debevec``'s exponents fixed to ``rho`` (a diagnostic patch)."""
    import functools

    import derender.hdr.stabilize.filmic as filmic
    import derender.hdr.stabilize.method as meth
    from derender.hdr.registry import merge_seeded

    orig_f, orig_m = filmic.unclipped_debevec, meth.unclipped_debevec
    patched = functools.partial(orig_f, exponents=rho)
    filmic.unclipped_debevec = meth.unclipped_debevec = patched
    try:
        return merge_seeded(st, method, seed)
    finally:
        filmic.unclipped_debevec, meth.unclipped_debevec = orig_f, orig_m


def main() -> None:
    from derender.evaluation.neutral import neutral_axis_truth
    from derender.hdr.registry import merge_seeded

    ap = argparse.ArgumentParser()
    ap.add_argument("--families", nargs="*", default=["camera"])
    ap.add_argument("--kinds", nargs="*", default=["outdoor", "indoor"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    ap.add_argument("--methods", nargs="*", default=["stabilized", "stabilized-joint"])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--no-oracle", action="store_true")
    ap.add_argument("--set", nargs="*", default=[], help="frame_exponents constants NAME=value (diagnostic)")
    a = ap.parse_args()
    import derender.hdr.stabilize.frame_exponents as fe

    for kv in a.set:
        k, v = kv.split("=")
        setattr(fe, k, type(getattr(fe, k))(float(v)) if not isinstance(getattr(fe, k), bool) else v == "1")
    rows = []
    for fam in a.families:
        for kind in a.kinds:
            for seed in a.seeds:
                b = bracket(fam, kind, seed)
                st = stack_of(b)
                rho_t = true_rho(b)
                for m in a.methods:
                    row = {"family": fam, "split": "tuning" if fam in TUNING else "held-out", "kind": kind,
                           "seed": seed, "method": m, "rho_true": np.round(rho_t, 3).tolist()}
                    r0 = merge_seeded(st, m, seed, options={"exponent_rounds": 0})
                    r1 = merge_seeded(st, m, seed, options={"exponent_rounds": a.rounds})
                    row["off"] = score(r0.radiance, b)
                    row["search"] = score(r1.radiance, b)
                    for k, r in (("off", r0), ("search", r1)):      # issue 27: greys per decade
                        row[k]["grey"] = neutral_axis_truth(b.truth_linear_srgb, r.radiance).max_deviation
                    row["rho_search"] = np.round(r1.info.get("rho", []), 3).tolist()
                    mf = r1.info.get("curve_misfit")
                    row["misfit_ratio"] = (float(np.mean(mf[1]) / np.mean(mf[0])) if mf and mf[0] is not None
                                           else None)
                    if not a.no_oracle:
                        row["oracle_rho"] = score(run_oracle(st, m, seed, rho_t).radiance, b)
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    for m in a.methods:
        for fam in a.families:
            rs = [r for r in rows if r["family"] == fam and r["method"] == m]
            cells = []
            for k in ("off", "search") + (() if a.no_oracle else ("oracle_rho",)):
                cells.append(f"{k} {np.mean([r[k]['L'] for r in rs]):.2f} / {np.mean([r[k]['rel4'] for r in rs]):.3f}"
                             + (f" / grey {np.nanmean([r[k]['grey'] for r in rs]):.3f}" if "grey" in rs[0][k] else ""))
            print(f"| {fam} | {rs[0]['split']} | {m} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
