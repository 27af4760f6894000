"""Small helpers shared by tests (not fixtures)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def run_cli(args, capsys=None) -> tuple[int, str, str]:
    """Run ``derender ARGS`` in-process through the console entry point; return (code, out, err)."""
    from derender.cli import main

    old = sys.argv
    sys.argv = ["derender", *[str(a) for a in args]]
    code = 0
    try:
        main()
    except SystemExit as exc:
        code = int(exc.code or 0) if not isinstance(exc.code, str) else 1
    finally:
        sys.argv = old
    out = err = ""
    if capsys is not None:
        cap = capsys.readouterr()
        out, err = cap.out, cap.err
    return code, out, err


def write_png_codes(path: Path, codes: np.ndarray) -> Path:
    import cv2

    arr = codes[..., ::-1] if codes.ndim == 3 and codes.shape[2] == 3 else codes
    assert cv2.imwrite(str(path), np.ascontiguousarray(arr))
    return path


def write_exif_jpeg(path: Path, codes: np.ndarray, t: float, n: float, iso: int, model: str = "Camera") -> Path:
    """A JPEG with EXIF Make "Test", Model, ExposureTime ``t``, FNumber ``n`` and ISOSpeedRatings
    ``iso``, written with Pillow directly (independent of derender's own writer, so that tests of
    derender's EXIF reading do not read what derender wrote)."""
    from fractions import Fraction

    from PIL import Image, TiffImagePlugin

    ex = Image.Exif()
    ex[0x010F], ex[0x0110] = "Test", model
    sub = ex.get_ifd(0x8769)
    f = Fraction(t).limit_denominator(1 << 30)
    sub[0x829A] = TiffImagePlugin.IFDRational(f.numerator, f.denominator)
    g = Fraction(n).limit_denominator(1000)
    sub[0x829D] = TiffImagePlugin.IFDRational(g.numerator, g.denominator)
    sub[0x8827] = iso
    Image.fromarray(codes).save(path, format="JPEG", quality=95, exif=ex.tobytes())
    return path


def profile_reuse_ratios(inputs_a, inputs_b, bracket_a, bracket_b, outputs, capsys, extra=()) -> np.ndarray:
    """The luminance family's profile protocol (issues 28 and 38): merge ``inputs_a`` with
    ``--spot`` on bracket A's grey card and ``--save-profile``, merge ``inputs_b`` with that
    profile only, and return B's luminance over its exact luminance on the smooth pixels off
    the card with truth >= 1 cd/m2. ``outputs``: (profile, map A, map B); ``extra``: further
    options of both merges (e.g. ``--method``)."""
    from derender.camera.luminance import truth_luminance_cd_m2
    from derender.evaluation.families import smooth_mask
    from derender.io.exr import read_exr
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.illuminance import luminance_cd_m2

    prof, a, b = outputs
    code, _, err = run_cli(["merge", *inputs_a, "-o", a, *extra, "--spot",
                            bracket_a.params["luminance"]["spot_option"], "--save-profile", prof], capsys)
    assert code == 0, err
    code, _, err = run_cli(["merge", *inputs_b, "-o", b, *extra, "--profile", prof], capsys)
    assert code == 0, err
    assert "from the profile" in err
    lt = truth_luminance_cd_m2(bracket_b.truth_linear_srgb)
    ok = smooth_mask(bracket_b.truth_linear_srgb) & (lt >= 1.0)
    x, y, w, h = bracket_b.params["luminance"]["grey_card"]
    ok[y:y + h, x:x + w] = False
    assert ok.sum() > 5000
    return luminance_cd_m2(read_exr(b), SRGB_PRIMARIES)[ok] / lt[ok]
