"""glTF 2.0 / GLB writer and reader (``export --format gltf|glb``).

One quad the size of the sample (plane z = 0, +z up, u along +x, v along −y) with one material:

- ``pbrMetallicRoughness``: base colour = the diffuse texture (sRGB PNG; see
  :mod:`torchmetal.formats.engine` for the light convention), metallic 0, roughness from the
  numeric GGX fit of the material's lobe (factor, or the G channel of a texture with gloss maps,
  clustered specular or flakes);
- ``KHR_materials_specular`` + ``KHR_materials_ior``: F0 = ((ior−1)/(ior+1))²·specularColor·
  specularFactor, F90 = specularFactor; ior is chosen so the specular colour stays in [0, 1];
- ``normalTexture`` for non-flat normals and baked flake normals (tangent frame = world frame);
- ``KHR_materials_clearcoat`` when the flake bake keeps the coat as a clear coat;
- ``extras.torchmetal``: the lobe fits (roughness, lobe error, textbook mapping), the flake
  statistics and the bake report.

Everything lives in one buffer (images in buffer views): a .gltf embeds it as a data URI, a .glb
as its binary chunk, so both are one self-contained file written atomically.
"""

from __future__ import annotations

import base64
import json
import math
import os
import struct
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchmetal.errors import ExportError
from torchmetal.formats.engine import Coat, EngineMaterial, engine_material
from torchmetal.formats.lobe_fit import resolve_views
from torchmetal.formats.textures import decode_png, hwc, is_constant, png_bytes, specular_encoding, to_linear, to_srgb
from torchmetal.geometry import is_flat
from torchmetal.io.capture import Capture
from torchmetal.io.images import atomic_write_bytes

if TYPE_CHECKING:
    from torchmetal.material import Material

GENERATOR = "torchmetal"


