"""The HTML report: its packing (known answers) and the page in a real browser (headless Chromium).

The browser test drives Debian's ``chromium`` through its ``chromedriver`` with selenium (no
browser is downloaded); it skips with the reason when they are absent, and ``.ci/run``
installs them and makes it mandatory (``DERENDER_REQUIRE_BROWSER=1``).
"""

from __future__ import annotations

import base64
import gzip
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli

from derender.engine.motion.run import MotionOptions


def test_reduce_map_is_an_area_average():
    from derender.applications.report import reduce_map

    a = np.arange(6 * 8 * 3, dtype=np.float32).reshape(6, 8, 3)
    small, f = reduce_map(a, max_pixels=12)
    assert f == 2 and small.shape == (3, 4, 3)
    np.testing.assert_allclose(small[1, 2], a[2:4, 4:6].reshape(-1, 3).mean(0))
    same, f1 = reduce_map(a, max_pixels=48)
    assert f1 == 1 and np.array_equal(same, a)


def test_pack_half_round_trip():
    from derender.applications.report import pack_half

    v = np.array([0.0, 1.0, 3.14159, 1e-4, 6.5e4, 1234.5], np.float32)
    raw = gzip.decompress(base64.b64decode(pack_half(v)))
    n = len(raw) // 2
    back = (np.frombuffer(raw[:n], np.uint8).astype(np.uint16) | (np.frombuffer(raw[n:], np.uint8).astype(np.uint16) << 8))
    np.testing.assert_array_equal(back.view(np.float16), v.astype(np.float16))
    rng = np.random.default_rng(0)
    w = np.exp(rng.uniform(-9, 11, 10_000)).astype(np.float32)
    raw = gzip.decompress(base64.b64decode(pack_half(w, mantissa_bits=8)))
    n = len(raw) // 2
    u = np.frombuffer(raw[:n], np.uint8).astype(np.uint16) | (np.frombuffer(raw[n:], np.uint8).astype(np.uint16) << 8)
    got = u.view(np.float16).astype(np.float64)
    normal = (w > 6.2e-5) & (w < 6.5e4)
    assert np.max(np.abs(got[normal] / w[normal] - 1)) <= 2 ** -9 + 2 ** -11   # 8 bits kept, half-float input


def _browser():
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if not chromium or not driver:
        msg = "headless browser test needs Debian's chromium and chromium-driver (apt-get install chromium chromium-driver)"
        if os.environ.get("DERENDER_REQUIRE_BROWSER") == "1":
            pytest.fail(msg + "; DERENDER_REQUIRE_BROWSER=1 makes it mandatory")
        pytest.skip(msg)
    from selenium import webdriver

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,1000", "--disable-dev-shm-usage"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(options=opts, service=webdriver.ChromeService(executable_path=driver))


_HASH = ("const c = document.getElementById('img'); const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
         "let h = 0; for (let i = 0; i < d.length; i++) h = (h * 31 + d[i]) | 0; return h;")


