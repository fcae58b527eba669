"""Engine maps and the glTF BRDF evaluator against torchmetal's renderer."""

import math

import pytest
import torch

from tests.formats.kinds import KINDS, SIZE, make_material
from torchmetal.formats.engine import EngineMaterial, check_lights, engine_material, engine_render, render_error
from torchmetal.formats.lobe_fit import fit_lobe
from torchmetal.phong import phong_render


def test_diffuse_only_matches_lambert_exactly():
    tex = torch.rand(3, 6, 7)
    n = torch.zeros(3, 6, 7)
    n[2] = 1
    em = EngineMaterial(base_color=tex, roughness=torch.full((1, 6, 7), 0.5), f0=torch.zeros(3, 6, 7),
                        f90=torch.zeros(1, 6, 7), normal=n, size=SIZE)
    light, inten, cam = check_lights(SIZE)
    ref = phong_render(tex, torch.zeros(3), torch.ones(3), n, light, inten, cam, SIZE)
    torch.testing.assert_close(engine_render(em, light, inten, cam), ref, rtol=1e-5, atol=1e-6)


def test_global_maps_are_the_fit():
    m = make_material("flat-global-noflakes")
    em = engine_material(m)
    fit = fit_lobe(m.s, m.alpha)
    assert torch.allclose(em.roughness, torch.full_like(em.roughness, fit.roughness), rtol=1e-5)
    assert torch.allclose(em.f0[:, 0, 0], torch.tensor(fit.f0, dtype=torch.float32), rtol=1e-4)
    keep = 1 - em.f0.max(0, keepdim=True).values
    torch.testing.assert_close(em.base_color, (m.texture / keep).clamp(0, 1))
    assert em.extras["lobe_fit"][0]["error"] == pytest.approx(list(fit.error))


def test_clustered_maps_follow_the_labels():
    m = make_material("flat-clustered-noflakes")
    em = engine_material(m)
    lab = m.spec_labels
    r0, r1 = em.roughness[0][lab == 0], em.roughness[0][lab == 1]
    assert bool((r0 == r0[0]).all()) and bool((r1 == r1[0]).all()) and float(r0[0]) > float(r1[0])  # α 15 rougher than α 100
    assert len(em.extras["lobe_fit"]) == 2


@pytest.mark.parametrize("kind", KINDS)
def test_engine_render_is_close_to_torchmetal(kind):
    m = make_material(kind)
    em = engine_material(m)
    err = render_error(em, m, *check_lights(m.size))
    assert err < 0.3, err  # the lobe-shape error on the specular part, diluted by the exact diffuse


def test_per_pixel_gloss_maps_are_binned():
    m = make_material("flat-global-noflakes")
    h, w = m.height, m.width
    a_map = torch.exp(torch.linspace(math.log(40), math.log(300), h * w)).reshape(1, h, w).expand(3, h, w)
    s_map = torch.full((3, h, w), 0.2)
    m.specular_maps = lambda: (s_map, a_map)  # a material with gloss maps (per-pixel α)
    em = engine_material(m)
    r = em.roughness.reshape(-1)
    assert bool(torch.isfinite(r).all()) and float(r[0]) > float(r[-1])
    assert 16 < len(em.extras["lobe_fit"]) <= 64 + 1  # ln(300/40)·16 ≈ 32 bins


def test_lobe_field_is_used():
    m = make_material("flat-global-noflakes")
    m.lobe = "blinn"
    em = engine_material(m)
    assert em.extras["lobe"] == "blinn" and em.extras["lobe_fit"][0]["lobe"] == "blinn"


def test_ggx_lobe_material():
    """A material fitted with torchmetal's GGX lobe exports at its own roughness k^¼, k = 2/(α + 2)."""
    m = make_material("flat-global-noflakes")
    m.lobe, m.s, m.alpha = "ggx", torch.full((3,), 0.2), torch.full((3,), 80.0)
    em = engine_material(m)
    fit = em.extras["lobe_fit"][0]
    assert fit["lobe"] == "ggx" and fit["roughness"] == pytest.approx((2 / 82) ** 0.25, rel=0.01)
    assert max(fit["error"]) < 0.01
    assert render_error(em, m, *check_lights(m.size)) < 0.03


def test_non_finite_specular_is_one_line(tmp_path):
    from torchmetal.cli import main
    from torchmetal.errors import ExportError
    from torchmetal.material import save_material

    m = make_material("flat-global-noflakes")
    m.alpha = torch.tensor([10.0, float("inf"), 10.0])
    with pytest.raises(ExportError, match="expected finite s and alpha"):
        engine_material(m)
    m.alpha = torch.tensor([10.0, 20.0, 10.0])
    mat = save_material(m, tmp_path / "mat")
    m.s = torch.tensor([0.1, float("nan"), 0.1])
    with pytest.raises(ExportError, match="finite"):
        engine_material(m)
    assert main(["export", str(mat), "--format", "glb"]) == 0  # the saved (finite) one exports