class _Builder:
    """Accumulates one binary buffer, its views, images and textures."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.images: list[dict] = []
        self.textures: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        v = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        self.blob.extend(data)
        self.views.append(v)
        return len(self.views) - 1

    def texture(self, planes: np.ndarray, name: str) -> dict:
        self.images.append({"bufferView": self.view(png_bytes(planes)), "mimeType": "image/png", "name": name})
        self.textures.append({"source": len(self.images) - 1, "sampler": 0, "name": name})
        return {"index": len(self.textures) - 1}


def gltf_document(em: EngineMaterial, extras: dict) -> tuple[dict, bytes]:
    """The glTF JSON (without the buffer's uri) and the binary buffer of ``em``."""
    b = _Builder()
    accessors, tangents = _quad(b, em)
    attributes = {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2, **({"TANGENT": 3} if tangents else {})}
    mat = _material(b, em, extras)
    doc = {
        "asset": {"version": "2.0", "generator": GENERATOR},
        "extensionsUsed": sorted(mat["extensions"]),
        "scene": 0,
        "scenes": [{"nodes": [0], "name": "torchmetal"}],
        "nodes": [{"mesh": 0, "name": "sample"}],
        "meshes": [{"name": "sample", "primitives": [{"attributes": attributes,
                                                       "indices": len(accessors) - 1, "material": 0}]}],
        "materials": [mat],
        "accessors": accessors,
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "textures": b.textures,
        "images": b.images,
        "bufferViews": b.views,
        "buffers": [{"byteLength": len(b.blob)}],
    }
    while len(b.blob) % 4:
        b.blob.append(0)
    return doc, bytes(b.blob)


def _quad(b: _Builder, em: EngineMaterial) -> tuple[list[dict], bool]:
    """The sample's quad (positions, normals, uvs, tangents with normal maps, indices) into ``b``: its
    accessors and whether it has tangents."""
    w, h = em.size
    pos = np.array([[-w / 2, h / 2, 0], [w / 2, h / 2, 0], [w / 2, -h / 2, 0], [-w / 2, -h / 2, 0]], np.float32)
    nrm = np.tile(np.array([[0, 0, 1]], np.float32), (4, 1))
    tan = np.tile(np.array([[1, 0, 0, 1]], np.float32), (4, 1))
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    idx = np.array([0, 3, 2, 0, 2, 1], np.uint16)  # counter-clockwise seen from +z
    accessors = []
    tangents = not em.flat or (em.coat is not None and not is_flat(em.coat.normal))  # only with normal maps
    arrays = ((pos, "VEC3"), (nrm, "VEC3"), (uv, "VEC2")) + (((tan, "VEC4"),) if tangents else ())
    for arr, typ in arrays:
        acc = {"bufferView": b.view(arr.tobytes(), 34962), "componentType": 5126, "count": 4, "type": typ}
        if arr is pos:
            acc["min"], acc["max"] = pos.min(0).tolist(), pos.max(0).tolist()
        accessors.append(acc)
    accessors.append({"bufferView": b.view(idx.tobytes(), 34963), "componentType": 5123, "count": 6, "type": "SCALAR"})
    return accessors, tangents


def _material(b: _Builder, em: EngineMaterial, extras: dict) -> dict:
    """The glTF material of ``em`` (metallic-roughness, specular, ior, clearcoat), its textures into ``b``."""
    pbr = {"baseColorTexture": b.texture(to_srgb(hwc(em.base_color)), "base_color"), "metallicFactor": 0.0}
    if is_constant(em.roughness):
        pbr["roughnessFactor"] = float(em.roughness.reshape(-1)[0])
    else:
        rough = hwc(em.roughness)
        pbr["metallicRoughnessTexture"] = b.texture(np.concatenate([np.ones_like(rough), rough, np.zeros_like(rough)], 2), "roughness")
        pbr["roughnessFactor"] = 1.0
    mat: dict = {"name": "torchmetal", "pbrMetallicRoughness": pbr, "extensions": {}}
    if not em.flat:
        mat["normalTexture"] = b.texture(0.5 * (hwc(em.normal) + 1.0), "normal")
    enc = specular_encoding(em)
    spec: dict = {"specularFactor": enc["specular_factor"], "specularColorFactor": [enc["color_factor"]] * 3}
    if not is_constant(enc["f90_map"]):
        f90 = hwc(enc["f90_map"])
        spec["specularTexture"] = b.texture(np.concatenate([np.ones_like(f90).repeat(3, 2), f90], 2), "specular")
    if not is_constant(enc["color_map"]):
        spec["specularColorTexture"] = b.texture(to_srgb(hwc(enc["color_map"])), "specular_color")
    else:
        spec["specularColorFactor"] = [enc["color_factor"] * float(c) for c in enc["color_map"][:, 0, 0]]
    mat["extensions"]["KHR_materials_specular"] = spec
    mat["extensions"]["KHR_materials_ior"] = {"ior": enc["ior"]}
    if em.coat is not None:
        mat["extensions"]["KHR_materials_clearcoat"] = _clearcoat(b, em.coat)
    mat["extras"] = {"torchmetal": extras}
    return mat


def _clearcoat(b: _Builder, coat: Coat) -> dict:
    cc: dict = {}
    wmax = float(coat.weight.max())
    cc["clearcoatFactor"] = wmax
    if not is_constant(coat.weight) and wmax > 0:
        wmap = hwc(coat.weight / wmax)
        cc["clearcoatTexture"] = b.texture(np.concatenate([wmap, wmap, wmap], 2), "clearcoat")
    if is_constant(coat.roughness):
        cc["clearcoatRoughnessFactor"] = float(coat.roughness.reshape(-1)[0])
    else:
        r = hwc(coat.roughness)
        cc["clearcoatRoughnessFactor"] = 1.0
        cc["clearcoatRoughnessTexture"] = b.texture(np.concatenate([r, r, r], 2), "clearcoat_roughness")
    if not is_flat(coat.normal):
        cc["clearcoatNormalTexture"] = b.texture(0.5 * (hwc(coat.normal) + 1.0), "clearcoat_normal")
    return cc


def _glb(doc: dict, blob: bytes) -> bytes:
    js = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(blob), b"BIN\x00") + blob)


