"""ONNX export of the renderer: checker, interface, self-contained file, parity with torch."""

from __future__ import annotations

import collections
import os
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

import torchmetal.onnx_export as ox
from tests.test_renderer import light_camera_cases, make_material
from torchmetal.errors import ExportError
from torchmetal.material import save_material
from torchmetal.onnx_export import PARITY_TOL, export_onnx, scaled_error, time_renderer, verify_onnx
from torchmetal.renderer import MaterialRenderer

EXPORT_KINDS = ("phong", "clustered", "flakes", "bumpy_flakes")
CATEGORIES = ("grazing", "overhead", "near", "far", "directional", "orthographic")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """kind → (renderer, path of its exported file, its folder)."""
    out = {}
    for kind in EXPORT_KINDS:
        d = tmp_path_factory.mktemp(f"onnx_{kind}")
        r = MaterialRenderer(make_material(kind)).eval()
        out[kind] = (r, export_onnx(r, d / "renderer.onnx"), d)
    return out


def session(path: Path) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def run(sess, light, inten, camera) -> np.ndarray:
    return sess.run(["image"], {"light": light.numpy(), "light_intensity": inten.numpy(), "camera": camera.numpy()})[0]


@pytest.mark.parametrize("kind", EXPORT_KINDS)
class TestFile:
    def test_checker_and_interface(self, exported, kind):
        r, path, _ = exported[kind]
        model = onnx.load(str(path))
        onnx.checker.check_model(model, full_check=True)
        ins = {i.name: i.type.tensor_type for i in model.graph.input}
        assert list(ins) == ["light", "light_intensity", "camera"]
        for name, c in (("light", 4), ("light_intensity", 3), ("camera", 4)):
            t = ins[name]
            assert t.elem_type == onnx.TensorProto.FLOAT
            dims = t.shape.dim
            assert len(dims) == 2 and dims[0].dim_param and not dims[0].HasField("dim_value") and dims[1].dim_value == c
        (out,) = model.graph.output
        assert out.name == "image" and out.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
        dims = out.type.tensor_type.shape.dim
        assert [d.dim_value for d in dims[1:]] == [3, r.height, r.width] and dims[0].dim_param
        assert model.opset_import[0].version == 20
        assert {ins[n].shape.dim[0].dim_param for n in ins} == {dims[0].dim_param}  # one shared batch
        meta = {p.key: p.value for p in model.metadata_props}
        assert meta["format"] == "torchmetal-renderer" and meta["height"] == str(r.height)

    def test_self_contained_no_random_ops(self, exported, kind):
        _, path, folder = exported[kind]
        assert sorted(p.name for p in folder.iterdir()) == ["renderer.onnx"]  # no .data, no temp files
        model = onnx.load(str(path), load_external_data=False)
        for init in model.graph.initializer:
            assert init.data_location == onnx.TensorProto.DEFAULT and not init.external_data
        ops = {n.op_type for n in model.graph.node}
        assert not any(op.startswith("Random") or op in ("Multinomial", "Bernoulli") for op in ops)

    @pytest.mark.parametrize("batch", [1, 16])
    def test_parity_random_mixed(self, exported, kind, batch):
        r, path, _ = exported[kind]
        sess = session(path)
        for seed in range(3):
            light, inten, camera = light_camera_cases(r.size, "mixed", batch=batch, seed=seed)
            got = run(sess, light, inten, camera)
            with torch.no_grad():
                ref = r(light, inten, camera).numpy()
            assert got.shape == ref.shape == (batch, 3, r.height, r.width)
            assert scaled_error(got, ref) <= PARITY_TOL

    @pytest.mark.parametrize("category", CATEGORIES)
    def test_parity_by_category(self, exported, kind, category):
        r, path, _ = exported[kind]
        light, inten, camera = light_camera_cases(r.size, category, batch=5, seed=11)
        got = run(session(path), light, inten, camera)
        with torch.no_grad():
            ref = r(light, inten, camera).numpy()
        assert scaled_error(got, ref) <= PARITY_TOL

    def test_identical_run_to_run(self, exported, kind):
        _, path, _ = exported[kind]
        light, inten, camera = light_camera_cases(category="mixed", batch=7, seed=2)
        a = run(session(path), light, inten, camera)
        s2 = session(path)
        b, c = run(s2, light, inten, camera), run(s2, light, inten, camera)
        assert np.array_equal(a, b) and np.array_equal(b, c)


