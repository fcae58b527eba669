"""Batched LM primitives: closed-form solves, damping bounds, acceptance, a full driver."""


import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchmetal.fit.lm import (
    LAMBDA_MAX,
    LAMBDA_MIN,
    NU_MAX,
    LMEval,
    accept_step,
    damped_step,
    levenberg_marquardt,
    marquardt_diag,
    predicted_reduction,
    solve_1x1,
    solve_2x2,
    update_damping,
)


def test_solve_2x2_matches_dense_solve():
    g = torch.Generator().manual_seed(0)
    m = torch.randn(500, 2, 2, generator=g, dtype=torch.float64)
    h = m @ m.transpose(1, 2) + 1e-3 * torch.eye(2, dtype=torch.float64)
    b = torch.randn(500, 2, generator=g, dtype=torch.float64)
    x1, x2 = solve_2x2(h[:, 0, 0], h[:, 0, 1], h[:, 1, 1], b[:, 0], b[:, 1])
    ref = -torch.linalg.solve(h, b)
    torch.testing.assert_close(torch.stack([x1, x2], -1), ref, rtol=1e-8, atol=1e-10)


def test_solve_2x2_badly_scaled_float32():
    h11 = torch.tensor([1e8, 1e-8], dtype=torch.float32)
    h22 = torch.tensor([1e-8, 1e8], dtype=torch.float32)
    h12 = torch.tensor([0.5, 0.5], dtype=torch.float32) * torch.sqrt(h11 * h22)
    g1, g2 = torch.tensor([1.0, 1.0]), torch.tensor([1.0, 1.0])
    x1, x2 = solve_2x2(h11, h12, h22, g1, g2)
    ref = -torch.linalg.solve(torch.stack([torch.stack([h11, h12], -1), torch.stack([h12, h22], -1)], -2).double(),
                              torch.stack([g1, g2], -1).double())
    torch.testing.assert_close(torch.stack([x1, x2], -1).double(), ref, rtol=1e-5, atol=0)


def test_singular_and_nan_elements_do_not_poison_the_batch():
    h11 = torch.tensor([0.0, 1.0, 1.0, float("nan")])
    h12 = torch.tensor([0.0, 1.0, 0.0, 0.0])
    h22 = torch.tensor([1.0, 1.0, 2.0, 1.0])
    g = torch.ones(4)
    x1, x2 = solve_2x2(h11, h12, h22, g, g)
    assert x1[0] == 0 and x2[0] == 0  # not positive definite
    assert x1[1] == 0 and x2[1] == 0  # singular
    torch.testing.assert_close(torch.stack([x1[2], x2[2]]), torch.tensor([-1.0, -0.5]))
    assert solve_1x1(torch.tensor([0.0, 2.0]), torch.tensor([1.0, 1.0])).tolist() == [0.0, -0.5]


def test_marquardt_floor_gives_a_damped_direction_for_zero_curvature():
    d = marquardt_diag(torch.zeros(3, 1), torch.zeros(3, 1), 1e-6)
    assert bool((d == 1e-6).all())
    step = damped_step(torch.ones(3, 1), torch.zeros(3, 1, 1), torch.ones(3), d)
    assert torch.isfinite(step).all() and bool((step < 0).all())


def test_damping_stays_bounded():
    lam = torch.tensor([1.0, 1.0])
    nu = torch.tensor([2.0, 2.0])
    for _ in range(200):
        lam, nu = update_damping(lam, nu, torch.tensor([False, True]), torch.tensor([0.0, 1.0]))
    assert lam[0] == LAMBDA_MAX and lam[1] == LAMBDA_MIN
    assert nu[0] == NU_MAX and nu[1] == 2.0
    assert torch.isfinite(lam).all()


def test_acceptance_rejects_nan_and_larger_cost():
    new = torch.tensor([1.0, 2.0, float("nan"), 1.0])
    old = torch.tensor([2.0, 1.0, 1.0, 1.0])
    assert accept_step(new, old).tolist() == [True, False, False, True]


