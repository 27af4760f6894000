"""What a new user meets first (issue 37, item 9), and one summary record (issue 36, item 7).

Every bad input names its file and its real cause, every option is checked before any work,
long first runs say what they are doing; the report and the CLI show the same reference
frame, shifts and counts.
"""

from __future__ import annotations

import base64
import gzip
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import require_shared
from helpers import run_cli, write_png_codes

REPO = Path(__file__).resolve().parents[2]


def _bracket(folder: Path, n: int = 3, size=(48, 64)) -> list[Path]:
    """Smooth 8-bit renderings of one scene at doubling exposures (PNG, times 1, 2, 4 ...)."""
    folder.mkdir(parents=True, exist_ok=True)
    h, w = size
    y, x = np.mgrid[0:h, 0:w]
    radiance = 0.02 + np.stack([x / w, y / h, (x + y) / (w + h)], -1)
    out = []
    for j in range(n):
        codes = np.clip(255.0 * (radiance * 2.0**j) ** (1 / 2.2), 0, 255).astype(np.uint8)
        out.append(write_png_codes(folder / f"in{j}.png", codes))
    return out


def _user_error(code: int, err: str) -> str:
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    return lines[0]


def _heic_without_exif(path: Path) -> Path:
    """A real HEIC (libheif through pillow-heif) that carries no EXIF."""
    from derender.io.headers import pillow_image

    Image = pillow_image()
    Image.new("RGB", (64, 48), (120, 90, 60)).save(path, format="HEIF")
    return path


