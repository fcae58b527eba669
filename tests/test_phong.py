"""Phong forward model: reference values, module == function, finite gradients."""

import numpy as np
import pytest
import torch

from tests.test_geometry import numpy_geometry, random_config
from torchmetal.geometry import shading_geometry
from torchmetal.phong import PhongModel, log1p_exact, phong_render, phong_shading, specular_lobe


def numpy_phong(texture, s, alpha, n, L, I, C, size):
    out = []
    for _l, _v, nl, rv, E in numpy_geometry(n, L, I, C, size):
        lobe = np.maximum(rv, 0.0)[None] ** alpha[:, None, None]
        out.append(E * (texture * np.maximum(nl, 0) + (nl > 0) * s[:, None, None] * lobe))
    return np.stack(out)


@pytest.mark.parametrize("grazing", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_float64_reference(seed, grazing):
    rng = np.random.default_rng(seed)
    n, L, I, C = random_config(rng, grazing=grazing)
    tex = rng.uniform(0, 1, size=n.shape)
    s = np.array([0.3, 1.0, 4.0])
    alpha = np.array([1.0, 40.0, 3000.0])
    got = phong_render(*(torch.from_numpy(x) for x in (tex, s, alpha, n, L, I, C)), (0.1, 0.1))
    ref = numpy_phong(tex, s, alpha, n, L, I, C, (0.1, 0.1))
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-6 * max(1.0, np.abs(ref).max()))


def test_lobe_precision_near_peak_float32():
    q64 = torch.logspace(-9, -2, 200, dtype=torch.float64)
    alpha = torch.tensor([1000.0, 1000.0, 1000.0])
    exact = (1 - q64) ** 1000
    got = specular_lobe(q64.float().view(-1, 1, 1, 1), alpha)[:, 0, 0, 0].double()
    assert (got - exact).abs().max() < 1e-5


def test_lobe_zero_past_horizon_and_finite_grad():
    q = torch.tensor([0.0, 0.5, 1.0, 1.5, 2.0], dtype=torch.float64).view(-1, 1, 1, 1).requires_grad_()
    alpha = torch.tensor([1.0, 100.0, 1e4], dtype=torch.float64, requires_grad=True)
    lobe = specular_lobe(q, alpha)
    assert torch.all(lobe[2:] == 0)
    lobe.sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(alpha.grad).all()


def test_log1p_exact():
    y = torch.tensor([0.0, 1e-12, -1e-8, -0.5, 3.0], dtype=torch.float64)
    np.testing.assert_allclose(log1p_exact(y).numpy(), np.log1p(y.numpy()), rtol=1e-12)


