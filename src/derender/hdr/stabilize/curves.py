"""Per-image linearisations ``L_j = G(J_j ** rho_j)`` of the stabiliser (paper 1, eq. 4 and 8).

Paper 1's model (eq. 4, 8) renders image j's sensor exposure ``x t_j`` as
``J_j = clip(A_j x t_j, 0, 1) ** (1 / gamma_j)``, with a per-image 3x3 matrix ``A_j`` (white
balance, colour matrix, gain) and a per-image *display gamma* ``gamma_j`` (the encoding
exponent is ``1 / gamma_j``; every gamma in this package is the display gamma, ~2.2).
Undoing it (Algorithm 1 step 3.1) gives linear images ``L_j = J_j ** gamma_j`` related by
3x3 matrices (eq. 9). A :class:`Curve` is one image's linearisation: that power law, or a
response table ``G`` common to the bracket (Debevec & Malik's ``g``, for tone curves that
are not power laws, :mod:`.filmic`) applied to exponent-warped codes ``J ** rho``.
Everything downstream (pair fits, colour matrices, the merge tables) reads images through
``Curve.lin``, its inverse ``Curve.code`` and its log slope.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Curve", "as_curve", "MIN_LOG_SLOPE"]


#: Floor of :meth:`Curve.noise_log_slope`, the ``d ln L / dJ`` a noise model may use. No
#: camera response is flatter in log terms than a linear one at white (``L = J``:
#: ``d ln L / dJ = 1 / J >= 1``; a power law of display gamma >= 1 has ``gamma / J >= 1``).
#: A fitted response table can be: isotonic regression turns the conflicting samples of a
#: local tone map into flat segments (the iPhone 6 bracket's Debevec curve is flat over codes
#: 191-232 in R, 186-254 in G, 178-205 in B), where ``log_slope`` drops to ~1e-5 and a
#: relative-noise weight ``1 / log_slope^2`` to 1e10 times the others.
MIN_LOG_SLOPE = 1.0


class Curve:
    """Per-image linearisation ``L = G(J ** rho)`` (per channel), with ``G`` either the power
    law ``u ** gamma`` (paper 1's model, eq. 4) or a common response table (natural log of
    ``G`` on equally spaced code levels, per channel, e.g. Debevec & Malik's ``g``).

    Multiplying a curve by a number scales ``rho`` (for a power law: the gamma), which is
    how the pairwise searches vary one image's exponent.

    ``toe`` (tables only): the offset ``a`` of a display encoding ``J = (1 + a) y ** (1 / gamma) - a``
    (sRGB's 0.055); the warp is then ``W(J) = (1 + a) ((J + a) / (1 + a)) ** rho - a`` (clipped at
    0), which takes such an encoding of gamma ``gamma`` exactly to gamma ``gamma / rho``
    (:mod:`.frame_exponents`). ``toe = 0``: ``W(J) = J ** rho``; with ``rho = 1`` it is the identity.
    """

    def __init__(self, rho: float = 1.0, gamma: float | None = None, log_table: np.ndarray | None = None,
                 toe: float = 0.0):
        if (gamma is None) == (log_table is None):
            raise ValueError("a Curve needs exactly one of gamma and log_table")
        self.rho = float(rho)
        self.toe = float(toe) if log_table is not None else 0.0
        self.gamma = None if gamma is None else float(gamma)
        self.table = None
        if log_table is not None:
            t = np.asarray(log_table, dtype=np.float64)
            if t.ndim == 1:
                t = np.repeat(t[:, None], 3, axis=1)
            # strictly increasing (invertible), finite
            t = np.maximum.accumulate(t, axis=0) + 1e-7 * np.arange(t.shape[0])[:, None]
            self.table = t
            self._levels = np.arange(t.shape[0], dtype=np.float64)
            self._dt = np.diff(t, axis=0)

    def __mul__(self, r: float) -> "Curve":
        r = float(r)
        if self.table is None:
            return Curve(1.0, gamma=self.gamma * self.rho * r)
        c = Curve.__new__(Curve)
        c.rho, c.gamma, c.table, c._levels, c._dt = self.rho * r, None, self.table, self._levels, self._dt
        c.toe = self.toe
        return c

    __rmul__ = __mul__

    @property
    def effective_gamma(self) -> float:
        """Display gamma of a power curve; for a table, the log-log slope of ``G`` between
        codes 0.2 and 0.8 (the gamma of the power law through those points)."""
        if self.table is None:
            return self.gamma * self.rho
        n = self.table.shape[0] - 1
        lo, hi = int(round(0.2 * n)), int(round(0.8 * n))
        slope = (self.table[hi] - self.table[lo]) / (np.log(hi / n) - np.log(lo / n))
        return float(np.mean(slope) * self.rho)

    def lin(self, j: np.ndarray) -> np.ndarray:
        """Linear values (same shape as ``j``, float64)."""
        u = np.clip(np.asarray(j, dtype=np.float64), 0.0, 1.0)
        if self.table is None:
            return u ** (self.gamma * self.rho)
        x, i0 = self._segments(u)
        ch = np.arange(3)
        return np.exp(self.table[i0, ch] + (x - i0) * self._dt[i0, ch])

    def _segments(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Table position ``x = W(u) * (levels - 1)`` of codes ``u`` in [0, 1] and its segment."""
        n = self.table.shape[0] - 1
        a = self.toe
        if self.rho == 1.0:
            x = u * n
        elif a == 0.0:
            x = u ** self.rho * n
        else:
            x = np.maximum((1.0 + a) * ((u + a) / (1.0 + a)) ** self.rho - a, 0.0) * n
        return x, np.minimum(x.astype(np.int64), n - 1)

    def code(self, lin: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`lin` (values below/above the table's range clamp to 0/1)."""
        lv = np.maximum(np.asarray(lin, dtype=np.float64), 1e-300)
        if self.table is None:
            return lv ** (1.0 / (self.gamma * self.rho))
        lg = np.log(lv)
        out = np.empty_like(lg)
        n = self.table.shape[0] - 1
        for c in range(3):
            out[..., c] = np.interp(lg[..., c], self.table[:, c], self._levels) / n
        out = np.clip(out, 0.0, 1.0)
        if self.rho == 1.0:
            return out
        a = self.toe
        if a == 0.0:
            return out ** (1.0 / self.rho)
        return np.clip((1.0 + a) * ((out + a) / (1.0 + a)) ** (1.0 / self.rho) - a, 0.0, 1.0)

    def dlin(self, j: np.ndarray) -> np.ndarray:
        """Derivative ``dL/dJ`` (float64, positive)."""
        u = np.clip(np.asarray(j, dtype=np.float64), 1e-6, 1.0)
        if self.table is None:
            g = self.gamma * self.rho
            return g * u ** (g - 1.0)
        return np.maximum(self.lin(u) * self.log_slope(u), 1e-300)

    def log_slope(self, j: np.ndarray) -> np.ndarray:
        """``d ln L / dJ`` (float64, positive; codes below 1e-6 count as 1e-6): ``gamma / J``
        for a power law, ``dG * (levels - 1) * W'(J)`` (``dG`` the table segment's log step,
        ``W'(J) = rho ((J + a) / (1 + a)) ** (rho - 1)``) for a table. Needs no exponential."""
        u = np.clip(np.asarray(j, dtype=np.float64), 1e-6, 1.0)
        if self.table is None:
            return (self.gamma * self.rho) / u
        _, i0 = self._segments(u)
        n = self.table.shape[0] - 1
        a = self.toe
        tail = n * self.rho if self.rho == 1.0 else (n * self.rho) * ((u + a) / (1.0 + a)) ** (self.rho - 1.0)
        return self._dt[i0, np.arange(3)] * tail

    def noise_log_slope(self, j: np.ndarray) -> np.ndarray:
        """:meth:`log_slope` floored at :data:`MIN_LOG_SLOPE`: the relative noise of a linear value
        per unit code noise, for weights. Equal to :meth:`log_slope` for power laws of display
        gamma >= 1; on a flat table segment (an artefact of the response fit, not a camera
        that resolves radiance infinitely finely) it keeps a weight ``1 / slope^2`` bounded."""
        return np.maximum(self.log_slope(j), MIN_LOG_SLOPE)


def as_curve(g: "float | Curve") -> Curve:
    """``g`` itself if it is a :class:`Curve`, else the power law of display gamma ``g``."""
    return g if isinstance(g, Curve) else Curve(1.0, gamma=float(g))
