"""CLI behaviour: user mistakes give one line on stderr and exit code 2, never a traceback."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli, write_png_codes


def _pngs(tmp_path, n=2, shapes=None):
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        shape = shapes[i] if shapes else (8, 8, 3)
        out.append(write_png_codes(tmp_path / f"i{i}.png", rng.integers(0, 256, shape, dtype=np.int64).astype(np.uint8)))
    return out


def _assert_user_error(code, err, needle):
    assert code == 2, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("error:")
    assert needle.lower() in err.lower()


def test_simulate_writes_bracket(tmp_path, capsys):
    code, out, err = run_cli(["simulate", tmp_path / "s", "--exposures", "3", "--size", "64x48", "--seed", "1"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "s" / "raw").iterdir()) == ["00.dng", "01.dng", "02.dng"]
    assert (tmp_path / "s" / "truth.exr").is_file() and (tmp_path / "s" / "scene.json").is_file()


@pytest.mark.parametrize("args,needle", [
    (["simulate", "OUT", "--size", "abc"], "--size"),
    (["simulate", "OUT", "--pipeline", "weird", "--size", "64x48"], "pipeline"),
    (["simulate", "OUT", "--camera", "no-such-camera", "--size", "64x48"], "unknown camera"),
    (["simulate", "OUT", "--bits", "10", "--size", "64x48"], "bits"),
    (["simulate"], "missing argument"),
    (["no-such-command"], "no such command"),
])
def test_user_errors_exit_2(tmp_path, capsys, args, needle):
    args = [str(tmp_path / "o") if a == "OUT" else a for a in args]
    code, out, err = run_cli(args, capsys)
    _assert_user_error(code, err, needle)
