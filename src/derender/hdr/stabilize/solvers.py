"""Scalar solvers of the stabiliser's searches: Brent's bounded minimiser and root finder.

* :func:`minimize_bounded` -- Brent's (1973, ch. 5) minimiser on an interval: golden-section
  steps, parabolic steps where the last three points allow (Forsythe, Malcolm & Moler
  1977, ``fmin``). Written as a coroutine, :func:`bounded_minimizer`, that yields the
  points to evaluate and receives their values, so that several searches advance in
  lock-step with their evaluations batched (the pairwise exponent searches of
  :func:`derender.hdr.stabilize.exponents.relative_exponents`); :func:`drive` runs one
  such coroutine against a function.
* :func:`find_root` -- Brent's (1973, ch. 4) root finder, ``zeroin``: inverse quadratic or
  secant steps kept inside the bisection bracket (the absolute gamma level from the
  exposure times, :func:`derender.hdr.stabilize.exponents.estimate_gammas`).

Both take the same steps as scipy's ``minimize_scalar(method="bounded")`` and ``brentq``
(tested) without importing ``scipy.optimize`` (0.4 s).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

__all__ = ["minimize_bounded", "bounded_minimizer", "drive", "find_root"]


def minimize_bounded(f: Callable[[float], float], lo: float, hi: float, xatol: float = 1e-5,
                     maxiter: int = 500) -> float:
    """Minimiser of ``f`` on [lo, hi] by Brent's method: golden-section steps, parabolic
    steps where the last three points allow (Brent 1973, ch. 5; Forsythe, Malcolm & Moler
    1977, ``fmin``), stopping when the bracket is within ``xatol / 3`` (plus a relative
    ``sqrt(eps)``) of the best point. The same steps as scipy's
    ``minimize_scalar(method="bounded")`` (tested: same points, same evaluations), without
    importing scipy.optimize (0.4 s here). The steps are :func:`bounded_minimizer`'s."""
    return drive(bounded_minimizer(lo, hi, xatol, maxiter), f)


def drive(steps: Any, f: Callable[[Any], float]) -> Any:
    """Run a coroutine that yields evaluation requests and receives ``f(request)``; its return value."""
    try:
        req = next(steps)
        while True:
            req = steps.send(f(req))
    except StopIteration as stop:
        return stop.value


def bounded_minimizer(lo: float, hi: float, xatol: float = 1e-5, maxiter: int = 500) -> Any:
    """Coroutine of :func:`minimize_bounded`: yields each point to evaluate, receives its
    value, returns the minimiser (lets several searches run in lock-step with their
    evaluations batched, :func:`relative_exponents`)."""
    sqrt_eps = float(np.sqrt(2.2e-16))
    golden = 0.5 * (3.0 - float(np.sqrt(5.0)))
    a, b = float(lo), float(hi)
    x = w = v = a + golden * (b - a)
    fx = fw = fv = yield x
    d = e = 0.0
    n = 1
    m = 0.5 * (a + b)
    tol1 = sqrt_eps * abs(x) + xatol / 3.0
    while abs(x - m) > 2.0 * tol1 - 0.5 * (b - a) and n < maxiter:
        parabolic = False
        if abs(e) > tol1:                       # parabola through x, w, v
            r = (x - w) * (fx - fv)
            q = (x - v) * (fx - fw)
            p = (x - v) * q - (x - w) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            e_prev, e = e, d
            if abs(p) < abs(0.5 * q * e_prev) and q * (a - x) < p < q * (b - x):
                d = p / q
                u = x + d
                if (u - a) < 2.0 * tol1 or (b - u) < 2.0 * tol1:
                    d = tol1 if m >= x else -tol1
                parabolic = True
        if not parabolic:                       # golden section into the larger part
            e = (a - x) if x >= m else (b - x)
            d = golden * e
        u = x + (1.0 if d >= 0 else -1.0) * max(abs(d), tol1)
        fu = yield u
        n += 1
        if fu <= fx:
            if u >= x:
                a = x
            else:
                b = x
            v, fv, w, fw, x, fx = w, fw, x, fx, u, fu
        else:
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, fv, w, fw = w, fw, u, fu
            elif fu <= fv or v == x or v == w:
                v, fv = u, fu
        m = 0.5 * (a + b)
        tol1 = sqrt_eps * abs(x) + xatol / 3.0
    return x


def find_root(f: Callable[[float], float], a: float, b: float, xtol: float = 1e-12, maxiter: int = 100) -> float:
    """Root of ``f`` in [a, b] (``f(a)``, ``f(b)`` of opposite signs) by Brent's method:
    inverse quadratic or secant steps kept inside the bisection bracket (Brent 1973, ch. 4;
    Forsythe, Malcolm & Moler 1977, ``zeroin``); within ``xtol`` (plus 4 eps relative)."""
    a, b = float(a), float(b)
    fa, fb = f(a), f(b)
    if fa == 0.0:
        return a
    if fb == 0.0:
        return b
    if (fa > 0) == (fb > 0):
        raise ValueError("the root is not bracketed")
    c, fc = a, fa
    d = e = b - a
    for _ in range(maxiter):
        if (fb > 0) == (fc > 0):                # keep the root between b and c
            c, fc = a, fa
            d = e = b - a
        if abs(fc) < abs(fb):                   # b is the best estimate
            a, b, c = b, c, b
            fa, fb, fc = fb, fc, fb
        tol = 4.0 * 2.2e-16 * abs(b) + 0.5 * xtol
        mid = 0.5 * (c - b)
        if abs(mid) <= tol or fb == 0.0:
            return b
        if abs(e) >= tol and abs(fa) > abs(fb):
            s = fb / fa
            if a == c:                          # secant
                p, q = 2.0 * mid * s, 1.0 - s
            else:                               # inverse quadratic interpolation
                q, r = fa / fc, fb / fc
                p = s * (2.0 * mid * q * (q - r) - (b - a) * (r - 1.0))
                q = (q - 1.0) * (r - 1.0) * (s - 1.0)
            if p > 0:
                q = -q
            else:
                p = -p
            if 2.0 * p < min(3.0 * mid * q - abs(tol * q), abs(e * q)):
                e, d = d, p / q
            else:
                d = e = mid
        else:
            d = e = mid
        a, fa = b, fb
        b += d if abs(d) > tol else (tol if mid > 0 else -tol)
        fb = f(b)
    return b