def test_report_in_a_real_browser(tmp_path, capsys):
    from helpers import write_png_codes
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.io.exr import read_exr, write_exr

    write_bracket(simulate_bracket(size=(320, 224), exposures=5, seed=9), tmp_path / "b")
    code, _, err = run_cli(["merge", *bracket_paths(tmp_path / "b", "jpeg"), "-o", tmp_path / "m.exr"], capsys)
    assert code == 0, err
    rad = read_exr(tmp_path / "m.exr")
    write_exr(tmp_path / "v.exr", ((0.05 * rad) ** 2).astype(np.float32))      # a known 5 % sd
    mask = np.zeros((224, 320, 3), np.uint8)
    mask[:20, :30] = 128                                                          # "over-exposed everywhere"
    mask[-20:, -30:] = 255                                                        # "under-exposed everywhere"
    ghosts = np.zeros_like(mask)
    ghosts[80:140, 120:200] = 255
    write_png_codes(tmp_path / "mask.png", mask)
    write_png_codes(tmp_path / "ghosts.png", ghosts)
    code, out, err = run_cli(["report", tmp_path / "m.exr", "--variance", tmp_path / "v.exr", "--mask",
                              tmp_path / "mask.png", "--ghost-mask", tmp_path / "ghosts.png",
                              "-o", tmp_path / "r.html", "--max-pixels", "20000"], capsys)
    assert code == 0, err and "reduced 2x" in out
    html_text = (tmp_path / "r.html").read_text()
    assert "http://" not in html_text and "https://" not in html_text        # offline: nothing fetched
    driver = _browser()
    try:
        driver.get((tmp_path / "r.html").as_uri())
        WebDriverWait(driver, 20).until(lambda d: d.execute_script("return document.body.dataset.ready === '1'"))
        before = driver.execute_script(_HASH)
        slider = driver.find_element(By.ID, "ev")
        slider.send_keys(Keys.ARROW_RIGHT, Keys.ARROW_RIGHT, Keys.ARROW_RIGHT, Keys.ARROW_RIGHT)   # keyboard: +1 EV
        after = driver.execute_script(_HASH)
        assert after != before
        # hover the centre of page pixel (x, y) = (30, 20): the 2x2 block mean of the EXR there
        canvas = driver.find_element(By.ID, "img")
        size = canvas.size
        w, h = driver.execute_script("return [document.getElementById('img').width, document.getElementById('img').height]")
        assert (w, h) == (160, 112)
        import re

        w_lum = np.array([0.2126, 0.7152, 0.0722])
        rng = np.random.default_rng(0)
        for x, y in zip(rng.integers(1, w - 1, 20), rng.integers(1, h - 1, 20)):      # 20 random pixels
            ActionChains(driver).move_to_element_with_offset(
                canvas, int((x + 0.5) * size["width"] / w - size["width"] / 2),
                int((y + 0.5) * size["height"] / h - size["height"] / 2)).perform()
            text = driver.find_element(By.ID, "readout").text
            px, py = (int(v) // 2 for v in re.search(r"pixel x (\d+)\.\.\d+, y (\d+)", text).groups())
            assert abs(px - x) <= 1 and abs(py - y) <= 1, text      # the pixel under the pointer (+-1 rounding)
            shown = float(driver.find_element(By.ID, "lum").text)
            block = rad[2 * py:2 * py + 2, 2 * px:2 * px + 2].reshape(-1, 3)
            assert shown == pytest.approx(179.0 * float(block.mean(0) @ w_lum), rel=0.01)
            # the variance is (0.05 r)^2 per pixel; the block mean of 4 independent pixels: / 4
            var_blk = ((0.05 * block) ** 2).mean(0) / 4
            sd_shown = float(driver.find_element(By.ID, "lumsd").text)
            assert sd_shown == pytest.approx(179.0 * np.sqrt(var_blk @ w_lum ** 2), rel=0.01)
        # keyboard readout: the focused image moves its cursor with the arrow keys
        canvas.send_keys(Keys.ARROW_RIGHT)
        assert f"x {2 * (px + 1)}.." in driver.find_element(By.ID, "readout").text
        driver.find_element(By.CSS_SELECTOR, "input[value='false']").click()
        assert driver.execute_script(_HASH) != after
        drawn = driver.execute_script("const c = document.getElementById('legend');"
                                      "return c.getContext('2d').getImageData(0, 0, c.width, c.height).data"
                                      ".filter((v, i) => i % 4 === 3 && v > 0).length")
        assert drawn > 2000                                         # the colour bar and its labels
        driver.find_element(By.CSS_SELECTOR, "input[value='unc']").click()
        shown_hashes = {driver.execute_script(_HASH)}
        for box in ("ovClip", "ovGhost", "ovDark"):                 # each overlay changes the picture
            driver.find_element(By.ID, box).click()
            shown_hashes.add(driver.execute_script(_HASH))
        assert len(shown_hashes) == 4
        for box in ("ovClip", "ovGhost", "ovDark"):
            driver.find_element(By.ID, box).click()
        driver.find_element(By.CSS_SELECTOR, "input[value='tone']").click()
        png = driver.get_screenshot_as_png()
        import cv2

        shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert shot is not None and shot.std() > 20 and len(np.unique(shot.reshape(-1, 3), axis=0)) > 500
        errors = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
        assert not errors, errors
    finally:
        driver.quit()


def test_merge_writes_its_report(tmp_path, capsys):
    import json
    import re

    from derender.camera import bracket_paths, simulate_bracket, write_bracket

    write_bracket(simulate_bracket(size=(96, 64), exposures=3, seed=10), tmp_path / "b")
    code, _, err = run_cli(["merge", *bracket_paths(tmp_path / "b", "jpeg"), "-o", tmp_path / "m.exr",
                            "--method", "stabilized", "--report", tmp_path / "r.html"], capsys)
    assert code == 0, err
    page = (tmp_path / "r.html").read_text()
    data = json.loads(re.search(r"const D = (\{.*?\});\n", page, flags=re.S).group(1))
    assert data["summary"]["method"] == "stabilized" and "reference frame" in data["summary"]
    assert data["summary"]["frames (by exposure time)"].startswith("image 1 (00.jpg): 1/2000 s")
    assert (data["width"], data["height"], data["factor"]) == (96, 64, 1)
    code, _, err = run_cli(["merge", *bracket_paths(tmp_path / "b", "jpeg"), "-o", tmp_path / "n.exr",
                            "--report", tmp_path / "r.txt"], capsys)
    assert code == 2 and "--report must end in .html" in err and not (tmp_path / "n.exr").exists()


def test_merge_report_shows_the_ghosts(tmp_path, capsys):
    """A moving, handheld bracket merged with --deghost: the report's summary names the
    reference frame (as given) and the ghost removal, and its ghost overlay (bit 2 of the
    overlays) is set exactly where the ghost map is (the report is at full size here)."""
    import base64
    import gzip
    import json
    import re

    from derender.camera import bracket_paths, simulate_bracket, write_bracket
    from derender.camera.motion import MotionSpec
    from derender.hdr.files import merge_files

    b = simulate_bracket(size=(96, 64), exposures=5, seed=3, motion=MotionSpec(objects=2, shake=3))
    write_bracket(b, tmp_path / "b")
    paths = bracket_paths(tmp_path / "b", "jpeg")
    code, _, err = run_cli(["merge", *paths, "-o", tmp_path / "m.exr", "--reference", "3", "--align", "translation",
                            "--deghost", "--report", tmp_path / "r.html"], capsys)
    assert code == 0, err
    page = (tmp_path / "r.html").read_text()
    data = json.loads(re.search(r"const D = (\{.*?\});\n", page, flags=re.S).group(1))
    assert data["summary"]["reference frame"] == f"image 3 ({paths[2].name})"
    assert "ghost removal" in data["summary"]
    overlays = np.frombuffer(gzip.decompress(base64.b64decode(data["overlays"])), np.uint8).reshape(64, 96)
    res = merge_files(paths, motion=MotionOptions(reference=2, align="translation", deghost=True))
    np.testing.assert_array_equal((overlays & 2) != 0, res.ghosts > 0)
    assert (res.ghosts > 0).any()


#: Where the README's and the docs' picture of the report goes (``DERENDER_WRITE_SCREENSHOT=1``).
SCREENSHOT = Path(__file__).resolve().parents[2] / "docs" / "images" / "report.png"


def test_report_of_a_real_bracket(tmp_path, capsys):
    """The sculpture garden (a real tripod bracket, pedestrians walking; its EXIF times are wrong,
    so they come from ``times.txt``) merged with ``--deghost --variance --report``: the page
    opens in Chromium without a JavaScript error, its summary names the five files with their
    given times, the reference and the ghost removal, the pedestrians show in the ghost overlay,
    and the luminance under the pointer is the EXR's block mean. With
    ``DERENDER_WRITE_SCREENSHOT=1`` it writes the README's picture, ``docs/images/report.png``
    (downsized, 256 colours: the picture is made here, never edited by hand)."""
    import base64
    import gzip
    import io
    import json
    import re

    from conftest import require_shared
    from PIL import Image
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    from derender.io.exr import read_exr

    folder = require_shared("motion-sculpture-garden")
    driver = _browser()                                          # skips before the merge when absent
    try:
        files = [folder / f"{k}.tif" for k in range(1, 6)]
        code, _, err = run_cli(["merge", *files, "--times-file", folder / "times.txt", "-o", tmp_path / "m.exr",
                                "--variance", tmp_path / "v.exr", "--deghost", "--report", tmp_path / "r.html"], capsys)
        assert code == 0, err
        page = (tmp_path / "r.html").read_text()
        data = json.loads(re.search(r"const D = (\{.*?\});\n", page, flags=re.S).group(1))
        frames = data["summary"]["frames (by exposure time)"]
        for k, t in zip(range(1, 6), ("1/320", "1/160", "1/80", "1/40", "1/20")):
            assert f"image {k} ({k}.tif): {t} s" in frames, frames
        assert "ghost removal" in data["summary"] and data["summary"]["reference frame"].startswith("image ")
        w, h, f = data["width"], data["height"], data["factor"]
        overlays = np.frombuffer(gzip.decompress(base64.b64decode(data["overlays"])), np.uint8).reshape(h, w)
        assert 0.001 < np.mean((overlays & 2) != 0) < 0.2          # the pedestrians, not the whole garden
        rad = read_exr(tmp_path / "m.exr")
        driver.get((tmp_path / "r.html").as_uri())
        WebDriverWait(driver, 60).until(lambda d: d.execute_script("return document.body.dataset.ready === '1'"))
        canvas = driver.find_element(By.ID, "img")
        size = canvas.size
        w_lum = np.array([0.2126, 0.7152, 0.0722])
        for x, y in ((w // 3, h // 2), (2 * w // 3, h // 4), (w // 2, 3 * h // 4)):
            ActionChains(driver).move_to_element_with_offset(
                canvas, int((x + 0.5) * size["width"] / w - size["width"] / 2),
                int((y + 0.5) * size["height"] / h - size["height"] / 2)).perform()
            text = driver.find_element(By.ID, "readout").text
            px, py = (int(v) // f for v in re.search(r"pixel x (\d+)\.\.\d+, y (\d+)", text).groups())
            block = rad[f * py:f * py + f, f * px:f * px + f].reshape(-1, 3)
            assert float(driver.find_element(By.ID, "lum").text) == pytest.approx(179.0 * float(block.mean(0) @ w_lum),
                                                                                 rel=0.01)
        driver.find_element(By.ID, "ovGhost").click()                # the picture shows where frames were left out
        driver.set_window_size(1100, 1250)                           # the whole map and the readout under it
        png = driver.get_screenshot_as_png()
        shot = Image.open(io.BytesIO(png)).convert("RGB")
        assert np.asarray(shot).std() > 20
        if os.environ.get("DERENDER_WRITE_SCREENSHOT") == "1":
            shot = shot.crop((0, 0, min(shot.width, 1060), shot.height))      # the page's width, not the window's
            small = shot.resize((shot.width * 7 // 10, shot.height * 7 // 10), Image.LANCZOS)
            small.quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(SCREENSHOT, optimize=True)
        errors = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
        assert not errors, errors
    finally:
        driver.quit()
