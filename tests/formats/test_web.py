"""``export --format web``: the static site's files, onnxruntime-web from node_modules, atomic writes."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from torchmetal.errors import ExportError, InputError
from torchmetal.formats import web


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """A 32² flake-free synthetic capture + its truth material, and its site written through the CLI."""
    from torchmetal.cli import main
    from torchmetal.material import save_material
    from torchmetal.synth import synth_capture, write_synth

    root = tmp_path_factory.mktemp("web")
    r = synth_capture(size=32, shots=2, seed=1, texture="procedural")
    write_synth(r, root / "capture")
    save_material(r.material(), root / "material")
    rc = main(["export", str(root / "material"), "--format", "web", "-o", str(root / "site"), "--capture", str(root / "capture")])
    assert rc == 0
    return root, r


def test_site_files(plain):
    root, _ = plain
    site = root / "site"
    names = {p.relative_to(site).as_posix() for p in site.rglob("*") if p.is_file()}
    from torchmetal.viewer.three import FILES as THREE_FILES

    assert names == {"index.html", "viewer.js", "state.js", "display.js", "style.css", "preview.js", "config.json",
                     "README.txt", "renderer.onnx", "photos/000.png", "photos/001.png",
                     *(f"ort/{n}" for n in web.WASM_FILES), "material.glb", *THREE_FILES}  # 3D preview: tests/viewer/test_preview.py
    cfg = json.loads((site / "config.json").read_text())
    assert (cfg["mode"], cfg["width"], cfg["height"], cfg["threads"]) == ("static", 32, 32, 1)
    assert cfg["graphs"] == {"plain": "renderer.onnx"}  # no flakes: one graph, flakes toggle disabled
    assert cfg["ort"]["wasm"] == "ort/ort.wasm.min.mjs" and cfg["ort"]["webgpu"] is None
    assert cfg["ort"]["version"].startswith("1.30.")
    assert [s["photo"] for s in cfg["shots"]] == ["photos/000.png", "photos/001.png"]


def test_ort_copied_from_node_modules(plain):
    root, _ = plain
    dist, version = web.find_ort_web()
    assert version.startswith("1.30.")
    for name in web.WASM_FILES:
        assert (root / "site" / "ort" / name).read_bytes() == (dist / name).read_bytes()


def test_page_loads_nothing_from_elsewhere(plain):
    """No absolute URLs in the page: ORT, the graphs and photos all come from the site folder."""
    root, _ = plain
    for name in ("index.html", "viewer.js", "state.js", "display.js", "style.css"):
        text = (root / "site" / name).read_text()
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", text, re.I), name
    assert 'wasmPaths = new URL("ort/", location.href)' in (root / "site" / "viewer.js").read_text()


def test_graph_is_the_material_renderer(plain):
    import onnxruntime as ort
    import torch

    from torchmetal.renderer import MaterialRenderer

    root, r = plain
    sess = ort.InferenceSession(str(root / "site" / "renderer.onnx"), providers=["CPUExecutionProvider"])
    c = r.capture
    got = sess.run(["image"], {"light": c.lights.numpy(), "light_intensity": c.intensities.numpy(), "camera": c.cameras.numpy()})[0]
    with torch.inference_mode():
        want = MaterialRenderer(r.material())(c.lights, c.intensities, c.cameras).numpy()
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_photos_are_srgb_of_the_capture(plain):
    from PIL import Image

    from torchmetal.io.images import linear_to_srgb, quantize

    root, r = plain
    img = np.asarray(Image.open(root / "site" / "photos" / "001.png").convert("RGB"))
    want = quantize(linear_to_srgb(r.capture.images[1].clamp(0, 1)).permute(1, 2, 0).numpy(), 8)
    assert np.array_equal(img, want)


def test_rewrite_over_previous_site(plain, tmp_path):
    root, r = plain
    site = tmp_path / "site"
    shutil.copytree(root / "site", site)
    (site / "stale.txt").write_text("old")
    web.write(r.material(), site)
    assert not (site / "stale.txt").exists() and json.loads((site / "config.json").read_text())["shots"] == []
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folders left


def test_missing_ort_says_npm_ci(plain, tmp_path, monkeypatch):
    _, r = plain
    with pytest.raises(ExportError, match=r"onnxruntime-web: expected .*ort.wasm.min.mjs.*run `npm ci`") as e:
        web.write(r.material(), tmp_path / "site", ort_dir=tmp_path)
    assert "\n" not in str(e.value)
    monkeypatch.setenv(web.ORT_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(ExportError, match="npm ci"):
        web.find_ort_web()
    assert not (tmp_path / "site").exists()


def test_env_var_names_another_folder(tmp_path, monkeypatch):
    dist, _ = web.find_ort_web()
    pkg = tmp_path / "ort-web"
    (pkg / "dist").mkdir(parents=True)
    for name in web.WASM_FILES:
        (pkg / "dist" / name).symlink_to(dist / name)
    (pkg / "package.json").write_text(json.dumps({"version": "1.30.0"}))
    monkeypatch.setenv(web.ORT_ENV, str(pkg))
    assert web.find_ort_web() == (pkg / "dist", "1.30.0")
    (pkg / "package.json").write_text(json.dumps({"version": "1.17.3"}))
    with pytest.raises(ExportError, match=r"expected version 1\.30\.x .* found 1\.17\.3"):
        web.find_ort_web()
    with pytest.raises(ExportError, match="WebGPU|asyncify"):
        (pkg / "package.json").write_text(json.dumps({"version": "1.30.0"}))
        web.find_ort_web(webgpu=True)


def test_refuses_foreign_folder_and_file(plain, tmp_path):
    _, r = plain
    other = tmp_path / "docs"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    with pytest.raises(ExportError, match="expected an empty folder or an earlier web export"):
        web.write(r.material(), other)
    assert (other / "keep.txt").read_text() == "mine" and len(list(other.iterdir())) == 1
    (tmp_path / "f").write_text("x")
    with pytest.raises(ExportError, match="found a file"):
        web.write(r.material(), tmp_path / "f")


def test_failure_leaves_nothing(plain, tmp_path, monkeypatch):
    from torchmetal.viewer import site

    _, r = plain

    def boom(*a, **k):
        raise ExportError("export failed on purpose")

    monkeypatch.setattr(site, "export_graphs", boom)
    with pytest.raises(ExportError, match="on purpose"):
        web.write(r.material(), tmp_path / "site")
    assert list(tmp_path.iterdir()) == []


def test_capture_of_another_surface(plain, tmp_path):
    from dataclasses import replace

    root, r = plain
    cap = replace(r.capture, size=(0.5, 0.5))
    with pytest.raises(InputError, match="capture: expected the material's surface"):
        web.write(r.material(), tmp_path / "site", capture=cap)


def test_bad_threads(plain, tmp_path):
    with pytest.raises(ExportError, match="threads: expected an integer >= 1"):
        web.write(plain[1].material(), tmp_path / "site", threads=0)


def test_cli_lists_web(capsys):
    from torchmetal.cli import main

    with pytest.raises(SystemExit):
        main(["export", "--help"])
    out = capsys.readouterr().out
    assert "web" in out and "--capture" in out and "--webgpu" in out
