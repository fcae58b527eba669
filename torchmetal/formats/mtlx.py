"""MaterialX writer and reader (``export --format mtlx``): ``open_pbr_surface`` + ``flake2d``.

The document (no library ``xi:include``s; MaterialX ≥ 1.39.5 resolves the nodes from its
standard libraries) holds one node graph feeding one ``open_pbr_surface`` and a
``surfacematerial``. Textures are 8-bit PNGs in ``<stem>.textures/`` beside the ``.mtlx``.

Without flakes the specular layer is the coat lobe, fitted as for glTF
(:mod:`torchmetal.formats.engine`): ``specular_roughness`` (factor or texture), ``specular_ior``,
``specular_color`` and ``specular_weight`` (F0 = F0(ior)·colour·weight, F90 = weight).
With flakes the coat lobe moves to OpenPBR's coat (``coat_weight`` = F0/F0(coat_ior) per texel,
``coat_ior`` from the brightest F0, ``coat_roughness``, ``geometry_coat_normal`` = the surface
normals), and the base specular becomes the flakes: ``flake2d`` (inputs from
:func:`~torchmetal.formats.flake2d.flake2d_inputs`: size, roughness, coverage) drives
``geometry_normal`` with its ``flakenormal``; ``specular_weight`` is 1 on a flake (``presence`` > 0)
and 0 elsewhere; ``specular_roughness``/``specular_ior``/``specular_color`` come from the GGX fit
of one glint (:func:`~torchmetal.formats.lobe_fit.fit_glint`) at the mean glint colour.
The flake statistics and the mapping are stored in the document's ``doc`` string as JSON.

A flake-density map (:attr:`~torchmetal.flakes.model.FlakeModel.density_map`) drives ``coverage``
with a gh×gw grey image (``flake_coverage.png``, closest filtering, times its maximum): at flake2d's one
cell ``size`` the flakes per texel follow the cell probability p, so block r gets the coverage whose
probability is p·λ_r (0 where the map is 0). ``flake2d.density_map`` in the stored JSON gives the
relative density each block gets after the 8-bit texture (and the mean over the sample against the
model's); ``flake2d.not_carried`` lists what flake2d cannot hold: per-block flake sizes
(``area_map``: one ``size``) and colours (``color_map``: the glint colour is the mean colour).
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import ExportError
from torchmetal.flakes.estimate.density_map import block_pixels
from torchmetal.formats.engine import EngineMaterial, engine_material
from torchmetal.formats.flake2d import density_to_probability, flake2d_inputs
from torchmetal.formats.lobe_fit import fit_glint, resolve_views
from torchmetal.formats.textures import (
    decode_png,
    f0_to_ior,
    gray,
    hwc,
    is_constant,
    specular_encoding,
    to_linear,
    to_srgb,
    write_texture_dir,
)
from torchmetal.geometry import is_flat
from torchmetal.io.capture import Capture
from torchmetal.io.images import atomic_write_bytes

if TYPE_CHECKING:
    import MaterialX

    from torchmetal.flakes.model import FlakeModel
    from torchmetal.formats.flake2d import Flake2dInputs
    from torchmetal.material import Material

TARGETS = ("glsl", "osl", "mdl")


def _mx():
    try:
        import MaterialX as mx
    except ImportError as e:  # pragma: no cover - materialx is a dependency
        raise ExportError(f"mtlx: expected the materialx package (>= 1.39.5), found none ({e})") from None
    return mx


@lru_cache(maxsize=1)
def stdlib() -> MaterialX.Document:
    """The MaterialX standard data libraries, loaded once (used as a read-only data library)."""
    mx = _mx()
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


def mtlx_plan(material: Material, views: Tensor | None = None) -> tuple[EngineMaterial, dict, dict[str, np.ndarray]]:
    """What the document holds: the engine maps (no flake bake), the shader/flake2d input values
    (floats, lists, or ``("texture", name)``) and the textures to write (name → (H, W, 3) planes)."""
    em = engine_material(replace(material, flakes=None), views=views)
    textures: dict[str, np.ndarray] = {"base_color": to_srgb(hwc(em.base_color))}
    ins: dict = {"base_color": ("texture", "base_color"), "base_weight": 1.0, "base_metalness": 0.0}
    normal = None if is_flat(em.normal) else "normal"
    if normal:
        textures["normal"] = 0.5 * (hwc(em.normal) + 1.0)
    flake = None
    if material.flakes is None:
        _specular_inputs(em, ins, textures)
    else:
        flake = _flake_inputs(material.flakes, em, ins, textures, views)
    if normal:
        ins["geometry_coat_normal" if flake else "geometry_normal"] = ("normal_map",)
        if flake:
            ins["flake_surface_normal"] = ("normal_map",)
    plan = {"inputs": ins, "flake2d": flake, "lobe_fit": em.extras.get("lobe_fit"),
            "light_convention": em.extras.get("light_convention")}
    return em, plan, textures


def _scalar_or_map(textures: dict[str, np.ndarray], name: str, x: torch.Tensor, scale: float = 1.0):
    """``x``'s one value × ``scale`` when it is constant, else ``("texture", name, scale)`` with the map added
    to ``textures``."""
    if is_constant(x):
        return float(x.reshape(-1)[0]) * scale
    textures[name] = gray(hwc(x))
    return ("texture", name, scale)


def _specular_inputs(em: EngineMaterial, ins: dict, textures: dict[str, np.ndarray]) -> None:
    """The shader's specular inputs of a flake-free material (no coat), into ``ins`` and ``textures``."""
    enc = specular_encoding(em)
    ins["specular_roughness"] = _scalar_or_map(textures, "roughness", em.roughness)
    ins["specular_ior"] = enc["ior"]
    ins["specular_weight"] = _scalar_or_map(textures, "specular_weight", enc["f90_map"], enc["specular_factor"])
    if is_constant(enc["color_map"]):
        ins["specular_color"] = [enc["color_factor"] * float(c) for c in enc["color_map"][:, 0, 0]]
    else:
        textures["specular_color"] = to_srgb(hwc(enc["color_map"]))
        ins["specular_color"] = ("texture", "specular_color", enc["color_factor"])
    ins["coat_weight"] = 0.0


