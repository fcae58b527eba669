"""Analytic Jacobians and the variable-projection terms against autograd (float64)."""

import torch
from torch.func import jvp

from tests.fit.helpers import synth
from torchmetal.fit.problem import build_observations
from torchmetal.fit.refine import element_terms, model_terms, spec_sums
from torchmetal.geometry import shading_geometry
from torchmetal.phong import phong_shading


def _setup(size=6, shots=5, seed=0):
    r = synth(size=size, shots=shots, seed=seed, layout="near", bumpy=True)
    cap = r.capture.to(dtype=torch.float64)
    obs = build_observations(cap)
    tex = r.truth["texture"].double()
    return cap, obs, tex


def test_per_observation_jacobian_matches_jvp():
    cap, obs, tex = _setup()
    s = torch.tensor([0.4, 0.7, 1.1], dtype=torch.float64)
    beta = torch.log(torch.tensor([3.0, 30.0, 300.0], dtype=torch.float64))
    geom = shading_geometry(cap.normals, cap.lights, cap.intensities, cap.cameras, cap.size)

    def render(t, s_, b_):
        return phong_shading(t, s_, torch.exp(b_), geom).reshape(cap.num_shots, 3, -1)

    a, b, db = model_terms(obs, torch.exp(beta).view(1, 3))
    dtex = torch.randn(tex.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    _, jd = jvp(render, (tex, s, beta), (dtex, torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)))
    torch.testing.assert_close(jd, a * dtex.reshape(1, 3, -1), rtol=1e-10, atol=1e-14)
    for c in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[c] = 1.0
        _, js = jvp(render, (tex, s, beta), (torch.zeros_like(tex), e, torch.zeros(3, dtype=torch.float64)))
        _, jb = jvp(render, (tex, s, beta), (torch.zeros_like(tex), torch.zeros(3, dtype=torch.float64), e))
        torch.testing.assert_close(js[:, c], b[:, c], rtol=1e-10, atol=1e-14)
        torch.testing.assert_close(jb[:, c], s[c] * db[:, c], rtol=1e-10, atol=1e-14)


def _dense_gn(obs, tex, s, beta, c):
    """Full Gauss–Newton system of channel c over (d_1..d_P, s, β) by autograd."""
    w = obs.valid[:, c].double()
    y = obs.y[:, c].double()

    def resid(params):
        d, sc, bc = params[:-2], params[-2], params[-1]
        a, b, _ = model_terms(obs, torch.exp(torch.stack([bc] * 3)).view(1, 3))
        return (w.sqrt() * (y - a[:, c] * d - sc * b[:, c])).reshape(-1)

    x = torch.cat([tex, torch.stack([s, beta])])
    jac = torch.autograd.functional.jacobian(resid, x)
    return jac, resid(x)


def test_variable_projection_terms_equal_the_schur_complement():
    cap, obs, _ = _setup(seed=1)
    alpha = torch.tensor([4.0, 40.0, 150.0], dtype=torch.float64)
    stats, eb, _ = spec_sums(obs, alpha.view(1, 3))
    A = obs.element_sum(obs.A, 1)
    s, cost, g, h = element_terms(stats, A)
    B, C, Bc, Cc, Yc, _ = stats.unbind(0)
    d_opt = obs.d0 - s.view(3, 1) * eb  # texture at the optimum for this α
    for c in range(3):
        jac, r = _dense_gn(obs, d_opt[c], s[0, c], torch.log(alpha[c]), c)
        p = obs.num_pixels
        m = jac.T @ jac
        u, wlin, v = m[:p, :p], m[:p, p:], m[p:, p:]
        schur = v - wlin.T @ torch.linalg.pinv(u) @ wlin  # tiny dense reference
        torch.testing.assert_close(C[0, c], schur[0, 0], rtol=1e-8, atol=1e-14)
        torch.testing.assert_close(s[0, c] * Bc[0, c], schur[0, 1], rtol=1e-8, atol=1e-14)
        torch.testing.assert_close(s[0, c] ** 2 * Cc[0, c], schur[1, 1], rtol=1e-8, atol=1e-14)
        grad = jac.T @ r  # J = ∂r/∂x: g = Jᵀ W r
        assert float(grad[:p].abs().max()) < 1e-12  # texture optimal
        assert abs(float(grad[p])) < 1e-10  # s optimal
        torch.testing.assert_close(g[0, c], grad[p + 1], rtol=1e-8, atol=1e-14)
        torch.testing.assert_close(cost[0, c], (r * r).sum(), rtol=1e-8, atol=1e-14)


def test_profile_gradient_matches_finite_differences():
    _, obs, _ = _setup(seed=2)
    A = obs.element_sum(obs.A, 1)
    beta = torch.log(torch.tensor([5.0, 25.0, 120.0], dtype=torch.float64))

    def profile(bt):
        stats, _, _ = spec_sums(obs, torch.exp(bt).view(1, 3))
        return element_terms(stats, A)

    _, _, g, _ = profile(beta)
    h = 1e-6
    for c in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[c] = h
        fd = (profile(beta + e)[1] - profile(beta - e)[1])[0, c] / (2 * h)
        torch.testing.assert_close(2 * g[0, c], fd, rtol=1e-5, atol=1e-12)
