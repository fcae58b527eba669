"""The paper's scheme (4.1): control points, the batched per-channel LM, the iteration."""

import math

import torch

from tests.fit.helpers import rel_err, synth
from torchmetal.fit.paper import BinSums, N_BINS, bin_index, bins_of, fit_control_points, paper_pass, paper_scheme, _new_cache
from torchmetal.fit.problem import LOG_OFF, build_observations


def test_bin_index_ranges():
    q = torch.tensor([0.0, 1e-7, 1e-6, 1e-3, 0.5, 0.999999])
    L = torch.log1p(-q)
    b = bin_index(L)
    assert b[0] == 0 and b[1] == 0
    assert bool((b[2:] >= 1).all()) and bool((b[2:] <= N_BINS).all())
    assert bool((b[2:].diff() >= 0).all())
    assert int(bin_index(torch.tensor([LOG_OFF]))[0]) == N_BINS + 1


def test_control_point_lm_recovers_exact_lobes():
    L = torch.log(torch.linspace(0.3, 1.0, 200, dtype=torch.float64)).expand(3, -1)
    s_true = torch.tensor([0.2, 0.6, 1.5], dtype=torch.float64)
    a_true = torch.tensor([3.0, 80.0, 900.0], dtype=torch.float64)
    c = s_true.view(3, 1) * torch.exp(a_true.view(3, 1) * L)
    use = torch.ones_like(c, dtype=torch.bool)
    beta0 = torch.full((3,), math.log(20.0), dtype=torch.float64)
    s, beta = fit_control_points((use, c, L), torch.ones(3, dtype=torch.float64), beta0)
    torch.testing.assert_close(s, s_true, rtol=1e-7, atol=0)
    torch.testing.assert_close(torch.exp(beta), a_true, rtol=1e-7, atol=0)


def test_bin_sums_average_per_channel():
    bs = BinSums(4, torch.device("cpu"))
    b = torch.tensor([[[0, 1, 1, 5]]])
    ok = torch.ones(1, 3, 4, dtype=torch.bool)
    ok[0, 2, 0] = False
    target = torch.arange(12, dtype=torch.float32).view(1, 3, 4)
    bs.add(b, ok, target, torch.zeros(1, 1, 4))
    use, mean, _ = bs.control_points(min_count=1)
    assert mean[0, 1] == 1.5 and mean[1, 0] == 4.0 and not use[2, 0] and use[2, 5]


def test_paper_scheme_noise_free_converges():
    r = synth(size=40, shots=12, seed=0)
    obs = build_observations(r.capture)
    log = []
    pf = paper_scheme(obs, tol=1e-6, max_iters=100, on_iter=lambda *a: log.append(a))
    assert pf.status == "converged"
    assert log[0][0] == "init" and log[-1][0] == "paper"
    assert rel_err(pf.s, r.truth["s"]) < 2e-3 and rel_err(pf.alpha, r.truth["alpha"]) < 2e-3
    tex = pf.texture.view(3, 40, 40)
    assert float((tex - r.truth["texture"]).abs().max()) < 2e-3
    errs = [h["rmse"] for h in pf.history]
    assert errs[-1] < 0.1 * errs[0]  # T⁰ → converged


def test_static_chunks_are_cached_without_changing_the_result():
    r = synth(size=32, shots=6, seed=1, alpha=(2000.0, 2000.0, 2000.0), layout="near")
    obs = build_observations(r.capture, chunk=32)
    bidx = bins_of(obs)
    s = torch.tensor([0.6, 0.6, 0.6], dtype=torch.float64)
    alpha = torch.tensor([2000.0, 2000.0, 2000.0], dtype=torch.float64)
    cache = _new_cache(obs, alpha)
    assert 0 < int(cache.static.sum()) < len(obs.chunks)  # narrow highlights: some chunks never lit
    t_ref, e_ref, b_ref, _ = paper_pass(obs, bidx, s, alpha)
    t1, e1, b1, f1 = paper_pass(obs, bidx, s, alpha, cache=cache)
    t2, e2, b2, f2 = paper_pass(obs, bidx, s, alpha, prev=t1, cache=cache)
    assert f1 == 1.0 and f2 < 1.0
    for t, e, b in ((t1, e1, b1), (t2, e2, b2)):
        torch.testing.assert_close(t, t_ref)
        assert math.isclose(e, e_ref, rel_tol=1e-9, abs_tol=1e-15)
        torch.testing.assert_close(b.sums, b_ref.sums, rtol=1e-6, atol=1e-9)
