"""Deterministic hash flake field and its glint shading (torchmetal.flakes.model.field)."""

import math

import pytest
import torch

from tests.flakes.scenes import true_flakes
from torchmetal.errors import InputError, MaterialError
from torchmetal.flakes.model import MAX_DENSITY, FlakeModel
from torchmetal.flakes.model.field import (
    FlakeField,
    cell_size,
    flake_field,
    hash32,
    hash_uniform,
    sparkle_render,
    sparkle_shading,
)
from torchmetal.geometry import normalize, shading_geometry

M32 = 0xFFFFFFFF


def lowbias32_ref(x: int) -> int:
    """Chris Wellons' lowbias32, in plain Python integers."""
    x &= M32
    x ^= x >> 16
    x = (x * 0x7FEB352D) & M32
    x ^= x >> 15
    x = (x * 0x846CA68B) & M32
    x ^= x >> 16
    return x


def flat_normals(h, w, dtype=torch.float32):
    n = torch.zeros(3, h, w, dtype=dtype)
    n[2] = 1.0
    return n


def rotate_y(v, deg):
    """Rotate the xyz part of homogeneous (B, 4) vectors about the y axis."""
    a = math.radians(deg)
    x, y, z, w = v.unbind(-1)
    return torch.stack([x * math.cos(a) + z * math.sin(a), y, -x * math.sin(a) + z * math.cos(a), w], -1)


class TestHash:
    def test_reference_values(self):
        vals = [0, 1, 2, 3, 255, 12345, 0x7FFFFFFF, 0x80000000, M32, 0xDEADBEEF]
        got = hash32(torch.tensor(vals, dtype=torch.int64)).tolist()
        assert got == [lowbias32_ref(v) for v in vals]
        assert got[0] == 0 and len(set(got)) == len(got)

    def test_random_values_bit_exact(self):
        gen = torch.Generator().manual_seed(0)
        x = torch.randint(0, 2**32, (2000,), generator=gen, dtype=torch.int64)
        assert hash32(x).tolist() == [lowbias32_ref(v) for v in x.tolist()]

    def test_only_low_32_bits_matter(self):
        x = torch.tensor([5, 123456789, M32])
        assert torch.equal(hash32(x + (7 << 32)), hash32(x))
        assert torch.equal(hash32(torch.tensor([-1])), hash32(torch.tensor([M32])))

    @pytest.mark.parametrize("dtype", [torch.int32, torch.int16, torch.uint8])
    def test_independent_of_integer_dtype(self, dtype):
        x = torch.arange(0, 120, 7, dtype=torch.int64)
        assert torch.equal(hash32(x.to(dtype)), hash32(x))
        assert hash32(x.to(dtype)).dtype == torch.int64
        if dtype == torch.int32:
            big = torch.tensor([2**31 - 1, -(2**31), -1], dtype=torch.int32)
            assert torch.equal(hash32(big), hash32(big.to(torch.int64)))

    def test_rejects_float(self):
        with pytest.raises(InputError, match="integer"):
            hash32(torch.tensor([1.0]))

    def test_repeatable(self):
        x = torch.arange(10000)
        assert torch.equal(hash32(x), hash32(x.clone()))

    def test_uniform_range_and_statistics(self):
        ci, cj = torch.meshgrid(torch.arange(120), torch.arange(120), indexing="ij")
        u = hash_uniform(ci, cj, 7, 0, torch.float64)
        assert float(u.min()) > 0 and float(u.max()) < 1
        n = u.numel()
        assert abs(float(u.mean()) - 0.5) < 4 * math.sqrt(1 / 12 / n)
        assert abs(float(u.var()) - 1 / 12) < 0.002
        hist = torch.histc(u, 10, 0, 1)
        chi2 = float(((hist - n / 10) ** 2 / (n / 10)).sum())
        assert chi2 < 30  # 9 dof: P(χ² > 30) ≈ 4e-4
        # draws, seeds and neighbouring cells are (nearly) uncorrelated
        for other in (hash_uniform(ci, cj, 7, 1, torch.float64), hash_uniform(ci, cj, 8, 0, torch.float64),
                      hash_uniform(ci, cj + 1, 7, 0, torch.float64), hash_uniform(ci + 1, cj, 7, 0, torch.float64)):
            r = torch.corrcoef(torch.stack([u.flatten(), other.flatten()]))[0, 1]
            assert abs(float(r)) < 4 / math.sqrt(n)

    def test_uniform_float32_is_float64_rounded(self):
        ci, cj = torch.meshgrid(torch.arange(128), torch.arange(128), indexing="ij")
        for draw in range(3):
            u64 = hash_uniform(ci, cj, 3, draw, torch.float64)
            u32 = hash_uniform(ci, cj, 3, draw, torch.float32)
            assert u32.dtype == torch.float32 and u64.dtype == torch.float64
            assert torch.equal(u32, u64.float())

    def test_uniform_integer_dtype_and_large_seed(self):
        ci, cj = torch.meshgrid(torch.arange(20), torch.arange(20), indexing="ij")
        ref = hash_uniform(ci, cj, 3, 2, torch.float64)
        assert torch.equal(hash_uniform(ci.int(), cj.int(), 3, 2, torch.float64), ref)
        assert torch.equal(hash_uniform(ci, cj, 3 + (1 << 32), 2, torch.float64), ref)  # no int64 overflow
        assert torch.equal(hash_uniform(ci, cj, -1, 2, torch.float64), hash_uniform(ci, cj, M32, 2, torch.float64))


