"""One search order for camera names, from any working directory (``derender cameras``)."""

from __future__ import annotations

import json
import os

import numpy as np
from helpers import run_cli


def _fake_root(tmp_path):
    """A data root in the shared/data layout holding one made-up rawtoaces camera JSON."""
    folder = tmp_path / "root" / "rawtoaces-spectral" / "data" / "camera"
    folder.mkdir(parents=True)
    wl = np.arange(380, 781, 5)
    main = {str(int(w)): [float(np.exp(-((w - c) / 40.0) ** 2)) for c in (600, 540, 450)] for w in wl}
    doc = {"header": {"manufacturer": "Testmaker", "model": "TM-1"}, "spectral_data": {"data": {"main": main}}}
    (folder / "Testmaker_TM-1_380_780_5.json").write_text(json.dumps(doc))
    return tmp_path / "root"


def test_cameras_from_any_directory_with_the_env_root(tmp_path, monkeypatch, capsys):
    root = _fake_root(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    monkeypatch.setenv("DERENDER_SHARED_DATA", str(root))
    code, out, err = run_cli(["cameras"], capsys)
    assert code == 0, err
    names = [line.split()[0] for line in out.splitlines()]
    assert names[:2] == ["nikon-d5100", "sigma-sd-merrill"] and "testmaker-tm-1" in names
    assert str(root / "rawtoaces-spectral" / "data" / "camera") in err
    # the simulator takes that name from the same search order
    from derender.camera.spectral import load_camera

    cam = load_camera("testmaker-tm-1")
    assert cam.make == "Testmaker" and cam.sensitivities.shape[1] == 3


def test_unknown_camera_lists_where_it_looked(tmp_path, monkeypatch, capsys):
    root = _fake_root(tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DERENDER_SHARED_DATA", str(root))
    code, out, err = run_cli(["chart-pairs", tmp_path / "cp", "--camera", "no-such-camera"], capsys)
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: unknown camera 'no-such-camera'")
    assert str(root / "rawtoaces-spectral" / "data" / "camera") in lines[0]
    assert os.fspath(tmp_path / "shared" / "data") in lines[0]       # the working directory's own shared/
    assert not (tmp_path / "cp").exists()


def test_shared_cameras_found_outside_the_checkout(rawtoaces_dir, tmp_path, monkeypatch, capsys):
    """The real rawtoaces cameras are found by name from a directory that has no shared/ near it
    (the checkout's sibling shared/ or DERENDER_SHARED_DATA): the bug was a CLI that only looked
    in ./shared and ../shared."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DERENDER_SHARED_DATA", str(rawtoaces_dir.parent))
    code, out, err = run_cli(["cameras"], capsys)
    assert code == 0, err
    assert "canon-powershot-s90" in out.split()
