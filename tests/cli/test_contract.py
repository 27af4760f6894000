"""The input contract of the CLI end to end (issue 15): every bad input or OS failure gives
exit 2 and one ``error:`` line naming the user's path, an interruption exit 130 and
``interrupted``; in every case no output is left behind and the inputs are unchanged.
"""

from __future__ import annotations

import errno
import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, write_png_codes

from derender.io.files import TEMP_PREFIX


def _bracket(tmp_path: Path, size=(48, 64), n=3) -> list[Path]:
    """Smooth 8-bit renderings of one scene at doubling exposures (PNG, times 1, 2, 4 ...)."""
    h, w = size
    y, x = np.mgrid[0:h, 0:w]
    radiance = 0.02 + np.stack([x / w, y / h, (x + y) / (w + h)], -1)
    paths = []
    for j in range(n):
        codes = np.clip(255.0 * (radiance * 2.0**j) ** (1 / 2.2), 0, 255).astype(np.uint8)
        paths.append(write_png_codes(tmp_path / f"in{j}.png", codes))
    return paths


def _digest(paths) -> dict:
    return {str(p): hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths}


def _listing(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()}


def _assert_error(code, err, needle):
    assert code == 2, err
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    assert needle.lower() in lines[0].lower(), err


TIMES = ["--times", "1,2,4"]


@pytest.mark.parametrize("extra,needle", [
    (["--preview", "{in0}"], "refusing to overwrite input"),
    (["--preview", "nodir/p.png"], "output folder does not exist"),
    (["--preview", "p.exr"], "--preview must end in"),
    (["--mask", "{out}"], "--mask must end in"),
    (["--preview", "o.png", "--mask", "o.png"], "same file"),
    (["--plot", "c.png", "--method", "stabilized"], "no response curves"),
    (["--variance", "v.txt"], "--variance must end in"),
    (["--times-inverse"], "--times-inverse applies to a --times-file"),
    (["--reference", "4"], "--reference 4 is out of range: 3 images given (1..3)"),
    (["--reference", "0"], "out of range"),
    (["--reference", "middle"], "--reference takes N (from 1) or 'auto'"),
    (["--align", "rotation"], "--align takes none, translation, homography"),
    (["--ghost-threshold", "3"], "add --deghost"),
    (["--ghost-mask", "g.png"], "--ghost-mask shows where --deghost or --align left frames out"),
    (["--deghost", "--ghost-mask", "g.exr"], "--ghost-mask must end in"),
    (["--align", "homography"], "no features"),
    (["--profile", "nope.json"], "no such camera profile"),
    (["--save-profile", "p.exr"], "--save-profile must end in"),
    (["--absolute", "meter"], "--absolute takes 'exif'"),
    (["--absolute", "exif", "--spot", "1,1,2,2=100"], "not both"),
    (["--absolute", "exif"], "needs ExposureTime, FNumber and ISO in every frame's EXIF; in0.png"),
])
def test_outputs_checked_before_any_work(tmp_path, capsys, monkeypatch, extra, needle):
    monkeypatch.chdir(tmp_path)
    ins = _bracket(tmp_path)
    before, listing = _digest(ins), _listing(tmp_path)
    args = ["merge", *ins, "-o", "o.exr", *TIMES,
            *[a.format(in0=ins[0], out="o.exr") for a in extra]]
    code, _, err = run_cli(args, capsys)
    _assert_error(code, err, needle)
    assert _listing(tmp_path) == listing and _digest(ins) == before


@pytest.mark.parametrize("text,needle", [
    ("not json", "not a camera profile (not JSON)"),
    ('{"format": "derender-camera-profile", "version": 9}', "version 9; this derender reads version 1"),
    ('{"format": "derender-camera-profile", "version": 1, "view": "-vq 3"}', "not a readable camera profile"),
])
def test_malformed_profile(tmp_path, capsys, monkeypatch, text, needle):
    """A malformed camera profile (issue 28): one error line, exit 2, no output."""
    monkeypatch.chdir(tmp_path)
    ins = _bracket(tmp_path)
    Path("bad.json").write_text(text)
    listing = _listing(tmp_path)
    code, _, err = run_cli(["merge", *ins, "-o", "o.exr", *TIMES, "--profile", "bad.json",
                            "--save-profile", "p.json"], capsys)
    _assert_error(code, err, needle)
    assert _listing(tmp_path) == listing


