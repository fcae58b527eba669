"""torchmetal.lbfgs.minimize: the iterates of torch.optim.LBFGS (strong Wolfe), without torch.optim."""

import torch

from torchmetal.lbfgs import minimize


def _rosenbrock(x):
    return (1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2 + (1 - x[2]) ** 2 + 10 * (x[3] - x[2] ** 2) ** 2


def _value_grad(x):
    x = x.detach().requires_grad_(True)
    f = _rosenbrock(x)
    return float(f.detach()), torch.autograd.grad(f, x)[0]


def _torch_lbfgs(x0, **kw):
    z = x0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([z], lr=1.0, line_search_fn="strong_wolfe", **kw)

    def closure():
        opt.zero_grad()
        f = _rosenbrock(z)
        f.backward()
        return f

    opt.step(closure)
    return z.detach(), opt.state[opt._params[0]]["n_iter"]


def test_same_iterates_as_torch_optim_lbfgs():
    x0 = torch.tensor([-1.2, 1.0, 0.5, -0.3], dtype=torch.float64)
    for max_iter in (1, 3, 10, 100):
        kw = dict(max_iter=max_iter, tolerance_grad=1e-5, tolerance_change=1e-9)
        want, n_want = _torch_lbfgs(x0, **kw)
        got, n_got = minimize(_value_grad, x0, **kw)
        assert n_got == n_want
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    assert float((got - 1.0).abs().max()) < 1e-4  # converged on the 100-iteration run


def test_stops_at_once_on_a_flat_start():
    x0 = torch.ones(4, dtype=torch.float64)
    x, n = minimize(_value_grad, x0)
    assert n == 0 and torch.equal(x, x0)


def test_a_step_into_non_finite_values_keeps_the_last_finite_iterate():
    """f is finite for x < 2 only (an exponent overflowing far from the data); its minimum lies beyond: the
    iteration stops at a finite x instead of returning NaN (the relief's fit on a random scene did, 2026-12-06)."""

    def value_grad(x):
        x = x.detach().requires_grad_(True)
        f = torch.where(x < 2.0, -x * 10.0, torch.full_like(x, float("nan"))).sum()
        (g,) = torch.autograd.grad(f, x)
        return float(f), g

    x, _ = minimize(value_grad, torch.zeros(1, dtype=torch.float64), max_iter=20)
    assert bool(torch.isfinite(x).all()) and float(x[0]) < 2.0