class TestGraphContents:
    """Only what the material uses is in the graph; parameters are compact."""

    @staticmethod
    def _summary(path):
        model = onnx.load(str(path))
        ops = collections.Counter(n.op_type for n in model.graph.node)
        inits = {i.name: (tuple(i.dims), i.data_type) for i in model.graph.initializer}
        return ops, inits, os.path.getsize(path)

    def test_phong_only_has_no_flake_or_gather_ops(self, exported):
        r, path, _ = exported["phong"]
        ops, inits, size = self._summary(path)
        assert "ScatterElements" not in ops and not any(op.startswith("Gather") for op in ops)
        assert not any(name.startswith(("flake", "spec_labels", "normals")) for name in inits)
        assert not any(t == onnx.TensorProto.INT64 and int(np.prod(d)) > 16 for d, t in inits.values())
        big = [k for k, (dims, _) in inits.items() if np.prod(dims) >= r.height * r.width]
        assert big == ["texture"]  # no dense point / normal / specular maps
        assert size < 3 * r.height * r.width * 4 + 64 * 1024

    def test_flakes_are_sparse(self, exported):
        r, path, _ = exported["flakes"]
        ops, inits, _ = self._summary(path)
        assert ops["ScatterElements"] == 1
        n = r.flake_pixels
        assert 0 < n < 0.25 * r.height * r.width
        index = [k for k, (dims, t) in inits.items() if t == onnx.TensorProto.INT64 and int(np.prod(dims)) == n]
        assert len(index) == 1  # the flake pixel indices (names are the exporter's)
        per_flake = [k for k, (dims, t) in inits.items() if t == onnx.TensorProto.FLOAT and dims and dims[-1] == n]
        assert all(int(np.prod(inits[k][0])) <= 3 * n for k in per_flake) and len(per_flake) <= 5
        big = [k for k, (dims, _) in inits.items() if np.prod(dims) >= r.height * r.width]
        assert big == ["texture"]

    def test_clustered_specular_is_labels_plus_table(self, tmp_path):
        # above the exporter's constant-folding limit (512² values) the (3, H, W) maps stay a
        # uint8 label map + (3, K) tables in the file; onnxruntime folds the gather at load
        m = make_material("clustered", h=300, w=304)
        r = MaterialRenderer(m)
        path = export_onnx(r, tmp_path / "c.onnx")
        _, inits, size = self._summary(path)
        labels = [k for k, (dims, t) in inits.items() if t == onnx.TensorProto.UINT8]
        assert len(labels) == 1 and inits[labels[0]][0] == (r.height, r.width)
        floats = [k for k, (dims, t) in inits.items() if t == onnx.TensorProto.FLOAT and np.prod(dims) >= r.height * r.width]
        assert floats == ["texture"]
        assert size < 3 * r.height * r.width * 4 + r.height * r.width + 64 * 1024

    def test_bumpy_keeps_normals(self, exported):
        r, path, _ = exported["bumpy_flakes"]
        _, inits, _ = self._summary(path)
        big = [int(np.prod(dims)) for k, (dims, _) in inits.items() if np.prod(dims) >= r.height * r.width and k != "texture"]
        assert sum(big) == 3 * r.height * r.width  # the normal map (possibly split per component)