def test_deghost_outputs_and_summary(tmp_path, capsys, monkeypatch):
    """--reference/--align/--deghost/--ghost-mask end to end: the ghost mask is written (8-bit, the
    size of the map), the summary names the reference frame as given, and nothing else appears."""
    from derender.io.images import read_codes

    monkeypatch.chdir(tmp_path)
    ins = _bracket(tmp_path)
    code, out, err = run_cli(["merge", *ins, "-o", "o.exr", *TIMES, "--reference", "2", "--align", "translation",
                              "--deghost", "--ghost-mask", "g.png"], capsys)
    assert code == 0, err
    assert "reference frame 2 (in1.png)" in out and "ghost removal left out" in out
    g = read_codes(tmp_path / "g.png")
    assert g.shape == (48, 64, 3) and g.max() <= 255
    assert not [n for n in _listing(tmp_path) if n.startswith(TEMP_PREFIX)]


def test_every_output_or_none(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ins = _bracket(tmp_path)
    code, _, err = run_cli(["merge", *ins, "-o", "o.exr", *TIMES, "--preview", "p.jpg", "--mask", "m.png",
                            "--plot", "c.png"], capsys)
    assert code == 0, err
    assert {"o.exr", "p.jpg", "m.png", "c.png"} <= _listing(tmp_path)
    assert Path("p.jpg").read_bytes()[:2] == b"\xff\xd8"          # a JPEG preview is a JPEG
    assert not [n for n in _listing(tmp_path) if n.startswith(TEMP_PREFIX)]


def test_disk_full_while_writing_names_the_output(tmp_path, capsys, monkeypatch):
    """A writer failing with ENOSPC (a fake writer: the last output's encoder) -> exit 2, one line
    naming the user's file, and none of the outputs (the EXR was already written) left."""
    import derender.io.preview as preview

    monkeypatch.chdir(tmp_path)
    ins = _bracket(tmp_path)
    listing = _listing(tmp_path)

    def full(path, *a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(preview, "write_preview", full)
    code, _, err = run_cli(["merge", *ins, "-o", "o.exr", *TIMES, "--preview", "p.png"], capsys)
    _assert_error(code, err, "no space left on device")
    assert "p.png" in err and TEMP_PREFIX not in err
    assert _listing(tmp_path) == listing


def test_out_of_memory_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    """A step the memory checks did not foresee runs out of memory (a fake: the preview's tone
    mapping raises NumPy's MemoryError after the EXR was written) -> exit 2, one line, no output."""
    import derender.io.preview as preview

    monkeypatch.chdir(tmp_path)
    ins = _bracket(tmp_path)
    listing = _listing(tmp_path)

    def oom(*a, **k):
        raise MemoryError("Unable to allocate 2.41 GiB for an array with shape (9, 4000, 6000, 3)")

    monkeypatch.setattr(preview, "reinhard_photographic", oom)
    code, _, err = run_cli(["merge", *ins, "-o", "o.exr", *TIMES, "--preview", "p.png"], capsys)
    _assert_error(code, err, "out of memory")
    assert "2.41 GiB" in err
    assert _listing(tmp_path) == listing


def test_address_space_limit_counts_as_available_memory():
    """``ulimit -v`` lowers what derender believes it can allocate (checked in a child)."""
    code = ("import resource; from derender.core.memory import available_memory; "
            "resource.setrlimit(resource.RLIMIT_AS, (3 << 30, resource.RLIM_INFINITY)); "
            "a = available_memory(); print(a); assert a is not None and a < 3 << 30")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def test_disk_full_on_a_real_small_filesystem(tmp_path):
    """The same on a 64 kB tmpfs (needs mount rights: root on Linux; skipped elsewhere)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        ins = _bracket(tmp_path, size=(200, 300))
        r = subprocess.run([sys.executable, "-m", "derender.cli", "merge", *map(str, ins), "-o", str(mnt / "o.exr"),
                            *TIMES], capture_output=True, text=True, timeout=120)
        _assert_error(r.returncode, r.stderr, "no space left")
        assert "o.exr" in r.stderr and TEMP_PREFIX not in r.stderr
        assert list(mnt.iterdir()) == []
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interruption_leaves_nothing(tmp_path, sig):
    """SIGINT/SIGTERM during a merge: exit 130, 'interrupted', no output, no temporary."""
    ins = _bracket(tmp_path, size=(1500, 2000), n=5)
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "derender.cli", "merge", *map(str, ins), "-o", str(out / "o.exr"),
                             "--preview", str(out / "p.png"), "--times", "1,2,4,8,16", "--method", "stabilized"],
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not any(out.iterdir()) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)   # the outputs' temporaries exist from the checks until the final rename
    assert proc.poll() is None, "the merge finished before it could be interrupted"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "interrupted" and "Traceback" not in err
    assert list(out.iterdir()) == []


def test_os_errors_are_user_errors(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ins = _bracket(tmp_path)
    code, _, err = run_cli(["merge", *ins, "-o", "a" * 300 + ".exr", *TIMES], capsys)
    _assert_error(code, err, "file name too long")
    Path("loop.exr").symlink_to("loop.exr")
    code, _, err = run_cli(["merge", *ins, "-o", "loop.exr", *TIMES], capsys)
    _assert_error(code, err, "symbolic link loop")
    # a folder stands for its images (issue 24): given beside some of them, they are given twice
    code, _, err = run_cli(["merge", tmp_path, *ins[1:], "-o", "o.exr", "--times", "1,2,4"], capsys)
    _assert_error(code, err, "given twice")
    code, _, err = run_cli(["merge", *ins, "-o", "o.exr", "--times-file", tmp_path], capsys)
    _assert_error(code, err, "is a folder")
    link = tmp_path / "in0-link.png"
    link.symlink_to(ins[0])
    code, _, err = run_cli(["merge", *ins, "-o", link, *TIMES], capsys)
    _assert_error(code, err, "must end in .exr")
    link2 = tmp_path / "in0-link.exr"
    link2.symlink_to(ins[0])
    code, _, err = run_cli(["merge", *ins, "-o", link2, *TIMES], capsys)
    _assert_error(code, err, "refusing to overwrite input")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere: permissions cannot be tested as root")
def test_permission_denied_names_the_folder(tmp_path, capsys):
    ins = _bracket(tmp_path)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    code, _, err = run_cli(["merge", *ins, "-o", ro / "o.exr", *TIMES], capsys)
    _assert_error(code, err, "permission denied")
    assert TEMP_PREFIX not in err


def test_exif_time_zero_is_named(tmp_path, capsys):
    from PIL import Image

    ex = Image.Exif()
    ex.get_ifd(0x8769)[0x829A] = 0.0
    Image.fromarray(np.full((16, 16, 3), 90, np.uint8)).save(tmp_path / "z.jpg", exif=ex)
    Image.fromarray(np.full((16, 16, 3), 180, np.uint8)).save(tmp_path / "y.jpg")
    code, _, err = run_cli(["merge", tmp_path / "z.jpg", tmp_path / "y.jpg", "-o", tmp_path / "o.exr"], capsys)
    _assert_error(code, err, "EXIF ExposureTime is 0")


def test_truncated_and_forged_inputs(tmp_path, capsys):
    import struct

    ins = _bracket(tmp_path)
    data = ins[1].read_bytes()
    ins[1].write_bytes(data[: len(data) // 2])
    for method in ("debevec", "robertson", "stabilized", "stabilized-joint"):
        code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "o.exr", *TIMES, "--method", method], capsys)
        _assert_error(code, err, "truncated")
    assert not (tmp_path / "o.exr").exists()
    ins[1].write_bytes(data)
    b = bytearray(data)
    b[16:24] = struct.pack(">II", 100000, 100000)
    ins[1].write_bytes(bytes(b))
    code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "o.exr", *TIMES], capsys)
    _assert_error(code, err, "MP limit")


def test_interrupts_deferred_holds_a_signal_until_the_block_ends():
    """A signal inside ``interrupts_deferred`` lets the block finish, then raises Interrupted;
    outside it, the handler raises at once (the race behind orphaned temporaries)."""
    from derender.core.errors import Interrupted, interrupt_handler, interrupts_deferred

    previous = signal.signal(signal.SIGUSR1, interrupt_handler)
    try:
        steps = []
        with pytest.raises(Interrupted, match="SIGUSR1"):
            with interrupts_deferred():
                os.kill(os.getpid(), signal.SIGUSR1)
                for _ in range(1000):   # the handler runs between bytecodes: give it many chances
                    steps.append(1)
                steps.append("done")
        assert steps[-1] == "done"
        with pytest.raises(Interrupted):
            os.kill(os.getpid(), signal.SIGUSR1)
            for _ in range(1000):
                time.sleep(0)
        with interrupts_deferred():   # nothing pending: the block ends normally
            pass
    finally:
        signal.signal(signal.SIGUSR1, previous)



def _help(capsys, monkeypatch, *args) -> str:
    import sys

    from derender.cli import main

    monkeypatch.setattr(sys, "argv", ["derender", *args, "--help"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 0
    return capsys.readouterr().out


def test_flags_are_shown_as_flags_in_help(capsys, monkeypatch):
    """Boolean options take no value and ``--help`` shows none (typer 0.29 printed ``<bool>``)."""
    for args in (("merge",), ("derender",), ()):
        out = _help(capsys, monkeypatch, *args)
        assert "<bool>" not in out and "--help" in out
    assert "--times-inverse" in _help(capsys, monkeypatch, "merge")


def test_console_entry_leaves_failed_runs_without_finalisation(monkeypatch, capsys):
    """A failed or interrupted ``derender`` process exits through ``os._exit`` (no interpreter
    finalisation under background threads still in native code: it crashed with SIGSEGV after
    ``interrupted``); a successful run exits normally."""
    import derender.cli as cli

    codes = []

    def fake_exit(code):
        codes.append(code)
        raise RuntimeError("os._exit")

    monkeypatch.setattr(cli.os, "_exit", fake_exit)
    monkeypatch.setattr(sys, "argv", ["derender", "merge", "missing-a.jpg", "missing-b.jpg", "-o", "x.exr"])
    with pytest.raises(RuntimeError, match="os._exit"):
        cli.console_main()
    assert codes == [2] and capsys.readouterr().err.startswith("error: ")
    monkeypatch.setattr(sys, "argv", ["derender", "--help"])
    with pytest.raises(SystemExit) as exc:
        cli.console_main()
    assert exc.value.code in (None, 0) and codes == [2]


def test_model_with_a_method_that_uses_none_is_refused(tmp_path, capsys):
    """``-m`` with a method that takes no de-rendering model is refused before any work (it
    was loaded, warned about and then rejected with the method's internal option list)."""
    ins = _bracket(tmp_path)
    code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "o.exr", "-m", tmp_path / "none.npz", *TIMES,
                            "--method", "robertson"], capsys)
    _assert_error(code, err, "uses no de-rendering model")
    assert "probabilistic" in err and not (tmp_path / "o.exr").exists()


def test_usage_lines_and_methods_read_as_text(capsys):
    code, out, _ = run_cli(["merge", "--help"], capsys)
    assert code == 0 and "Usage: derender merge [OPTIONS] IMAGES..." in out and "{" not in out.split("\n\n")[0]
    code, out, _ = run_cli(["methods"], capsys)
    assert code == 0 and "``" not in out and ":func:" not in out
    blocks = [b for b in out.split("\n") if b and not b.startswith(" ")]
    assert set(blocks) >= {"debevec", "robertson", "stabilized", "stabilized-joint", "probabilistic",
                           "stabilized-probabilistic"}
    assert out.count("Output: ") == len(blocks)
    summaries = [b.strip() for b in out.split("\n") if b.startswith("    ") and not b.startswith("     ")]
    assert all(s for s in summaries)


def test_method_options_reach_the_method(tmp_path, capsys):
    """``--option NAME=VALUE`` is typed from the method's signature and reaches it: the CLI's
    output equals the library call with the same keyword, and differs from the default."""
    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.hdr.files import merge_files
    from derender.io.exr import read_exr

    write_bracket(simulate_bracket(size=(96, 64), exposures=5, pipeline="auto", seed=4), tmp_path / "b")
    ins = bracket_paths(tmp_path / "b", "jpeg")
    code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "o4.exr", "--method", "stabilized",
                            "--option", "block=4", "-O", "use_times=false"], capsys)
    assert code == 0, err
    lib = merge_files(ins, options={"block": 4, "use_times": False}, method="stabilized")
    np.testing.assert_array_equal(read_exr(tmp_path / "o4.exr"), lib.radiance)
    default = merge_files(ins, method="stabilized")
    assert not np.array_equal(default.radiance, lib.radiance)


def test_misspelt_method_option_lists_the_valid_ones(tmp_path, capsys):
    ins = _bracket(tmp_path)
    code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "o.exr", *TIMES, "--method", "stabilized",
                            "--option", "blok=4"], capsys)
    _assert_error(code, err, "has no option 'blok'")
    assert "block (int, default 2)" in err and "exposure_rounds" in err
    for bad, needle in (("block=x", "takes int"), ("block", "NAME=VALUE"), ("use_times=maybe", "takes bool")):
        code, _, err = run_cli(["merge", *ins, "-o", tmp_path / "o.exr", *TIMES, "--method", "stabilized",
                                "--option", bad], capsys)
        _assert_error(code, err, needle)
    assert not (tmp_path / "o.exr").exists()
