"""Weight functions of the merge: hat (Debevec & Malik 1997), trapezoid (paper 1), Gaussian (Robertson 2003).

Each takes normalised codes ``z`` in [0, 1] and returns a weight in [0, 1]; the engine
tabulates them on the 256 codes (:func:`derender.engine.tables.weight_table`).

**The bracket's black floor** (:func:`black_codes`, :func:`floor_weights`). Every weight is 0
at code 0 only, but a bracket's black need not be code 0: a film scan's base and fog, a
scanner's or a pipeline's black offset put the unexposed scene at codes 13-18 (Debevec's
Memorial: R 13, G 17, B 15-16 over most of its shortest frame). Such a code does not follow
the exposure: halving the exposure leaves it where it is, and ``g(z) - ln t_j`` of it is off
by the factor between the frame's exposure and the floor's (1 to 3 in ln on Memorial's short
frames). With a weight of a few per cent of mid-grey's, eight such frames are a tenth of a
dark pixel's weight: they raised Memorial's darkest decade by 1.7x (debevec) and 1.9x
(robertson) against Debevec's own ``memorial.hdr``, and the frames' spread ``D`` they cause
made the variance's disagreement term a median 0.6 in ln. A code ``z`` is at the floor when,
over the pixels that show it in a frame ``j``, at least :data:`FLOOR_SHARE` of them show at
least ``z - 1`` in the longest frame with at most half of ``t_j`` (the exposure halved, the
code did not fall); the floor is the run of such codes from code 0 up (codes seen fewer than
:data:`FLOOR_MIN_COUNT` times are passed over). A floor below :data:`FLOOR_MIN_CODE` is a
digital camera's crushed blacks (code 0 already has no weight) and is left as it is; so is a
run the shortest frame does not pile up in (:data:`FLOOR_PILE`: a black offset is where the
unexposed scene sits). The
channels of the ``"mean"`` weight mode share one weight per pixel: a channel at its floor then
adds nothing to that weight, but its value still enters the mean with the other channels'
weight (measured on Memorial: the floor halves the debevec merge's excess in the darkest decade).
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
    "FLOOR_SHARE",
    "FLOOR_MIN_COUNT",
    "FLOOR_MIN_CODE",
    "FLOOR_MAX_CODE",
    "FLOOR_PILE",
    "black_codes",
    "floor_weights",
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


#: Share of a code's observations whose exposure halved did not lower it (by more than one code),
#: from which the code is at the bracket's black floor (:func:`black_codes`): half of them. Memorial's
#: floor codes measure 0.92-0.99 and its next codes 0.52-0.81 (floor R 15, G 20, B 19); the
#: simulator's families and the digital real brackets measure a floor of codes 1-6 (``paper``:
#: 2-4; iPhone: 3-6; Frobisher: 0-2), left as it is (:data:`FLOOR_MIN_CODE`).
FLOOR_SHARE = 0.5
#: Codes seen fewer times than this (in frames with a frame of at most half their time) are
#: passed over by :func:`black_codes`.
FLOOR_MIN_COUNT = 50
#: A floor below this code is a digital camera's crushed blacks and is left as it is
#: (:func:`black_codes`): the highest measured on a digital bracket is 6 (iPhone, green), where
#: the Gaussian weight is below 1 % of mid-grey's.
FLOOR_MIN_CODE = 8
#: A floor is where the unexposed scene piles up: at least this share of the shortest frame's
#: pixels sit at codes 1 to the floor (Memorial: 0.9 and more per channel). Without it, codes a
#: steep toe leaves sparse and noise dominates (a synthetic gamma-and-knee bracket with read
#: noise: "floors" of 26-33) would pass the halving test.
FLOOR_PILE = 0.25
#: :func:`black_codes` looks for the floor below this code only.
FLOOR_MAX_CODE = 64


def black_codes(codes: np.ndarray, times) -> list[int]:
    """Per channel, the bracket's black floor (module docstring): the highest code of the run,
    from code 0 up, of codes that did not fall when the exposure was halved; 0 when that is
    below :data:`FLOOR_MIN_CODE` or when fewer than :data:`FLOOR_PILE` of the shortest frame's pixels
    sit at codes 1 to it. ``codes`` (N, P, 3) integer codes of the same P pixels in
    every frame (a method's samples, or a subsample of the held frames), ``times`` (N,)."""
    z = np.asarray(codes)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    out = [0, 0, 0]
    if z.ndim != 3 or z.shape[0] != t.size or z.shape[0] < 2:
        return out
    z = z.astype(np.int64, copy=False)
    order = np.argsort(t, kind="stable")
    tot = np.zeros((3, FLOOR_MAX_CODE), dtype=np.int64)
    flat = np.zeros((3, FLOOR_MAX_CODE), dtype=np.int64)
    for i in range(1, order.size):
        j = order[i]
        shorter = [k for k in order[:i] if t[k] <= 0.5 * t[j]]
        if not shorter:
            continue
        k = shorter[-1]
        for c in range(3):
            zj, zk = z[j, :, c], z[k, :, c]
            sel = zj < FLOOR_MAX_CODE
            zj, zk = zj[sel], zk[sel]
            tot[c] += np.bincount(zj, minlength=FLOOR_MAX_CODE)
            flat[c] += np.bincount(zj[zk >= zj - 1], minlength=FLOOR_MAX_CODE)
    for c in range(3):
        floor = 0
        for code in range(FLOOR_MAX_CODE):
            if tot[c, code] < FLOOR_MIN_COUNT:
                continue
            if flat[c, code] < FLOOR_SHARE * tot[c, code]:
                break
            floor = code
        zs = z[order[0], :, c]
        pile = float(np.mean((zs >= 1) & (zs <= floor)))
        out[c] = floor if floor >= FLOOR_MIN_CODE and pile >= FLOOR_PILE else 0
    return out


def floor_weights(weights: np.ndarray, black: list[int]) -> np.ndarray:
    """A (256, 3) or (N, 256, 3) weight table with no weight at or below each channel's black
    floor ``black`` (:func:`black_codes`); the table itself when there is none. Those codes are
    then read as 0 is: a pixel no frame measures takes the saturation policy's bound."""
    if not any(int(b) > 0 for b in black):
        return weights
    out = np.array(weights, dtype=np.float32, copy=True)
    for c, b in enumerate(black):
        if int(b) > 0:
            out[..., : int(b) + 1, c] = 0.0
    return np.ascontiguousarray(out)


def get_weight(weight: str | Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    """Resolve a weight name from :data:`WEIGHTS` (or pass a callable through)."""
    if callable(weight):
        return weight
    try:
        return WEIGHTS[str(weight)]
    except KeyError:
        raise InputError(f"unknown weight {weight!r}; known: {', '.join(sorted(WEIGHTS))}") from None
