"""The simulated sensor: Bayer mosaic, exposure, shot and read noise, black/white level, ADC.

:func:`mosaic_signal` samples camera RGB on the CFA (RGGB); :func:`expose_mosaic` turns a
signal per second into a raw mosaic for exposure time ``t``: Poisson shot noise in
electrons (full well), Gaussian read noise, black level and 12/14-bit quantisation,
clipped at the white level.
"""

from __future__ import annotations

import numpy as np

from derender.camera.spectral import CameraSpectral

__all__ = [
    "CFA_PATTERN",
    "mosaic_signal",
    "expose_mosaic",
]

#: Bayer pattern of the simulated sensor (top-left 2x2 block).
CFA_PATTERN = "RGGB"


# --------------------------------------------------------------------------- sensor
def _cfa_index(shape: tuple[int, int], pattern: str = CFA_PATTERN) -> np.ndarray:
    lut = {"R": 0, "G": 1, "B": 2}
    tile = np.array([[lut[pattern[0]], lut[pattern[1]]], [lut[pattern[2]], lut[pattern[3]]]])
    h, w = shape
    return np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def mosaic_signal(camera_rgb: np.ndarray, pattern: str = CFA_PATTERN) -> np.ndarray:
    """Pick each photosite's colour from an (H, W, 3) image: the Bayer sampling."""
    ci = _cfa_index(camera_rgb.shape[:2], pattern)
    return np.take_along_axis(camera_rgb, ci[..., None], axis=2)[..., 0]


def expose_mosaic(signal_per_s: np.ndarray, camera: CameraSpectral, time: float,
                  rng: np.random.Generator | None) -> np.ndarray:
    """Sensor model: normalised signal per second (1 = white level) -> uint16 mosaic in DN.

    electrons ~ Poisson(signal * t * full_well); DN = black + electrons * (white - black) /
    full_well + N(0, read_noise); rounded and clipped to [0, white]. ``rng=None`` gives
    the noise-free, rounded mosaic.
    """
    gain = (camera.white_level - camera.black_level) / camera.full_well
    lam = np.clip(signal_per_s * time * camera.full_well, 0.0, 4.0 * camera.full_well)
    if rng is None:
        dn = camera.black_level + lam * gain
    else:
        electrons = rng.poisson(lam).astype(np.float64)
        dn = camera.black_level + electrons * gain + rng.normal(0.0, camera.read_noise, lam.shape)
    return np.clip(np.rint(dn), 0, camera.white_level).astype(np.uint16)
