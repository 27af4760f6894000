"""docs/calibrate.md's worked example runs as written: every command of its bash block, in order."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from helpers import run_cli

DOC = Path(__file__).resolve().parents[1] / "docs" / "calibrate.md"


def _commands() -> list[list[str]]:
    blocks = re.findall(r"```bash\n(.*?)```", DOC.read_text(encoding="utf-8"), flags=re.S)
    assert blocks, "docs/calibrate.md has no bash block"
    lines = [line.strip() for line in blocks[0].splitlines() if line.strip() and not line.startswith("#")]
    assert all(line.startswith("derender ") for line in lines), lines
    return [shlex.split(line)[1:] for line in lines]


@pytest.mark.slow
def test_worked_example_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    outputs = {}
    for args in _commands():
        code, out, err = run_cli(args, capsys)
        assert code == 0, f"derender {' '.join(args)}: {err}"
        outputs[args[0]] = out
    for name in ("mycam.npz", "mean.exr", "variance.exr", "hdr.exr", "hdr-variance.exr", "mask.png"):
        assert (tmp_path / name).is_file(), name
    assert "auto chose" in outputs["calibrate"]
    lum = re.search(r"L (\d+\.\d+) dB", outputs["evaluate"])
    assert lum and float(lum.group(1)) > 30.0, outputs["evaluate"]     # against the simulator's exact radiance
    assert "coverage" in outputs["evaluate"]
