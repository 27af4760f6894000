"""Every method that needs no model on real brackets (issue 16, item 8): the iPhone 6 bracket
(8 JPEGs stored rotated, EXIF times), Debevec's Memorial (PNG, HDRShop times list) and
colour-hdri's Frobisher (3 JPEGs). There is no ground-truth radiance for these, so the
oracles are the files themselves and the methods' agreement:

* upright (the iPhone frames carry EXIF orientation 6: the result is 2448 wide, 3264 tall),
  finite and non-negative;
* the methods agree on the picture: log-luminance correlation >= 0.98 between every pair;
* colours agree with the camera's own rendering where it is well exposed: the median angle
  between a merged pixel and the frame's sRGB-decoded code (codes 25-230 in every channel)
  stays below 15 degrees (measured 2.8-9.0), and the iPhone's sky is blue (B the largest
  channel), as in every frame of the bracket.

Cost (CI, 2 cores): every bracket is decoded once (EXIF orientation applied) and merged in
memory by every method, the iPhone's 8 MP frames on every 4th row and column (816 x 612
codes, the camera's own codes, not resampled); one full-size ``merge_files`` (Debevec,
streamed, ~4 s) checks that the product path keeps the frames upright.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require_shared

from derender.core.colorimetry import luminance

METHODS = ("debevec", "robertson", "stabilized", "stabilized-joint")


#: Pixel step of the in-memory merges (the iPhone's 3264 x 2448 frames -> 816 x 612).
STEP = {"iphone": 4, "memorial": 1, "frobisher": 1}


def _bracket(name: str):
    if name == "iphone":
        d = require_shared("iphone6-bracket")
        return sorted(d.glob("*.JPG")), {}
    if name == "memorial":
        d = require_shared("debevec-memorial")
        return sorted(d.glob("memorial00*.png")), {"times_file": d / "memorial.hdr_image_list.txt",
                                                   "times_file_inverse": True}
    d = require_shared("colour-hdri-frobisher")
    return sorted(d.glob("IMG_*.jpg")), {}


@pytest.fixture(scope="module", params=["iphone", "memorial", "frobisher"])
def merged(request):
    """(name, frames as decoded, in time order and subsampled, {method: radiance}) of one bracket."""
    from derender.core.types import Stack
    from derender.engine.tables import code_values
    from derender.hdr.registry import merge_seeded
    from derender.io.exif import file_times
    from derender.io.images import read_codes

    name = request.param
    paths, kw = _bracket(name)
    times = np.asarray(file_times(paths, None, kw.get("times_file"), kw.get("times_file_inverse", False)))
    order = np.argsort(times, kind="stable")
    s = STEP[name]
    full = [read_codes(paths[i]) for i in order]
    if name == "iphone":
        assert all(f.shape == (3264, 2448, 3) for f in full)      # EXIF orientation 6 applied
    frames = np.stack([np.ascontiguousarray(f[::s, ::s]) for f in full])
    stack = Stack(images=code_values()[frames], times=times[order])
    return name, frames, {m: np.asarray(merge_seeded(stack, m, 0).radiance) for m in METHODS}


def test_product_path_keeps_the_iphone_upright():
    from derender.hdr.files import merge_files

    paths, kw = _bracket("iphone")
    rad = np.asarray(merge_files(paths, method="debevec", **kw).radiance)
    assert rad.shape == (3264, 2448, 3)
    assert np.all(np.isfinite(rad)) and rad.min() >= 0


def _srgb_decode(codes: np.ndarray) -> np.ndarray:
    c = codes / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def test_upright_finite_non_negative(merged):
    name, frames, results = merged
    for method, rad in results.items():
        assert rad.shape == frames.shape[1:], method
        if name == "iphone":
            assert rad.shape == (816, 612, 3), method
        assert np.all(np.isfinite(rad)), method
        assert rad.min() >= 0, (method, float(rad.min()), int((rad < 0).sum()))


def test_methods_agree_on_log_luminance(merged):
    _, _, results = merged
    logl = {m: np.log(np.maximum(luminance(r[::4, ::4]), 1e-12)).ravel() for m, r in results.items()}
    names = list(logl)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert np.corrcoef(logl[a], logl[b])[0, 1] >= 0.98, (a, b)


def test_colours_follow_the_camera_rendering(merged):
    name, frames, results = merged
    # every frame's well-exposed pixels (codes 25-230 in every channel), decoded and normalised once
    where, camera = [], []
    for j, codes in enumerate(frames):
        ok = np.flatnonzero(((codes.min(-1) >= 25) & (codes.max(-1) <= 230)).ravel())
        a = _srgb_decode(codes.reshape(-1, 3)[ok].astype(np.float64))
        where.append(ok)
        camera.append(a / np.linalg.norm(a, axis=1, keepdims=True))
    for method, rad in results.items():
        flat = rad.reshape(-1, 3).astype(np.float64)
        angles = []
        for ok, a in zip(where, camera):
            b = flat[ok]
            cos = (a * b).sum(1) / np.maximum(np.linalg.norm(b, axis=1), 1e-30)
            angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        assert np.median(np.concatenate(angles)) < 15.0, method
        if name == "iphone":
            h, w, _ = rad.shape
            sky = np.median(rad[: int(h * 0.15), : int(w * 0.7)].reshape(-1, 3), axis=0)
            assert np.argmax(sky) == 2, (method, sky / sky.max())


def test_iphone_greys_stay_grey(merged):
    """Issue 27: pixels that a mid frame (4-7, counting from 1 in time order) renders neutral come
    out neutral: the result's R/G and B/G medians per luminance decade
    (:func:`derender.evaluation.neutral.neutral_axis`). Measured at this size (largest deviation
    from 1 over the decades, frames 4 / 5 / 6 / 7): debevec 0.106 / 0.083 / 0.010 / 0.073 (its merge's
    lambda 60; 0.095 / 0.076 / 0.013 / 0.070 at 30),
    robertson 0.120 / 0.103 / 0.030 / 0.100 with the channel tie (before it 0.180 / 0.165 / 0.074 /
    0.052, 0.153 / 0.178 / 0.110 / 0.070); stabilized 0.069 / 0.060 / 0.059 / 0.117,
    stabilized-joint 0.060 / 0.045 / 0.055 / 0.107 with the grey balance
    (:mod:`derender.hdr.stabilize.grey_balance`; before it 0.285 / 0.274 / 0.211 / 0.269 and
    0.230 / 0.212 / 0.151 / 0.186). Bounds: 0.16 for the classic merges, 0.13 for the stabilised
    ones. The issue's 5 % is not met by every method and frame:
    the iPhone's frames disagree about grey (pixels frame 4 renders neutral have B/G 1.13 in frame
    3 and 0.80 in frame 8, decoded with gamma 2.2), so one radiance per pixel cannot match every
    frame's grey."""
    from derender.evaluation.neutral import neutral_axis

    name, frames, results = merged
    if name != "iphone":
        pytest.skip("the iPhone bracket only")
    for method, rad in results.items():
        dev = [neutral_axis(frames, rad, j).max_deviation for j in (3, 4, 5, 6)]
        assert np.all(np.isfinite(dev)), method
        assert max(dev) < (0.16 if method in ("debevec", "robertson") else 0.13), (method, dev)
