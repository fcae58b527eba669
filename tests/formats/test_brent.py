"""formats.brent.minimize_bounded: scipy's bounded Brent without scipy (the exporters' 1-D fits)."""

import math

import numpy as np
import pytest

from torchmetal.formats.brent import minimize_bounded

FUNCS = [
    (lambda x: (x - 0.3) ** 2, -2.0, 2.0),
    (lambda x: math.cos(3 * x) + 0.1 * x * x, -1.0, 3.0),
    (lambda x: abs(x - 1.7) ** 1.5, 0.0, 1.0),  # minimum on the bound
    (lambda x: math.exp(x) - 2 * x, -4.0, 4.0),
    (lambda x: -math.sin(x) / (x + 0.1), 0.0, 6.0),
]


@pytest.mark.parametrize("k", range(len(FUNCS)))
def test_same_as_scipy(k):
    opt = pytest.importorskip("scipy.optimize")  # installed with the test extra
    f, lo, hi = FUNCS[k]
    for xatol in (1e-5, 1e-8):
        x, fx = minimize_bounded(f, lo, hi, xatol=xatol)
        ref = opt.minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
        assert x == pytest.approx(float(ref.x), abs=1e-12) and fx == pytest.approx(float(ref.fun), abs=1e-12)


def test_known_minima():
    x, fx = minimize_bounded(lambda t: (t - 0.3) ** 2 + 1.0, -2.0, 2.0, xatol=1e-8)
    assert abs(x - 0.3) < 1e-6 and abs(fx - 1.0) < 1e-10
    x, _ = minimize_bounded(lambda t: t, 0.5, 4.0)  # monotone: the lower bound
    assert abs(x - 0.5) < 1e-4
    x, _ = minimize_bounded(lambda t: float(np.log1p((t - 2.5) ** 2)), 0.0, 10.0)
    assert abs(x - 2.5) < 1e-4


def test_bad_bounds():
    with pytest.raises(ValueError, match="lo < hi"):
        minimize_bounded(lambda t: t, 1.0, 1.0)
