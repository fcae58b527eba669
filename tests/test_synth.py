"""Synthetic captures: reproducibility, ground-truth consistency, layouts, quantisation, files."""

import json
import sys

import numpy as np
import pytest
import torch

from torchmetal.errors import InputError
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.field import sparkle_render
from torchmetal.geometry import shading_geometry
from torchmetal.io.capture import load_capture
from torchmetal.phong import phong_render
from torchmetal.synth import LAYOUTS, SURFACE, read_synth_truth, synth_capture, write_synth

SMALL = dict(size=32, shots=6)


def tensors(result):
    c = result.capture
    out = {f: getattr(c, f) for f in ("images", "normals", "mask", "lights", "intensities", "cameras", "saturated")}
    out.update({f"truth.{k}": v for k, v in result.truth.items() if isinstance(v, torch.Tensor)})
    return out


class TestReproducible:
    @pytest.mark.parametrize("texture", ["procedural", "photo"])
    def test_same_seed_identical(self, texture):
        kw = dict(SMALL, texture=texture, bumpy=True, noise=0.05, spec_clusters=3, flakes=FlakeModel(0.02, seed=1))
        a, b = tensors(synth_capture(seed=3, **kw)), tensors(synth_capture(seed=3, **kw))
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), k

    def test_different_seed_differs(self):
        a = synth_capture(seed=0, texture="procedural", noise=0.01, **SMALL)
        b = synth_capture(seed=1, texture="procedural", noise=0.01, **SMALL)
        assert not torch.equal(a.truth["texture"], b.truth["texture"])
        assert not torch.equal(a.capture.lights, b.capture.lights)
        assert not torch.equal(a.capture.images, b.capture.images)

    def test_global_rng_untouched(self):
        torch.manual_seed(123)
        before = torch.rand(3)
        torch.manual_seed(123)
        synth_capture(noise=0.1, texture="procedural", bumpy=True, spec_clusters=2, **SMALL)
        assert torch.equal(torch.rand(3), before)

    def test_options_do_not_reshuffle_each_other(self):
        a = synth_capture(seed=5, texture="procedural", **SMALL)
        b = synth_capture(seed=5, texture="procedural", noise=0.1, bumpy=True, **SMALL)
        assert torch.equal(a.truth["texture"], b.truth["texture"])
        assert torch.equal(a.capture.lights, b.capture.lights)


