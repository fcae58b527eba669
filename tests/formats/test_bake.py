"""Flake baking: texels, layouts, texel density, bad input."""

import pytest
import torch

from tests.formats.kinds import make_material
from torchmetal.errors import ExportError
from torchmetal.flakes.model.field import flake_field
from torchmetal.formats.engine import engine_material, engine_render
from torchmetal.renderer import MaterialRenderer


def test_flake_texels_carry_the_flake_normals():
    m = make_material("bumpy-global-flakes")
    em = engine_material(m, flakes="base")
    f = flake_field(m.flakes, m.height, m.width, m.flat_normals())
    flake = f.weight[0] >= 0.5
    assert int(flake.sum()) > 0
    torch.testing.assert_close(em.normal[:, flake], f.normal[:, flake].float())
    torch.testing.assert_close(em.normal[:, ~flake], m.normals[:, ~flake], atol=1e-6, rtol=0)
    assert em.coat is None and em.extras["flake_bake"]["mode"] == "base"
    assert em.extras["flakes"] == m.flakes.to_dict()


def test_clearcoat_layout_and_auto_choice():
    m = make_material("flat-global-flakes")
    cc = engine_material(m, flakes="clearcoat")
    assert cc.coat is not None and float(cc.coat.weight.max()) <= 1.0
    f = flake_field(m.flakes, m.height, m.width)
    assert float(cc.f0[:, f.weight[0] < 0.5].abs().max()) == 0.0  # the base holds only the flakes
    auto = engine_material(m)
    errs = auto.extras["flake_bake"]["render_error"]
    assert set(errs) == {"base", "clearcoat", "flake_clearcoat"}
    assert auto.extras["flake_bake"]["mode"] == min(errs, key=errs.get)
    no_coat_normals = engine_material(m, coat_normals=False)
    assert set(no_coat_normals.extras["flake_bake"]["render_error"]) == {"base", "clearcoat"}


def test_flakes_as_clear_coat_over_the_coat():
    m = make_material("bumpy-clustered-flakes")
    em = engine_material(m, flakes="flake_clearcoat")
    f = flake_field(m.flakes, m.height, m.width, m.flat_normals())
    flake = f.weight[0] >= 0.5
    assert em.coat is not None and float(em.coat.weight[0, ~flake].abs().max()) == 0.0
    assert float(em.coat.weight[0, flake].min()) > 0.0
    torch.testing.assert_close(em.coat.normal[:, flake], f.normal[:, flake].float())
    torch.testing.assert_close(em.normal, m.normals, atol=1e-6, rtol=0)  # the base keeps the surface normals
    assert torch.equal(em.roughness, engine_material(_without_flakes(m)).roughness)



def test_baked_flake_glints_where_torchmetal_glints():
    """Light the strongest flake at its glint (h = its normal): the baked texel shines like
    torchmetal's sparkle, the unbaked coat does not."""
    m = make_material("flat-global-flakes")
    f = flake_field(m.flakes, m.height, m.width)
    i, j = divmod(int(f.weight[0].argmax()), m.width)
    mn = f.normal[:, i, j].double()
    v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    l = 2 * (mn @ v) * mn - v  # mirror of the camera about the flake normal
    light = torch.cat([l, torch.zeros(1, dtype=torch.float64)]).float().view(1, 4)
    cam, inten = torch.tensor([[0.0, 0.0, 1.0, 0.0]]), torch.ones(1, 3)
    ref = MaterialRenderer(m)(light, inten, cam)[0, :, i, j]
    no_flakes = m.to("cpu")
    no_flakes.flakes = None
    coat = MaterialRenderer(no_flakes)(light, inten, cam)[0, :, i, j]
    plain = engine_render(engine_material(no_flakes), light, inten, cam)[0, :, i, j]
    assert float((ref - coat).min()) > 0.3  # a strong sparkle in torchmetal
    for layout in ("base", "flake_clearcoat"):
        baked = engine_render(engine_material(m, flakes=layout), light, inten, cam)[0, :, i, j]
        assert float((baked - ref).abs().max()) < 0.5 * float((plain - ref).abs().max()), (layout, ref, baked, plain)


def test_finer_texels():
    m = make_material("flat-global-flakes")
    em = engine_material(m, flakes="base", texels_per_pixel=2)
    assert em.base_color.shape == (3, 2 * m.height, 2 * m.width) and em.extras["flake_bake"]["texels_per_pixel"] == 2


def _without_flakes(m):
    out = m.to("cpu")
    out.flakes = None
    return out


@pytest.mark.parametrize("kw, match", [({"flakes": "sparkly"}, "flakes: expected one of"),
                                       ({"texels_per_pixel": 0}, "texels_per_pixel")])
def test_bad_options(kw, match):
    with pytest.raises(ExportError, match=match):
        engine_material(make_material("flat-global-flakes"), **kw)