class TestExportApi:
    def test_material_and_material_dir(self, tmp_path):
        m = make_material("flakes", h=24, w=20)
        p = export_onnx(m, tmp_path / "a" / "r.onnx", check=True)
        assert p == tmp_path / "a" / "r.onnx" and p.is_file()
        save_material(m, tmp_path / "mat", extra_files={"renderer.onnx": p})
        p2 = export_onnx(tmp_path / "mat", tmp_path / "b.onnx", check=False)
        onnx.checker.check_model(onnx.load(str(p2)))
        p3 = export_onnx(m, tmp_path / "c.onnx", flakes=False, check=False)
        assert "ScatterElements" not in {n.op_type for n in onnx.load(str(p3)).graph.node}

    def test_dense_flake_fallback_exports(self, tmp_path, monkeypatch):
        import torchmetal.renderer as renderer_mod

        monkeypatch.setattr(renderer_mod, "DENSE_FLAKE_FRACTION", 0.0)
        r = MaterialRenderer(make_material("bumpy_flakes", h=24, w=28))
        assert r.flake_pixels == -1
        path = export_onnx(r, tmp_path / "dense.onnx")  # includes the parity check
        light, inten, camera = light_camera_cases(r.size, "mixed", batch=6, seed=5)
        with torch.no_grad():
            assert scaled_error(run(session(path), light, inten, camera), r(light, inten, camera).numpy()) <= PARITY_TOL

    def test_small_alpha_exact_horizon_exports(self, tmp_path):
        m = make_material("bumpy", h=20, w=24)
        m.alpha = torch.tensor([0.0, 0.3, 2.0])
        r = MaterialRenderer(m)
        assert r.exact_horizon
        export_onnx(r, tmp_path / "a.onnx")  # parity-checked

    def test_export_is_quiet(self, tmp_path, capfd):
        export_onnx(make_material("phong", h=16, w=16), tmp_path / "q.onnx")
        out, err = capfd.readouterr()
        assert out == "" and err == ""

    def test_parity_mismatch_raises_one_line(self, exported):
        _, path, _ = exported["flakes"]
        other = MaterialRenderer(make_material("flakes", seed=9))
        with pytest.raises(ExportError, match="expected onnxruntime == torch") as e:
            verify_onnx(path, other)
        assert "\n" not in str(e.value)

    def test_failed_verification_leaves_nothing(self, tmp_path, monkeypatch):
        def fail(*a, **k):
            raise ExportError("boom")

        monkeypatch.setattr(ox, "verify_onnx", fail)
        with pytest.raises(ExportError, match="boom"):
            export_onnx(make_material("phong", h=16, w=16), tmp_path / "x.onnx")
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize(
        "model, kwargs, match",
        [
            ("not-a-material", {}, "expected a Material"),
            (None, {"opset": 11}, "opset: expected an integer >= 18"),
        ],
    )
    def test_bad_arguments(self, tmp_path, model, kwargs, match):
        model = make_material("phong", h=8, w=8) if model is None else model
        with pytest.raises(ExportError, match=match) as e:
            export_onnx(model, tmp_path / "x.onnx", **kwargs)
        assert "\n" not in str(e.value)

    def test_time_renderer(self, exported):
        r, path, _ = exported["flakes"]
        keys = {"backend", "height", "width", "batch", "repeats", "threads", "ms_median", "ms_min", "ms_mean", "ms_per_shot", "fps",
                "cpu_ms", "load_1min"}
        for target in (path, str(path), session(path), r):
            t = time_renderer(target, repeats=2, warmup=1, batch=2)
            assert keys <= set(t) and t["height"] == r.height and t["ms_min"] > 0 and t["batch"] == 2
            assert t["cpu_ms"] > 0 and t["load_1min"] >= 0
        assert time_renderer(r, repeats=1)["backend"] == "torch-eager"
        with pytest.raises(ExportError):
            time_renderer(path, repeats=0)


def test_session_options_no_spinning_all_optimisations(tmp_path):
    so = ox.session_options(2, profile_prefix=str(tmp_path / "p"))
    assert so.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert so.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert so.intra_op_num_threads == 2 and so.enable_profiling
    assert ox.session_options().intra_op_num_threads == 0 and not ox.session_options().enable_profiling


@pytest.mark.parametrize("lobe", ["phong", "ggx"])
def test_channel_shared_cluster_alpha_exports(tmp_path, lobe):
    m = make_material("clustered")
    m.lobe = lobe
    m.cluster_alpha = torch.tensor([[8.0] * 3, [900.0] * 3, [60.0] * 3])
    r = MaterialRenderer(m)
    assert r.alpha_uniform
    assert verify_onnx(export_onnx(r, tmp_path / "u.onnx"), r) <= PARITY_TOL
