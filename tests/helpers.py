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