def _exp_oracle(x_obs, y_obs):
    """Residuals y − s·exp(−a·x) for M problems; x = (s, log a)."""

    def oracle(p):
        s, a = p[:, :1], torch.exp(p[:, 1:])
        e = torch.exp(-a * x_obs)
        r = y_obs - s * e
        js, jb = -e, s * a * x_obs * e
        cost = (r * r).sum(-1)
        h12 = (js * jb).sum(-1)
        hess = torch.stack([torch.stack([(js * js).sum(-1), h12], -1), torch.stack([h12, (jb * jb).sum(-1)], -1)], -2)
        return LMEval(cost, torch.stack([(js * r).sum(-1), (jb * r).sum(-1)], -1), hess)

    return oracle


def test_driver_recovers_exponentials_batched():
    g = torch.Generator().manual_seed(1)
    m = 64
    s_true = 0.5 + torch.rand(m, 1, generator=g, dtype=torch.float64)
    a_true = torch.exp(torch.rand(m, 1, generator=g, dtype=torch.float64) * 3)
    x_obs = torch.linspace(0, 2, 25, dtype=torch.float64).expand(m, -1)
    y_obs = s_true * torch.exp(-a_true * x_obs)
    x0 = torch.zeros(m, 2, dtype=torch.float64) + torch.tensor([1.0, 0.0], dtype=torch.float64)
    res = levenberg_marquardt(_exp_oracle(x_obs, y_obs), x0, lower=torch.tensor([0.0, -5.0], dtype=torch.float64),
                              upper=torch.tensor([10.0, 10.0], dtype=torch.float64), tol=1e-14, xtol=1e-12, max_iters=200)
    assert res.status == "converged"
    torch.testing.assert_close(res.x[:, :1], s_true, rtol=1e-6, atol=0)
    torch.testing.assert_close(torch.exp(res.x[:, 1:]), a_true, rtol=1e-6, atol=0)


def test_predicted_reduction_is_positive_for_damped_steps():
    g = torch.Generator().manual_seed(2)
    m = torch.randn(100, 2, 2, generator=g, dtype=torch.float64)
    h = m @ m.transpose(1, 2)
    grad = torch.randn(100, 2, generator=g, dtype=torch.float64)
    step = damped_step(grad, h, torch.full((100,), 0.1, dtype=torch.float64), torch.diagonal(h, dim1=1, dim2=2).clamp_min(1e-9))
    assert bool((predicted_reduction(grad, h, step) > 0).all())


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    noise=st.floats(0.0, 0.5),
    start=st.tuples(st.floats(-3.0, 3.0), st.floats(-4.0, 4.0)),
)
def test_hypothesis_accepted_steps_never_raise_the_cost(seed, noise, start):
    g = torch.Generator().manual_seed(seed)
    m = 8
    s_true = torch.rand(m, 1, generator=g, dtype=torch.float64) * 2
    a_true = torch.exp(torch.randn(m, 1, generator=g, dtype=torch.float64))
    x_obs = torch.rand(m, 12, generator=g, dtype=torch.float64) * 3
    y_obs = s_true * torch.exp(-a_true * x_obs) + noise * torch.randn(m, 12, generator=g, dtype=torch.float64)
    x0 = torch.tensor(start, dtype=torch.float64).expand(m, 2).clone()
    res = levenberg_marquardt(_exp_oracle(x_obs, y_obs), x0, lower=torch.tensor([-10.0, -6.0], dtype=torch.float64),
                              upper=torch.tensor([10.0, 6.0], dtype=torch.float64), tol=1e-12, max_iters=60)
    costs = torch.stack(res.costs)
    assert torch.isfinite(costs).all() and torch.isfinite(res.x).all()
    assert bool((costs[1:] <= costs[:-1]).all()), "an accepted step raised the cost"
