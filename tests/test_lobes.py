"""Specular lobes (torchmetal.lobes): values, shapes, numerics, gradients, renderer, material, ONNX."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchmetal.errors import InputError, MaterialError
from torchmetal.geometry import pixel_axes, shading_geometry
from torchmetal.lobes import (
    F0,
    LOBES,
    LobeModel,
    blinn_lobe,
    check_lobe,
    fresnel_ratio,
    ggx_k,
    ggx_lobe,
    ggx_log_core,
    grid_half_terms,
    half_terms,
    lobe_render,
    lobe_shading,
    lobe_value,
)
from torchmetal.material import Material, load_material, save_material
from torchmetal.phong import phong_shading
from torchmetal.renderer import MaterialRenderer

SIZE = (0.1, 0.08)


def _normals(h: int, w: int, bumpy: bool, dtype=torch.float64, seed: int = 0) -> torch.Tensor:
    n = torch.zeros(3, h, w, dtype=dtype)
    n[2] = 1.0
    if bumpy:
        g = torch.Generator().manual_seed(seed)
        n[:2] = 0.3 * torch.randn(2, h, w, generator=g, dtype=dtype)
        n = n / n.norm(dim=0, keepdim=True)
    return n


def _shots(dtype=torch.float64):
    light = torch.tensor([[0.02, 0.01, 0.2, 1.0], [0.3, 0.2, 0.9, 0.0], [0.5, 0.0, 0.03, 0.0], [0.0, 0.0, 1.0, 0.0]],
                         dtype=dtype)
    camera = torch.tensor([[-0.01, 0.0, 0.3, 1.0], [-0.3, -0.2, 0.9, 0.0], [0.0, 0.0, 1.0, 0.0], [0.4, 0.0, 0.02, 0.0]],
                          dtype=dtype)
    return light, torch.ones(4, 3, dtype=dtype), camera


def _reference_ggx(n, l, v, alpha):
    """Cook–Torrance with textbook GGX D, Schlick F, separable Smith G, scaled by 4πk/F0 (float64)."""
    h = l + v
    h = h / h.norm(dim=1, keepdim=True)
    nh, nl, nv, vh = ((n * h).sum(1, keepdim=True), (n * l).sum(1, keepdim=True), (n * v).sum(1, keepdim=True),
                      (v * h).sum(1, keepdim=True))
    k = (2.0 / (alpha + 2.0)).view(1, 3, 1, 1)
    d = k / (math.pi * (nh * nh * (k - 1.0) + 1.0) ** 2)
    f = F0 + (1 - F0) * (1 - vh) ** 5
    g1 = lambda x: 2 * x / (x + torch.sqrt(k + (1 - k) * x * x))  # noqa: E731
    brdf_nl = d * f * g1(nl) * g1(nv) / (4 * nv)  # BRDF × n·l
    val = brdf_nl * 4 * math.pi * k / F0
    return torch.where((nl > 0) & (nv > 0), val, torch.zeros_like(val))


class TestLobeValues:
    @pytest.mark.parametrize("bumpy", [False, True])
    def test_reference_values(self, bumpy):
        h, w = 6, 7
        n = _normals(h, w, bumpy)
        light, inten, cam = _shots()
        geom = shading_geometry(n, light, inten, cam, SIZE)
        alpha = torch.tensor([3.0, 60.0, 900.0], dtype=torch.float64)
        hv = geom.half
        nh = (geom.n * hv).sum(1, keepdim=True)
        blinn_ref = torch.where(nh > 0, nh.clamp_min(0) ** alpha.view(1, 3, 1, 1), torch.zeros_like(nh))
        torch.testing.assert_close(lobe_value("blinn", geom, alpha), blinn_ref, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(lobe_value("ggx", geom, alpha) * (geom.n_dot_l > 0),
                                   _reference_ggx(geom.n, geom.l, geom.v, alpha), rtol=1e-9, atol=1e-12)

    def test_peak_is_one_and_shapes(self):
        n = _normals(3, 4, False, torch.float32)
        top = torch.tensor([[0.0, 0.0, 1.0, 0.0]])
        geom = shading_geometry(n, top, torch.ones(1, 3), top, SIZE)
        for lobe in LOBES:
            out = lobe_value(lobe, geom, torch.tensor([1.0, 100.0, 1e4]))
            assert out.shape == (1, 3, 3, 4)
            torch.testing.assert_close(out, torch.ones_like(out))
        maps = torch.full((3, 3, 4), 50.0)  # per-pixel α
        assert lobe_value("ggx", geom, maps).shape == (1, 3, 3, 4)

    def test_widths_match_near_the_peak(self):
        """Blinn α ≈ 4× Phong α, GGX k = 2/(α+2) ≈ Blinn of exponent 2(α+2): equal at small angles."""
        theta = torch.tensor([0.01, 0.02], dtype=torch.float64)
        q = 1 - torch.cos(theta)  # 1 − n·h for a half-angle θ
        blinn = blinn_lobe(q.view(1, 1, 2, 1), torch.full((3,), 2 * 102.0, dtype=torch.float64))
        ggx_d = (ggx_k(torch.tensor(100.0, dtype=torch.float64)) / (ggx_k(torch.tensor(100.0, dtype=torch.float64))
                 + (1 - ggx_k(torch.tensor(100.0, dtype=torch.float64))) * torch.sin(theta) ** 2)) ** 2
        torch.testing.assert_close(blinn[0, 0, :, 0], ggx_d, rtol=2e-3, atol=0)

    def test_fresnel(self):
        x = torch.tensor([1.0, 0.0, -0.5, 2.0])
        torch.testing.assert_close(fresnel_ratio(x), torch.tensor([1.0, 1 / F0, 1 / F0, 1.0]))

    def test_bad_lobe(self):
        with pytest.raises(InputError, match="lobe: expected one of"):
            check_lobe("cook")
        geom = shading_geometry(_normals(2, 2, False), *_shots(), SIZE)
        with pytest.raises(InputError):
            lobe_value("beckmann", geom, torch.ones(3, dtype=torch.float64))

    def test_phong_is_phong_shading_exactly(self):
        geom = shading_geometry(_normals(5, 5, True, torch.float32), *(x.float() for x in _shots()), SIZE)
        tex = torch.rand(3, 5, 5)
        s, a = torch.tensor([0.2, 0.4, 0.8]), torch.tensor([5.0, 50.0, 500.0])
        assert torch.equal(lobe_shading(tex, s, a, geom, "phong"), phong_shading(tex, s, a, geom))


class TestNumerics:
    @pytest.mark.parametrize("alpha", [0.0, 1e-3, 1.0, 1e4, 1e8, 1e12])
    def test_extremes_finite(self, alpha):
        """Grazing light and view, back-facing view, l = −v, and α from 0 to 1e12: finite values and grads."""
        hq = torch.tensor([0.0, 1e-9, 0.3, 1.0, 2.0, 0.5], dtype=torch.float64).view(1, 1, 6, 1)
        nl = torch.tensor([1.0, 1e-9, 0.0, 0.5, 0.0, -0.2], dtype=torch.float64).view(1, 1, 6, 1)
        nv = torch.tensor([1.0, 1e-12, 0.0, -0.5, 0.0, 0.9], dtype=torch.float64).view(1, 1, 6, 1)
        vh = torch.tensor([1.0, 1e-6, 0.0, 0.0, -1.0, 0.4], dtype=torch.float64).view(1, 1, 6, 1)
        a = torch.full((3,), alpha, dtype=torch.float64, requires_grad=True)
        geo = [x.clone().requires_grad_() for x in (hq, nl, nv, vh)]
        out = ggx_lobe(*geo, a) + blinn_lobe(geo[0], a)
        assert bool(torch.isfinite(out).all())
        grads = torch.autograd.grad(out.sum(), [a, *geo], allow_unused=True)
        assert all(g is None or bool(torch.isfinite(g).all()) for g in grads)
        assert float(ggx_lobe(hq, nl, nv, vh, a.detach())[0, :, 3].abs().max()) == 0.0  # n·v < 0: unseen

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(1)
        hq = (0.4 * torch.rand(2, 1, 3, 2, generator=g, dtype=torch.float64)).requires_grad_()
        nl = (0.1 + 0.8 * torch.rand(2, 1, 3, 2, generator=g, dtype=torch.float64)).requires_grad_()
        nv = (0.1 + 0.8 * torch.rand(2, 1, 3, 2, generator=g, dtype=torch.float64)).requires_grad_()
        vh = (0.2 + 0.7 * torch.rand(2, 1, 3, 2, generator=g, dtype=torch.float64)).requires_grad_()
        alpha = torch.tensor([2.0, 30.0, 400.0], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(ggx_lobe, (hq, nl, nv, vh, alpha))
        assert torch.autograd.gradcheck(blinn_lobe, (hq, alpha))

    def test_shading_gradcheck(self):
        n = _normals(3, 3, True)
        geom = shading_geometry(n, *_shots(), SIZE)
        tex = torch.rand(3, 3, 3, dtype=torch.float64, requires_grad=True)
        s = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float64, requires_grad=True)
        a = torch.tensor([4.0, 40.0, 200.0], dtype=torch.float64, requires_grad=True)
        for lobe in ("blinn", "ggx"):
            assert torch.autograd.gradcheck(lambda t, s_, a_: lobe_shading(t, s_, a_, geom, lobe), (tex, s, a))

    def test_log_core_derivative(self):
        """∂ log core/∂β of ggx_log_core against autograd, and exp(log core)·F̂ == the lobe."""
        g = torch.Generator().manual_seed(2)
        hq = 0.5 * torch.rand(4, 1, 5, generator=g, dtype=torch.float64)
        nl = 0.05 + 0.9 * torch.rand(4, 1, 5, generator=g, dtype=torch.float64)
        nv = 0.05 + 0.9 * torch.rand(4, 1, 5, generator=g, dtype=torch.float64)
        beta = torch.tensor([0.0, 3.0, 9.0], dtype=torch.float64).view(1, 3, 1).requires_grad_()
        log_core, t = ggx_log_core(hq, nl, nv, ggx_k(beta.exp()))
        jac = torch.autograd.grad(log_core.sum(), beta)[0]
        torch.testing.assert_close(jac, t.sum((0, 2), keepdim=True).detach())
        vh = torch.full_like(hq, 0.8)
        lobe = ggx_lobe(hq.unsqueeze(-1), nl.unsqueeze(-1), nv.unsqueeze(-1), vh.unsqueeze(-1), beta.detach().exp().view(3))
        torch.testing.assert_close(lobe[..., 0], torch.exp(log_core.detach()) * fresnel_ratio(vh))


class TestGeometry:
    @pytest.mark.parametrize("bumpy", [False, True])
    def test_grid_half_terms_match(self, bumpy):
        h, w = 5, 6
        n = _normals(h, w, bumpy)
        light, inten, cam = _shots()
        geom = shading_geometry(n, light, inten, cam, SIZE)
        x, y = pixel_axes(h, w, SIZE, dtype=torch.float64)
        got = grid_half_terms(light, cam, x, y, None if not bumpy else n)
        for a, b in zip(got, half_terms(geom)):
            torch.testing.assert_close(a, b[:, 0], rtol=1e-9, atol=1e-12)


class TestModule:
    def test_module_is_function(self):
        n = _normals(4, 5, True, torch.float32)
        tex = torch.rand(3, 4, 5)
        s, a = torch.tensor([0.3, 0.4, 0.5]), torch.tensor([20.0, 40.0, 80.0])
        light, inten, cam = (x.float() for x in _shots())
        for lobe in LOBES:
            m = LobeModel(tex, s, a, n, SIZE, lobe=lobe)
            torch.testing.assert_close(m(light, inten, cam), lobe_render(tex, s, a, n, light, inten, cam, SIZE, lobe))
            assert m.lobe == lobe
        with pytest.raises(InputError):
            LobeModel(tex, s, a, n, SIZE, lobe="nope")


def _material(lobe: str, bumpy: bool, clustered: bool, h: int = 12, w: int = 16) -> Material:
    g = torch.Generator().manual_seed(3)
    tex = torch.rand(3, h, w, generator=g)
    normals = _normals(h, w, True, torch.float32) if bumpy else None
    kw = {}
    if clustered:
        kw = dict(spec_labels=(torch.arange(h * w).reshape(h, w) % 2), cluster_s=torch.tensor([[0.2, 0.3, 0.4], [0.9, 0.8, 0.7]]),
                  cluster_alpha=torch.tensor([[10.0, 20.0, 30.0], [300.0, 400.0, 500.0]]))
    return Material(tex, torch.tensor([0.3, 0.5, 0.7]), torch.tensor([8.0, 80.0, 800.0]), SIZE, normals, lobe=lobe, **kw)


class TestRendererAndMaterial:
    @pytest.mark.parametrize("lobe", LOBES)
    @pytest.mark.parametrize("bumpy,clustered", [(False, False), (True, False), (False, True)])
    def test_renderer_matches_function(self, lobe, bumpy, clustered):
        from torchmetal.onnx_export import parity_inputs

        m = _material(lobe, bumpy, clustered)
        r = MaterialRenderer(m)
        assert r.lobe == lobe
        light, inten, cam = parity_inputs(m.size, batch=8)
        with torch.no_grad():
            got = r(light, inten, cam)
        s, a = m.specular_maps()
        ref = lobe_render(m.texture.double(), s.double(), a.double(), m.flat_normals().double(), light.double(),
                          inten.double(), cam.double(), m.size, lobe)
        scale = ref.abs().amax((1, 2, 3), keepdim=True).clamp_min(1e-30)
        assert float(((got.double() - ref) / scale).abs().max()) < 2e-5

    def test_material_roundtrip_and_old_materials(self, tmp_path):
        m = _material("ggx", False, False)
        save_material(m, tmp_path / "m")
        meta = json.loads((tmp_path / "m" / "material.json").read_text())
        assert meta["lobe"] == "ggx"
        assert load_material(tmp_path / "m").lobe == "ggx"
        del meta["lobe"]  # a material written before the lobe choice
        (tmp_path / "m" / "material.json").write_text(json.dumps(meta))
        assert load_material(tmp_path / "m").lobe == "phong"
        meta["lobe"] = "cook-torrance"
        (tmp_path / "m" / "material.json").write_text(json.dumps(meta))
        with pytest.raises(MaterialError, match="lobe: expected one of"):
            load_material(tmp_path / "m")
        assert m.to("cpu").lobe == "ggx"


@pytest.mark.parametrize("lobe,bumpy,clustered", [("blinn", True, False), ("ggx", True, True)])
def test_onnx_parity(tmp_path, lobe, bumpy, clustered):
    pytest.importorskip("onnxruntime")
    import onnx

    from torchmetal.onnx_export import export_onnx, verify_onnx

    m = _material(lobe, bumpy, clustered)
    path = export_onnx(m, tmp_path / "r.onnx")  # checks parity ≤ 1e-4 itself
    meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert meta["lobe"] == lobe
    assert verify_onnx(path, MaterialRenderer(m)) <= 1e-4


def test_cli_fit_lobe(tmp_path, capsys):
    """``torchmetal fit --lobe ggx`` writes a GGX material that renders; a bad --lobe is a usage error."""
    from torchmetal.cli import main

    cap, mat = tmp_path / "cap", tmp_path / "mat"
    assert main(["synth", "-o", str(cap), "--size", "24", "--shots", "5"]) == 0
    assert main(["fit", str(cap), "-o", str(mat), "-q", "--lobe", "ggx"]) == 0
    assert "lobe ggx" in capsys.readouterr().out
    m = load_material(mat)
    assert m.lobe == "ggx" and m.report["lobe"] == "ggx"
    assert main(["render", str(mat), "--light", "0 0.05 0.3 1", "--camera", "0 0 0.3 1", "-o", str(tmp_path / "r.npy")]) == 0
    with pytest.raises(SystemExit) as e:
        main(["fit", str(cap), "-o", str(mat), "--lobe", "cook"])
    assert e.value.code != 0


@pytest.mark.parametrize("lobe", ["blinn", "ggx"])
@pytest.mark.parametrize("bumpy", [False, True])
def test_the_plane_path_without_gradients_matches_the_vector_path(lobe, bumpy):
    """lobe_render without a gradient builds Blinn and GGX from the plane's separable terms (lobes._plane_lobe);
    with one, from the vector geometry: the same values at grazing and back-facing shots, directional lights,
    normal maps and α maps from 1 to 3000."""
    h, w = 6, 7
    n = _normals(h, w, bumpy, seed=3)
    light, intensity, camera = _shots()
    g = torch.Generator().manual_seed(5)
    tex = torch.rand(3, h, w, generator=g, dtype=torch.float64)
    s = torch.tensor([0.3, 1.0, 4.0], dtype=torch.float64)
    a = torch.tensor([1.0, 40.0, 3000.0], dtype=torch.float64)[:, None, None] * (0.5 + torch.rand(3, h, w, generator=g,
                                                                                                  dtype=torch.float64))
    with torch.no_grad():
        plane = lobe_render(tex, s, a, n, light, intensity, camera, SIZE, lobe)
    tex_g = tex.clone().requires_grad_(True)
    vector = lobe_render(tex_g, s, a, n, light, intensity, camera, SIZE, lobe)
    torch.testing.assert_close(plane, vector.detach(), rtol=1e-10, atol=1e-12)
    assert vector.grad_fn is not None


def test_the_plane_path_keeps_the_overflow_rule_for_every_lobe():
    """An irradiance that overflows float32 is inf where the surface is lit and 0 where it faces away, without a
    gradient as with one."""
    n = torch.zeros(3, 2, 2)
    n[2, :, 0], n[2, :, 1] = 1.0, -1.0
    light, cam = torch.tensor([[0.01, 0.0, 0.3, 1.0]]), torch.tensor([[0.0, 0.0, 0.3, 1.0]])
    for lobe in ("blinn", "ggx"):
        with torch.no_grad():
            out = lobe_render(torch.full((3, 2, 2), 0.5), torch.ones(3), torch.full((3,), 10.0), n, light,
                              torch.full((1, 3), 3e38), cam, (0.1, 0.1), lobe)
        assert bool(torch.isinf(out[..., 0]).all()) and bool((out[..., 1] == 0).all()), lobe