def _flake_inputs(model: FlakeModel, em: EngineMaterial, ins: dict, textures: dict[str, np.ndarray],
                  views: Tensor | None) -> dict:
    """The coat (the Phong specular) and the flake2d glints' shader inputs, into ``ins`` and ``textures``;
    returns the plan's flake2d entry."""
    coat_f0 = em.f0.mean(0, keepdim=True)
    top = float(coat_f0.max())
    ins["coat_ior"] = f0_to_ior(top)
    f0_ior = ((ins["coat_ior"] - 1) / (ins["coat_ior"] + 1)) ** 2
    ins["coat_weight"] = _scalar_or_map(textures, "coat_weight", (coat_f0 / f0_ior).clamp(0.0, 1.0))
    ins["coat_roughness"] = _scalar_or_map(textures, "roughness", em.roughness)
    ins["coat_color"] = [1.0, 1.0, 1.0]
    glint = fit_glint(model.color_mean, model.glint_sigma, views=views)
    f0 = np.array(glint.f0)
    ins["specular_ior"] = f0_to_ior(float(f0.max()))
    f0_spec = ((ins["specular_ior"] - 1) / (ins["specular_ior"] + 1)) ** 2
    ins["specular_color"] = [float(min(c / f0_spec, 1.0)) if f0_spec > 0 else 0.0 for c in f0]
    ins["specular_roughness"] = glint.roughness
    ins["specular_weight"] = ("flake_presence",)
    ins["geometry_normal"] = ("flake_normal",)
    fi = flake2d_inputs(model, em.width)
    flake = {"size": fi.size, "roughness": fi.roughness, "coverage": fi.coverage,
             "aspect": em.height / em.width, "mapping": vars(fi), "glint_fit": glint.to_dict(),
             "statistics": model.to_dict(), "not_carried": []}
    if model.density_map is not None:
        planes, flake["coverage_scale"], flake["density_map"] = coverage_map(model, fi, em.height, em.width)
        textures["flake_coverage"] = gray(planes[:, :, None])
    if model.area_map is not None:
        ratio = torch.exp(model.area_map)
        flake["not_carried"].append({
            "what": "area_map", "why": "flake2d has one flake size",
            "block_median_area_ratio": [float(ratio.min()), float(ratio.max())]})
    if model.color_map is not None:
        cm = model.color_map.mean(-1) / max(sum(model.color_mean) / 3.0, 1e-12)
        flake["not_carried"].append({
            "what": "color_map", "why": "the glint colour (specular_color) is the mean colour everywhere",
            "block_brightness_ratio": [float(cm.min()), float(cm.max())]})
    return flake


