"""Radiance's own programs (from PyPI ``pyradiance``, a test dependency) as reference readers."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np


def radiance_bin(name: str) -> Path:
    """Path of a Radiance program shipped inside the ``pyradiance`` wheel."""
    import pyradiance

    path = Path(pyradiance.__file__).parent / "bin" / name
    assert path.is_file(), f"pyradiance ships no {name} at {path}"
    return path


def getinfo(path, *args: str) -> str:
    return subprocess.run([str(radiance_bin("getinfo")), *args, str(path)], check=True, capture_output=True,
                          text=True).stdout


def pvalue_pixels(path) -> np.ndarray:
    """(H, W, 3) float64 as ``pvalue -o -h -H`` prints them (original units: EXPOSURE undone)."""
    dims = getinfo(path, "-d").split()
    h, w = int(dims[-3]), int(dims[-1])
    out = subprocess.run([str(radiance_bin("pvalue")), "-o", "-h", "-H", str(path)], check=True,
                         capture_output=True, text=True).stdout
    vals = np.array(out.split(), dtype=np.float64).reshape(h * w, 5)
    img = np.zeros((h, w, 3))
    img[h - 1 - vals[:, 1].astype(int), vals[:, 0].astype(int)] = vals[:, 2:]   # Radiance: y = 0 at the bottom
    return img
