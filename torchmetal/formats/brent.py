"""Bounded scalar minimisation (Brent's method) in plain Python, for the exporters' 1-D fits.

The same algorithm as ``scipy.optimize.minimize_scalar(method="bounded")`` (Brent's fminbound:
golden-section steps with parabolic interpolation), so the exporters need no scipy: a plain
``pip install torchmetal`` exports every format. ``tests/formats/test_brent.py`` checks it against
scipy where scipy is installed.
"""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["minimize_bounded"]

_SQRT_EPS = math.sqrt(2.2e-16)
_GOLDEN = 0.5 * (3.0 - math.sqrt(5.0))


def _sign(x: float) -> float:
    return 1.0 if x >= 0 else -1.0  # sign with sign(0) = 1, as fminbound's np.sign(x) + (x == 0)


def minimize_bounded(f: Callable[[float], float], lo: float, hi: float, *, xatol: float = 1e-5,
                     maxiter: int = 500) -> tuple[float, float]:
    """The minimiser of ``f`` on ``[lo, hi]`` and its value, to ``xatol``: ``(x, f(x))``."""
    a, b = float(lo), float(hi)
    if not a < b:
        raise ValueError(f"bounds: expected lo < hi, found ({lo}, {hi})")
    fulc = a + _GOLDEN * (b - a)
    nfc = xf = fulc
    rat = e = 0.0
    fx = float(f(xf))
    ffulc = fnfc = fx
    xm = 0.5 * (a + b)
    tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
    tol2 = 2.0 * tol1
    for _ in range(maxiter):
        if abs(xf - xm) <= tol2 - 0.5 * (b - a):
            break
        golden = True
        if abs(e) > tol1:  # try a parabola through the three best points
            golden = False
            r = (xf - nfc) * (fx - ffulc)
            q = (xf - fulc) * (fx - fnfc)
            p = (xf - fulc) * q - (xf - nfc) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            r, e = e, rat
            if abs(p) < abs(0.5 * q * r) and q * (a - xf) < p < q * (b - xf):
                rat = p / q
                x = xf + rat
                if (x - a) < tol2 or (b - x) < tol2:
                    rat = tol1 * _sign(xm - xf)
            else:
                golden = True
        if golden:
            e = (a - xf) if xf >= xm else (b - xf)
            rat = _GOLDEN * e
        x = xf + _sign(rat) * max(abs(rat), tol1)
        fu = float(f(x))
        a, b, xf, fx, nfc, fnfc, fulc, ffulc = _bracket(x, fu, a, b, xf, fx, nfc, fnfc, fulc, ffulc)
        xm = 0.5 * (a + b)
        tol1 = _SQRT_EPS * abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1
    return xf, fx


def _bracket(x: float, fu: float, a: float, b: float, xf: float, fx: float, nfc: float, fnfc: float, fulc: float,
             ffulc: float) -> tuple[float, float, float, float, float, float, float, float]:
    """The bracket [a, b] and the three best points (xf, nfc, fulc) with their values after evaluating
    ``f(x) = fu``."""
    if fu <= fx:
        if x >= xf:
            a = xf
        else:
            b = xf
        fulc, ffulc = nfc, fnfc
        nfc, fnfc = xf, fx
        xf, fx = x, fu
    else:
        if x < xf:
            a = x
        else:
            b = x
        if fu <= fnfc or nfc == xf:
            fulc, ffulc = nfc, fnfc
            nfc, fnfc = x, fu
        elif fu <= ffulc or fulc == xf or fulc == nfc:
            fulc, ffulc = x, fu
    return a, b, xf, fx, nfc, fnfc, fulc, ffulc