def coverage_map(model: FlakeModel, fi: Flake2dInputs, height: int, width: int) -> tuple[np.ndarray, float, dict]:
    """flake2d ``coverage`` per block of ``model.density_map`` (module docstring): the (gh, gw) texture
    planes in [0, 1] (8-bit values), their scale (the largest coverage), and the report: the model's
    relative density per block, the one flake2d gets from the 8-bit coverage, and their pixel-weighted
    means over the sample (``mean_relative_density`` [model, flake2d])."""
    lam = model.density_map.double().numpy()
    p_max = float(density_to_probability(1.0))
    xs = np.linspace(0.0, 1.0, 20001)
    curve = density_to_probability(xs)
    p_r = np.minimum(fi.probability * lam, p_max)
    cov = np.interp(p_r, curve, xs)
    scale = float(cov.max())
    planes = np.round(cov / scale * 255.0) / 255.0 if scale > 0 else np.zeros_like(cov)
    got = density_to_probability(planes * scale) / fi.probability
    wpx = block_pixels(height, width, tuple(lam.shape)).numpy()
    mean = [float((lam * wpx).sum() / wpx.sum()), float((got * wpx).sum() / wpx.sum())]
    return planes, scale, {"relative_density": lam.tolist(), "flake2d_relative_density": got.tolist(),
                           "max_abs_error": float(np.abs(got - lam).max()), "mean_relative_density": mean,
                           "mean_density_ratio": mean[1] / mean[0] if mean[0] > 0 else None,
                           "capped_blocks": int((fi.probability * lam > p_max).sum())}


_TYPES = {"base_color": "color3", "specular_color": "color3", "coat_color": "color3",
          "geometry_normal": "vector3", "geometry_coat_normal": "vector3"}


def build_document(plan: dict, files: dict[str, str]) -> MaterialX.Document:
    """The MaterialX document of a plan; ``files`` maps texture names to (relative) file names."""
    mx = _mx()
    doc = mx.createDocument()
    ng = doc.addNodeGraph("NG_torchmetal")
    shader = doc.addNode("open_pbr_surface", "SR_torchmetal", "surfaceshader")
    g = _Graph(ng, ng.addNode("texcoord", "uv", "vector2"), files)
    outputs: dict[str, object] = {}
    normal_node = None
    if "normal" in files:
        img = g.image("normal", "vector3", False)
        normal_node = ng.addNode("normalmap", "normal_map", "vector3")
        normal_node.addInput("in", "vector3").setConnectedNode(img)
    flake = plan.get("flake2d")
    if flake:
        _flake_nodes(mx, g, flake, normal_node, outputs)
    if normal_node is not None:
        outputs["normal_map"] = g.out("normal_map", normal_node, "vector3")
    _shader_inputs(mx, g, shader, plan["inputs"], outputs)
    material = doc.addMaterialNode("M_torchmetal", shader)
    material.setDocString(json.dumps({"torchmetal": {k: v for k, v in plan.items() if k != "inputs"}}, allow_nan=False))
    return doc


