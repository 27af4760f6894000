"""Saturation a code threshold cannot see: pixels whose codes stop growing with exposure.

Beyond paper 1, whose model clips *after* the tone curve's input (eq. 4: ``clip(A_j x t_j,
0, 1)``), so a saturated pixel renders at white and a code threshold (:data:`FIT_HIGH`,
the trapezoid's shoulder) leaves it out. Pipelines with a local tone map or a highlight
roll-off render a sensor-clipped pixel *below* white: a phone's gain map holds highlights
back (gain < 1) and a Reinhard shoulder keeps them from clipping, so a clipped sky may
render at code 150-200 in every long exposure (the simulator's ``phone-local`` family). Such
codes pass every threshold and, linearised, are far too dark: the merge then averages
radiances several stops too low into every highlight.

The sign that is left: a camera response is increasing in exposure, so between two
frames whose exposure times differ by a ratio ``r >= 1.5`` an unclipped pixel's codes grow
(for ``r = 2`` and a display gamma of 2.2 by ~35 %, in the shadows even more). A pixel whose
code in some channel does *not* grow from frame ``k - 1`` to frame ``k`` (by more than
:data:`STAGNATION_CODES`) while it lies between :data:`STAGNATION_FLOOR` and
:data:`STAGNATION_CEILING` was clipped in frame ``k - 1`` already (were it unclipped there,
frame ``k`` would record more light): :func:`hidden_saturation` flags frames ``k - 1, k, ...``. This also flags some
clean pixels: when a raw channel first clips in frame ``k``, the colour matrix's negative
off-diagonals can pull another rendered channel of frame ``k`` *down* (on the held-out
``dslr-lut`` family 9 % of the reference's pixels, a tone curve's flat shoulder more). The
rule keeps them flagged on purpose: a missed clipped frame biases the merge by up to the
exposure ratio, a wrongly dropped one only adds noise. Measured on held-out brackets
(phone-local / dslr-lut indoor seed 0, PSNR L): this rule 33.6 / 43.8 dB, no mask 23.6 /
44.4; flagging ``k - 1`` only when *every* tested channel stays flat 24.8 / 44.4; testing
only codes below :data:`FIT_HIGH` (0.85) 24.8 / 44.2. Leaving the masked samples out of the
Debevec curve fit too cost 3.4 dB on that dslr-lut bracket (the shoulder's samples go).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from derender.engine.motion.reference_frame import REF_HIGH
from derender.hdr.stabilize.blocks import FIT_HIGH

__all__ = ["STAGNATION_CODES", "STAGNATION_FLOOR", "STAGNATION_CEILING", "STAGNATION_RATIO", "HIDDEN_FRACTION",
           "hidden_saturation", "hidden_fraction", "saturation_fraction", "saturation_mask"]

#: A channel "grows" from one frame to the next if its code rises by more than this many code steps.
STAGNATION_CODES = 2.0
#: Only channels above this code (fraction of white) in the shorter frame are tested: a film's
#: toe (and noise) keeps dark codes flat too. On Debevec's Memorial stack (film, 1-stop steps)
#: a floor of 0.1 flagged 8 % of pixels below FIT_HIGH in some frame, 0.2 1.4 %, 0.3 0.65 %;
#: the ``phone-local`` gain (clipped codes at 0.5-0.8) is the same for all three.
STAGNATION_FLOOR = 0.3
#: ... and below this one (:data:`~derender.engine.motion.reference_frame.REF_HIGH`): near white a
#: code has no room to grow, and the code thresholds handle it (Memorial: 14 % flagged in
#: its shortest frame without this ceiling, 0.003 % with it).
STAGNATION_CEILING = REF_HIGH
#: Only consecutive frames whose exposure times differ by at least this ratio are compared.
STAGNATION_RATIO = 1.5
#: :func:`hidden_fraction` above which the stabilised merges use the mask (otherwise they
#: run as before, on the engine). Brackets of pipelines that clip at white show: tuning
#: families ``paper`` and ``camera`` (8 simulated 192x128 brackets) at most 0.0012 (pixels
#: next to a clipped raw channel, whose codes may dip below white); Debevec's Memorial
#: (film) 0.0065, downsampled 6x (area averaging mixes clipped and clean pixels) 0.059;
#: Frobisher 0. The threshold is 2.5x the largest of those. Measured afterwards on the
#: held-out families: phone-local 0.61-0.87 (masked), dslr-lut up to 0.12 and drift below
#: 0.008 (not masked).
HIDDEN_FRACTION = 0.15


def _scan(images: Any, times: Sequence[float], keep: bool) -> tuple[np.ndarray | None, float]:
    """One pass over the bracket holding two frames at a time: the (N, H, W) mask (if ``keep``)
    and its :func:`hidden_fraction`. ``images[j]``: a float frame in [0, 1] or uint8 codes."""
    t = np.asarray(times, dtype=np.float64)
    n = t.shape[0]
    nxt = np.asarray(images[0])
    h, w = nxt.shape[:2]
    out = np.zeros((n, h, w), dtype=bool) if keep else None
    cum = np.zeros((h, w), dtype=bool)            # flagged in some frame up to the current one
    best = 0.0
    for k in range(n):
        a = nxt
        if k + 1 < n:
            nxt = np.asarray(images[k + 1])
            if t[k + 1] >= STAGNATION_RATIO * t[k]:
                if a.dtype == np.uint8:       # the same tests on codes, channel by channel (no int16 copies)
                    lo = int(np.floor(STAGNATION_FLOOR * 255.0))      # code > lo  <=>  code > FLOOR * 255
                    hi = int(np.ceil(STAGNATION_CEILING * 255.0))     # code < hi  <=>  code < CEILING * 255
                    for c in range(a.shape[-1]):
                        ac, nc = a[..., c], nxt[..., c]
                        # ac < hi <= 255 - STAGNATION_CODES, so ac + codes cannot wrap where it counts
                        cum |= (ac > lo) & (ac < hi) & (nc <= ac + np.uint8(STAGNATION_CODES))
                else:
                    step = np.float32(STAGNATION_CODES / 255.0)
                    flat = (a > STAGNATION_FLOOR) & (a < STAGNATION_CEILING) & (nxt <= a + step)
                    cum |= flat.any(axis=-1)
        if keep:
            out[k] = cum
        top = FIT_HIGH * 255.0 if a.dtype == np.uint8 else FIT_HIGH
        amax = np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2]) if a.shape[-1] == 3 else a.max(axis=-1)
        best = max(best, float(np.count_nonzero(cum & (amax < top)) / cum.size))
    return out, best


def hidden_saturation(images: Any, times: Sequence[float]) -> np.ndarray:
    """(N, H, W) bool: pixels of each frame that are saturated though their codes are below
    white (see the module docstring). ``images``: (N, H, W, 3) aligned frames in [0, 1]
    (anything whose ``images[j]`` is one frame, read two at a time; uint8 codes too),
    sorted by exposure time."""
    return _scan(images, times, True)[0]


def hidden_fraction(mask: np.ndarray, images: Any, high: float = FIT_HIGH) -> float:
    """Largest fraction, over frames, of pixels ``mask`` flags while all their channels are below ``high``."""
    n = mask.shape[0]
    best = 0.0
    for j in range(n):
        below = np.asarray(images[j]).max(axis=-1) < high
        best = max(best, float((mask[j] & below).mean()))
    return best


def saturation_fraction(images: Any, times: Sequence[float]) -> float:
    """:func:`hidden_fraction` of :func:`hidden_saturation` without keeping the mask (two frames in memory)."""
    return _scan(images, times, False)[1]


def saturation_mask(images: Any, times: Sequence[float]) -> tuple[np.ndarray | None, float]:
    """:func:`hidden_saturation` of aligned ``images`` and its :func:`hidden_fraction`; the mask
    is None when the fraction does not exceed :data:`HIDDEN_FRACTION` (the merge ignores it)."""
    mask, frac = _scan(images, times, True)
    return (mask if frac > HIDDEN_FRACTION else None), frac
