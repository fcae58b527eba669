"""MaterialX: Document.validate() and GLSL/OSL/MDL generation for every kind, read back."""

import numpy as np
import pytest

from tests.formats.kinds import KINDS, make_material
from torchmetal.errors import ExportError
from torchmetal.formats import mtlx
from torchmetal.formats.engine import check_lights, engine_material, render_error
from torchmetal.formats.flake2d import flake2d_inputs
from torchmetal.formats.textures import decode_png, hwc, to_srgb

mx = pytest.importorskip("MaterialX")


@pytest.fixture(scope="module")
def lib():
    return mtlx.stdlib()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("mtlx")
    return {kind: (make_material(kind), mtlx.write(make_material(kind), root / f"{kind}.mtlx")) for kind in KINDS}


def _doc(path):
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    return doc


@pytest.mark.parametrize("kind", KINDS)
def test_validates_and_generates(kind, exported, lib):
    m, path = exported[kind]
    text = path.read_text()
    assert "xi:include" not in text and "open_pbr_surface" in text
    doc = _doc(path)
    ok, msg = mtlx.validate(doc, lib)
    assert ok, msg
    for target in mtlx.TARGETS:
        src = mtlx.generate(doc, target, lib)
        assert len(src) > 1000
        if m.flakes is not None:
            assert "flake" in src, target


@pytest.mark.parametrize("kind", KINDS)
def test_read_back(kind, exported):
    m, path = exported[kind]
    back = mtlx.read(path)
    em, plan, textures = mtlx.mtlx_plan(m)
    ins = back["inputs"]
    for name, value in plan["inputs"].items():
        if name.startswith("flake_"):
            continue
        got = ins[name]
        if isinstance(value, tuple) and value[0] == "texture":
            planes = decode_png((path.parent / got["file"]).read_bytes())[:, :, :3]
            np.testing.assert_allclose(planes, np.clip(textures[value[1]], 0, 1), atol=0.6 / 255 + 1e-9)
            assert got["scale"] == pytest.approx(value[2] if len(value) > 2 else 1.0, rel=1e-5)  # 6 digits in XML
        elif isinstance(value, tuple):
            assert "node" in got
        else:
            assert got == pytest.approx(value, rel=1e-5)
    np.testing.assert_allclose(decode_png((path.parent / ins["base_color"]["file"]).read_bytes())[:, :, :3],
                               to_srgb(hwc(em.base_color)), atol=0.6 / 255)
    if m.flakes is None:
        assert back["flake2d"] is None and ins["coat_weight"] == 0.0
    else:
        fi = flake2d_inputs(m.flakes, m.width)
        assert back["flake2d"] == pytest.approx({"size": fi.size, "roughness": fi.roughness, "coverage": fi.coverage}, rel=1e-5)
        assert ins["geometry_normal"] == {"node": "flake2d"} and ins["specular_weight"] == {"node": "ifgreater"}
        assert back["torchmetal"]["flake2d"]["statistics"] == m.flakes.to_dict()
    assert back["torchmetal"]["lobe_fit"][0]["error"]


@pytest.mark.parametrize("kind", KINDS)
def test_read_back_coat_renders_like_the_material(kind, exported):
    """The coat read back from the .mtlx, evaluated with the glTF-equivalent BRDF, renders like the
    engine maps written directly (the flakes, procedural in MaterialX, are left out on both sides)."""
    m, path = exported[kind]
    coat = m.to("cpu")
    coat.flakes = None
    shots = check_lights(m.size)
    back = render_error(mtlx.to_engine(mtlx.read(path), m.size), coat, *shots)
    direct = render_error(engine_material(coat), coat, *shots)
    assert back < direct + 0.03, (back, direct)


def test_rewrite_replaces_textures(tmp_path):
    p = mtlx.write(make_material("bumpy-clustered-noflakes"), tmp_path / "a.mtlx")
    names = sorted(f.name for f in (tmp_path / "a.textures").iterdir())
    mtlx.write(make_material("flat-global-noflakes"), p)
    assert sorted(f.name for f in (tmp_path / "a.textures").iterdir()) == ["base_color.png"] != names
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.mtlx", "a.textures"]


def test_bad_inputs_one_line(tmp_path, lib):
    bad = tmp_path / "x.mtlx"
    bad.write_text("<materialx version='1.39'><nodegraph")
    with pytest.raises(ExportError, match="expected a MaterialX document"):
        mtlx.read(bad)
    with pytest.raises(ExportError, match="target: expected one of"):
        mtlx.generate(_doc(mtlx.write(make_material("flat-global-noflakes"), tmp_path / "y.mtlx")), "hlsl", lib)


def test_cli_export(tmp_path):
    from torchmetal.cli import main
    from torchmetal.material import save_material

    mat = save_material(make_material("bumpy-global-flakes"), tmp_path / "mat")
    assert main(["export", str(mat), "--format", "mtlx"]) == 0
    assert (mat / "material.mtlx").is_file() and (mat / "material.textures" / "base_color.png").is_file()
