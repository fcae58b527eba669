"""USD writer (``export --format usd``): a quad bound to one material with two render contexts.

- The universal context: ``UsdPreviewSurface`` in the specular workflow (``useSpecularWorkflow`` 1):
  ``diffuseColor`` = the base colour, ``specularColor`` = F0 (the preview's grazing reflectance is
  1, not the fitted F90), ``roughness``, ``normal`` (tangent-space
  map, scale 2 / bias −1), ``clearcoat``/``clearcoatRoughness`` — the glTF engine maps of
  :mod:`torchmetal.formats.engine` with the flakes baked (:mod:`torchmetal.formats.bake`; "base" or "clearcoat": the
  preview's coat has no normal of its own).
- The ``mtlx`` context: the MaterialX graph of :mod:`torchmetal.formats.mtlx` (``open_pbr_surface``
  + ``flake2d``) as UsdShade shaders whose ``info:id`` are the MaterialX node definitions
  (``ND_open_pbr_surface_surfaceshader``, ``ND_flake2d``, …), bound to ``outputs:mtlx:surface``.

Textures are 8-bit PNGs in ``<stem>.textures/`` beside the ``.usda``; the layer is written to a
temporary file and moved into place.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.errors import ExportError
from torchmetal.formats import mtlx
from torchmetal.formats.engine import EngineMaterial, engine_material
from torchmetal.formats.lobe_fit import resolve_views
from torchmetal.formats.textures import gray, hwc, is_constant, to_srgb, write_texture_dir
from torchmetal.geometry import is_flat
from torchmetal.io.capture import Capture
from torchmetal.io.images import atomic_write_bytes

if TYPE_CHECKING:
    from torch import Tensor

    from torchmetal.material import Material


ROOT = "/torchmetal"
MATERIAL = f"{ROOT}/Looks/M_torchmetal"


def _pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt
    except ImportError as e:  # pragma: no cover - usd-core is a dependency
        raise ExportError(f"usd: expected the usd-core package, found none ({e})") from None
    return Gf, Sdf, Usd, UsdGeom, UsdShade, Vt


def _quad(stage, em: EngineMaterial):
    Gf, Sdf, Usd, UsdGeom, UsdShade, Vt = _pxr()
    w, h = em.size
    mesh = UsdGeom.Mesh.Define(stage, f"{ROOT}/sample")
    pts = [(-w / 2, h / 2, 0), (w / 2, h / 2, 0), (w / 2, -h / 2, 0), (-w / 2, -h / 2, 0)]
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in pts])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 3, 2, 1])  # counter-clockwise seen from +z
    mesh.CreateExtentAttr([Gf.Vec3f(-w / 2, -h / 2, 0), Gf.Vec3f(w / 2, h / 2, 0)])
    mesh.CreateNormalsAttr([Gf.Vec3f(0, 0, 1)] * 4)
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set([Gf.Vec2f(0, 1), Gf.Vec2f(1, 1), Gf.Vec2f(1, 0), Gf.Vec2f(0, 0)])  # USD: v up, row 0 at v = 1
    return mesh


def _preview(stage, material, em: EngineMaterial, files: dict[str, str]):
    """UsdPreviewSurface network under the material; returns its surface output."""
    Gf, Sdf, Usd, UsdGeom, UsdShade, Vt = _pxr()
    base = MATERIAL  # shaders sit directly under the material (USD encapsulation rules)
    surf = UsdShade.Shader.Define(stage, f"{base}/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    reader = UsdShade.Shader.Define(stage, f"{base}/preview_st_reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    st_out = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)

    def texture(name: str, channels: str, srgb: bool, normal: bool = False):
        tex = UsdShade.Shader.Define(stage, f"{base}/{name}_texture")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(files[name])
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_out)
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB" if srgb else "raw")
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
        if normal:
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2, 2, 2, 1))
            tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(-1, -1, -1, 0))
        typ = Sdf.ValueTypeNames.Float3 if channels == "rgb" else Sdf.ValueTypeNames.Float
        return tex.CreateOutput(channels, typ)

    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(texture("preview_base_color", "rgb", True))
    spec = surf.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f)
    if is_constant(em.f0):
        spec.Set(Gf.Vec3f(*[float(c) for c in em.f0[:, 0, 0]]))
    else:
        spec.ConnectToSource(texture("preview_specular_color", "rgb", True))
    rough = surf.CreateInput("roughness", Sdf.ValueTypeNames.Float)
    if is_constant(em.roughness):
        rough.Set(float(em.roughness.reshape(-1)[0]))
    else:
        rough.ConnectToSource(texture("preview_roughness", "r", False))
    if not is_flat(em.normal):
        surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(texture("preview_normal", "rgb", False, True))
    if em.coat is not None:
        cc = surf.CreateInput("clearcoat", Sdf.ValueTypeNames.Float)
        if is_constant(em.coat.weight):
            cc.Set(float(em.coat.weight.reshape(-1)[0]))
        else:
            cc.ConnectToSource(texture("preview_clearcoat", "r", False))
        ccr = surf.CreateInput("clearcoatRoughness", Sdf.ValueTypeNames.Float)
        if is_constant(em.coat.roughness):
            ccr.Set(float(em.coat.roughness.reshape(-1)[0]))
        else:
            ccr.ConnectToSource(texture("preview_clearcoat_roughness", "r", False))
    return surf.CreateOutput("surface", Sdf.ValueTypeNames.Token)


def preview_textures(em: EngineMaterial) -> dict[str, np.ndarray]:
    """The PNG planes the preview network reads."""
    t = {"preview_base_color": to_srgb(hwc(em.base_color))}
    if not is_constant(em.f0):
        t["preview_specular_color"] = to_srgb(hwc(em.f0.clamp(0.0, 1.0)))
    if not is_constant(em.roughness):
        t["preview_roughness"] = gray(hwc(em.roughness))
    if not is_flat(em.normal):
        t["preview_normal"] = 0.5 * (hwc(em.normal) + 1.0)
    if em.coat is not None:
        if not is_constant(em.coat.weight):
            t["preview_clearcoat"] = gray(hwc(em.coat.weight))
        if not is_constant(em.coat.roughness):
            t["preview_clearcoat_roughness"] = gray(hwc(em.coat.roughness))
    return t


_SDF = {"float": "Float", "color3": "Color3f", "vector2": "Float2", "vector3": "Float3", "vector4": "Float4",
        "color4": "Color4f", "filename": "Asset", "string": "String", "integer": "Int", "boolean": "Bool",
        "surfaceshader": "Token", "material": "Token"}


def _sdf_type(mx_type: str):
    _, Sdf, *_ = _pxr()
    if mx_type not in _SDF:
        raise ExportError(f"usd: expected a MaterialX type in {sorted(_SDF)}, found {mx_type!r}")
    return getattr(Sdf.ValueTypeNames, _SDF[mx_type])


def _value(inp):
    v = inp.getValue()
    if inp.getType() == "filename":
        return str(v)
    return tuple(v.asTuple()) if hasattr(v, "asTuple") else v


def _mtlx_network(stage, material, doc, lib):
    """The MaterialX document as UsdShade shaders (info:id = node definition); returns the surface
    shader's output."""
    Gf, Sdf, Usd, UsdGeom, UsdShade, Vt = _pxr()
    doc.setDataLibrary(lib)
    ng = doc.getNodeGraph("NG_torchmetal")
    ng_prim = UsdShade.NodeGraph.Define(stage, f"{MATERIAL}/{ng.getName()}")
    shaders: dict[str, object] = {}

    def output_of(node, output: str = ""):
        nd = node.getNodeDef()
        name = output or "out"
        typ = nd.getOutput(name).getType() if output else node.getType()
        return shaders[node.getName()].CreateOutput(name, _sdf_type(typ))

    def define(node, parent: str):
        nd = node.getNodeDef()
        if nd is None:
            raise ExportError(f"usd: expected a MaterialX node definition for {node.getName()!r}, found none")
        sh = UsdShade.Shader.Define(stage, f"{parent}/{node.getName()}")
        sh.CreateIdAttr(nd.getName())
        shaders[node.getName()] = sh
        return sh

    nodes = ng.getNodes()
    for node in nodes:
        define(node, ng_prim.GetPath().pathString)
    for node in nodes:
        sh = shaders[node.getName()]
        for inp in node.getInputs():
            u = sh.CreateInput(inp.getName(), _sdf_type(inp.getType()))
            src = inp.getConnectedNode()
            if src is not None:
                u.ConnectToSource(output_of(src, inp.getOutputString() if src.getType() == "multioutput" else ""))
            else:
                u.Set(_value(inp))
                if inp.getColorSpace():
                    u.GetAttr().SetColorSpace(inp.getColorSpace())
    ng_outputs = {}
    for o in ng.getOutputs():
        src = o.getConnectedNode()
        out = ng_prim.CreateOutput(o.getName(), _sdf_type(o.getType()))
        out.ConnectToSource(output_of(src, o.getOutputString() if src.getType() == "multioutput" else ""))
        ng_outputs[o.getName()] = out
    surf_node = doc.getNodes("open_pbr_surface")[0] if doc.getNodes("open_pbr_surface") else next(
        n for n in doc.getNodes() if n.getCategory() == "open_pbr_surface")
    surf = define(surf_node, MATERIAL)
    for inp in surf_node.getInputs():
        u = surf.CreateInput(inp.getName(), _sdf_type(inp.getType()))
        if inp.getOutputString():
            u.ConnectToSource(ng_outputs[inp.getOutputString()])
        else:
            u.Set(_value(inp))
    return surf.CreateOutput("out", Sdf.ValueTypeNames.Token)


