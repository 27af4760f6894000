"""``derender experiment families`` on one held-out family and one tiny bracket (issues 16, 18)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run_cli

from derender.core.errors import InputError
from derender.evaluation.families import (
    FAMILY_METHODS,
    PEERS,
    TUNING_FAMILIES,
    family_comparison,
    smooth_mask,
    summarise_families,
)


def test_one_family_one_bracket_rows_and_the_oracle_is_best():
    rows = family_comparison(["phone-local"], kinds=("outdoor",), seeds=(0,), size=(64, 48), exposures=4)
    methods = [r["method"] for r in rows]
    assert methods == ["oracle", "oracle-q", *FAMILY_METHODS, *PEERS]
    for r in rows:
        assert r["family"] == "phone-local" and r["held_out"] and r["scene"] == "outdoor-0"
        for k in ("R", "G", "B", "L", "rel_median", "rel_p90", "log_psnr_L", "L_smooth", "rel_median_smooth"):
            assert np.isfinite(r[k]), (r["method"], k)
    by = {r["method"]: r for r in rows}
    # where the camera's spatial filters keep the truth, knowing the pipeline wins
    assert by["oracle-q"]["rel_median_smooth"] == min(r["rel_median_smooth"] for r in rows)
    assert by["oracle-q"]["L_smooth"] > by["debevec"]["L_smooth"]
    summary = summarise_families(rows)
    assert [s["method"] for s in summary] == methods
    assert all(s["held_out"] == "yes" and s["brackets"] == 1 for s in summary)
    oracle = next(s for s in summary if s["method"] == "oracle")
    assert oracle["rel_to_oracle"] == pytest.approx(1.0)
    deb = next(s for s in summary if s["method"] == "debevec")
    assert deb["dL"] == 0.0


def test_tuning_families_and_bad_names():
    assert TUNING_FAMILIES == ("paper", "camera")
    with pytest.raises(InputError, match="phone-local"):
        family_comparison(["nope"], seeds=(0,))
    with pytest.raises(InputError):
        family_comparison(["paper"], seeds=(0,), peers=("opencv-mertens",))


def test_smooth_mask_excludes_edges_and_border():
    g = np.ones((40, 40, 3))
    g[:, 20:] = 10.0
    m = smooth_mask(g)
    assert not m[:4].any() and not m[:, -4:].any()
    assert not m[20, 17:23].any() and m[20, 8] and m[20, 30]


def test_cli_experiment_families_writes_json(tmp_path, capsys):
    out = tmp_path / "f.json"
    code, stdout, err = run_cli(["experiment", "families", "--families", "dslr-lut", "--kinds", "indoor", "--seeds", "1",
                                 "--size", "48x32", "--exposures", "3", "--methods", "debevec", "--peers", "",
                                 "--json", out], capsys)
    assert code == 0, err
    assert "dslr-lut" in stdout and "oracle" in stdout and "held out" in stdout
    data = json.loads(out.read_text())
    assert {r["method"] for r in data["brackets"]} == {"oracle", "oracle-q", "debevec"}
    code, _, err = run_cli(["experiment", "families", "--families", "nope"], capsys)
    assert code == 2 and err.strip().splitlines()[-1].startswith("error:")
