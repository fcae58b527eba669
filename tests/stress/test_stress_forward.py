"""Numerical stress of the forward model: phong_render, specular_lobe and the material renderer.

Extremes a user can give: α from 1 to 5000, s from 0 to 10, lights at 0.5° elevation, the light at
the camera, normals pointing down, a 1×1 image, float16/float64 inputs, intensities from 1e-6
to 1e6. Every case must give finite values (and finite gradients) that obey the model's bounds.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchmetal.phong import phong_render, specular_lobe

STRESS = settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
SIZE = (0.1, 0.1)


def flat_normals(h: int, w: int, dtype=torch.float32, z: float = 1.0) -> torch.Tensor:
    n = torch.zeros(3, h, w, dtype=dtype)
    n[2] = z
    return n


def light_at(elev_deg: float, azim_deg: float, *, point: bool, dist: float = 0.3, dtype=torch.float64) -> torch.Tensor:
    e, a = math.radians(elev_deg), math.radians(azim_deg)
    d = [math.cos(e) * math.cos(a), math.sin(a) * math.cos(e), math.sin(e)]
    if point:
        return torch.tensor([[dist * d[0], dist * d[1], dist * d[2], 1.0]], dtype=dtype)
    return torch.tensor([[d[0], d[1], d[2], 0.0]], dtype=dtype)


log_uniform = lambda lo, hi: st.floats(math.log(lo), math.log(hi)).map(math.exp)  # noqa: E731


def upper_bound(texture, s, intensity, light, h, w) -> torch.Tensor:
    """E·(d·max(n·l,0) + s) ≥ the Phong value (the lobe is ≤ 1), flat normals, float64."""
    from torchmetal.geometry import shading_geometry

    g = shading_geometry(flat_normals(h, w, torch.float64), light.double(), intensity.double(),
                         torch.tensor([[0.0, 0.0, 0.3, 1.0]], dtype=torch.float64), SIZE)
    return g.irradiance * (texture.double() * g.n_dot_l.clamp_min(0) + s.double().view(1, 3, 1, 1) * (g.n_dot_l > 0))


@STRESS
@given(
    alpha=log_uniform(1.0, 5000.0),
    s=st.floats(0.0, 10.0),
    elev=st.sampled_from([0.5, 1.0, 5.0, 30.0, 60.0, 89.5, 90.0]),
    azim=st.floats(0.0, 360.0),
    point=st.booleans(),
    intensity=log_uniform(1e-6, 1e6),
    seed=st.integers(0, 2**16),
)
def test_phong_render_extremes_finite_and_bounded(alpha, s, elev, azim, point, intensity, seed):
    h = w = 5
    g = torch.Generator().manual_seed(seed)
    tex = torch.rand(3, h, w, generator=g, dtype=torch.float64)
    light = light_at(elev, azim, point=point)
    inten = torch.full((1, 3), intensity, dtype=torch.float64)
    cam = torch.tensor([[0.0, 0.0, 0.3, 1.0]], dtype=torch.float64)
    s_t = torch.full((3,), s, dtype=torch.float64)
    a_t = torch.full((3,), alpha, dtype=torch.float64)
    ref = phong_render(tex, s_t, a_t, flat_normals(h, w, torch.float64), light, inten, cam, SIZE)
    out = phong_render(tex.float(), s_t.float(), a_t.float(), flat_normals(h, w), light.float(), inten.float(), cam.float(), SIZE)
    assert torch.isfinite(ref).all() and torch.isfinite(out).all()
    assert (ref >= 0).all() and (out >= 0).all()
    bound = upper_bound(tex, s_t, inten, light, h, w)
    assert (ref <= bound * (1 + 1e-12) + 1e-300).all()
    # float32 agrees with float64 to a precision relative to the scene's scale (α·eps near the peak)
    scale = float(bound.max()) or 1.0
    assert float((out.double() - ref).abs().max()) <= 2e-3 * scale


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("alpha", [1.0, 100.0, 5000.0])
def test_light_at_camera_gives_the_full_highlight(dtype, alpha):
    """Directional light and orthographic camera both along n: r·v = 1 exactly → E·(d + s) for any α."""
    h = w = 3
    tex = torch.full((3, h, w), 0.25, dtype=dtype)
    s = torch.tensor([0.0, 1.0, 10.0], dtype=dtype)
    up = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=dtype)
    out = phong_render(tex, s, torch.full((3,), alpha, dtype=dtype), flat_normals(h, w, dtype), up,
                       torch.full((1, 3), 2.0, dtype=dtype), up, SIZE)
    want = 2.0 * (0.25 + s).view(1, 3, 1, 1).expand(1, 3, h, w)
    torch.testing.assert_close(out, want, rtol=1e-6, atol=0)


@pytest.mark.parametrize("point", [True, False])
def test_normals_pointing_down_give_black_and_finite_gradients(point):
    h = w = 4
    tex = torch.rand(3, h, w, dtype=torch.float64, requires_grad=True)
    s = torch.tensor([1.0, 5.0, 10.0], dtype=torch.float64, requires_grad=True)
    log_a = torch.log(torch.tensor([1.0, 100.0, 5000.0], dtype=torch.float64)).requires_grad_()
    light = light_at(45.0, 10.0, point=point)
    out = phong_render(tex, s, log_a.exp(), flat_normals(h, w, torch.float64, z=-1.0), light,
                       torch.ones(1, 3, dtype=torch.float64), torch.tensor([[0.0, 0.0, 0.3, 1.0]], dtype=torch.float64), SIZE)
    assert (out == 0).all()
    out.sum().backward()
    for p in (tex, s, log_a):
        assert torch.isfinite(p.grad).all() and (p.grad == 0).all()


@pytest.mark.parametrize("elev", [-0.5, 0.0, 0.5])
def test_grazing_and_below_horizon_lights(elev):
    """0.5° elevation: tiny but positive n·l; at or below the horizon: exactly black."""
    h = w = 6
    tex = torch.full((3, h, w), 0.5, dtype=torch.float64, requires_grad=True)
    log_a = torch.log(torch.full((3,), 5000.0, dtype=torch.float64)).requires_grad_()
    s = torch.full((3,), 10.0, dtype=torch.float64, requires_grad=True)
    light = light_at(elev, 0.0, point=False)
    out = phong_render(tex, s, log_a.exp(), flat_normals(h, w, torch.float64), light, torch.ones(1, 3, dtype=torch.float64),
                       torch.tensor([[0.0, 0.0, 0.3, 1.0]], dtype=torch.float64), SIZE)
    assert torch.isfinite(out).all()
    if elev <= 0:
        assert (out == 0).all()
    else:
        nl = math.sin(math.radians(elev))
        # the camera sits overhead: no highlight, only the diffuse term d·n·l
        torch.testing.assert_close(out, torch.full_like(out, 0.5 * nl), rtol=1e-9, atol=1e-12)
    out.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in (tex, s, log_a))


def test_one_by_one_image_and_many_shots():
    tex = torch.full((3, 1, 1), 0.3)
    lights = torch.cat([light_at(e, 0.0, point=True).float() for e in (0.5, 30.0, 90.0)])
    cams = torch.tensor([[0.0, 0.0, 0.3, 1.0]]).repeat(3, 1)
    out = phong_render(tex, torch.full((3,), 2.0), torch.full((3,), 50.0), flat_normals(1, 1), lights, torch.ones(3, 3), cams, SIZE)
    assert out.shape == (3, 3, 1, 1)
    assert torch.isfinite(out).all()
    # the overhead light sits at the camera: the centre pixel is the mirror point → E·(d + s)
    torch.testing.assert_close(out[2, :, 0, 0], torch.full((3,), (0.3 + 2.0) / 0.09), rtol=1e-5, atol=0)


@pytest.mark.parametrize("intensity", [1e-6, 1e-3, 1.0, 1e3, 1e6])
def test_output_is_linear_in_intensity(intensity):
    h = w = 4
    tex = torch.rand(3, h, w, generator=torch.Generator().manual_seed(1))
    args = (torch.tensor([0.5, 1.0, 10.0]), torch.tensor([1.0, 300.0, 5000.0]), flat_normals(h, w))
    light, cam = light_at(60.0, 30.0, point=True).float(), torch.tensor([[0.01, 0.0, 0.3, 1.0]])
    one = phong_render(tex, *args, light, torch.ones(1, 3), cam, SIZE)
    out = phong_render(tex, *args, light, torch.full((1, 3), intensity), cam, SIZE)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, one * intensity, rtol=1e-5, atol=0)


@pytest.mark.parametrize("alpha", [1.0, 30.0, 1000.0, 5000.0])
def test_specular_lobe_gradcheck_near_the_peak(alpha):
    q = torch.tensor([1e-7, 1e-5, 1e-4, 3e-3, 0.2, 0.9], dtype=torch.float64).view(-1, 1, 1, 1).requires_grad_()
    a = torch.full((3,), alpha, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(specular_lobe, (q, a), eps=1e-9, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_specular_lobe_gradients_finite_at_singular_points(dtype):
    """q = 0 (mirror), q = 1 (r ⟂ v, the cut-off), q = 2 (anti-mirror); α from 1 to 5000."""
    q = torch.tensor([0.0, 1e-12, 1.0 - 1e-7, 1.0, 1.5, 2.0], dtype=dtype).view(-1, 1, 1, 1).requires_grad_()
    log_a = torch.log(torch.tensor([1.0, 300.0, 5000.0], dtype=dtype)).requires_grad_()
    lobe = specular_lobe(q, log_a.exp())
    assert torch.isfinite(lobe).all() and (lobe >= 0).all() and (lobe <= 1).all()
    assert (lobe[0] == 1).all() and (lobe[3:] == 0).all()
    (lobe * torch.arange(1, 4, dtype=dtype).view(1, 3, 1, 1)).sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(log_a.grad).all()


def test_float16_inputs_match_float64_where_representable():
    h = w = 4
    kw = dict(dtype=torch.float16)
    tex = torch.full((3, h, w), 0.5, **kw)
    light = torch.tensor([[0.01, 0.0, 0.3, 1.0]], **kw)
    cam = torch.tensor([[0.0, 0.0, 0.3, 1.0]], **kw)
    for inten in (1e-6, 1.0, 100.0):  # E·(d + s) ≤ 1.2e4 < 65504
        for alpha in (1.0, 100.0, 5000.0):
            args = [tex, torch.full((3,), 10.0, **kw), torch.full((3,), alpha, **kw), flat_normals(h, w, torch.float16),
                    light, torch.full((1, 3), inten, **kw), cam]
            half = phong_render(*args, SIZE)
            ref = phong_render(*[a.double() for a in args], SIZE)
            assert half.dtype == torch.float16
            assert torch.isfinite(half).all()
            assert float((half.double() - ref).abs().max()) <= 1e-2 * float(ref.abs().max())


def test_float16_irradiance_overflow_is_never_nan():
    """6e4 W/sr at 0.3 m is 6.7e5 irradiance: beyond float16. Inf is honest, NaN is not."""
    h = w = 2
    kw = dict(dtype=torch.float16)
    out = phong_render(torch.full((3, h, w), 0.5, **kw), torch.ones(3, **kw), torch.full((3,), 5.0, **kw),
                       flat_normals(h, w, torch.float16, z=-1.0), torch.tensor([[0.01, 0.0, 0.3, 1.0]], **kw),
                       torch.full((1, 3), 6e4, **kw), torch.tensor([[0.0, 0.0, 0.3, 1.0]], **kw), SIZE)
    assert not torch.isnan(out).any()


@pytest.mark.parametrize("elev", [0.5, 45.0, 90.0])
def test_material_renderer_with_flakes_is_finite_at_extremes(elev):
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.material import Material
    from torchmetal.renderer import MaterialRenderer

    h = w = 16
    mat = Material(texture=torch.full((3, h, w), 0.3), s=torch.tensor([10.0, 1.0, 0.0]),
                   alpha=torch.tensor([1.0, 300.0, 5000.0]), size=SIZE, flakes=FlakeModel(density=0.05, glint_sigma=1e-3))
    r = MaterialRenderer(mat)
    light = torch.cat([light_at(elev, 20.0, point=True).float(), light_at(elev, 20.0, point=False).float()])
    cams = torch.tensor([[0.0, 0.0, 0.3, 1.0], [0.0, 0.0, 1.0, 0.0]])
    for inten in (1e-6, 1.0, 1e6):
        out = r(light, torch.full((2, 3), inten), cams)
        assert out.shape == (2, 3, h, w)
        assert torch.isfinite(out).all() and (out >= 0).all()