def test_gradcheck_float64():
    rng = np.random.default_rng(0)
    n, L, I, C = (torch.from_numpy(x) for x in random_config(rng, b=3, h=3, w=3))
    geom = shading_geometry(n, L, I, C, (0.1, 0.1))
    tex = torch.rand(3, 3, 3, dtype=torch.float64, requires_grad=True)
    s = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64, requires_grad=True)
    beta = torch.tensor([1.0, 3.0, 6.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t, s_, b: phong_shading(t, s_, torch.exp(b), geom), (tex, s, beta))


def test_gradients_finite_at_grazing_and_huge_alpha():
    n = torch.zeros(3, 2, 2, dtype=torch.float64)
    n[2] = 1
    L = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)  # n·l = 0, overhead
    C = torch.tensor([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=torch.float64)  # r·v = 1, r·v = 0
    m = PhongModel(torch.rand(3, 2, 2, dtype=torch.float64), torch.ones(3, dtype=torch.float64),
                   torch.tensor([1.0, 1e3, 1e4], dtype=torch.float64), n)
    m(L, torch.ones(2, 3, dtype=torch.float64), C).sum().backward()
    for p in m.parameters():
        assert torch.isfinite(p.grad).all()


def test_module_equals_function():
    rng = np.random.default_rng(4)
    n, L, I, C = (torch.from_numpy(x).float() for x in random_config(rng))
    tex, s, a = torch.rand(3, 5, 7), torch.tensor([0.5, 0.6, 0.7]), torch.tensor([10.0, 50.0, 200.0])
    m = PhongModel(tex, s, a, n, (0.1, 0.1))
    torch.testing.assert_close(m(L, I, C), phong_render(tex, s, a, n, L, I, C, (0.1, 0.1)))


def test_spatially_varying_maps_broadcast_like_globals():
    rng = np.random.default_rng(6)
    n, L, I, C = (torch.from_numpy(x).float() for x in random_config(rng))
    tex, s, a = torch.rand(3, 5, 7), torch.tensor([0.5, 0.6, 0.7]), torch.tensor([10.0, 50.0, 200.0])
    maps = phong_render(tex, s[:, None, None].expand(3, 5, 7), a[:, None, None].expand(3, 5, 7), n, L, I, C, (0.1, 0.1))
    torch.testing.assert_close(maps, phong_render(tex, s, a, n, L, I, C, (0.1, 0.1)))


def _overflow_geometry(dtype):
    """2×2 pixels, one shot: left column facing the light, right column facing away; E = inf."""
    n = torch.zeros(3, 2, 2, dtype=dtype)
    n[2, :, 0], n[2, :, 1] = 1.0, -1.0
    light = torch.tensor([[0.01, 0.0, 0.3, 1.0]], dtype=dtype)
    cam = torch.tensor([[0.0, 0.0, 0.3, 1.0]], dtype=dtype)
    geom = shading_geometry(n, light, torch.ones(1, 3, dtype=dtype), cam, (0.1, 0.1))
    geom.irradiance = torch.full_like(geom.irradiance, float("inf"))
    return geom


def test_overflowed_irradiance_is_inf_where_lit_and_zero_where_dark():
    geom = _overflow_geometry(torch.float16)
    out = phong_shading(torch.full((3, 2, 2), 0.5, dtype=torch.float16), torch.ones(3, dtype=torch.float16),
                        torch.full((3,), 5.0, dtype=torch.float16), geom)
    assert out.dtype == torch.float16 and not torch.isnan(out).any()
    assert torch.isinf(out[..., 0]).all() and (out[..., 1] == 0).all()


def test_overflowed_irradiance_gives_finite_gradients_where_dark():
    geom = _overflow_geometry(torch.float64)
    dark = geom.n_dot_l[0, 0] <= 0
    geom.n_dot_l = torch.where(dark, geom.n_dot_l, -geom.n_dot_l)  # every pixel faces away
    tex = torch.full((3, 2, 2), 0.5, dtype=torch.float64, requires_grad=True)
    s = torch.ones(3, dtype=torch.float64, requires_grad=True)
    alpha = torch.full((3,), 5.0, dtype=torch.float64, requires_grad=True)
    out = phong_shading(tex, s, alpha, geom)
    assert (out == 0).all()
    out.sum().backward()
    for g in (tex.grad, s.grad, alpha.grad):
        assert torch.isfinite(g).all()


def test_zero_texture_keeps_its_gradient_under_finite_irradiance():
    """The overflow guard must not touch finite irradiance: d(out)/d(texture) = E·n·l even where
    the texture (and so the shading term) is 0."""
    rng = np.random.default_rng(4)
    n, L, I, C = (torch.from_numpy(x) for x in random_config(rng, b=2, h=3, w=3))
    geom = shading_geometry(n, L, I, C, (0.1, 0.1))
    tex = torch.zeros(3, 3, 3, dtype=torch.float64, requires_grad=True)
    phong_shading(tex, torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64), geom).sum().backward()
    expected = (geom.irradiance * geom.n_dot_l.clamp_min(0.0)).sum(0)
    torch.testing.assert_close(tex.grad, expected)


def test_the_plane_path_without_gradients_matches_the_autograd_path():
    """phong_render without a gradient uses the plane's separable terms (phong._plane_phong); with one, the
    vector geometry: the same values, normal maps and spatially varying α up to the thousands included."""
    rng = np.random.default_rng(11)
    n, L, I, C = (torch.from_numpy(x) for x in random_config(rng, grazing=True))
    tex = torch.rand(3, *n.shape[1:], dtype=torch.float64)
    s = torch.tensor([0.3, 1.0, 4.0], dtype=torch.float64)
    a = torch.tensor([1.0, 40.0, 3000.0], dtype=torch.float64)[:, None, None].expand(3, *n.shape[1:]).clone()
    with torch.no_grad():
        plane = phong_render(tex, s, a, n, L, I, C, (0.1, 0.1))
    tex_g = tex.clone().requires_grad_(True)
    vector = phong_render(tex_g, s, a, n, L, I, C, (0.1, 0.1))
    torch.testing.assert_close(plane, vector.detach(), rtol=1e-10, atol=1e-12)
    vector.sum().backward()
    assert tex_g.grad is not None and bool(torch.isfinite(tex_g.grad).all())


def test_the_plane_path_keeps_the_overflow_rule():
    """An irradiance that overflows float32 (intensity 3e38 at 0.3 units) is inf where the surface is lit and 0
    where it faces away, through phong_render's plane path as through phong_shading."""
    n = torch.zeros(3, 2, 2)
    n[2, :, 0], n[2, :, 1] = 1.0, -1.0
    light = torch.tensor([[0.01, 0.0, 0.3, 1.0]])
    cam = torch.tensor([[0.0, 0.0, 0.3, 1.0]])
    with torch.no_grad():
        out = phong_render(torch.full((3, 2, 2), 0.5), torch.ones(3), torch.full((3,), 10.0), n, light,
                           torch.full((1, 3), 3e38), cam, (0.1, 0.1))
    assert bool(torch.isinf(out[..., 0]).all()) and bool((out[..., 1] == 0).all())
