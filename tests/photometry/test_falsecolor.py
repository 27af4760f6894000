"""Falsecolor luminance maps: the scale and the written figure."""

from __future__ import annotations

import numpy as np
from helpers import run_cli


def test_scale_top_rounds_up_the_999th_percentile():
    from derender.photometry.falsecolor import scale_top

    lum = np.linspace(1.0, 3100.0, 100_000)
    assert scale_top(lum) == 5000.0                 # p99.9 = 3097 -> 5 x 10^3
    assert scale_top(np.full(10, 100.0)) == 100.0
    assert scale_top(np.full(10, 101.0)) == 200.0


def test_falsecolor_cli_writes_a_figure_with_the_scale(tmp_path, capsys):
    import cv2

    from derender.io.exr import write_exr

    y, x = np.mgrid[0:60, 0:90]
    lum = 10 ** (x / 90 * 4)                        # 1 .. 10^4 cd/m2 across the image
    write_exr(tmp_path / "m.exr", (lum[..., None] * np.ones(3) / 179.0).astype(np.float32))
    code, out, err = run_cli(["falsecolor", tmp_path / "m.exr", "-o", tmp_path / "fc.png", "--absolute"], capsys)
    assert code == 0, err
    assert "log scale" in out and "cd/m²" in out
    img = cv2.imread(str(tmp_path / "fc.png"))
    assert img is not None and img.shape[0] > 200 and img.std() > 10
    code, out, err = run_cli(["falsecolor", tmp_path / "m.exr", "-o", tmp_path / "fc2.png", "--log", "0",
                              "--max", "500", "--relative"], capsys)
    assert code == 0 and "linear scale 0..500 relative" in out
    for args, needle in ((["--max", "-1"], "positive"), (["--log", "-2"], "decades")):
        code, out, err = run_cli(["falsecolor", tmp_path / "m.exr", "-o", tmp_path / "x.png", *args], capsys)
        assert code == 2 and err.startswith("error:") and needle in err
    assert not (tmp_path / "x.png").exists()


def _bracket(tmp_path):
    from helpers import write_png_codes

    y, x = np.mgrid[0:48, 0:64]
    radiance = 0.02 + np.stack([x / 64, y / 48, (x + y) / 112], -1)
    for j in range(3):
        codes = np.clip(255.0 * (radiance * 2.0**j) ** (1 / 2.2), 0, 255).astype(np.uint8)
        write_png_codes(tmp_path / f"in{j}.png", codes)
    return [tmp_path / f"in{j}.png" for j in range(3)]


def test_falsecolor_labels_cd_only_for_a_map_that_says_it_is_absolute(tmp_path, capsys):
    """Issue 37: a relative map (a plain merge) was labelled cd/m² unless --relative was given.
    Now the legend is cd/m² only when the map's header says it is absolute (merge --spot writes
    whiteLuminance into an EXR, DERENDER_PHOTOMETRY= into a .hdr) or --absolute is given."""
    frames = _bracket(tmp_path)
    times = ["--times", "1,2,4"]
    for name, extra in (("rel.exr", []), ("rel.hdr", []), ("abs.exr", ["--spot", "8,8,16,16=100"]),
                        ("abs.hdr", ["--spot", "8,8,16,16=100"])):
        code, out, err = run_cli(["merge", *frames, *times, "-o", tmp_path / name, *extra], capsys)
        assert code == 0, err
    for name, units in (("rel.exr", "relative"), ("rel.hdr", "relative"), ("abs.exr", "cd/m²"),
                        ("abs.hdr", "cd/m²")):
        code, out, err = run_cli(["falsecolor", tmp_path / name, "-o", tmp_path / f"{name}.png"], capsys)
        assert code == 0, err
        assert units in out and ("cd/m²" not in out if units == "relative" else "relative" not in out), (name, out)
    # the explicit flags win over the header; both at once are refused
    code, out, err = run_cli(["falsecolor", tmp_path / "abs.exr", "-o", tmp_path / "r.png", "--relative"], capsys)
    assert code == 0 and "relative" in out
    code, out, err = run_cli(["falsecolor", tmp_path / "rel.exr", "-o", tmp_path / "a.png", "--absolute"], capsys)
    assert code == 0 and "cd/m²" in out
    code, out, err = run_cli(["falsecolor", tmp_path / "rel.exr", "-o", tmp_path / "b.png", "--absolute",
                              "--relative"], capsys)
    assert code == 2 and err.startswith("error:") and not (tmp_path / "b.png").exists()
