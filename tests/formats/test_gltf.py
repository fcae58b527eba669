"""glTF/GLB: the Khronos validator on every material kind, read back, atomic writes, CLI."""

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from tests.formats.kinds import KINDS, make_material
from torchmetal.cli import main
from torchmetal.errors import ExportError
from torchmetal.formats import export_material, gltf
from torchmetal.formats.engine import check_lights, engine_material, engine_render
from torchmetal.material import save_material

ROOT = Path(__file__).resolve().parents[2]
RUNNER = Path(__file__).with_name("gltf_validate.cjs")


def validate(files: list[Path]) -> list[dict]:
    """The Khronos glTF-Validator report of each file (via node)."""
    if shutil.which("node") is None:
        pytest.skip("Node.js is not installed: the Khronos glTF validator needs it")
    if not (ROOT / "node_modules" / "gltf-validator").is_dir():
        pytest.fail("node_modules/gltf-validator is missing: run `npm ci` in the repository root")
    out = subprocess.run(["node", str(RUNNER), *map(str, files)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return [json.loads(line) for line in out.stdout.splitlines()]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("gltf")
    files = {}
    for kind in KINDS:
        m = make_material(kind)
        em = engine_material(m)
        files[kind] = (m, em, gltf.write_engine(em, root / f"{kind}.gltf"), gltf.write_engine(em, root / f"{kind}.glb"))
    return files


def test_validator_reports_no_errors_or_warnings(exported):
    paths = [p for *_, a, b in exported.values() for p in (a, b)]
    reports = validate(paths)
    assert len(reports) == len(paths)
    for r in reports:
        assert r["errors"] == 0 and r["warnings"] == 0, r
        assert "KHR_materials_specular" in r["extensions"] and "KHR_materials_ior" in r["extensions"]


def test_validator_catches_a_broken_file(tmp_path, exported):
    """The runner really validates: a file with an out-of-range factor fails."""
    *_, path, _ = exported["flat-global-noflakes"]
    doc = json.loads(path.read_text())
    doc["materials"][0]["pbrMetallicRoughness"]["roughnessFactor"] = 3.0
    bad = tmp_path / "bad.gltf"
    bad.write_text(json.dumps(doc))
    (r,) = validate([bad])
    assert r["errors"] > 0


@pytest.mark.parametrize("kind", KINDS)
def test_read_back(kind, exported):
    m, em, path_gltf, path_glb = exported[kind]
    for path in (path_gltf, path_glb):
        back = gltf.read(path)
        assert back.size == pytest.approx(m.size, rel=1e-6)
        torch.testing.assert_close(back.base_color, em.base_color, atol=6e-3, rtol=0)  # 8-bit sRGB
        torch.testing.assert_close(back.roughness, em.roughness, atol=2.5e-3, rtol=0)
        torch.testing.assert_close(back.f90, em.f90, atol=float(em.f90.max()) / 200 + 1e-7, rtol=0)
        torch.testing.assert_close(back.f0, em.f0, atol=float(em.f0.max()) / 60 + 1e-7, rtol=0)
        torch.testing.assert_close(back.normal, em.normal, atol=8e-3, rtol=0)
        assert (back.coat is None) == (em.coat is None)
        light, inten, cam = check_lights(m.size)
        a, b = engine_render(back, light, inten, cam), engine_render(em, light, inten, cam)
        assert float((a - b).norm() / b.norm()) < 0.01
        extras = back.extras
        assert extras["lobe_fit"][0]["roughness"] > 0 and len(extras["lobe_fit"][0]["error"]) == 3
        if m.flakes is not None:
            assert extras["flakes"] == m.flakes.to_dict() and extras["flake_bake"]["mode"] in ("base", "clearcoat", "flake_clearcoat")


def test_glb_is_one_binary_file(exported):
    *_, glb = exported["bumpy-clustered-flakes"]
    data = glb.read_bytes()
    assert data[:4] == b"glTF" and int.from_bytes(data[8:12], "little") == len(data)
    assert sorted(p.name for p in glb.parent.iterdir() if p.name.startswith("bumpy-clustered-flakes")) == [
        "bumpy-clustered-flakes.glb", "bumpy-clustered-flakes.gltf"]


@pytest.mark.parametrize("layout, texels", [("clearcoat", 1), ("flake_clearcoat", 1), ("base", 2)])
def test_every_flake_layout_validates(tmp_path, layout, texels):
    m = make_material("bumpy-global-flakes")
    path = gltf.write(m, tmp_path / "f.glb", flakes=layout, texels_per_pixel=texels)
    (r,) = validate([path])
    assert r["errors"] == 0 and r["warnings"] == 0, r
    back = gltf.read(path)
    assert ("KHR_materials_clearcoat" in r["extensions"]) == (layout != "base") == (back.coat is not None)
    assert back.base_color.shape[1:] == (texels * m.height, texels * m.width)


def test_interrupted_write_leaves_nothing(tmp_path, monkeypatch):
    import torchmetal.formats.gltf as mod

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(mod, "gltf_document", boom)  # fails after the fit, before any byte is written
    with pytest.raises(KeyboardInterrupt):
        mod.write(make_material("flat-global-noflakes"), tmp_path / "x.glb")
    assert list(tmp_path.iterdir()) == []


def test_read_garbage_is_one_line(tmp_path):
    bad = tmp_path / "x.gltf"
    bad.write_text("not json")
    with pytest.raises(ExportError, match="expected a glTF/GLB file"):
        gltf.read(bad)


def test_cli_export(tmp_path, capsys):
    mat = save_material(make_material("bumpy-global-flakes"), tmp_path / "mat")
    assert main(["export", str(mat), "--format", "glb", "-o", str(tmp_path / "m.glb")]) == 0
    assert main(["export", str(mat), "--format", "gltf"]) == 0
    assert (tmp_path / "m.glb").is_file() and (mat / "material.gltf").is_file()
    assert "as glb" in capsys.readouterr().out
    assert export_material(make_material("flat-global-noflakes"), "glb", tmp_path / "api.glb").is_file()


def test_cli_export_over_the_capture_views(tmp_path):
    """``export --capture`` fits the lobe over the capture's own views (here all overhead)."""
    from torchmetal.synth import synth_capture, write_synth

    cap = tmp_path / "cap"
    write_synth(synth_capture(size=16, shots=4, seed=1), cap)
    mat = save_material(make_material("flat-global-noflakes"), tmp_path / "mat")
    assert main(["export", str(mat), "--format", "glb", "--capture", str(cap), "-o", str(tmp_path / "c.glb")]) == 0
    assert main(["export", str(mat), "--format", "glb", "-o", str(tmp_path / "d.glb")]) == 0
    seen, default = (gltf.read(tmp_path / n).extras["lobe_fit"][0] for n in ("c.glb", "d.glb"))
    assert seen["samples"] < default["samples"] and max(seen["error"]) < max(default["error"])