def build_stage(material: Material, tex_dir_name: str, *, views: Tensor | None = None, flakes: str = "auto", texels_per_pixel: int = 1):
    """The stage (in memory) and the textures it reads (file name → planes)."""
    Gf, Sdf, Usd, UsdGeom, UsdShade, Vt = _pxr()
    # the preview surface has one normal for both layers: no flake_clearcoat layout
    em = engine_material(material, views=views, flakes=flakes, texels_per_pixel=texels_per_pixel, coat_normals=False)
    _, plan, mx_tex = mtlx.mtlx_plan(material, views)
    textures = {**preview_textures(em), **mx_tex}
    files = {name: f"./{tex_dir_name}/{name}.png" for name in textures}
    lib = mtlx.stdlib()
    doc = mtlx.build_document(plan, {k: v[2:] for k, v in files.items()})
    ok, msg = mtlx.validate(doc, lib)
    if not ok:
        raise ExportError(f"usd: expected a valid MaterialX graph, found: {msg.strip()}")

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, ROOT)
    stage.SetDefaultPrim(root.GetPrim())
    mesh = _quad(stage, em)
    UsdGeom.Scope.Define(stage, f"{ROOT}/Looks")
    mat = UsdShade.Material.Define(stage, MATERIAL)
    mat.CreateSurfaceOutput().ConnectToSource(_preview(stage, mat, em, files))
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(_mtlx_network(stage, mat, doc, lib))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    extras = {"engine": em.extras, "mtlx": {k: v for k, v in plan.items() if k != "inputs"}}
    root.GetPrim().SetCustomDataByKey("torchmetal", json.dumps(extras, allow_nan=False, default=float))
    return stage, textures


