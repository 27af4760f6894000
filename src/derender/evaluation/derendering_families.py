"""Paper 2's de-rendering models on every camera-pipeline family (``derender experiment derender-families``).

The models (``gp``, ``poly``, ``rbf``) were tuned on calibration sessions rendered by the
``paper`` and ``camera`` pipelines (:data:`derender.evaluation.families.TUNING_FAMILIES`);
:func:`derender_families` re-runs the calibration session (:func:`derender.camera.chart.chart_pairs`
with ``family=``) through each family of :data:`derender.camera.families.FAMILIES` and scores the
models on it, under two splits:

* ``random``: 5000 random pairs for training, every other pair for testing (paper 2 Table 1);
* ``held-out illuminants``: train on 5000 pairs of 12 gel illuminants, test on every pair of
  the other 4 (:data:`HELDOUT_ILLUMINANTS`; paper 2's protocol for the illuminant hold-out).

Per (family, split, method): relative RMSE (MAP point estimate, as in
:func:`derender.evaluation.experiments.derender_table`) over all test colours, over those with a
channel clipped at 255 and over those outside the sRGB gamut, and the 95 % interval coverage
per channel (predictive mean and variance), the relative RMSE of the predictive *mean* as a
point estimate, and for both points the largest share one test colour has of the squared
relative error (:func:`~derender.evaluation.derendering_metrics.max_colour_share`). A ``floor`` row per (family, split) gives the
smallest relative RMSE *any* function of the JPEG code can reach on the same test colours
(:func:`derender.evaluation.derendering_metrics.code_floor_errors`): where it rises with the
family, the rendering itself has become one-to-many, not the model worse. The RAW side (the truth) of every family is the
same; only the JPEG engine differs, and in the held-out families it also changes from
exposure to exposure (gain jitter, switching or drifting white balance, a local tone map),
so that one JPEG colour no longer has one RAW colour.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "HELDOUT_ILLUMINANTS",
    "SPLITS",
    "derender_families",
]

#: Illuminants (indices into :func:`derender.camera.chart.gel_illuminants`) held out by the
#: ``held-out illuminants`` split: the bare lamp, a blue gel and two coloured gels (the four
#: of ``derender experiment threshold-sweep``'s documented run).
HELDOUT_ILLUMINANTS = (0, 3, 7, 12)

#: Train/test splits of :func:`derender_families`.
SPLITS = ("random", "held-out illuminants")


def _split(pairs, split: str, n_train: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    n = pairs.jpeg.shape[0]
    if split == "random":
        perm = rng.permutation(n)
        return perm[:n_train], perm[n_train:]
    n_il = int(pairs.illuminant.max()) + 1
    held = [i for i in HELDOUT_ILLUMINANTS if i < n_il] or [n_il - 1]
    test = np.isin(pairs.illuminant, held)
    if test.all():
        raise InputError("the held-out illuminant split needs at least 2 illuminants")
    tr = np.flatnonzero(~test)
    tr = rng.permutation(tr)[:n_train]
    return np.sort(tr), np.flatnonzero(test)


def derender_families(families: Sequence[str] | None = None, *, cameras: Sequence[str] | None = None,
                      methods: Sequence[str] = ("gp", "poly", "rbf"), splits: Sequence[str] = SPLITS,
                      n_train: int = 5000, seed: int = 0, n_illuminants: int = 16, n_exposures: int = 22,
                      floor: bool = True, progress: Callable[[str], None] | None = None) -> list[dict]:
    """One row per (camera, family, split, method); see the module doc.

    Keys: ``camera``, ``family``, ``role`` (``"tuning"`` or ``"held out"``), ``split``,
    ``method``, ``n_train``, ``n_test``, ``rel_rmse_all``, ``rel_rmse_clipped``,
    ``rel_rmse_oog`` (NaN when no test colour is clipped / out of gamut), ``coverage95``
    (R, G, B), ``coverage95_mean``, ``rel_rmse_mean`` (the predictive mean as point),
    ``max_colour_share`` and ``max_colour_share_mean`` (largest one-colour share of the squared
    relative error, MAP and mean), ``share_clipped``, ``share_oog``, ``fit_seconds``.
    ``floor`` rows (when ``floor``) carry the three relative RMSEs, ``n_train`` 0 and no coverage.
    Defaults: every family, nikon-d5100, 5000 training pairs.
    """
    from derender.camera.chart import chart_pairs
    from derender.camera.families import FAMILIES, check_family
    from derender.camera.spectral import camera_search_dirs, load_camera
    from derender.evaluation.derendering_metrics import (
        code_floor_errors,
        fit_and_predict,
        max_colour_share,
        relative_rmse,
    )
    from derender.evaluation.families import TUNING_FAMILIES

    families = list(families) if families else list(FAMILIES)
    for f in families:
        check_family(f)
    for s in splits:
        if s not in SPLITS:
            raise InputError(f"unknown split {s!r}: choose from {', '.join(SPLITS)}")
    rows = []
    for cam_name in cameras or ["nikon-d5100"]:
        cam = load_camera(cam_name, search_dirs=camera_search_dirs())
        for fam in families:
            pairs = chart_pairs(cam, n_illuminants=n_illuminants, n_exposures=n_exposures, seed=seed, family=fam)
            for si, split in enumerate(splits):
                tr, te = _split(pairs, split, n_train, np.random.default_rng([int(seed), si]))
                x = pairs.raw[te]
                oog = pairs.out_of_gamut[te]
                clipped = np.any(pairs.jpeg[te] == 255, axis=1)
                for m in methods:
                    fp = fit_and_predict(m, pairs.jpeg[tr], pairs.raw[tr], pairs.jpeg[te], x, seed=seed)
                    fit_s, cov, point = fp["fit_seconds"], fp["coverage"], fp["point"]
                    rows.append({
                        "camera": cam.name, "family": fam, "role": "tuning" if fam in TUNING_FAMILIES else "held out",
                        "split": split, "method": m, "n_train": int(tr.size), "n_test": int(te.size),
                        "rel_rmse_all": relative_rmse(point, x),
                        "rel_rmse_clipped": relative_rmse(point[clipped], x[clipped]) if clipped.any() else float("nan"),
                        "rel_rmse_oog": relative_rmse(point[oog], x[oog]) if oog.any() else float("nan"),
                        "coverage95": [float(c) for c in cov], "coverage95_mean": float(np.mean(cov)),
                        "rel_rmse_mean": relative_rmse(fp["mean"], x),
                        "max_colour_share": max_colour_share(point, x),
                        "max_colour_share_mean": max_colour_share(fp["mean"], x),
                        "share_clipped": float(clipped.mean()), "share_oog": float(oog.mean()),
                        "fit_seconds": fit_s,
                    })
                    if progress:
                        r = rows[-1]
                        progress(f"{cam.name} {fam} {split} {m}: rel RMSE {r['rel_rmse_all']:.3f} "
                                 f"(clipped {r['rel_rmse_clipped']:.3f}, oog {r['rel_rmse_oog']:.3f}), "
                                 f"coverage {r['coverage95_mean']:.3f}, largest one-colour share "
                                 f"{r['max_colour_share']:.4f} (mean as point: rel RMSE {r['rel_rmse_mean']:.3f}, "
                                 f"share {r['max_colour_share_mean']:.4f}), {fit_s:.1f} s fit")
                if floor:
                    jt = pairs.jpeg[te]

                    def fl(sel):
                        return float(np.sqrt(code_floor_errors(jt[sel], x[sel]).mean())) if sel.any() else float("nan")

                    rows.append({
                        "camera": cam.name, "family": fam, "role": "tuning" if fam in TUNING_FAMILIES else "held out",
                        "split": split, "method": "floor", "n_train": 0, "n_test": int(te.size),
                        "rel_rmse_all": fl(np.ones(te.size, bool)), "rel_rmse_clipped": fl(clipped),
                        "rel_rmse_oog": fl(oog), "share_clipped": float(clipped.mean()),
                        "share_oog": float(oog.mean()),
                    })
    return rows
