"""Glitter where it is: the flake-density map (torchmetal.flakes.estimate.density_map, density_choice), its field,
its material files, its ONNX renderer and its choice on left-out shots."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import torchmetal.flakes.density_choice as dc
from torchmetal.errors import MaterialError
from torchmetal.flakes.estimate.density_map import AREA_P, estimate_map, map_grid, with_map
from torchmetal.flakes.estimate.results import FlakeStageResult, Particles
from torchmetal.flakes.model import MAX_DENSITY, FlakeModel
from torchmetal.flakes.model.field import flake_field
from torchmetal.material import Material, load_material, save_material


def _fields_equal(a, b) -> bool:
    return a.count == b.count and all(torch.equal(x, y) for x, y in ((a.weight, b.weight), (a.normal, b.normal),
                                                                      (a.color, b.color)))


@pytest.mark.parametrize("density,dtype,shape", [(0.003, torch.float32, (97, 130)), (MAX_DENSITY, torch.float32, (64, 64)),
                                                 (0.02, torch.float64, (50, 41)), (0.0, torch.float32, (32, 32))])
def test_uniform_map_is_todays_field_bit_for_bit(density, dtype, shape):
    m = FlakeModel(density=density, seed=7, tilt_sigma=0.2)
    n = torch.zeros(3, *shape, dtype=dtype)
    n[2] = 1.0
    for grid in ((1, 1), (5, 4), (16, 16)):
        assert _fields_equal(flake_field(m, *shape, n), flake_field(replace(m, density_map=np.ones(grid)), *shape, n))


def test_map_puts_flakes_and_colours_where_it_says():
    m = FlakeModel(density=0.01, seed=3, density_map=torch.tensor([[2.0, 0.0]]),
                   color_map=torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]]), color_cov=((0.0,) * 3,) * 3)
    f = flake_field(m, 128, 128)
    assert float(f.weight[0, :, 64:].sum()) == 0.0 and float(f.weight[0, :, :64].sum()) > 0
    on = f.weight[0] > 0
    assert torch.allclose(f.color[:, on].mean(1), torch.tensor([1.0, 0.0, 0.0]))
    uniform = flake_field(replace(m, density_map=None, color_map=None), 128, 128)
    assert 0.75 * uniform.count < f.count < 1.3 * uniform.count  # twice the density on half the sample


@pytest.mark.parametrize("kw,expect", [
    (dict(density=0.1, density_map=[[2.0]]), "capacity"),
    (dict(density=0.01, density_map=[[float("nan"), 1.0]]), "finite"),
    (dict(density=0.01, density_map=[[-1.0, 1.0]]), ">= 0"),
    (dict(density=0.01, density_map=[1.0, 1.0]), "2 dimensions"),
    (dict(density=0.01, density_map="abc"), "numeric array"),
    (dict(density=0.01, color_map=[[[1.0, 1.0, 1.0]]]), "density_map"),
    (dict(density=0.01, density_map=[[1.0, 1.0]], color_map=[[[1.0, 1.0, 1.0]]]), "shape (1, 2, 3)"),
    (dict(density=0.01, density_map=[[1.0]], color_map=[[[1.0, -1.0, 1.0]]]), "finite values in"),
])
def test_bad_maps_are_one_line_errors(kw, expect):
    with pytest.raises(MaterialError) as e:
        FlakeModel(**kw)
    assert expect in str(e.value) and "\n" not in str(e.value) and "expected" in str(e.value)


def _material(flakes: FlakeModel, h: int = 40, w: int = 48) -> Material:
    g = torch.Generator().manual_seed(0)
    return Material(0.05 + 0.6 * torch.rand(3, h, w, generator=g), torch.tensor([0.3, 0.6, 1.2]),
                    torch.tensor([15.0, 120.0, 900.0]), (0.1, 0.08), flakes=flakes)


MAPPED = FlakeModel(density=0.01, seed=4, glint_sigma=0.05, density_map=torch.tensor([[3.0, 0.0], [1.0, 0.5]]),
                    color_map=torch.tensor([[[0.9, 0.2, 0.1], [0.5, 0.5, 0.5]], [[0.1, 0.3, 0.9], [0.8, 0.8, 0.8]]]))


def test_material_round_trip_keeps_the_maps(tmp_path):
    m = _material(MAPPED)
    save_material(m, tmp_path / "m")
    assert (tmp_path / "m" / "flakes_density_map.npy").is_file() and (tmp_path / "m" / "flakes_color_map.npy").is_file()
    back = load_material(tmp_path / "m").flakes
    assert torch.equal(back.density_map, MAPPED.density_map) and torch.equal(back.color_map, MAPPED.color_map)
    assert _fields_equal(flake_field(back, 40, 48), flake_field(MAPPED, 40, 48))
    plain = _material(replace(MAPPED, density_map=None, color_map=None))
    save_material(plain, tmp_path / "p")
    assert "maps" not in json.loads((tmp_path / "p" / "material.json").read_text())["flakes"]
    assert load_material(tmp_path / "p").flakes.density_map is None


def test_bad_map_file_is_a_one_line_material_error(tmp_path):
    save_material(_material(MAPPED), tmp_path / "m")
    np.save(tmp_path / "m" / "flakes_density_map.npy", np.full((2, 2), np.inf, np.float32))
    with pytest.raises(MaterialError, match="finite") as e:
        load_material(tmp_path / "m")
    assert "\n" not in str(e.value)
    (tmp_path / "m" / "flakes_density_map.npy").unlink()
    with pytest.raises(MaterialError, match="found nothing"):
        load_material(tmp_path / "m")


def test_onnx_parity_with_a_map(tmp_path):
    from torchmetal.onnx_export import PARITY_TOL, export_onnx, verify_onnx
    from torchmetal.renderer import MaterialRenderer

    m = _material(MAPPED)
    r = MaterialRenderer(m)
    assert r.has_flakes
    cols = (r.flake_index % 48)[(r.flake_index // 48) < 20]  # top half: the zero block is on the right
    assert bool((cols < 24).all())
    path = export_onnx(m, tmp_path / "r.onnx", check=False)
    assert verify_onnx(path, r) <= PARITY_TOL


# ----------------------------------------------------------------------------- estimate and choice


def _capture(n: int = 4, h: int = 64, w: int = 64):
    normals = torch.zeros(3, h, w)
    normals[2] = 1.0
    lights = torch.tensor([[0.02 * k, 0.01, 0.3, 1.0] for k in range(n)])
    return SimpleNamespace(images=torch.full((n, 3, h, w), 0.2), normals=normals, mask=torch.ones(1, h, w, dtype=torch.bool),
                           saturated=torch.zeros(n, 3, h, w, dtype=torch.bool), lights=lights,
                           intensities=torch.ones(n, 3), cameras=lights.clone(), size=(0.1, 0.1), num_shots=n)


def _left_particles(n_shots: int = 4, flakes: int = 120, w: int = 64, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    cy = torch.rand(flakes, generator=g) * 64
    cx = torch.rand(flakes, generator=g) * (w / 2)
    shot = torch.arange(flakes) % n_shots
    one = torch.ones(flakes)
    rgb = torch.where((cy < 32).view(-1, 1), torch.tensor([0.8, 0.2, 0.1]), torch.tensor([0.1, 0.3, 0.8]))
    p = Particles(shot=shot, area=2 * one, cy=cy, cx=cx, major=2 * one, minor=2 * one, angle=0 * one,
                  rgb=rgb + 0.02 * torch.randn(flakes, 3, generator=g), lab=torch.zeros(flakes, 3), peak=rgb, amp=one,
                  snr=20 * one, flux=one, sigma=0.02 * one)
    return p, torch.arange(flakes)


def test_estimate_map_left_half():
    cap = _capture()
    model = FlakeModel(density=0.01, tilt_sigma=0.3)
    p, fid = _left_particles()
    assert map_grid(64, 64, 120) == (3, 3) and map_grid(1024, 1024, 10**6) == (16, 16)
    dm = estimate_map(cap, model, p, fid, grid=(2, 2), mode="area")
    assert not dm.uniform and dm.grid == (2, 2)
    assert float(dm.density[:, 1].max()) == 0.0 and float(dm.density[:, 0].min()) > 1.5  # zero where none was found
    assert dm.report["zero_blocks"] == 2
    assert dm.color is not None and float(dm.color[0, 0, 0]) > float(dm.color[1, 0, 0])  # red top, blue bottom
    glint = estimate_map(cap, model, p, fid, grid=(2, 2), mode="glint")
    assert float(glint.density[:, 1].max()) == 0.0
    assert estimate_map(cap, model, p.select(torch.arange(10)), fid[:10]) is None  # too few flakes
    m2 = with_map(model, dm)
    assert m2.density_map is not None and with_map(model, None) is model


def test_choice_report_and_rule(monkeypatch):
    cap = _capture()
    p, fid = _left_particles()
    model = FlakeModel(density=0.01, tilt_sigma=0.3)
    mat = _material(model, 64, 64)
    result = FlakeStageResult(model, p, {}, fid)
    monkeypatch.setattr(dc, "estimate_map", lambda *a, **k: estimate_map(*a, **{**k, "grid": (2, 2)}))

    def fake(better: bool):
        def score(material, capture, k, grid, pred=None):
            has = material.flakes.density_map is not None
            md = 10.0 if (has == better) else 20.0
            return {"md": md, "block_error": md / 10, "predicted": [[0.0] * grid[1]] * grid[0],
                    "observed": [[0.0] * grid[1]] * grid[0]}
        return score

    monkeypatch.setattr(dc, "score_shot", fake(True))
    flakes, rep = dc.choose_density_map(cap, mat, result)
    assert rep["candidates"] == ["uniform", "map:glint", "map:area"] and len(rep["held"]) == 2
    assert rep["kept"] and rep["winner"].startswith("map:") and flakes.density_map is not None
    assert set(rep["scores"]) == set(rep["candidates"]) and "map_estimate" in rep and "reason" in rep
    monkeypatch.setattr(dc, "score_shot", fake(False))
    flakes, rep = dc.choose_density_map(cap, mat, result)
    assert not rep["kept"] and rep["winner"] == "uniform" and flakes is model
    none, rep = dc.choose_density_map(cap, replace(mat, flakes=None), result)
    assert none is None and not rep["kept"] and not rep["held"] and "folds" not in rep  # no flake model: no fold run


def test_sparkle_counts_per_block():
    img = torch.zeros(3, 32, 32)
    img[:, 5, 5] = 1.0
    img[:, 20, 25] = 1.0
    pred, obs = dc.sparkle_counts(img, torch.zeros(3, 32, 32) + 0.001 * torch.randn(3, 32, 32), (2, 2))
    assert pred.tolist() == [[1.0, 0.0], [0.0, 1.0]] and float(obs.sum()) == 0.0
    assert dc.block_error(pred, obs) == pytest.approx(0.5 * np.log(2))


@pytest.mark.slow
def test_half_glitter_zoo_scene(tmp_path):
    """Zoo flakes_half: the fit keeps a map, its density right of the glitter ≪ left, and the render has
    no flake right of it."""
    from torchmetal.flakes.model.observed import material_flake_field
    from torchmetal.io.capture import load_capture
    from torchmetal.pipeline import fit_material
    from torchmetal.synth.zoo import SCENES, make_case

    case = make_case(SCENES["flakes_half"], tmp_path / "half")
    res = fit_material(load_capture(case.capture_dir), seed=0)
    fl = res.material.flakes
    choice = res.flakes.report["density_map_choice"]
    assert fl is not None and choice["kept"], choice.get("reason")
    dm = fl.density_map
    g = dm.shape[1]
    left, right = dm[:, : g // 2].mean(), dm[:, g - g // 2:].mean()  # the middle column (odd g) straddles the edge
    assert float(right) < 0.1 * float(left)
    m = res.material
    f = material_flake_field(fl, m.observed_flakes, m.height, m.width, m.flat_normals(), m.size)
    edge = int(np.ceil(m.width * ((g + 1) // 2) / g))  # right of the blocks that touch the glitter
    assert float(f.weight[0, :, :edge].sum()) > 0 and float(f.weight[0, :, edge:].sum()) == 0.0


# ----------------------------------------------------------------------------- per-block flake size

import math  # noqa: E402

from torchmetal.flakes.model.field import field_cell  # noqa: E402

AREA_MAPPED = replace(MAPPED, area_map=torch.tensor([[math.log(2.0), 0.0], [-0.4, 0.2]]))


def test_zero_area_map_is_the_same_field_bit_for_bit():
    """The area draw with a (zero) area map uses the same hash bits as without one: where the cell is
    unchanged the field is bit for bit the same (a model without an area map takes the unchanged path)."""
    m = FlakeModel(density=0.003, seed=5, density_map=torch.tensor([[1.0, 0.0], [2.0, 0.5]]))
    z = replace(m, area_map=torch.zeros(2, 2))
    assert field_cell(z) == field_cell(m)
    for dtype, shape in ((torch.float32, (97, 130)), (torch.float64, (50, 41))):
        n = torch.zeros(3, *shape, dtype=dtype)
        n[2] = 1.0
        assert _fields_equal(flake_field(m, *shape, n), flake_field(z, *shape, n))


def test_area_map_draws_each_block_its_size():
    m = FlakeModel(density=0.01, seed=3, density_map=torch.ones(1, 2), area_map=torch.tensor([[math.log(4.0), 0.0]]),
                   color_cov=((0.0,) * 3,) * 3)
    f = flake_field(m, 256, 256)
    w = f.weight[0]
    ratio = float(w[:, :128].sum()) / float(w[:, 128:].sum())  # the same flake count on both halves (± Poisson)
    assert 3.2 < ratio < 4.9, ratio
    assert field_cell(m) > field_cell(replace(m, area_map=None))  # room for the larger flakes


@pytest.mark.parametrize("kw,expect", [
    (dict(density=0.01, area_map=[[0.0]]), "density_map"),
    (dict(density=0.01, density_map=[[1.0, 1.0]], area_map=[[0.0]]), "shape (1, 2)"),
    (dict(density=0.01, density_map=[[1.0, 1.0]], area_map=[[0.0, float("inf")]]), "finite log-area offsets"),
    (dict(density=0.01, density_map=[[1.0, 1.0]], area_map=[[0.0, 7.0]]), "finite log-area offsets"),
    (dict(density=0.01, density_map=[[1.0, 1.0]], area_map=[0.0, 0.0]), "2 dimensions"),
])
def test_bad_area_maps_are_one_line_errors(kw, expect):
    with pytest.raises(MaterialError) as e:
        FlakeModel(**kw)
    assert expect in str(e.value) and "\n" not in str(e.value) and "expected" in str(e.value)


def test_material_round_trip_keeps_the_area_map(tmp_path):
    save_material(_material(AREA_MAPPED), tmp_path / "m")
    entry = json.loads((tmp_path / "m" / "material.json").read_text())["flakes"]
    assert entry["maps"]["area_map"] == "flakes_area_map.npy" and "area_map" not in {k for k in entry if k != "maps"}
    back = load_material(tmp_path / "m").flakes
    assert torch.equal(back.area_map, AREA_MAPPED.area_map)
    assert _fields_equal(flake_field(back, 40, 48), flake_field(AREA_MAPPED, 40, 48))
    np.save(tmp_path / "m" / "flakes_area_map.npy", np.zeros((3, 3), np.float32))
    with pytest.raises(MaterialError, match="area_map: expected shape") as e:
        load_material(tmp_path / "m")
    assert "\n" not in str(e.value)


def test_onnx_parity_with_an_area_map(tmp_path):
    from torchmetal.onnx_export import PARITY_TOL, export_onnx, verify_onnx
    from torchmetal.renderer import MaterialRenderer

    m = _material(AREA_MAPPED)
    r = MaterialRenderer(m)
    path = export_onnx(m, tmp_path / "r.onnx", check=False)
    err = verify_onnx(path, r)
    assert err <= PARITY_TOL and err <= 1e-4


def _sized_particles(big: float, small: float, flakes: int = 240, seed: int = 1, n_shots: int = 4):
    """Flakes all over a 64×64 sample; flux/peak area ``big`` in the top half, ``small`` below (5 % jitter)."""
    g = torch.Generator().manual_seed(seed)
    cy, cx = torch.rand(flakes, generator=g) * 64, torch.rand(flakes, generator=g) * 64
    one = torch.ones(flakes)
    area = torch.where(cy < 32, torch.full_like(cy, big), torch.full_like(cy, small))
    area = area * torch.exp(0.05 * torch.randn(flakes, generator=g))
    rgb = torch.tensor([0.5, 0.5, 0.5]).expand(flakes, 3).clone()
    p = Particles(shot=torch.arange(flakes) % n_shots, area=area, cy=cy, cx=cx, major=2 * one, minor=2 * one,
                  angle=0 * one, rgb=rgb, lab=torch.zeros(flakes, 3), peak=rgb, amp=one, snr=40 * one, flux=area,
                  sigma=0.02 * one)
    return p, torch.arange(flakes)


def test_estimate_area_map_where_sizes_differ():
    cap = _capture()
    model = FlakeModel(density=0.01, tilt_sigma=0.3)
    p, fid = _sized_particles(12.0, 3.0)
    dm = estimate_map(cap, model, p, fid, grid=(2, 2), mode="area")
    rep = dm.report["area"]
    assert rep["kept"] and rep["p"] < 1e-6 and not dm.uniform and dm.area is not None
    top, bottom = dm.area[0].mean(), dm.area[1].mean()
    assert float(top - bottom) == pytest.approx(math.log(4.0), abs=0.05)  # many flakes: hardly shrunk
    n = torch.tensor(rep["counts"])
    assert float((n * dm.area.double()).sum()) == pytest.approx(0.0, abs=1e-4)  # flake-weighted mean 0
    m2 = with_map(model, dm)
    assert torch.equal(m2.area_map, dm.area)
    same = estimate_map(cap, model, *_sized_particles(6.0, 6.0), grid=(2, 2), mode="area")
    assert not same.report["area"]["kept"] and same.area is None and same.report["area"]["p"] >= AREA_P


def test_area_map_shrinks_blocks_with_few_flakes():
    cap = _capture()
    model = FlakeModel(density=0.01, tilt_sigma=0.3)
    p, fid = _sized_particles(12.0, 3.0)
    lone = (p.cy >= 32) & (p.cx >= 32)  # the bottom-right block: keep 3 of its flakes, made big
    keep = ~lone | (torch.cumsum(lone.long(), 0) <= 3)
    p, fid = p.select(keep), torch.arange(int(keep.sum()))
    big = (p.cy >= 32) & (p.cx >= 32)
    p.flux[big] = 12.0
    p.area[big] = 12.0
    dm = estimate_map(cap, model, p, fid, grid=(2, 2), mode="area")
    assert dm.area is not None
    full = float(dm.area[0].mean())  # the big top blocks
    assert 0.0 < float(dm.area[1, 1]) < full  # 3 big flakes: shrunk toward the global size


def test_bake_follows_a_half_zero_map():
    """glTF/USD preview bake: flake texels only where the density map is > 0 (left half: a flake whose cell
    centre is left of the edge may reach one cell past it), at k = 1 and 2."""
    from torchmetal.formats.engine import engine_material

    fl = FlakeModel(density=0.02, seed=2, glint_sigma=0.05, density_map=torch.tensor([[2.0, 0.0]]),
                    area_map=torch.tensor([[0.3, 0.0]]))
    m = _material(fl, 40, 48)
    plain = engine_material(replace(m, flakes=None))
    for k in (1, 2):
        em = engine_material(m, flakes="base", texels_per_pixel=k)
        base = plain.f0.repeat_interleave(k, 1).repeat_interleave(k, 2)
        diff = (em.f0 != base).any(0)
        half = 24 * k
        c = field_cell(replace(fl, density=fl.density / (k * k), area_log_mean=fl.area_log_mean + 2 * math.log(k)))
        assert bool(diff[:, :half].any()) and not bool(diff[:, half + c:].any())
        assert int(diff[:, :half].sum()) > 20 * int(diff[:, half:].sum())
        assert em.extras["flake_bake"]["flakes"] > 0


def test_chi2_sf_is_the_upper_tail_without_scipy():
    from torchmetal.flakes.estimate import density_map
    from torchmetal.flakes.estimate.density_map import chi2_sf

    # reference values: the χ² upper tail (scipy.stats.chi2.sf) at a few points
    assert chi2_sf(0.0, 3) == 1.0
    assert abs(chi2_sf(1.5, 3) - 0.6822703303362125) < 1e-12
    assert abs(chi2_sf(10.0, 4) - 0.04042768199451279) < 1e-12
    assert abs(chi2_sf(100.0, 15) - 1.3047043436251422e-14) < 1e-24
    assert "scipy" not in density_map.__dict__


def test_left_out_renders_in_one_renderer_equal_one_by_one():
    """The choices render several left-out shots with one renderer (the flake field baked once): the same
    values as a renderer per shot."""
    from torchmetal.flakes.choice import render_held

    cap, mat = _capture(), _material(MAPPED, 64, 64)
    both = render_held(mat, cap, [1, 3])
    assert both.shape == (2, 3, 64, 64) and float(both.max()) > 0
    assert torch.equal(both[0], render_held(mat, cap, [1])[0]) and torch.equal(both[1], render_held(mat, cap, [3])[0])