def write(material: Material, path: str | os.PathLike, *, views: Tensor | None = None, capture: Capture | str | os.PathLike | None = None,
          flakes: str = "auto",
          texels_per_pixel: int = 1) -> Path:
    """Write ``material`` as ``path`` (.usda) plus ``<stem>.textures/`` (see the module docstring);
    ``views`` / ``capture``: the views of the lobe fit (:func:`torchmetal.formats.lobe_fit.resolve_views`)."""
    path = Path(path)
    tex_dir = path.with_name(f"{path.stem}.textures")
    stage, textures = build_stage(material, tex_dir.name, views=resolve_views(views, capture), flakes=flakes,
                                  texels_per_pixel=texels_per_pixel)
    text = stage.GetRootLayer().ExportToString()
    write_texture_dir(tex_dir, textures)
    atomic_write_bytes(path, text.encode())
    return path


def validate(path: str | os.PathLike) -> dict:
    """Run every registered UsdValidation validator on the stage at ``path``.

    Returns ``{"errors": [...], "warnings": [...], "sdr_skipped": [...], "validators": N}``; the
    ``ShaderSdrCompliance`` findings on MaterialX node ids (``ND_*``) go to ``sdr_skipped`` when
    this USD build has no MaterialX Sdr plugin (then those ids are unknown to Sdr by construction).
    """
    from pxr import Sdr, Usd, UsdValidation

    stage = Usd.Stage.Open(str(path))
    reg = UsdValidation.ValidationRegistry()
    validators = reg.GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    mtlx_in_sdr = Sdr.Registry().GetShaderNodeByIdentifier("ND_open_pbr_surface_surfaceshader") is not None
    out = {"errors": [], "warnings": [], "sdr_skipped": [], "validators": len(validators)}
    for e in errors:
        if e.HasNoError():
            continue
        text = e.GetErrorAsString()
        name = e.GetValidator().GetMetadata().name if e.GetValidator() else ""
        sites = " ".join(str(s.GetPrim().GetPath()) for s in e.GetSites() if s.IsPrim())
        if not mtlx_in_sdr and name.endswith("ShaderSdrCompliance") and "ND_" in (text + sites + _ids(stage, e)):
            out["sdr_skipped"].append(text)
        elif e.GetType() == UsdValidation.ValidationErrorType.Error:
            out["errors"].append(f"{name}: {text}")
        else:
            out["warnings"].append(f"{name}: {text}")
    return out


def _ids(stage, err) -> str:
    from pxr import UsdShade

    ids = []
    for s in err.GetSites():
        if s.IsPrim():
            sh = UsdShade.Shader(s.GetPrim())
            if sh:
                ids.append(str(sh.GetIdAttr().Get()))
    return " ".join(ids)
