"""Weight functions of the merge: hat (Debevec & Malik 1997), trapezoid (paper 1), Gaussian (Robertson 2003).

Each takes normalised codes ``z`` in [0, 1] and returns a weight in [0, 1]; the engine
tabulates them on the 256 codes (:func:`derender.engine.tables.weight_table`).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from derender.core.errors import InputError

__all__ = [
    "F32_MAX",
    "weight_hat",
    "weight_trapezoid",
    "weight_gaussian",
    "WEIGHTS",
    "get_weight",
]


#: Largest finite float32: radiance values are clipped to it so that outputs stay finite.
F32_MAX = float(np.finfo(np.float32).max)


# --------------------------------------------------------------------------- weights
def weight_hat(z: np.ndarray) -> np.ndarray:
    """Debevec & Malik (1997) hat ``w(z) = 1 - |2z - 1|`` on normalised codes ``z`` in [0, 1].

    Zero at 0 and 1 (black and clipped codes never count), 1 at mid-grey. It is the
    paper's ``z - Zmin`` / ``Zmax - z`` rescaled to a peak of 1 (the scale cancels).
    """
    z = np.clip(np.asarray(z, dtype=np.float32), 0.0, 1.0)
    return (1.0 - np.abs(2.0 * z - 1.0)).astype(np.float32)


def weight_trapezoid(z: np.ndarray, low: float = 0.02, high: float = 0.98, ramp: float = 0.1) -> np.ndarray:
    """Trapezoid weight: 0 for ``z <= low`` and ``z >= high``, linear ramps of width ``ramp``, plateau 1.

    ``w = 0`` on [0, low] (noise floor / crushed blacks), rises linearly to 1 at
    ``low + ramp``, stays 1 up to ``high - ramp``, falls to 0 at ``high`` and is 0 on
    [high, 1] (clipped). Paper 1 (Sec. 3, last step) averages with "a trapezoidal
    function discarding saturated and noisy pixels" from its ref. [2] (Bertalmio,
    *Image Processing for Cinema*, 2014); the paper gives no breakpoints, so the
    defaults (2/98 % of full scale, 10 % ramps) are ours.
    """
    if not (0.0 <= low < high <= 1.0) or ramp <= 0 or low + 2 * ramp > high + 1e-12:
        raise InputError(f"trapezoid weight needs 0 <= low < low+2*ramp <= high <= 1, got low={low}, high={high}, ramp={ramp}")
    z = np.asarray(z, dtype=np.float32)
    up = (z - low) / ramp
    down = (high - z) / ramp
    return np.clip(np.minimum(up, down), 0.0, 1.0).astype(np.float32)


_E4 = float(np.exp(-4.0))


def weight_gaussian(z: np.ndarray) -> np.ndarray:
    """Robertson et al. (2003) Gaussian-like weight ``exp(-16 (z - 1/2)^2)``, shifted and scaled to 0 at the ends.

    ``w(z) = (exp(-16 (z - 0.5)^2) - e^-4) / (1 - e^-4)``: 1 at mid-grey, exactly 0 at
    0 and 1 (the same shifted form as OpenCV's ``RobertsonWeights``).
    """
    z = np.clip(np.asarray(z, dtype=np.float32), 0.0, 1.0)
    return ((np.exp(-16.0 * (z - 0.5) ** 2) - _E4) / (1.0 - _E4)).astype(np.float32)


#: Weight functions on normalised code values in [0, 1], by name.
WEIGHTS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "hat": weight_hat,
    "trapezoid": weight_trapezoid,
    "gaussian": weight_gaussian,
}


def get_weight(weight: str | Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    """Resolve a weight name from :data:`WEIGHTS` (or pass a callable through)."""
    if callable(weight):
        return weight
    try:
        return WEIGHTS[str(weight)]
    except KeyError:
        raise InputError(f"unknown weight {weight!r}; known: {', '.join(sorted(WEIGHTS))}") from None
