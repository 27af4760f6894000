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
    code, out, err = run_cli(["falsecolor", tmp_path / "m.exr", "-o", tmp_path / "fc.png"], capsys)
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
