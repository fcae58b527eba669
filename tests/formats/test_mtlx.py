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


# ----------------------------------------------------------------------------- the flake-density map


def _mapped(area: bool = True):
    import math
    from dataclasses import replace

    import torch

    m = make_material("bumpy-global-flakes")
    fl = replace(m.flakes, density_map=torch.tensor([[2.0, 0.0], [1.0, 0.5]]),
                 area_map=torch.tensor([[math.log(1.5), 0.0], [-0.3, 0.0]]) if area else None)
    return replace(m, flakes=fl)


def test_density_map_drives_flake2d_coverage(tmp_path, lib):
    """The density map becomes a closest-filtered coverage texture × scale on flake2d; the document
    validates and generates; the stored report gives each block's density and says the area map is lost."""
    from torchmetal.formats.flake2d import density_to_probability

    m = _mapped()
    path = mtlx.write(m, tmp_path / "m.mtlx")
    doc = _doc(path)
    ok, msg = mtlx.validate(doc, lib)
    assert ok, msg
    for target in mtlx.TARGETS:
        assert "flake" in mtlx.generate(doc, target, lib)
    img = doc.getNodeGraph("NG_torchmetal").getNode("flake_coverage_image")
    assert img.getInputValue("filtertype") == "closest"
    back = mtlx.read(path)
    cov = back["flake2d"]["coverage"]
    planes = decode_png((path.parent / cov["file"]).read_bytes())[:, :, 0]
    assert planes.shape == (2, 2) and planes[0, 1] == 0.0 and planes[0, 0] == 1.0
    fi = flake2d_inputs(m.flakes, m.width)
    rel = density_to_probability(planes * cov["scale"]) / fi.probability  # flakes per texel ∝ p at one size
    np.testing.assert_allclose(rel, m.flakes.density_map.numpy(), atol=0.01)
    rep = back["torchmetal"]["flake2d"]
    assert rep["density_map"]["mean_density_ratio"] == pytest.approx(1.0, abs=0.005)
    assert rep["density_map"]["max_abs_error"] < 0.01 and rep["density_map"]["capped_blocks"] == 0
    lost = {e["what"]: e for e in rep["not_carried"]}
    assert set(lost) == {"area_map"} and lost["area_map"]["block_median_area_ratio"] == pytest.approx([np.exp(-0.3), 1.5])
    from dataclasses import replace

    import torch

    coloured = replace(m, flakes=replace(m.flakes, color_map=torch.full((2, 2, 3), 0.5)))
    lost = {e["what"] for e in mtlx.mtlx_plan(coloured)[1]["flake2d"]["not_carried"]}
    assert lost == {"area_map", "color_map"}
    plain = mtlx.read(mtlx.write(make_material("bumpy-global-flakes"), tmp_path / "p.mtlx"))
    assert isinstance(plain["flake2d"]["coverage"], float) and plain["torchmetal"]["flake2d"]["not_carried"] == []


def test_flake2d_port_follows_the_block_coverage():
    """The numpy port of flake2d at each block's (8-bit) coverage: flakes per texel follow the map."""
    m = _mapped(area=False)
    fi = flake2d_inputs(m.flakes, m.width)
    planes, scale, rep = mtlx.coverage_map(m.flakes, fi, m.height, m.width)
    side = 160
    t = (np.arange(side) + 0.5) / m.width
    yy, xx = np.meshgrid(t, t, indexing="ij")
    pts = np.stack([xx.ravel(), yy.ravel()], 1)
    counts = {}
    for lam, c in zip(m.flakes.density_map.numpy().ravel(), planes.ravel()):
        from torchmetal.formats.flake2d import flake2d_pattern

        key, _ = flake2d_pattern(pts, fi.size, fi.roughness, float(c * scale))
        counts[float(lam)] = len(np.unique(key[key >= 0])) / side**2
    assert counts[0.0] == 0.0
    for lam in (2.0, 0.5):
        assert counts[lam] / counts[1.0] == pytest.approx(lam, rel=0.15), counts


def test_usd_mtlx_context_carries_the_coverage_map():
    pytest.importorskip("pxr")
    from torchmetal.formats import usd

    stage, textures = usd.build_stage(_mapped(), "x.textures", flakes="base")
    assert "flake_coverage" in textures
    prim = stage.GetPrimAtPath(f"{usd.MATERIAL}/NG_torchmetal/flake_coverage_image")
    assert prim.IsValid() and prim.GetAttribute("inputs:filtertype").Get() == "closest"
    from pxr import UsdShade

    flakes = UsdShade.Shader(stage.GetPrimAtPath(f"{usd.MATERIAL}/NG_torchmetal/flakes"))
    assert flakes.GetInput("coverage").HasConnectedSource()
