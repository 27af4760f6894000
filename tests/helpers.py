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