@pytest.mark.parametrize("kind", ["text", "fake-jpg", "corrupt-heic", "truncated-heic"])
def test_an_unreadable_image_is_named_before_the_missing_exif_times(tmp_path, capsys, kind):
    """A text file, a text file named .jpg and a damaged HEIC used to say "no EXIF ExposureTime
    ... give --times"; the real cause showed only once times were given. Now the first error
    is the real one, naming the file."""
    good = _bracket(tmp_path / "b", n=1)[0]
    bad = {"text": tmp_path / "notes.txt", "fake-jpg": tmp_path / "photo.jpg",
           "corrupt-heic": tmp_path / "photo.heic", "truncated-heic": tmp_path / "cut.heic"}[kind]
    if kind in ("text", "fake-jpg"):
        bad.write_text("this is not an image\n")
    elif kind == "corrupt-heic":
        bad.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    else:
        data = _heic_without_exif(tmp_path / "whole.heic").read_bytes()
        bad.write_bytes(data[: len(data) // 2])
    line = _user_error(*run_cli(["merge", bad, good, "-o", tmp_path / "m.exr"], capsys)[::2])
    assert "not a readable image" in line and str(bad) in line, line
    assert "EXIF" not in line
    assert not (tmp_path / "m.exr").exists()


def test_a_readable_image_without_times_still_asks_for_them(tmp_path, capsys):
    """The readability check does not hide the times' message for a good file."""
    heic = _heic_without_exif(tmp_path / "a.heic")
    line = _user_error(*run_cli(["merge", heic, _bracket(tmp_path / "b", n=1)[0], "-o", tmp_path / "m.exr"],
                                capsys)[::2])
    assert "no EXIF ExposureTime" in line and "a.heic" in line and "--times" in line


def test_a_missing_folder_is_named(tmp_path, capsys):
    """It said "an exposure stack needs at least two images"."""
    missing = tmp_path / "no-such-bracket"
    line = _user_error(*run_cli(["merge", missing, "-o", tmp_path / "m.exr"], capsys)[::2])
    assert "no such file or folder" in line and str(missing) in line and "at least two" not in line


@pytest.mark.shared_data
def test_duplicate_exif_times_name_the_files_and_the_times_file(tmp_path, capsys):
    """The sculpture-garden bracket's EXIF gives all five frames 1/20 s; its times.txt has the
    real times. The error names the files and suggests --times-file with that file."""
    folder = require_shared("motion-sculpture-garden")
    line = _user_error(*run_cli(["merge", folder, "-o", tmp_path / "m.exr"], capsys)[::2])
    for name in ("1.tif", "2.tif", "3.tif", "4.tif", "5.tif"):
        assert name in line
    assert "1/20 s" in line and f"--times-file {folder / 'times.txt'}" in line, line
    code, out, err = run_cli(["merge", folder, "--times-file", folder / "times.txt", "-o", tmp_path / "m.exr"],
                             capsys)
    assert code == 0, err


def test_duplicate_given_times_name_the_files(tmp_path, capsys):
    frames = _bracket(tmp_path / "b")
    line = _user_error(*run_cli(["merge", *frames, "--times", "1,2,2", "-o", tmp_path / "m.exr"], capsys)[::2])
    assert "in1.png, in2.png" in line and "--times" in line


@pytest.mark.parametrize("args,needles", [
    (["--method", "stabilised"], ["did you mean 'stabilized'?"]),
    (["--method", "debevek"], ["did you mean 'debevec'?"]),
    (["--method", "stabilized", "--option", "exposure_round=1"], ["did you mean 'exposure_rounds'?"]),
    (["--method", "stabilized", "--option", "response=foo"], ["response", "'auto', 'power', 'curve'", "'foo'"]),
    (["--method", "stabilized", "--option", "weight=gausian"], ["did you mean 'gaussian'?"]),
    (["--method", "stabilized", "--option", "path=weird"], ["path"]),
    (["--method", "stabilized", "--option", "block=-3"], ["block", ">= 1"]),
    (["--method", "stabilized", "--option", "exposure_rounds=-1"], ["exposure_rounds", ">= 0"]),
    (["--method", "stabilized", "--option", "gammas=1,2,3"], ["gammas", "3 value(s) for 2 images"]),
    (["--option", "lam=-1"], ["lam", ">= 0"]),
    (["--option", "channel_weights=x"], ["channel_weights"]),
    (["--method", "robertson", "--option", "n_iter=0"], ["n_iter"]),
    (["--seed", "-3"], ["--seed"]),                             # was a traceback from NumPy's seeding
    (["--deghost", "--ghost-threshold", "-1"], ["--ghost-threshold", "positive"]),
    (["--max-megapixels", "-1"], ["--max-megapixels", "positive"]),
])
def test_bad_method_and_option_values_are_refused_before_any_work(tmp_path, capsys, args, needles):
    """A bad --option value was refused only after 3.3 s of work (weight=bogus on the iPhone
    bracket), some not at all (block=-3 merged). Here the frames are unreadable: the option's
    error comes first, so no frame was read."""
    frames = [tmp_path / "a.jpg", tmp_path / "b.jpg"]
    for f in frames:
        f.write_text("not an image; the options are checked before any file is read\n")
    line = _user_error(*run_cli(["merge", *frames, "-o", tmp_path / "m.exr", *args], capsys)[::2])
    for needle in needles:
        assert needle in line, line
    assert "not a readable image" not in line


def _kernel_env(cache: Path) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(REPO / "src"))
    return env


@pytest.mark.slow
def test_a_cold_kernel_cache_is_announced_once(tmp_path):
    """The first merge with an empty numba cache says it is compiling (one stderr line); the
    second, with the kernels cached, does not (--deghost: its test is a compiled kernel)."""
    frames = _bracket(tmp_path / "b", size=(96, 128))
    env = _kernel_env(tmp_path / "numba")
    errs = []
    for k in range(2):
        r = subprocess.run([sys.executable, "-m", "derender.cli", "merge", *map(str, frames), "--times", "1,2,4",
                            "--deghost", "-o", str(tmp_path / f"m{k}.exr")], env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        errs.append(r.stderr)
    assert errs[0].count("compiling kernels (first run only") == 1
    assert "compiling" not in errs[1]


# --------------------------------------------------------------------------- one summary record
def _page_data(path: Path) -> dict:
    return json.loads(re.search(r"const D = (\{.*?\});\n", path.read_text(), flags=re.S).group(1))


@pytest.mark.shared_data
def test_report_and_cli_agree_on_reference_shifts_and_counts(tmp_path, capsys):
    """Issue 36, item 7, on a real handheld bracket (pingpong: 3 frames of 1920x1080, given out
    of time order here, so that "as given" and "by time" differ). The CLI's lines, the report
    written by the merge and the report ``derender report`` makes from the map's header all
    show the reference as given (from 1, with its name), the same shifts and the same counts;
    the count taken from the shortest exposure is the number of 128 codes in the --mask PNG."""
    import cv2

    folder = require_shared("motion-pingpong")
    frames = [folder / "Img3.JPG", folder / "Img1.JPG", folder / "Img2.JPG"]
    code, out, err = run_cli(["merge", *frames, "--reference", "2", "--align", "translation", "--deghost",
                              "-o", tmp_path / "m.exr", "--mask", tmp_path / "mask.png",
                              "--report", tmp_path / "r.html"], capsys)
    assert code == 0, err
    m = re.search(r"\((?:[\d.]+) s; (\d+) px clipped even in the shortest exposure; (\d+) px taken from the shortest "
                  r"exposure, (\d+) px from the longest", out)
    clipped, shortest, longest = (int(v) for v in m.groups())
    m = re.search(r"reference frame (\d+) \(([^)]+)\); aligned by translation \(largest shift (\d+) px\)", out)
    ref, ref_name, largest = int(m.group(1)), m.group(2), int(m.group(3))
    assert (ref, ref_name) == (2, "Img1.JPG")
    assert largest > 0
    mask = cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_GRAYSCALE)
    assert shortest == int(np.count_nonzero(mask == 128)) and longest == int(np.count_nonzero(mask == 255))

    code, out2, err = run_cli(["report", tmp_path / "m.exr", "-o", tmp_path / "again.html"], capsys)
    assert code == 0, err
    for page in ("r.html", "again.html"):
        rows = _page_data(tmp_path / page)["summary"]
        assert rows["reference frame"] == "image 2 (Img1.JPG)", page
        assert rows["clipped even in the shortest exposure"] == f"{clipped} px"
        assert rows["taken from the shortest exposure (mask)"] == f"{shortest} px"
        assert rows["taken from the longest exposure (mask)"] == f"{longest} px"
        shifts = {name: (int(dy), int(dx)) for name, dy, dx in
                  re.findall(r"image \d+ \(([^)]+)\) (-?\d+),(-?\d+)", rows["alignment shifts (dy,dx px)"])}
        assert set(shifts) == {"Img1.JPG", "Img2.JPG", "Img3.JPG"} and shifts["Img1.JPG"] == (0, 0)
        assert max(max(abs(a), abs(b)) for a, b in shifts.values()) == largest
        assert rows["frames (by exposure time)"].startswith("image 2 (Img1.JPG): 1/1000 s")
    # the ghost overlay of the report is where the merge left frames out
    overlays = np.frombuffer(gzip.decompress(base64.b64decode(_page_data(tmp_path / "r.html")["overlays"])),
                             np.uint8)
    assert (overlays & 2).any()


@pytest.mark.parametrize("suffix,extra", [(".exr", []), (".hdr", []), (".exr", ["--spot", "8,8,16,16=100"])])
def test_the_summary_record_round_trips_through_the_output(tmp_path, capsys, suffix, extra):
    """The record is in the output's header whichever way it was written (an EXR written while
    merging, filled afterwards; a .hdr line; an EXR written after a --spot calibration, with its
    factor), and ``derender report`` shows what ``derender merge`` printed."""
    from derender.cli.app import map_summary, read_radiance_map

    frames = _bracket(tmp_path / "b")
    given = [frames[2], frames[0], frames[1]]                  # out of time order
    out_map = tmp_path / f"m{suffix}"
    code, out, err = run_cli(["merge", *given, "--times", "4,1,2", "--reference", "3", "-o", out_map, *extra],
                             capsys)
    assert code == 0, err
    assert "reference frame 3 (in1.png)" in out
    rec = map_summary(read_radiance_map(out_map)[1])
    assert rec is not None and rec.reference == 3 and rec.frame(3).name == "in1.png"
    assert [f.name for f in rec.frames] == ["in2.png", "in0.png", "in1.png"]
    assert [f.time_s for f in rec.frames] == [4.0, 1.0, 2.0]
    assert rec.counts_text() in out
    if extra:
        assert rec.photometric_factor is not None and "spot" in rec.photometric_source
    code, _, err = run_cli(["report", out_map, "-o", tmp_path / "r.html"], capsys)
    assert code == 0, err
    rows = _page_data(tmp_path / "r.html")["summary"]
    assert rows["reference frame"] == "image 3 (in1.png)"
    assert ("photometric factor" in rows) == bool(extra)
