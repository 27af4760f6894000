"""The README's quick start runs as written, on a bracket of 'your own photos' the simulator makes."""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

from helpers import run_cli

README = Path(__file__).resolve().parents[1] / "README.md"


def _block_after(heading: str) -> list[list[str]]:
    text = README.read_text(encoding="utf-8")
    part = text.split(heading, 1)[1]
    block = re.search(r"```bash\n(.*?)```", part, flags=re.S).group(1)
    lines = [line.split("#", 1)[0].strip() for line in block.splitlines()]
    return [shlex.split(line)[1:] for line in lines if line.startswith("derender ")]


def test_readme_opens_with_the_two_commands_and_stays_short():
    text = README.read_text(encoding="utf-8")
    first = re.search(r"```bash\n(.*?)```", text, flags=re.S).group(1).strip().splitlines()
    assert first == ["pip install . && derender demo", "pip install -e '.[test]' && pytest"]
    assert len(text.split()) < 1500


def test_quick_start_on_own_photos(tmp_path, monkeypatch, capsys):
    from derender.camera import simulate_bracket, write_bracket

    write_bracket(simulate_bracket(size=(128, 96), exposures=5, seed=11), tmp_path / "camera")
    shutil.copytree(tmp_path / "camera" / "jpeg", tmp_path / "photos")         # a folder of JPEGs, as shot
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli(["groundtruth", *sorted((tmp_path / "camera" / "raw").glob("*.dng")),
                            "-o", "groundtruth.exr"], capsys)
    assert code == 0, err
    commands = _block_after("## Your own photos in three commands")
    assert [c[0] for c in commands] == ["merge", "falsecolor", "evaluate"]
    outs = []
    for args in commands:
        code, out, err = run_cli(args, capsys)
        assert code == 0, f"derender {' '.join(args)}: {err}"
        outs.append(out)
    for name in ("hdr.exr", "hdr.png", "falsecolor.png"):
        assert (tmp_path / name).is_file()
    lum = float(re.search(r"L (\d+\.\d+) dB", outs[2]).group(1))
    assert lum > 30.0                     # the stabilised merge against the RAW ground truth