class _Graph:
    """The document's node graph, its texture coordinates and the texture files, with the two ways nodes
    are added: a graph output and an image node."""

    def __init__(self, ng, uv, files: dict[str, str]) -> None:
        self.ng, self.uv, self.files = ng, uv, files

    def out(self, name: str, node, typ: str, output: str | None = None):
        o = self.ng.addOutput(f"{name}_out", typ)
        o.setConnectedNode(node)
        if output:
            o.setOutputString(output)
        return o

    def image(self, name: str, typ: str, srgb: bool, closest: bool = False):
        node = self.ng.addNode("image", f"{name}_image", typ)
        node.setInputValue("file", self.files[name], "filename")
        if srgb:
            node.getInput("file").setColorSpace("srgb_texture")
        node.addInput("texcoord", "vector2").setConnectedNode(self.uv)
        node.setInputValue("uaddressmode", "clamp", "string")
        node.setInputValue("vaddressmode", "clamp", "string")
        if closest:
            node.setInputValue("filtertype", "closest", "string")
        return node


def _flake_nodes(mx, g: _Graph, flake: dict, normal_node, outputs: dict) -> None:
    """The flake2d node, its presence switch and their graph outputs ("flake_presence", "flake_normal")."""
    ng, uv = g.ng, g.uv
    coords = uv
    if abs(flake["aspect"] - 1.0) > 1e-9:  # one texcoord unit = the texture width on both axes
        coords = ng.addNode("multiply", "flake_uv", "vector2")
        coords.addInput("in1", "vector2").setConnectedNode(uv)
        coords.setInputValue("in2", mx.Vector2(1.0, float(flake["aspect"])), "vector2")
    flake_node = ng.addNode("flake2d", "flakes", "multioutput")
    for k in ("size", "roughness", "coverage"):
        if k == "coverage" and "coverage_scale" in flake:  # the density map: coverage per block
            cov = ng.addNode("multiply", "flake_coverage_scaled", "float")
            cov.addInput("in1", "float").setConnectedNode(g.image("flake_coverage", "float", False, closest=True))
            cov.setInputValue("in2", float(flake["coverage_scale"]), "float")
            flake_node.addInput("coverage", "float").setConnectedNode(cov)
            continue
        flake_node.setInputValue(k, float(flake[k]), "float")
    flake_node.addInput("texcoord", "vector2").setConnectedNode(coords)
    if normal_node is not None:
        flake_node.addInput("normal", "vector3").setConnectedNode(normal_node)
    presence = ng.addNode("ifgreater", "flake_presence", "float")
    presence.addInput("value1", "float").setConnectedNode(flake_node)
    presence.getInput("value1").setOutputString("presence")
    presence.setInputValue("value2", 0.0, "float")
    presence.setInputValue("in1", 1.0, "float")
    presence.setInputValue("in2", 0.0, "float")
    outputs["flake_presence"] = g.out("flake_presence", presence, "float")
    outputs["flake_normal"] = g.out("flake_normal", flake_node, "vector3", "flakenormal")


def _shader_inputs(mx, g: _Graph, shader, ins: dict, outputs: dict) -> None:
    """The shader's inputs: values, textures (scaled where the plan says) or graph outputs."""
    for name, value in ins.items():
        if name.startswith("flake_"):
            continue
        typ = _TYPES.get(name, "float")
        inp = shader.addInput(name, typ)
        if isinstance(value, tuple):
            if value[0] == "texture":
                node = g.image(value[1], typ, typ == "color3")
                if len(value) > 2 and value[2] != 1.0:
                    scaled = g.ng.addNode("multiply", f"{value[1]}_scaled", typ)
                    scaled.addInput("in1", typ).setConnectedNode(node)
                    scaled.setInputValue("in2", float(value[2]), "float")
                    node = scaled
                key = f"{name}_map"
                outputs[key] = g.out(key, node, typ)
                inp.setConnectedOutput(outputs[key])
            else:
                inp.setConnectedOutput(outputs[value[0]])
        elif typ == "color3":
            inp.setValue(mx.Color3(*[float(c) for c in value]))
        else:
            inp.setValue(float(value))


def validate(doc: MaterialX.Document, lib: MaterialX.Document | None = None) -> tuple[bool, str]:
    """``Document.validate()`` against the standard libraries."""
    doc.setDataLibrary(lib if lib is not None else stdlib())
    return doc.validate()


