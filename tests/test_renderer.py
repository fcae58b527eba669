"""MaterialRenderer: == functional phong_render + sparkle_render, graph contents, continuity."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

import torchmetal.renderer as renderer_mod
from torchmetal.errors import InputError
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.field import flake_field, sparkle_render
from torchmetal.material import Material
from torchmetal.onnx_export import scaled_error
from torchmetal.phong import phong_render
from torchmetal.renderer import MaterialRenderer

KINDS = ("phong", "clustered", "bumpy", "flakes", "clustered_flakes", "bumpy_flakes")
SIZE = (0.08, 0.1)  # surface width, height (non-square on purpose)


def make_material(kind: str, h: int = 40, w: int = 48, seed: int = 0) -> Material:
    """Small test materials; ``kind`` names the features (see KINDS)."""
    g = torch.Generator().manual_seed(seed)
    texture = 0.05 + 0.6 * torch.rand(3, h, w, generator=g)
    s = torch.tensor([0.3, 0.6, 1.2])
    alpha = torch.tensor([15.0, 120.0, 900.0])
    normals = labels = cs = ca = None
    if "bumpy" in kind:
        n = torch.zeros(3, h, w)
        n[:2] = 0.15 * torch.randn(2, h, w, generator=g)
        n[2] = 1.0
        normals = n / n.norm(dim=0, keepdim=True)
    if "clustered" in kind:
        labels = torch.randint(0, 3, (h, w), generator=g)
        cs = torch.tensor([[0.2, 0.3, 0.4], [1.0, 0.8, 0.6], [0.05, 0.05, 0.05]])
        ca = torch.tensor([[8.0, 12.0, 20.0], [300.0, 500.0, 2500.0], [60.0, 60.0, 60.0]])
    flakes = FlakeModel(density=0.01, seed=seed + 3, glint_sigma=0.05) if "flakes" in kind else None
    return Material(texture, s, alpha, SIZE, normals, labels, cs, ca, flakes)


def light_camera_cases(size=SIZE, category: str = "mixed", batch: int = 12, seed: int = 0):
    """Lights, intensities, cameras (float32) of one category or all mixed.

    Categories: grazing, overhead, near, far, directional (light), orthographic (camera).
    Intensities are scaled so the irradiance at the sample is about 1.
    """
    g = np.random.default_rng(seed)
    ext = max(size)
    cats = ["grazing", "overhead", "near", "far", "directional", "orthographic"]

    def direction(theta_lo, theta_hi):
        th = g.uniform(theta_lo, theta_hi)
        ph = g.uniform(0, 2 * math.pi)
        return np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])

    lights, cams = [], []
    for k in range(batch):
        c = cats[k % len(cats)] if category == "mixed" else category
        if c == "grazing":
            l = np.r_[direction(math.radians(86), math.radians(89.5)) * ext * g.uniform(1, 4), 1.0]
            v = np.r_[direction(0, 1.4) * ext * g.uniform(1, 4), 1.0]
        elif c == "overhead":
            l = np.r_[direction(0, 0.05) * ext * g.uniform(0.5, 3), 1.0]
            v = np.r_[direction(0, 0.3) * ext * g.uniform(0.5, 3), 1.0]
        elif c == "near":
            l = np.r_[direction(0, 1.2) * ext * g.uniform(0.1, 0.4), 1.0]
            v = np.r_[direction(0, 1.2) * ext * g.uniform(0.1, 0.4), 1.0]
        elif c == "far":
            l = np.r_[direction(0, 1.3) * ext * g.uniform(50, 500), 1.0]
            v = np.r_[direction(0, 1.3) * ext * g.uniform(50, 500), 1.0]
        elif c == "directional":
            l = np.r_[direction(0, 1.45), 0.0]
            v = np.r_[direction(0, 1.3) * ext * g.uniform(0.5, 3), 1.0]
        elif c == "orthographic":
            l = np.r_[direction(0, 1.3) * ext * g.uniform(0.3, 3), float(g.uniform() < 0.7)]
            v = np.r_[direction(0, 1.3), 0.0]
        else:
            raise ValueError(c)
        lights.append(l)
        cams.append(v)
    light = torch.tensor(np.array(lights), dtype=torch.float32)
    camera = torch.tensor(np.array(cams), dtype=torch.float32)
    d2 = (light[:, :3] ** 2).sum(1, keepdim=True)
    inten = torch.where(light[:, 3:] > 0.5, d2, torch.ones_like(d2)) * torch.tensor(g.uniform(0.5, 1.0, (batch, 3)), dtype=torch.float32)
    return light, inten, camera


def reference(m: Material, light, inten, camera, flakes: bool = True, field=None) -> torch.Tensor:
    """The functional model: phong_render (+ sparkle_render of the flake field)."""
    normals = m.flat_normals()
    s, alpha = m.specular_maps()
    img = phong_render(m.texture, s, alpha, normals, light, inten, camera, m.size)
    if flakes and m.flakes is not None:
        if field is None:
            field = flake_field(m.flakes, m.height, m.width, normals)
        img = img + sparkle_render(field, normals, light, inten, camera, m.size)
    return img


@functools.lru_cache(maxsize=None)
def material_renderer_field(kind: str):
    """(material, renderer, flake field or None) of a test kind, built once per session."""
    m = make_material(kind)
    field = flake_field(m.flakes, m.height, m.width, m.flat_normals()) if m.flakes is not None else None
    return m, MaterialRenderer(m), field


@pytest.fixture(scope="module", params=KINDS)
def kind(request):
    return request.param


class TestModuleEqualsFunction:
    @pytest.mark.parametrize("category", ["mixed", "grazing", "overhead", "near", "far", "directional", "orthographic"])
    def test_matches_functional_model(self, kind, category):
        m, r, field = material_renderer_field(kind)
        light, inten, camera = light_camera_cases(m.size, category, batch=12, seed=len(category))
        with torch.no_grad():
            got = r(light, inten, camera)
            ref = reference(m, light, inten, camera, field=field)
        assert got.shape == (12, 3, m.height, m.width) and got.dtype == torch.float32
        assert scaled_error(got.numpy(), ref.numpy()) <= 2e-5

    def test_batch_one_equals_batch_many(self, kind):
        m = make_material(kind)
        r = MaterialRenderer(m)
        light, inten, camera = light_camera_cases(m.size, batch=6, seed=4)
        with torch.no_grad():
            many = r(light, inten, camera)
            ones = torch.cat([r(light[i:i + 1], inten[i:i + 1], camera[i:i + 1]) for i in range(6)])
        assert scaled_error(ones.numpy(), many.numpy()) <= 1e-6

    def test_flakes_false_is_phong_only(self):
        m = make_material("flakes")
        r = MaterialRenderer(m, flakes=False)
        assert not r.has_flakes
        light, inten, camera = light_camera_cases(m.size, batch=6)
        with torch.no_grad():
            got = r(light, inten, camera)
        ref = reference(m, light, inten, camera, flakes=False)
        assert scaled_error(got.numpy(), ref.numpy()) <= 2e-5

    def test_light_below_surface_is_black(self):
        m = make_material("flakes")
        r = MaterialRenderer(m)
        light = torch.tensor([[0.01, 0.02, -0.05, 1.0], [0.3, 0.1, -1.0, 0.0]])
        out = r(light, torch.ones(2, 3), torch.tensor([[0.0, 0.0, 1.0, 0.0]] * 2))
        assert torch.all(out == 0)

    def test_float64_inputs_and_determinism(self):
        m = make_material("flakes")
        r = MaterialRenderer(m)
        light, inten, camera = light_camera_cases(m.size, batch=4)
        a = r(light.double(), inten.double(), camera.double())
        b = r(light, inten, camera)
        assert a.dtype == torch.float32 and torch.equal(a, b)
        assert torch.equal(b, r(light, inten, camera))

    def test_high_alpha_peak_precision(self):
        # camera exactly at the mirror position of a point light over the centre: lobe peak 1
        m = make_material("phong", h=33, w=33)
        m.alpha = torch.tensor([3000.0, 3000.0, 3000.0])
        r = MaterialRenderer(m)
        light = torch.tensor([[0.02, 0.0, 0.05, 1.0]])
        camera = torch.tensor([[-0.02, 0.0, 0.05, 1.0]])
        got = r(light, torch.ones(1, 3), camera)
        ref = reference(m, light, torch.ones(1, 3), camera)
        assert scaled_error(got.numpy(), ref.numpy()) <= 2e-5
        assert r.alpha_uniform


@pytest.mark.parametrize("kind", ["phong", "clustered", "bumpy"])
def test_small_alpha_is_exact_past_the_horizon(kind):
    m = make_material(kind)
    if m.clustered:
        m.cluster_alpha = torch.tensor([[0.0, 0.3, 1.0], [0.05, 2.0, 5.0], [0.5, 0.5, 0.5]])
    else:
        m.alpha = torch.tensor([0.0, 0.2, 0.9])
    r = MaterialRenderer(m)
    assert r.exact_horizon and not MaterialRenderer(make_material(kind)).exact_horizon
    light, inten, camera = light_camera_cases(m.size, "mixed", batch=12, seed=3)
    with torch.no_grad():
        assert scaled_error(r(light, inten, camera).numpy(), reference(m, light, inten, camera).numpy()) <= 2e-5


def _assert_matches_lobe_render(m, r, light, inten, camera):
    """The renderer ``r`` of material ``m`` == lobes.lobe_render in float64 (scaled error ≤ 2e-5)."""
    from torchmetal.lobes import lobe_render

    s, alpha = m.specular_maps()
    with torch.no_grad():
        got = r(light, inten, camera)
        ref = lobe_render(m.texture.double(), s.double(), alpha.double(), m.flat_normals().double(), light.double(),
                          inten.double(), camera.double(), m.size, m.lobe)
    assert scaled_error(got.numpy(), ref.numpy()) <= 2e-5


@pytest.mark.parametrize("lobe", ["blinn", "ggx"])
@pytest.mark.parametrize("kind", ["phong", "clustered", "bumpy"])
@pytest.mark.parametrize("category", ["mixed", "grazing", "overhead", "near", "directional", "orthographic"])
def test_lobes_match_functional_model(lobe, kind, category):
    """Blinn and GGX (select-free, folded in the renderer) == lobes.lobe_render in float64."""
    m = make_material(kind)
    m.lobe = lobe
    r = MaterialRenderer(m)
    _assert_matches_lobe_render(m, r, *light_camera_cases(m.size, category, batch=12, seed=len(category) + 7))


@pytest.mark.parametrize("lobe", ["phong", "ggx"])
@pytest.mark.parametrize("kind", ["clustered", "bumpy"])
def test_channel_shared_alpha_is_one_channel(lobe, kind):
    """α shared by the channels (per cluster or global): a (B,1,H,W) lobe, same image as the function."""
    m = make_material(kind)
    m.lobe = lobe
    if m.clustered:
        m.cluster_alpha = torch.tensor([[8.0] * 3, [900.0] * 3, [60.0] * 3])
    else:
        m.alpha = torch.full((3,), 150.0)
    r = MaterialRenderer(m)
    assert r.alpha_uniform and not MaterialRenderer(make_material(kind)).alpha_uniform
    _assert_matches_lobe_render(m, r, *light_camera_cases(m.size, "mixed", batch=12, seed=5))


class TestState:
    def test_only_what_the_material_uses(self):
        phong = MaterialRenderer(make_material("phong"))
        names = set(dict(phong.named_buffers()))
        assert names == {"texture", "xs", "ys", "s", "alpha"}
        assert phong.flat and not phong.clustered and not phong.has_flakes

        cl = MaterialRenderer(make_material("clustered_flakes"))
        state = cl.state_dict()
        assert state["spec_labels"].dtype == torch.uint8
        assert state["cluster_s"].shape == (3, 3) and "_s_map" not in state and "s" not in state
        assert cl.has_flakes and 0 < cl.flake_pixels < 0.25 * 40 * 48
        assert state["flake_index"].shape == (cl.flake_pixels,)
        assert state["flake_wc"].shape == (3, 1, cl.flake_pixels)

        bumpy = MaterialRenderer(make_material("bumpy_flakes"))
        assert not bumpy.flat and "normals" in dict(bumpy.named_buffers())
        assert "flake_surface_normal" in dict(bumpy.named_buffers())

    def test_explicit_flat_normals_are_folded(self):
        m = make_material("phong")
        n = torch.zeros_like(m.texture)
        n[2] = 1
        m.normals = n
        r = MaterialRenderer(m)
        assert r.flat and "normals" not in dict(r.named_buffers())

    def test_state_dict_roundtrip(self):
        m = make_material("clustered_flakes")
        a = MaterialRenderer(m)
        other = make_material("clustered_flakes")
        other.spec_labels = (other.spec_labels + 1) % 3  # other specular maps before loading
        b = MaterialRenderer(other)
        b.load_state_dict(a.state_dict())
        light, inten, camera = light_camera_cases(m.size, batch=3)
        assert torch.equal(a(light, inten, camera), b(light, inten, camera))

    def test_dense_flake_fallback_equals_sparse(self, monkeypatch):
        m = make_material("bumpy_flakes")
        sparse = MaterialRenderer(m)
        monkeypatch.setattr(renderer_mod, "DENSE_FLAKE_FRACTION", 0.0)
        dense = MaterialRenderer(m)
        assert dense.flake_pixels == -1 and sparse.flake_pixels > 0
        light, inten, camera = light_camera_cases(m.size, batch=6)
        with torch.no_grad():
            assert scaled_error(dense(light, inten, camera).numpy(), sparse(light, inten, camera).numpy()) <= 1e-6

    def test_no_flake_pixels_means_no_flake_ops(self):
        m = make_material("flakes")
        m.flakes = FlakeModel(density=0.0)
        r = MaterialRenderer(m)
        assert not r.has_flakes


class TestBadInput:
    def test_not_a_material(self):
        with pytest.raises(InputError, match="expected a torchmetal Material"):
            MaterialRenderer("material/")

    @pytest.mark.parametrize(
        "light, inten, camera, match",
        [
            (torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2, 4), r"light: expected shape \(B, 4\)"),
            (torch.ones(2, 4), torch.ones(3, 3), torch.ones(2, 4), "same B"),
            (torch.ones(2, 4), torch.ones(2, 3), torch.full((2, 4), float("nan")), "camera: expected finite"),
            (torch.ones(2, 4, dtype=torch.int64), torch.ones(2, 3), torch.ones(2, 4), "floating-point"),
        ],
    )
    def test_check_inputs_one_line(self, light, inten, camera, match):
        with pytest.raises(InputError, match=match) as e:
            MaterialRenderer.check_inputs(light, inten, camera)
        assert "\n" not in str(e.value)


class TestContinuity:
    """Sparkles fade, they don't flicker: 0.1° light steps change the glint image by a bounded amount."""

    STEP = math.radians(0.1)

    def _sweep(self, m: Material, steps: int, vary: str = "light"):
        r = MaterialRenderer(m)
        phong = MaterialRenderer(m, flakes=False)
        ang = torch.arange(steps, dtype=torch.float64) * self.STEP
        moving = torch.stack([torch.sin(ang), 0.2 * torch.ones_like(ang), torch.cos(ang), torch.zeros_like(ang)], 1)
        moving[:, :3] /= moving[:, :3].norm(dim=1, keepdim=True)
        fixed = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64).expand(steps, 4)
        light, camera = (moving, fixed) if vary == "light" else (fixed, moving)
        inten = torch.ones(steps, 3)
        with torch.no_grad():
            sparkle = r(light.float(), inten, camera.float()) - phong(light.float(), inten, camera.float())
        return r, sparkle

    @pytest.mark.parametrize("vary", ["light", "camera"])
    def test_small_bounded_steps_across_glints(self, vary):
        m = make_material("flakes", h=64, w=64, seed=1)
        m.flakes = FlakeModel(density=0.01, seed=5, tilt_sigma=0.15, glint_sigma=0.03)
        r, sparkle = self._sweep(m, steps=400, vary=vary)  # 0°..40° in 0.1° steps
        peak = float(r.flake_wc.max())  # largest possible glint (irradiance 1)
        # |Δh| ≤ Δθ/2 for a unit half vector, and |d/dx exp(−x²/2σ²)| ≤ e^{-1/2}/σ
        bound = peak * (self.STEP / 2) / r.glint_sigma * math.exp(-0.5)
        steps = (sparkle[1:] - sparkle[:-1]).abs().amax(dim=(1, 2, 3))
        assert float(steps.max()) <= 1.3 * bound, (float(steps.max()), bound)
        assert bound <= 0.02 * peak  # a 0.1° move changes any glint by at most ~2 % of its peak
        # the sweep really crosses glints: some flake lights up to most of its peak and goes dark
        assert float(sparkle.max()) >= 0.5 * peak
        per_pixel_range = sparkle.amax(0) - sparkle.amin(0)
        assert float(per_pixel_range.max()) >= 0.5 * peak