class TestGroundTruth:
    @pytest.mark.parametrize("layout", LAYOUTS)
    def test_render_truth_reproduces_images(self, layout):
        r = synth_capture(layout=layout, texture="procedural", **SMALL)
        c, t = r.capture, r.truth
        img = phong_render(t["texture"], t["s"], t["alpha"], t["normals"], c.lights, c.intensities, c.cameras, c.size)
        assert (img - c.images).abs().max() <= 1e-6

    def test_clustered_bumpy_flakes_reproduce_images(self):
        flakes = FlakeModel(0.02, seed=4)
        r = synth_capture(texture="procedural", bumpy=True, spec_clusters=3, flakes=flakes, **SMALL)
        c, t = r.capture, r.truth
        lab = t["spec_labels"]
        s_map = t["cluster_s"][lab].permute(2, 0, 1)
        a_map = t["cluster_alpha"][lab].permute(2, 0, 1)
        img = phong_render(t["texture"], s_map, a_map, c.normals, c.lights, c.intensities, c.cameras, c.size)
        img = img + sparkle_render(t["flake_field"], c.normals, c.lights, c.intensities, c.cameras, c.size)
        assert (img - c.images).abs().max() <= 1e-6
        assert torch.equal(r.render_clean(), c.images)
        assert t["flakes"] is flakes and t["flake_field"].count > 0

    def test_render_clean_subset(self):
        r = synth_capture(texture="procedural", noise=0.05, **SMALL)
        clean = r.render_clean([1, 3])
        assert clean.shape == (2, 3, 32, 32)
        noise = r.capture.images[[1, 3]] - clean
        assert 0.01 < float(noise.std() / clean.mean()) < 0.1

    def test_truth_ranges(self):
        r = synth_capture(texture="procedural", size=48, shots=3)
        t = r.truth
        assert t["texture"].shape == (3, 48, 48) and t["texture"].dtype == torch.float32
        assert float(t["texture"].min()) >= 0.05 - 1e-6 and float(t["texture"].max()) <= 0.7 + 1e-6
        assert torch.equal(t["s"], torch.tensor([0.6, 0.6, 0.6])) and torch.equal(t["alpha"], torch.tensor([40.0, 60.0, 80.0]))
        assert r.capture.flat and t["flakes"] is None and t["flake_field"] is None and "spec_labels" not in t

    def test_photo_texture_in_range(self):
        pytest.importorskip("skimage")
        r = synth_capture(texture="photo", size=40, shots=2, seed=1)
        assert r.params["texture"].startswith("photo:")
        tex = r.truth["texture"]
        assert float(tex.min()) >= 0.05 - 1e-6 and float(tex.max()) <= 0.7 + 1e-6 and float(tex.std()) > 0.02

    def test_photo_falls_back_without_skimage(self, monkeypatch):
        monkeypatch.setitem(sys.modules, "skimage", None)
        r = synth_capture(texture="photo", **SMALL)
        assert r.params["texture"] == "procedural"

    def test_bumpy_normals(self):
        r = synth_capture(bumpy=True, texture="procedural", **SMALL)
        n = r.capture.normals
        assert not r.capture.flat and torch.allclose(n.norm(dim=0), torch.ones(32, 32), atol=1e-6)
        slope = torch.sqrt(n[0] ** 2 + n[1] ** 2) / n[2]
        assert 0.1 < float(slope.max()) <= 0.15 + 1e-4
        assert r.truth["height_field"].shape == (32, 32)

    def test_spec_clusters(self):
        r = synth_capture(spec_clusters=4, texture="procedural", size=64, shots=2)
        t = r.truth
        assert t["spec_labels"].shape == (64, 64) and t["spec_labels"].dtype == torch.int64
        assert sorted(t["spec_labels"].unique().tolist()) == [0, 1, 2, 3]
        assert t["cluster_s"].shape == (4, 3) and t["cluster_alpha"].shape == (4, 3)
        assert torch.allclose(t["cluster_s"][0], torch.tensor([0.6] * 3))
        assert torch.allclose(t["cluster_alpha"][0], torch.tensor([40.0, 60.0, 80.0]))
        assert len({tuple(v) for v in t["cluster_alpha"].tolist()}) == 4

    def test_material(self):
        r = synth_capture(spec_clusters=2, bumpy=True, texture="procedural", flakes=FlakeModel(0.01), **SMALL)
        m = r.material()
        assert m.clustered and m.normals is not None and m.flakes == r.truth["flakes"] and m.size == SURFACE

    def test_float64(self):
        r = synth_capture(dtype=torch.float64, texture="procedural", **SMALL)
        c = r.capture
        assert c.images.dtype == c.lights.dtype == r.truth["texture"].dtype == torch.float64


class TestLayouts:
    @pytest.mark.parametrize("layout", LAYOUTS)
    def test_lights_and_cameras_above_surface(self, layout):
        c = synth_capture(layout=layout, texture="procedural", shots=16, size=16).capture
        assert (c.lights[:, 2] > 0).all() and (c.cameras[:, 2] > 0).all()
        assert (c.cameras[:, 3] == 1).all() and (c.cameras[:, 2] - 0.3).abs().max() <= 0.01
        w = 1.0 if layout in ("ring", "hemisphere", "near") else 0.0
        assert (c.lights[:, 3] == w).all()
        assert (c.intensities > 0).all()

    def test_grazing_elevation(self):
        c = synth_capture(layout="grazing", texture="procedural", shots=16, size=16).capture
        elev = torch.rad2deg(torch.asin(c.lights[:, 2] / c.lights[:, :3].norm(dim=1)))
        assert float(elev.min()) >= 5 - 1e-4 and float(elev.max()) <= 15 + 1e-4

    def test_near_is_near(self):
        c = synth_capture(layout="near", texture="procedural", **SMALL).capture
        assert float(c.lights[:, 2].max()) <= 0.08 + 1e-6

    @pytest.mark.parametrize("layout", ["ring", "hemisphere", "near"])
    def test_every_shot_has_a_highlight(self, layout):
        c = synth_capture(layout=layout, texture="procedural", shots=12, size=64).capture
        g = shading_geometry(c.normals, c.lights, c.intensities, c.cameras, c.size)
        # mirror direction hits the camera somewhere on the sample (r·v within ~2.5° of 1)
        assert (g.spec_q.amin(dim=(1, 2, 3)) < 1e-3).all()

    @pytest.mark.parametrize("layout", LAYOUTS)
    def test_exposure_typical(self, layout):
        c = synth_capture(layout=layout, texture="procedural", shots=8, size=32).capture
        med = c.images.flatten(1).median(dim=1).values
        assert (med > 0.1).all() and (med < 0.6).all(), med

    def test_exposure_scales(self):
        a = synth_capture(texture="procedural", **SMALL).capture
        b = synth_capture(texture="procedural", exposure=2.0, **SMALL).capture
        assert torch.allclose(b.intensities, 2 * a.intensities)