class TestFlakeField:
    def test_smoke_shapes_dtypes(self):
        f = flake_field(FlakeModel(density=0.01, seed=1), 40, 56)
        assert isinstance(f, FlakeField)
        assert f.weight.shape == (1, 40, 56) and f.normal.shape == (3, 40, 56) and f.color.shape == (3, 40, 56)
        assert f.weight.dtype == f.normal.dtype == f.color.dtype == torch.float32
        assert 0.0 <= float(f.weight.min()) and float(f.weight.max()) <= 1.0
        torch.testing.assert_close(f.normal.norm(dim=0), torch.ones(40, 56))
        assert bool((f.color >= 0).all()) and f.count > 0 and f.glint_sigma == 0.03

    def test_dtype_follows_normals(self):
        m = FlakeModel(density=0.01, seed=4)
        f32 = flake_field(m, 48, 48)
        f64 = flake_field(m, 48, 48, flat_normals(48, 48, torch.float64))
        assert f64.weight.dtype == f64.normal.dtype == f64.color.dtype == torch.float64
        assert f32.count == f64.count
        assert torch.equal(f32.weight > 0, f64.weight > 0)  # same flakes, same footprints
        torch.testing.assert_close(f64.weight.float(), f32.weight, atol=2e-5, rtol=0)
        torch.testing.assert_close(f64.normal.float(), f32.normal, atol=1e-5, rtol=0)
        torch.testing.assert_close(f64.color.float(), f32.color, atol=1e-5, rtol=0)

    def test_bit_exact_repeat(self):
        m = FlakeModel(density=0.01, seed=3, tilt_sigma=0.2)
        a, b = flake_field(m, 64, 80), flake_field(m, 64, 80)
        for name in ("weight", "normal", "color"):
            assert torch.equal(getattr(a, name), getattr(b, name))
        assert a.count == b.count

    def test_window_independent(self):
        # the field is a function of the cell, not of the image size: a crop is the smaller field
        m = FlakeModel(density=0.008, seed=9)
        small, big = flake_field(m, 48, 64), flake_field(m, 96, 128)
        for name in ("weight", "normal", "color"):
            assert torch.equal(getattr(small, name), getattr(big, name)[:, :48, :64])

    def test_seed_changes_field(self):
        a = flake_field(FlakeModel(density=0.01, seed=1), 64, 64)
        b = flake_field(FlakeModel(density=0.01, seed=2), 64, 64)
        overlap = float(((a.weight > 0) & (b.weight > 0)).float().sum() / (a.weight > 0).float().sum())
        assert overlap < 0.3

    @pytest.mark.parametrize("density", [0.001, 0.005, 0.025])
    def test_density_matches_model(self, density):
        m = FlakeModel(density=density, seed=5, area_log_mean=math.log(2.0))
        c = cell_size(density)
        side = c * (200 // c)  # whole cells, so the expectation is exactly density·area
        f = flake_field(m, side, side)
        cells = (side // c) ** 2
        p = density * c * c
        sd = math.sqrt(cells * p * (1 - p))
        assert abs(f.count - density * side * side) < 4 * sd
        # count is the number of flakes actually drawn (one per occupied cell)
        wc = f.weight[0].reshape(side // c, c, side // c, c).sum((1, 3))
        assert int((wc > 0).sum()) == f.count
        assert true_flakes(m, side, side, flat_normals(side, side))["count"] == f.count

    def test_density_zero(self):
        f = flake_field(FlakeModel(density=0.0), 32, 32)
        assert f.count == 0 and float(f.weight.abs().sum()) == 0.0

    def test_density_above_one_ninth_is_rejected(self):
        """One flake per cell and cells >= 3 px: the field cannot draw more than 1/9 per px."""
        with pytest.raises(MaterialError, match="density"):
            FlakeModel(density=0.2, seed=5)
        m = FlakeModel(density=MAX_DENSITY, seed=5, area_log_mean=math.log(1.0))
        f = flake_field(m, 240, 240)
        assert abs(f.count / 240**2 - MAX_DENSITY) < 0.01

    @pytest.mark.parametrize(
        "kw",
        [{}, {"aspect_mean": 0.35, "aspect_std": 0.05}, {"area_log_mean": math.log(20.0), "density": 0.002}],
        ids=["default", "elongated", "large"],
    )
    def test_footprint_area(self, kw):
        # Σ weight of each flake ≈ its drawn area (the anti-aliased edge is compensated)
        args = {"density": 0.005, "seed": 2} | kw
        m = FlakeModel(**args)
        c = cell_size(m.density)
        side = c * (240 // c)
        f = flake_field(m, side, side)
        t = true_flakes(m, side, side, flat_normals(side, side))
        wc = f.weight[0].reshape(side // c, c, side // c, c).sum((1, 3))  # a flake never leaves its cell
        got = wc[t["row"] // c, t["col"] // c]
        ratio = got / t["area"]
        assert abs(float(got.sum() / t["area"].sum()) - 1) < 0.02
        assert abs(float(ratio.median()) - 1) < 0.02
        assert float(ratio.min()) > 0.85 and float(ratio.max()) < 1.15

    def test_tilt_statistics(self):
        m = FlakeModel(density=0.02, seed=6, tilt_sigma=0.1)
        t = true_flakes(m, 240, 240, flat_normals(240, 240))
        slope = t["normal"][:, :2] / t["normal"][:, 2:]
        assert abs(float(slope.std()) - 0.1) < 0.01
        f = flake_field(m, 240, 240)
        # every pixel of a flake carries that flake's normal
        got = f.normal[:, t["row"], t["col"]].t()
        torch.testing.assert_close(got, t["normal"], atol=1e-6, rtol=0)


class TestSparkle:
    def _setup(self, h=48, w=48, dtype=torch.float32, **kw):
        m = FlakeModel(density=0.01, seed=11, area_log_mean=math.log(12.0), **kw)
        normals = flat_normals(h, w, dtype)
        return flake_field(m, h, w, normals), normals

    def test_shapes_and_zero_off_flakes(self):
        f, n = self._setup()
        light = torch.tensor([[0.2, 0.1, 2.0, 1.0], [0.0, 0.0, 1.0, 0.0]])
        img = sparkle_render(f, n, light, torch.full((2, 3), 4.0), torch.tensor([[0.0, 0.0, 2.5, 1.0]] * 2), (1.0, 1.0))
        assert img.shape == (2, 3, 48, 48) and img.dtype == torch.float32
        assert bool((img >= 0).all())
        assert float(img[:, :, f.weight[0] == 0].abs().max()) == 0.0

    def test_dtype_follows_input(self):
        f, n = self._setup(dtype=torch.float64)
        img = sparkle_render(f, n, torch.tensor([[0.1, 0.0, 2.0, 1.0]], dtype=torch.float64),
                             torch.full((1, 3), 4.0, dtype=torch.float64),
                             torch.tensor([[0.0, 0.0, 2.5, 1.0]], dtype=torch.float64), (1.0, 1.0))
        assert img.dtype == torch.float64

    def test_light_below_surface_is_dark(self):
        f, n = self._setup()
        img = sparkle_render(f, n, torch.tensor([[0.0, 0.3, -1.0, 0.0]]), torch.ones(1, 3),
                             torch.tensor([[0.0, 0.0, 1.0, 0.0]]), (1.0, 1.0))
        assert float(img.abs().max()) == 0.0

    def test_deterministic(self):
        f, n = self._setup()
        args = (n, torch.tensor([[0.2, 0.1, 2.0, 1.0]]), torch.full((1, 3), 4.0), torch.tensor([[0.0, 0.0, 2.5, 1.0]]), (1.0, 1.0))
        assert torch.equal(sparkle_render(f, *args), sparkle_render(f, *args))

    def test_matches_formula(self):
        f, n = self._setup(dtype=torch.float64)
        light = torch.tensor([[0.3, -0.2, 1.5, 1.0]], dtype=torch.float64)
        inten = torch.tensor([[3.0, 4.0, 5.0]], dtype=torch.float64)
        cam = torch.tensor([[0.1, 0.0, 2.0, 1.0]], dtype=torch.float64)
        geom = shading_geometry(n, light, inten, cam, (1.0, 1.0))
        h = normalize(geom.l + geom.v)
        g = torch.exp(-((f.normal.unsqueeze(0) - h) ** 2).sum(1, keepdim=True) / (2 * f.glint_sigma**2))
        ref = geom.irradiance * f.weight * f.color * g
        torch.testing.assert_close(sparkle_render(f, n, light, inten, cam, (1.0, 1.0)), ref)
        torch.testing.assert_close(sparkle_shading(f, geom), ref)

    @pytest.mark.parametrize("camera", [(0.0, 0.0, 1.0), (0.3, -0.2, 1.0)])
    def test_glint_peaks_at_bisector(self, camera):
        # directional light and camera: h is the same everywhere; pick the biggest flake's normal
        f, n = self._setup(dtype=torch.float64, tilt_sigma=0.2, glint_sigma=0.05)
        p = torch.nonzero(f.weight[0] == f.weight[0].max())[0]
        m = f.normal[:, p[0], p[1]]
        v = normalize(torch.tensor(camera, dtype=torch.float64), dim=0)
        l_star = 2 * (m @ v) * m - v  # mirror of v about m: (l + v) ∥ m
        cam = torch.cat([v, torch.zeros(1, dtype=torch.float64)]).view(1, 4)
        inten = torch.ones(1, 3, dtype=torch.float64)

        def glint(l):
            light = torch.cat([l / l.norm(), torch.zeros(1, dtype=torch.float64)]).view(1, 4)
            return float(sparkle_render(f, n, light, inten, cam, (1.0, 1.0))[0, :, p[0], p[1]].sum())

        peak = glint(l_star)
        wc = float((f.weight[0, p[0], p[1]] * f.color[:, p[0], p[1]]).sum())
        assert peak == pytest.approx(wc, rel=1e-9)  # g = 1 exactly at the bisector
        # any move of the light dims it, monotonically with the angle
        gen = torch.Generator().manual_seed(0)
        axis = torch.linalg.cross(l_star, torch.randn(3, generator=gen, dtype=torch.float64))
        axis = axis / axis.norm()
        prev = peak
        for deg in (0.5, 1, 2, 4, 8):
            a = math.radians(deg)
            l = l_star * math.cos(a) + torch.linalg.cross(axis, l_star) * math.sin(a)
            val = glint(l)
            assert val < prev
            prev = val
        for _ in range(20):
            d = torch.randn(3, generator=gen, dtype=torch.float64) * 0.05
            assert glint(l_star + d) < peak

    @pytest.mark.parametrize("moving", ["light", "camera"])
    def test_continuity_under_small_move(self, moving):
        # 0.1° light (or camera) move: every pixel changes by at most the glint lobe's steepest
        # slope (e^-½/σ_g per radian of half-vector change) times its flux — glints fade, never jump
        f, n = self._setup(h=64, w=64, dtype=torch.float64, tilt_sigma=0.15)
        inten = torch.full((1, 3), 4.0, dtype=torch.float64)
        cam0 = torch.tensor([[0.0, 0.0, 2.5, 1.0]], dtype=torch.float64)
        light0 = torch.tensor([[0.4, 0.1, 2.0, 1.0]], dtype=torch.float64)
        steps = [rotate_y(light0 if moving == "light" else cam0, 0.1 * k) for k in range(60)]
        imgs, geoms = [], []
        for x in steps:
            light, cam = (x, cam0) if moving == "light" else (light0, x)
            geoms.append(shading_geometry(n, light, inten, cam, (1.0, 1.0)))
            imgs.append(sparkle_shading(f, geoms[-1]))
        flux = f.weight * f.color
        biggest_step = 0.0
        for k in range(1, len(steps)):
            dh = (geoms[k].half - geoms[k - 1].half).norm(dim=1, keepdim=True)
            de = (geoms[k].irradiance - geoms[k - 1].irradiance).abs()
            e = torch.maximum(geoms[k].irradiance, geoms[k - 1].irradiance)
            bound = flux * (de + e * math.exp(-0.5) * dh / f.glint_sigma) * 1.05 + 1e-12
            step = (imgs[k] - imgs[k - 1]).abs()
            assert bool((step <= bound).all())
            biggest_step = max(biggest_step, float(step.max() / (e * flux).max()))
        assert 0 < biggest_step < 0.03  # ≤ 3 % of a full glint per 0.1°
        # over the 6° sweep glints really do turn on and off — through intermediate values
        stack = torch.cat(imgs)
        full = geoms[0].irradiance[0] * flux  # each pixel's glint at g = 1
        on = full > 1e-3
        swing = (stack.amax(0) - stack.amin(0))[on] / full[on]
        assert float(swing.max()) > 0.5


def test_flat_surface_tangent_frame_is_the_general_one_bit_for_bit():
    """A flat surface takes a shortcut (x and y, broadcast): the same bits as the general frame, whose
    normal-dependent case still serves tilted normals."""
    from torchmetal.flakes.model.field import _tangent_frame

    flat = torch.zeros(3, 5, 7)
    flat[2] = 1.0
    t1, t2 = _tangent_frame(flat)
    ex = torch.zeros_like(flat)
    ex[0] = 1.0
    g1 = normalize(ex - (ex * flat).sum(0, keepdim=True) * flat, dim=0)
    g2 = torch.cross(flat, g1, dim=0)
    assert t1.shape == (3, 1, 1) and torch.equal(t1.expand_as(g1), g1) and torch.equal(t2.expand_as(g2), g2)
    tilted = normalize(flat + 0.1 * torch.randn(3, 5, 7, generator=torch.Generator().manual_seed(0)), dim=0)
    u1, u2 = _tangent_frame(tilted)
    assert u1.shape == (3, 5, 7) and float((u1 * tilted).sum(0).abs().max()) < 1e-6
    assert float((u2 * tilted).sum(0).abs().max()) < 1e-6 and torch.allclose(u1.norm(dim=0), torch.ones(5, 7))