def _json_safe(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def write(material: Material, path: str | os.PathLike, *, binary: bool | None = None, views: torch.Tensor | None = None,
          capture: Capture | str | os.PathLike | None = None,
          flakes: str = "auto", texels_per_pixel: int = 1) -> Path:
    """Write ``material`` as glTF 2.0 (``.gltf``, data-URI buffer) or GLB (``.glb``), atomically.

    Args:
        binary: GLB or not; default from the suffix (``.glb`` → GLB).
        views, flakes, texels_per_pixel: see :func:`~torchmetal.formats.engine.engine_material`.
        capture: a capture (or its directory) whose views the lobe is fitted over (when no ``views``).
    """
    em = engine_material(material, views=resolve_views(views, capture), flakes=flakes, texels_per_pixel=texels_per_pixel)
    return write_engine(em, path, binary=binary)


def write_engine(em: EngineMaterial, path: str | os.PathLike, *, binary: bool | None = None) -> Path:
    """Write engine maps (:func:`~torchmetal.formats.engine.engine_material`) as glTF/GLB, atomically."""
    path = Path(path)
    binary = path.suffix.lower() == ".glb" if binary is None else binary
    doc, blob = gltf_document(em, _json_safe(em.extras))
    if binary:
        data = _glb(doc, blob)
    else:
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        data = json.dumps(doc, indent=1, allow_nan=False).encode()
    atomic_write_bytes(path, data)
    return path


def write_glb(material: Material, path: str | os.PathLike, **options) -> Path:
    """GLB writer (``export --format glb``)."""
    return write(material, path, binary=True, **options)


def write_gltf(material: Material, path: str | os.PathLike, **options) -> Path:
    """glTF JSON writer (``export --format gltf``)."""
    return write(material, path, binary=False, **options)


# -------------------------------------------------------------------------------------- reading
def _load(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    if data[:4] == b"glTF":
        jlen = struct.unpack_from("<I", data, 12)[0]
        doc = json.loads(data[20:20 + jlen])
        off = 20 + jlen
        blen = struct.unpack_from("<I", data, off)[0]
        return doc, data[off + 8:off + 8 + blen]
    doc = json.loads(data)
    uri = doc["buffers"][0]["uri"]
    return doc, base64.b64decode(uri.split(",", 1)[1])


def read(path: str | os.PathLike) -> EngineMaterial:
    """Read back a file written by :func:`write` as an :class:`EngineMaterial` (maps decoded)."""
    path = Path(path)
    try:
        doc, blob = _load(path)
        mat = doc["materials"][0]
    except (OSError, ValueError, KeyError, IndexError, struct.error) as e:
        raise ExportError(f"{path}: expected a glTF/GLB file written by torchmetal, found unreadable data ({e})") from None

    def tex(info) -> np.ndarray:
        image = doc["images"][doc["textures"][info["index"]]["source"]]
        v = doc["bufferViews"][image["bufferView"]]
        return decode_png(blob[v.get("byteOffset", 0):v.get("byteOffset", 0) + v["byteLength"]])

    def chw(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1))).float()

    pbr = mat["pbrMetallicRoughness"]
    base = chw(to_linear(tex(pbr["baseColorTexture"])[:, :, :3]))
    _, hh, ww = base.shape
    full = lambda c, x: torch.full((c, hh, ww), float(x))  # noqa: E731
    if "metallicRoughnessTexture" in pbr:
        rough = chw(tex(pbr["metallicRoughnessTexture"])[:, :, 1:2]) * pbr.get("roughnessFactor", 1.0)
    else:
        rough = full(1, pbr.get("roughnessFactor", 1.0))
    normal = chw(tex(mat["normalTexture"])[:, :, :3] * 2.0 - 1.0) if "normalTexture" in mat else torch.cat([full(2, 0.0), full(1, 1.0)])
    normal = normal / normal.norm(dim=0, keepdim=True).clamp_min(1e-12)
    spec = mat["extensions"].get("KHR_materials_specular", {})
    ior = mat["extensions"].get("KHR_materials_ior", {}).get("ior", 1.5)
    f0_ior = ((ior - 1.0) / (ior + 1.0)) ** 2
    k = spec.get("specularFactor", 1.0)
    f90 = full(1, k) * (chw(tex(spec["specularTexture"])[:, :, 3:4]) if "specularTexture" in spec else 1.0)
    colour = torch.tensor(spec.get("specularColorFactor", [1.0] * 3), dtype=torch.float32).view(3, 1, 1)
    if "specularColorTexture" in spec:
        colour = colour * chw(to_linear(tex(spec["specularColorTexture"])[:, :, :3]))
    f0 = (f0_ior * colour).clamp(max=1.0) * f90
    coat = None
    cc = mat["extensions"].get("KHR_materials_clearcoat")
    if cc is not None:
        weight = full(1, cc.get("clearcoatFactor", 0.0))
        if "clearcoatTexture" in cc:
            weight = weight * chw(tex(cc["clearcoatTexture"])[:, :, 0:1])
        cr = full(1, cc.get("clearcoatRoughnessFactor", 0.0))
        if "clearcoatRoughnessTexture" in cc:
            cr = cr * chw(tex(cc["clearcoatRoughnessTexture"])[:, :, 1:2])
        cn = chw(tex(cc["clearcoatNormalTexture"])[:, :, :3] * 2.0 - 1.0) if "clearcoatNormalTexture" in cc else torch.cat([full(2, 0.0), full(1, 1.0)])
        coat = Coat(weight=weight, roughness=cr, normal=cn / cn.norm(dim=0, keepdim=True).clamp_min(1e-12))
    pos = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    size = (pos["max"][0] - pos["min"][0], pos["max"][1] - pos["min"][1])
    return EngineMaterial(base_color=base, roughness=rough, f0=f0, f90=f90, normal=normal, size=size, coat=coat,
                          extras=mat.get("extras", {}).get("torchmetal", {}))
