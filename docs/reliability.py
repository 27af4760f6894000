"""The reliability diagram of ``docs/uncertainty.md``: observed against nominal coverage (issue 29).

``python docs/reliability.py --measure`` runs what ``derender experiment uncertainty`` runs
(GP calibrated on the simulated D5100's chart session, 5000 pairs; a 192x128, 7-exposure
bracket of every pipeline family, seeds 0 and 1) for ``probabilistic`` (shared-error variance),
``probabilistic`` with eq. 3's independent variance (``variance_model="independent"``, the
variance before issue 29) and ``stabilized-probabilistic``, and writes the share of
pixel-channels inside the central ``p`` interval, for 19 levels ``p``, to
``docs/data/reliability.json`` (~1 minute). :func:`draw_reliability` draws the diagram from
that file when the docs are built (``docs/figures.py``'s :func:`draw_all`); a calibrated
variance lies on the diagonal.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

__all__ = ["LEVELS", "measure", "draw_reliability"]

DATA = Path(__file__).resolve().parent / "data" / "reliability.json"
#: Nominal coverage levels of the diagram.
LEVELS = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 0.975, 0.99)
FAMILIES = ("paper", "camera", "dslr-lut", "phone-local", "drift")
TUNING = ("paper", "camera")
VARIANTS = {"probabilistic": ("probabilistic", {}),
            "probabilistic, eq. 3 (before)": ("probabilistic", {"variance_model": "independent"}),
            "stabilized-probabilistic": ("stabilized-probabilistic", {})}


def measure(path: Path = DATA, seeds=(0, 1)) -> Path:
    """Measure the coverages (module docstring) and write them as JSON to ``path``."""
    import numpy as np

    from derender.camera import simulate_bracket
    from derender.core.types import Stack
    from derender.evaluation.uncertainty import chart_model, coverage_scores
    from derender.hdr.registry import merge_seeded

    model = chart_model("nikon-d5100", n_train=5000)
    out: dict = {"levels": list(LEVELS), "seeds": list(seeds), "size": [192, 128], "exposures": 7, "curves": {}}
    for family in FAMILIES:
        for seed in seeds:
            b = simulate_bracket("nikon-d5100", size=(192, 128), exposures=7, seed=seed, family=family)
            stack = Stack(images=b.jpeg_codes.astype(np.float32) / np.float32(255), times=b.times)
            for name, (method, opts) in VARIANTS.items():
                res = merge_seeded(stack, method, seed, options={**opts, "model": model})
                cov = coverage_scores(res.radiance, res.variance, b.truth_linear_srgb, levels=LEVELS)["coverage"]
                out["curves"].setdefault(name, {}).setdefault(family, []).append([cov[float(p)] for p in LEVELS])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    return path


def draw_reliability(path: Path, data: Path = DATA) -> Path:
    """Observed against nominal coverage, one panel per variant, a line per family (mean over
    the seeds; tuning families solid, held-out dashed) and the band 0.93-0.97 at 95 %."""
    d = json.loads(Path(data).read_text())
    levels = d["levels"]
    names = list(d["curves"])
    fig, axes = plt.subplots(1, len(names), figsize=(4.1 * len(names), 3.9), sharey=True)
    colours = dict(zip(FAMILIES, ("#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#ff7f0e")))
    for ax, name in zip(axes, names):
        ax.plot([0, 1], [0, 1], color="#888888", linewidth=0.8)
        ax.add_patch(plt.Rectangle((0.94, 0.93), 0.02, 0.04, color="#bbbbbb", alpha=0.6, linewidth=0))
        ax.add_patch(plt.Rectangle((0.49, 0.45), 0.02, 0.10, color="#bbbbbb", alpha=0.6, linewidth=0))
        for family, runs in d["curves"][name].items():
            mean = [sum(r[i] for r in runs) / len(runs) for i in range(len(levels))]
            ax.plot(levels, mean, "-" if family in TUNING else "--", marker="o", markersize=2.5,
                    color=colours.get(family, "#333333"),
                    label=f"{family} ({'tuning' if family in TUNING else 'held out'})")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("nominal coverage p", fontsize=8.5)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.tick_params(labelsize=7.5)
        ax.grid(alpha=0.3, linewidth=0.5)
    axes[0].set_ylabel("share of pixel-channels inside", fontsize=8.5)
    axes[-1].legend(fontsize=7, loc="upper left")
    fig.tight_layout(pad=0.4)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)
    return path


if __name__ == "__main__":
    if "--measure" in sys.argv[1:]:
        print(measure())
    else:
        print(draw_reliability(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/_generated") / "reliability.png"))