def generate(doc: MaterialX.Document, target: str, lib: MaterialX.Document | None = None) -> str:
    """Shader source for ``target`` ("glsl", "osl", "mdl") of the document's material; raises
    :class:`ExportError` when generation fails."""
    mx = _mx()
    import MaterialX.PyMaterialXGenShader as gs

    if target not in TARGETS:
        raise ExportError(f"target: expected one of {', '.join(TARGETS)}, found {target!r}")
    if target == "glsl":
        from MaterialX.PyMaterialXGenGlsl import GlslShaderGenerator as Gen
    elif target == "osl":
        from MaterialX.PyMaterialXGenOsl import OslShaderGenerator as Gen
    else:
        from MaterialX.PyMaterialXGenMdl import MdlShaderGenerator as Gen
    lib = lib if lib is not None else stdlib()
    doc.setDataLibrary(lib)
    gen = Gen.create()
    ctx = gs.GenContext(gen)
    ctx.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
    cms = gs.DefaultColorManagementSystem.create(gen.getTarget())
    cms.loadLibrary(lib)
    gen.setColorManagementSystem(cms)
    nodes = gs.findRenderableElements(doc)
    if not nodes:
        raise ExportError("mtlx: expected a renderable material, found none")
    try:
        shader = gen.generate(nodes[0].getName(), nodes[0], ctx)
    except Exception as e:  # MaterialX raises its own exception types
        raise ExportError(f"mtlx: {target} shader generation failed: {e}") from None
    stage = "pixel" if target == "glsl" else gs.PIXEL_STAGE
    return shader.getSourceCode(stage)


def write(material: Material, path: str | os.PathLike, *, views: Tensor | None = None, capture: Capture | str | os.PathLike | None = None) -> Path:
    """Write ``material`` as ``path`` (.mtlx) plus ``<stem>.textures/``; validated before it is
    written (an invalid document raises :class:`ExportError` and writes nothing). ``views`` /
    ``capture``: the views of the lobe fit (see :func:`torchmetal.formats.lobe_fit.resolve_views`)."""
    mx = _mx()
    path = Path(path)
    em, plan, textures = mtlx_plan(material, resolve_views(views, capture))
    tex_dir = path.with_name(f"{path.stem}.textures")
    files = {name: f"{tex_dir.name}/{name}.png" for name in textures}
    doc = build_document(plan, files)
    ok, msg = validate(doc)
    if not ok:
        raise ExportError(f"mtlx: expected a valid MaterialX document, found: {msg.strip()}")
    opts = mx.XmlWriteOptions()
    opts.writeXIncludeEnable = False
    opts.elementPredicate = lambda e: not e.hasSourceUri()  # never the library elements
    text = mx.writeToXmlString(doc, opts)
    write_texture_dir(tex_dir, textures)
    atomic_write_bytes(path, text.encode())
    return path


