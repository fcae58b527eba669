"""The numeric GGX fit: reference values, self-consistency, the textbook mapping, bad input."""

import math

import numpy as np
import pytest
import torch

from torchmetal.errors import ExportError
from torchmetal.formats.lobe_fit import (
    capture_views,
    fit_glint,
    fit_lobe,
    ggx_terms,
    lobe_directions,
    lobe_target,
    phong_cone,
    phong_target,
    textbook_roughness,
)


def test_textbook_mapping_reference():
    # α = 100: Blinn 400, α_GGX = √(2/402), roughness = √α_GGX
    assert textbook_roughness(100.0) == pytest.approx(math.sqrt(math.sqrt(2.0 / 402.0)), rel=1e-12)


def test_ggx_albedo_below_one_and_near_one_for_smooth():
    """∫ D·V·(n·l) dω_l ≤ 1 (a white furnace), ≈ 1 for a smooth lobe seen from above."""
    k = 200_000
    g = torch.Generator().manual_seed(0)
    u1, u2 = torch.rand(k, generator=g, dtype=torch.float64), torch.rand(k, generator=g, dtype=torch.float64)
    z = u1  # uniform on the hemisphere: pdf 1/(2π)
    r = torch.sqrt(1 - z * z)
    l = torch.stack([r * torch.cos(2 * math.pi * u2), r * torch.sin(2 * math.pi * u2), z], -1)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    # single-scattering GGX loses energy as it gets rough (and towards grazing views)
    for rough, view, lo in ((0.3, [0.0, 0.0, 1.0], 0.97), (0.3, [0.6, 0.0, 0.8], 0.95), (0.7, [0.6, 0.0, 0.8], 0.6)):
        v = torch.tensor(view, dtype=torch.float64).expand(k, 3)
        lobe, _ = ggx_terms(l, v, n, rough)  # π·D·V·n·l
        albedo = float(lobe.mean() * 2 * math.pi / math.pi)
        assert lo < albedo <= 1.01, (rough, view, albedo)


def test_numpy_and_torch_agree():
    l, v = lobe_directions(0.6)
    n = torch.zeros_like(l)
    n[:, 2] = 1
    a, sa = ggx_terms(l, v, n, 0.3)
    b, sb = ggx_terms(l.numpy(), v.numpy(), n.numpy(), 0.3)
    np.testing.assert_allclose(a.numpy(), b, rtol=1e-12)
    np.testing.assert_allclose(sa.numpy(), sb, rtol=1e-12)


def test_directions_are_unit_above_horizon_and_cover_the_cone():
    cone = 0.5
    l, v = lobe_directions(cone, per_view=400)
    assert torch.allclose(l.norm(dim=-1), torch.ones(len(l), dtype=l.dtype)) and bool((l[:, 2] > 0).all())
    mirror = torch.stack([-v[:, 0], -v[:, 1], v[:, 2]], -1)
    dev = torch.acos((l * mirror).sum(-1).clamp(-1, 1))
    assert float(dev.max()) <= cone + 1e-9 and float(dev.max()) > 0.95 * cone
    # uniform in solid angle: mean cos of the deviation = (1 + cos cone)/2
    assert float(torch.cos(dev[: 400]).mean()) == pytest.approx((1 + math.cos(cone)) / 2, abs=2e-3)


def test_torchmetal_ggx_lobe_is_recovered():
    """torchmetal's GGX lobe (k = m² = 2/(α + 2), Schlick F with F0 = 0.04) is a GGX lobe of
    roughness k^¼: the fit finds it (the Smith forms differ slightly: separable vs height-correlated)."""
    alpha = 60.0
    fit = fit_lobe(torch.full((3,), 0.2), torch.full((3,), alpha), "ggx")
    assert fit.textbook_roughness == pytest.approx((2 / (alpha + 2)) ** 0.25, rel=1e-12)
    assert fit.roughness == pytest.approx(fit.textbook_roughness, rel=0.01)
    assert fit.max_error < 0.01, fit.error
    assert fit.f90 == pytest.approx(25 * fit.f0[0], rel=0.05)  # Schlick with F0 = 0.04: F90/F0 = 25
    # a coloured s needs a F90 per channel; glTF has one (specularFactor): the fit shares it
    coloured = fit_lobe(torch.tensor([0.1, 0.2, 0.3]), torch.full((3,), alpha), "ggx")
    assert coloured.roughness == pytest.approx(fit.roughness, rel=0.01) and min(coloured.error) < 0.01


