"""hdrgen's camera response files (``.rsp``): one polynomial per channel.

Greg Ward's ``hdrgen`` (``radiance-org/hdrgen``, with ``radiance-org/panlib``) stores the
response it solved for (``-r cam.rsp``: written when the file does not exist, read and used
instead of solving when it does) as three lines, red, green, blue, each

    n  c_n  c_{n-1}  ...  c_1  c_0

the polynomial's order ``n`` (0..5, ``P_MAXEXP``) and its coefficients from the highest power
down (panlib ``phdrimg.h``, ``operator<<(ostream&, const PPolynomial&)``; read back by
``operator>>``, which fails on an order outside 0..5). The polynomial maps a normalised
8-bit code ``x = (v + 0.5) / 256`` (``PbyteVal``) to relative radiance
``p(x) = sum_k c_k x^k``; hdrgen's own fits are normalised to ``p(1) = 1`` in each channel
(``FindPoly``: ``coef[n] = 1 - sum_{j<n} coef[j]``). Below code 19 (``P_LINRESP``), and from
the first code down where ``p`` or ``p'`` is not positive, hdrgen replaces the curve by a
linear toe through the origin (``PHDImageMaker::GetResponse``): :func:`rsp_tables` does the same.

This module reads and writes the format and turns polynomials into 256-entry tables and back
(:func:`fit_rsp`, weighted least squares on codes 19..255); the conversion to derender's
response curves is in :mod:`derender.photometry.profile`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from derender.core.errors import InputError

__all__ = ["RSP_MAX_ORDER", "RSP_LINEAR_TOE", "read_rsp", "write_rsp", "rsp_tables", "fit_rsp", "rsp_code_values"]

#: Highest polynomial order hdrgen reads (``P_MAXEXP``).
RSP_MAX_ORDER = 5
#: Codes below this follow hdrgen's linear toe (``P_LINRESP``).
RSP_LINEAR_TOE = 19


def rsp_code_values(n_levels: int = 256) -> np.ndarray:
    """hdrgen's normalised code values ``(v + 0.5) / 256`` of the 8-bit codes, float64."""
    return (np.arange(n_levels, dtype=np.float64) + 0.5) / float(n_levels)


def read_rsp(path: str | os.PathLike) -> list[np.ndarray]:
    """The three polynomials (R, G, B) of an hdrgen ``.rsp`` file, each as its coefficients
    from ``c_0`` up (``numpy.polynomial`` order). A file that hdrgen would not read (fewer than
    three polynomials, an order outside 0..5, missing or non-finite coefficients) is an
    :class:`InputError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such response file: {path}")
    try:
        tokens = path.read_text(encoding="ascii").split()
    except (UnicodeDecodeError, OSError):
        raise InputError(f"{path} is not an hdrgen response file (not ASCII text)") from None
    polys, i = [], 0
    for channel in "RGB":
        try:
            order = int(tokens[i])
            if not 0 <= order <= RSP_MAX_ORDER:
                raise ValueError
            coef = np.array([float(t) for t in tokens[i + 1:i + 2 + order]], dtype=np.float64)
            if coef.size != order + 1 or not np.all(np.isfinite(coef)):
                raise ValueError
        except (IndexError, ValueError):
            raise InputError(f"{path} is not an hdrgen response file: the {channel} polynomial is not "
                             f"'order c_n ... c_0' with an order 0..{RSP_MAX_ORDER}") from None
        polys.append(coef[::-1].copy())
        i += order + 2
    if i != len(tokens):
        raise InputError(f"{path} is not an hdrgen response file: {len(tokens) - i} token(s) after the three "
                         "polynomials")
    return polys


def write_rsp(path: str | os.PathLike, polys, inputs=()) -> Path:
    """Write three polynomials (coefficients from ``c_0`` up, order <= 5) as an hdrgen ``.rsp`` file, atomically.

    One line per channel: the order, then the coefficients from the highest power down, 17
    significant digits."""
    from derender.io.files import atomic_output

    if len(polys) != 3:
        raise InputError(f"an hdrgen response file holds three polynomials, got {len(polys)}")
    lines = []
    for c in polys:
        c = np.asarray(c, dtype=np.float64).ravel()
        if not 1 <= c.size <= RSP_MAX_ORDER + 1 or not np.all(np.isfinite(c)):
            raise InputError(f"an hdrgen polynomial has order 0..{RSP_MAX_ORDER} and finite coefficients")
        lines.append(" ".join([str(c.size - 1)] + [f"{v:.17g}" for v in c[::-1]]))
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="ascii")
    return path


def rsp_tables(polys, n_levels: int = 256) -> np.ndarray:
    """(n_levels, 3) relative radiance of every code as hdrgen evaluates it: ``p(x)`` from the
    top code down while ``p`` and ``p'`` stay positive and the code is at least 19, a linear toe
    ``x p(x_t) / x_t`` below that code ``t``. A polynomial not positive and increasing at the top
    code describes no response: :class:`InputError`."""
    x = rsp_code_values(n_levels)
    out = np.empty((n_levels, 3), dtype=np.float64)
    for k, c in enumerate(polys):
        c = np.asarray(c, dtype=np.float64)
        p = np.polynomial.polynomial.polyval(x, c)
        d = np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyder(c)) if c.size > 1 else 0 * x
        toe = n_levels - 1
        if not (p[toe] > 0 and d[toe] > 0):
            raise InputError(f"the {'RGB'[k]} response polynomial is not positive and increasing at the top code")
        while toe > RSP_LINEAR_TOE and p[toe - 1] > 0 and d[toe - 1] > 0:
            toe -= 1
        out[:, k] = p
        out[:toe, k] = x[:toe] * (p[toe] / x[toe])
    return out


def fit_rsp(relative: np.ndarray, order: int = RSP_MAX_ORDER, weights: np.ndarray | None = None) -> list[np.ndarray]:
    """Polynomials of ``order`` fitted to (n_levels, 3) relative radiance per code at hdrgen's
    code values, on codes 19 up (hdrgen's linear toe takes the others), by weighted least
    squares on the relative error (weights ``1 / f^2`` times ``weights``); coefficients from
    ``c_0`` up."""
    f = np.asarray(relative, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != 3 or not np.all(np.isfinite(f)) or f.min() <= 0:
        raise InputError("a response to export is (n_levels, 3) positive relative radiance")
    if not 1 <= order <= RSP_MAX_ORDER:
        raise InputError(f"an hdrgen polynomial has order 1..{RSP_MAX_ORDER}, got {order}")
    x = rsp_code_values(f.shape[0])
    lo = int(round(RSP_LINEAR_TOE * f.shape[0] / 256))
    vander = np.vander(x[lo:], order + 1, increasing=True)
    polys = []
    for k in range(3):
        w = 1.0 / f[lo:, k]
        if weights is not None:
            w = w * np.sqrt(np.asarray(weights, dtype=np.float64)[lo:, k])
        coef, *_ = np.linalg.lstsq(vander * w[:, None], f[lo:, k] * w, rcond=None)
        polys.append(coef)
    return polys