def read(path: str | os.PathLike) -> dict:
    """Read back a file written by :func:`write`: ``{"inputs": {name: value | {"file", "scale"}},
    "flake2d": {size, roughness, coverage (a value, or {"file", "scale"} with a density map)} | None,
    "torchmetal": the stored JSON}``."""
    mx = _mx()
    path = Path(path)
    doc = mx.createDocument()
    try:
        mx.readFromXmlFile(doc, str(path))
    except Exception as e:
        raise ExportError(f"{path}: expected a MaterialX document, found unreadable data ({e})") from None
    shaders = doc.getNodes("open_pbr_surface") or [n for n in doc.getNodes() if n.getCategory() == "open_pbr_surface"]
    if not shaders:
        raise ExportError(f"{path}: expected an open_pbr_surface, found none")
    ng = doc.getNodeGraph("NG_torchmetal")
    res: dict = {"inputs": {}, "flake2d": None}
    for inp in shaders[0].getInputs():
        if inp.getOutputString():
            node = ng.getOutput(inp.getOutputString()).getConnectedNode()
            scale = 1.0
            if node.getCategory() == "multiply":
                scale = float(node.getInputValue("in2"))
                node = node.getInput("in1").getConnectedNode()
            if node.getCategory() == "image":
                res["inputs"][inp.getName()] = {"file": str(path.parent / node.getInputValue("file")), "scale": scale}
            else:
                res["inputs"][inp.getName()] = {"node": node.getCategory()}
                src = node.getInput("in").getConnectedNode() if node.getCategory() == "normalmap" else None
                if src is not None and src.getCategory() == "image":
                    res["inputs"][inp.getName()]["file"] = str(path.parent / src.getInputValue("file"))
        else:
            v = inp.getValue()
            res["inputs"][inp.getName()] = list(v.asTuple()) if hasattr(v, "asTuple") else float(v)
    flakes = ng.getNodes("flake2d") if ng is not None else []
    if flakes:
        res["flake2d"] = {}
        for k in ("size", "roughness", "coverage"):
            src = flakes[0].getInput(k).getConnectedNode() if flakes[0].getInput(k) is not None else None
            if src is None:
                res["flake2d"][k] = float(flakes[0].getInputValue(k))
            else:  # the density map's coverage: image × scale
                img = src.getInput("in1").getConnectedNode()
                res["flake2d"][k] = {"file": str(path.parent / img.getInputValue("file")),
                                     "scale": float(src.getInputValue("in2"))}
    mat = doc.getNodes("surfacematerial") or [n for n in doc.getNodes() if n.getCategory() == "surfacematerial"]
    res["torchmetal"] = json.loads(mat[0].getDocString()).get("torchmetal") if mat and mat[0].getDocString() else None
    return res


def to_engine(back: dict, size: tuple[float, float]) -> EngineMaterial:
    """The coat of a read-back document (:func:`read`) as glTF-equivalent engine maps: F0 =
    F0(ior)·colour·weight, F90 = weight, the base colour and normals from the textures; flakes
    (procedural ``flake2d``) and OpenPBR's exact dielectric Fresnel are not represented."""
    ins = back["inputs"]
    coat = back["flake2d"] is not None
    pre = "coat_" if coat else "specular_"

    def load(name: str, srgb: bool) -> torch.Tensor:
        v = ins[name]
        planes = decode_png(Path(v["file"]).read_bytes())[:, :, :3]
        planes = to_linear(planes) if srgb else planes
        return torch.from_numpy(np.ascontiguousarray(planes.transpose(2, 0, 1))).float() * float(v["scale"])

    base = load("base_color", True)
    _, h, w = base.shape

    def value(name: str, channels: int, srgb: bool = False) -> torch.Tensor:
        v = ins[name]
        if isinstance(v, dict):
            x = load(name, srgb)
            return x[:channels] if channels == 1 else x
        t = torch.tensor(v if isinstance(v, list) else [v], dtype=torch.float32).view(-1, 1, 1)
        return t.expand(channels, h, w).clone()

    rough = value(f"{pre}roughness", 1)
    ior = float(ins[f"{pre}ior"])
    f0_ior = ((ior - 1.0) / (ior + 1.0)) ** 2
    if coat:
        weight = value("coat_weight", 1)
        f0, f90 = (f0_ior * weight).expand(3, h, w).clone(), (f0_ior * weight).clone()
    else:
        weight = value("specular_weight", 1)
        f0 = (f0_ior * value("specular_color", 3, srgb=True)).clamp(max=1.0) * weight
        f90 = weight
    normal = torch.zeros(3, h, w)
    normal[2] = 1.0
    maps = [v["file"] for v in ins.values() if isinstance(v, dict) and v.get("node") == "normalmap" and "file" in v]
    if maps:
        n = decode_png(Path(maps[0]).read_bytes())[:, :, :3].transpose(2, 0, 1) * 2.0 - 1.0
        n = torch.from_numpy(np.ascontiguousarray(n)).float()
        normal = n / n.norm(dim=0, keepdim=True).clamp_min(1e-12)
    return EngineMaterial(base_color=base, roughness=rough, f0=f0, f90=f90, normal=normal, size=size)