def test_target_is_the_renderer_lobe():
    """The fit's target is torchmetal's own lobe: compare with a 1-pixel render."""
    from torchmetal.lobes import lobe_render

    l = torch.tensor([[0.3, 0.1, math.sqrt(1 - 0.1)]], dtype=torch.float64)
    v = torch.tensor([[-0.25, -0.05, math.sqrt(1 - 0.065)]], dtype=torch.float64)
    s, a = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64), torch.tensor([30.0, 40.0, 50.0], dtype=torch.float64)
    for kind in ("phong", "blinn", "ggx"):
        img = lobe_render(torch.zeros(3, 1, 1, dtype=torch.float64), s, a, torch.tensor([0.0, 0, 1], dtype=torch.float64).view(3, 1, 1),
                          torch.cat([l, torch.zeros(1, 1, dtype=torch.float64)], 1), torch.ones(1, 3, dtype=torch.float64),
                          torch.cat([v, torch.zeros(1, 1, dtype=torch.float64)], 1), (1.0, 1.0), lobe=kind)
        torch.testing.assert_close(lobe_target(kind, s, a)(l, v), img.reshape(1, 3))


@pytest.mark.parametrize("alpha", [10.0, 100.0, 1000.0])
def test_phong_fit_beats_the_textbook_mapping(alpha):
    fit = fit_lobe(torch.tensor([0.2, 0.2, 0.2]), torch.tensor([alpha] * 3))
    assert fit.textbook_roughness is not None
    assert max(fit.error) < min(fit.textbook_error)
    assert max(fit.error) < 0.32  # measured 0.27-0.28: the GGX tails vs the Phong lobe
    assert 0.5 < fit.roughness / fit.textbook_roughness < 1.5


def test_roughness_falls_with_the_exponent_and_f0_scales_with_s():
    r = [fit_lobe(torch.ones(3), torch.full((3,), a)).roughness for a in (5.0, 50.0, 500.0)]
    assert r[0] > r[1] > r[2]
    f1 = fit_lobe(torch.full((3,), 0.1), torch.full((3,), 50.0))
    f2 = fit_lobe(torch.full((3,), 0.2), torch.full((3,), 50.0))
    assert f2.f0[0] == pytest.approx(2 * f1.f0[0], rel=1e-6) and f2.roughness == pytest.approx(f1.roughness, rel=1e-6)


def test_blinn_and_glint_targets():
    b = fit_lobe(torch.full((3,), 0.2), torch.full((3,), 200.0), "blinn")
    p = fit_lobe(torch.full((3,), 0.2), torch.full((3,), 50.0), "phong")
    assert b.roughness == pytest.approx(p.roughness, rel=0.25)  # Blinn n ≈ 4·Phong α
    g_narrow, g_wide = fit_glint((1, 1, 1), 0.03), fit_glint((1, 1, 1), 0.1)
    assert g_narrow.roughness < g_wide.roughness and g_narrow.max_error < 0.4


def test_no_specular_is_zero():
    fit = fit_lobe(torch.zeros(3), torch.full((3,), 10.0))
    assert fit.f0 == (0.0, 0.0, 0.0) and fit.error == (0.0, 0.0, 0.0)


def test_phong_target_matches_definition():
    l = torch.tensor([[0.3, 0.0, math.sqrt(1 - 0.09)]], dtype=torch.float64)
    v = torch.tensor([[-0.2, 0.1, math.sqrt(1 - 0.05)]], dtype=torch.float64)
    r = torch.tensor([-l[0, 0], -l[0, 1], l[0, 2]])
    got = phong_target(torch.tensor([0.5, 0.5, 0.5]), torch.tensor([20.0, 20.0, 20.0]))(l, v)
    assert float(got[0, 0]) == pytest.approx(0.5 * float(r @ v[0]) ** 20, rel=1e-9)
    assert phong_cone(10.0) == pytest.approx(math.acos(1e-3 ** 0.1))


@pytest.mark.parametrize("call, match", [
    (lambda: fit_lobe(torch.tensor([0.1, float("nan"), 0.1]), torch.ones(3)), "finite"),
    (lambda: fit_lobe(torch.ones(3), torch.ones(3), "cook"), "lobe: expected one of"),
    (lambda: lobe_directions(0.3, torch.tensor([[0.0, 0.0, -1.0]])), "above the surface"),
])
def test_bad_input_one_line(call, match):
    with pytest.raises(ExportError, match=match):
        call()


def test_capture_views():
    cams = torch.tensor([[0.0, 0.0, 0.3, 1.0], [0.0, 0.0, 2.0, 1.0], [1.0, 0.0, 1.0, 0.0], [1.0, 0.0, -0.2, 0.0]])
    v = capture_views(cams)
    assert v.shape == (2, 3) and torch.allclose(v.norm(dim=-1), torch.ones(2, dtype=v.dtype))
    near = fit_lobe(torch.full((3,), 0.2), torch.full((3,), 50.0), views=capture_views(cams[:1]))
    wide = fit_lobe(torch.full((3,), 0.2), torch.full((3,), 50.0))
    assert near.max_error < wide.max_error  # one view (normal incidence) is easier to match than 0-60°
    with pytest.raises(ExportError, match="above the surface"):
        capture_views(cams[3:])