class TestQuantised:
    @pytest.mark.parametrize("bits", [8, 16])
    def test_values_on_the_grid_and_saturation(self, bits):
        top = 2**bits - 1
        c = synth_capture(bits=bits, exposure=3.0, texture="procedural", **SMALL).capture
        q = torch.round(c.images.double() * top)
        assert torch.equal(q.float() / top, c.images)  # exactly what a reader gets from the file
        assert float(c.images.max()) == 1.0
        assert torch.equal(c.saturated, c.images == 1.0) and c.saturated.any()

    def test_float_not_clipped(self):
        c = synth_capture(exposure=3.0, texture="procedural", **SMALL).capture
        assert float(c.images.max()) > 1.0 and not c.saturated.any() and float(c.images.min()) >= 0

    def test_noise_clamped_non_negative(self):
        c = synth_capture(noise=3.0, texture="procedural", **SMALL).capture
        assert float(c.images.min()) == 0.0


class TestFiles:
    @pytest.mark.parametrize("bits", [None, 8, 16])
    def test_write_and_reload_exact(self, tmp_path, bits):
        r = synth_capture(bits=bits, bumpy=True, spec_clusters=2, flakes=FlakeModel(0.02, seed=2), exposure=2.0,
                          texture="procedural", **SMALL)
        path = write_synth(r, tmp_path / "syn")
        c = load_capture(path)
        for f in ("images", "normals", "mask", "lights", "intensities", "cameras", "saturated"):
            assert torch.equal(getattr(c, f), getattr(r.capture, f)), f
        assert c.size == r.capture.size and bool(r.capture.saturated.any()) == (bits is not None)
        suffix = ".npy" if bits is None else ".png"
        assert all(n.endswith(suffix) for n in c.names)
        t = read_synth_truth(path)
        assert torch.equal(t["texture"], r.truth["texture"])
        assert torch.equal(t["s"], r.truth["s"]) and torch.equal(t["alpha"], r.truth["alpha"])
        assert torch.equal(t["spec_labels"], r.truth["spec_labels"])
        assert torch.equal(t["cluster_alpha"], r.truth["cluster_alpha"])
        assert t["flakes"] == r.truth["flakes"] and t["params"] == r.params
        meta = json.loads((path / "truth" / "truth.json").read_text())
        assert meta["format"] == "torchmetal-synth-truth" and meta["normals"] == "../normals.npy"
        assert np.load(path / "truth" / "texture.npy").shape == (32, 32, 3)
        # the noise-free, unclipped render of every shot: what held-out shots are scored against
        assert torch.equal(t["clean"], r.render_clean().float())
        assert float(t["clean"].max()) > 1.0  # exposure 2: the clean render is not clipped at 1

    def test_rewrite_replaces(self, tmp_path):
        write_synth(synth_capture(texture="procedural", **SMALL), tmp_path / "syn")
        r = synth_capture(texture="procedural", size=16, shots=2, seed=9)
        write_synth(r, tmp_path / "syn")
        assert load_capture(tmp_path / "syn").images.shape == (2, 3, 16, 16)
        assert read_synth_truth(tmp_path / "syn" / "truth")["flakes"] is None
        assert sorted(p.name for p in tmp_path.iterdir()) == ["syn"]


BAD_ARGS = {
    "size": (dict(size=2), "size"),
    "shots": (dict(shots=0), "shots"),
    "texture": (dict(texture="marble"), "texture"),
    "layout": (dict(layout="spiral"), "layout"),
    "alpha": (dict(alpha=(1.0, 2.0)), "alpha"),
    "s": (dict(s=(0.1, -0.1, 0.1)), "s"),
    "noise": (dict(noise=-1.0), "noise"),
    "bits": (dict(bits=12), "bits"),
    "exposure": (dict(exposure=0.0), "exposure"),
    "flakes": (dict(flakes={"density": 0.1}), "flakes"),
    "spec_clusters": (dict(spec_clusters=0), "spec_clusters"),
}


@pytest.mark.parametrize("case", sorted(BAD_ARGS))
def test_bad_arguments(case):
    kw, name = BAD_ARGS[case]
    with pytest.raises(InputError) as e:
        synth_capture(**kw)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{name}: expected")
