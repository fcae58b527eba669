"""What the served page and the static site share: page assets, ONNX graphs, shots and config.

The page (``static/``) reads ``config.json``:
```json
{"format": "torchmetal-viewer", "version": 1, "mode": "served" | "static",
 "title": "…", "width": W, "height": H, "surface": [width, height],
 "graphs": {"plain": "renderer-noflakes.onnx", "flakes": "renderer.onnx"},   // "flakes" absent without flakes
 "shots": [{"name": "000", "photo": "photos/000.png", "light": [x, y, z, w],
            "light_intensity": [r, g, b], "camera": [x, y, z, w]}, …],
 "ort": {"wasm": "ort/ort.wasm.min.mjs", "webgpu": "ort/ort.webgpu.min.mjs" | null} | null,
 "threads": 1,
 "preview": {"glb": "material.glb", "three": "0.187.0"} | null, "preview_note": "…"}
```
Two graphs because the ONNX renderer bakes the flake term in (docs/design.md §2.4): "flakes off" runs the
graph exported with ``flakes=False``, so each toggle state is exactly the torch renderer's image.
Photos are 8-bit sRGB PNGs of the capture's linear images (clipped to [0, 1]); the page decodes
them to linear and applies the same exposure and sRGB encoding as to the renders.

The 3D preview (``preview.js``) shows ``material.glb`` (the glTF export, flakes baked) with three.js
served from ``three/`` (:mod:`torchmetal.viewer.three`, from npm); without three.js, or when the
export fails, ``preview`` is null and ``preview_note`` says why.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

from torchmetal.errors import ExportError, InputError, TorchmetalError
from torchmetal.viewer import three

if TYPE_CHECKING:  # annotations only: a real import would load torch (this module imports nothing heavy)
    from torchmetal.io.capture import Capture
    from torchmetal.material import Material

CONFIG_FORMAT = "torchmetal-viewer"
CONFIG_VERSION = 1
GRAPH_FLAKES = "renderer.onnx"
GRAPH_PLAIN = "renderer-noflakes.onnx"
PAGE_FILES = ("index.html", "viewer.js", "display.js", "state.js", "style.css", "preview.js")
PREVIEW_GLB = "material.glb"


def static_dir() -> Path:
    """The folder of the page assets (package data, shared by served and static modes)."""
    return Path(str(resources.files("torchmetal.viewer") / "static"))


def page_bytes(name: str) -> bytes:
    """Bytes of one page asset (``name`` in :data:`PAGE_FILES`)."""
    if name not in PAGE_FILES:
        raise KeyError(name)
    return (static_dir() / name).read_bytes()


def onnx_meta(path: str | os.PathLike) -> dict[str, str]:
    """The metadata props of an exported renderer (height, width, flakes, …), read with onnx."""
    import onnx

    proto = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in proto.metadata_props}


def _matches(path: Path, material, flakes: bool) -> bool:
    """Whether ``path`` is a renderer of ``material``'s size with (or without) its flakes."""
    try:
        meta = onnx_meta(path)
    except Exception:  # unreadable file: export a fresh one
        return False
    has = meta.get("flakes", "none") != "none"
    return (meta.get("height"), meta.get("width")) == (str(material.height), str(material.width)) and has == flakes


def export_graphs(material: Material, out_dir: str | os.PathLike, *, reuse: Sequence[str | os.PathLike] = (),
                  opset: int = 20, log=None) -> dict[str, str]:
    """The viewer's ONNX graphs of ``material`` in ``out_dir``; returns config ``graphs``.

    ``plain`` is the renderer without flakes; ``flakes`` (only when the material has flakes)
    the full renderer. A file in ``reuse`` (e.g. ``MATERIAL/renderer.onnx``) is copied instead
    of exporting when it has the material's size and flake setting and passes
    :func:`~torchmetal.onnx_export.verify_onnx` against this material's torch renderer (so a
    stale file from an earlier fit is never shown). ``log(text)``, if given, is told before each export.

    Returns:
        {"plain": file name, "flakes": file name} (names inside ``out_dir``).
    """
    import shutil

    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.onnx_export import export_onnx, verify_onnx
    from torchmetal.renderer import MaterialRenderer

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    want = {"plain": (GRAPH_PLAIN, False)}
    if material.flakes is not None:
        want["flakes"] = (GRAPH_FLAKES, True)
    else:
        want["plain"] = (GRAPH_FLAKES, False)  # one graph: it is the renderer.onnx of the material
    graphs = {}
    for key, (name, flakes) in want.items():
        renderer = MaterialRenderer(material, flakes=flakes).eval()
        for cand in (Path(p) for p in reuse):
            if cand.is_file() and _matches(cand, material, flakes):
                try:
                    verify_onnx(cand, renderer, batch=2)
                except ExportError:
                    continue
                if cand.resolve() != (out / name).resolve():
                    shutil.copyfile(cand, out / name)
                break
        else:
            if log is not None:
                log(f"exporting {name} ({material.height}x{material.width}, flakes {'on' if flakes else 'off'}) to ONNX…")
            export_onnx(renderer, out / name, opset=opset)
        graphs[key] = name
    return graphs


def shots_of(capture: Capture, material: Material) -> list[dict]:
    """Config ``shots`` of a :class:`Capture` (light, intensity, camera, photo name)."""
    if tuple(capture.size) != tuple(material.size):
        raise InputError(f"capture: expected the material's surface {tuple(material.size)}, found {tuple(capture.size)}")
    out = []
    for k in range(capture.num_shots):
        out.append({
            "name": Path(capture.names[k]).stem if k < len(capture.names) else f"{k:03d}",
            "photo": f"photos/{k:03d}.png",
            "light": [float(v) for v in capture.lights[k].tolist()],
            "light_intensity": [float(v) for v in capture.intensities[k].tolist()],
            "camera": [float(v) for v in capture.cameras[k].tolist()],
        })
    return out


def photo_png(capture: Capture, k: int) -> bytes:
    """Shot ``k`` of ``capture`` as 8-bit sRGB PNG bytes (linear clipped to [0, 1], then encoded)."""
    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.io.images import encode_image, linear_to_srgb

    img = capture.images[k].detach().cpu().float().clamp(0, 1)
    return encode_image(linear_to_srgb(img).permute(1, 2, 0).numpy(), ".png", bits=8)


def write_preview(material: Material, out_dir: str | os.PathLike) -> tuple[dict | None, str]:
    """The 3D preview's ``material.glb`` in ``out_dir`` (when three.js is installed); returns the
    config's (``preview``, ``preview_note``)."""
    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.formats.gltf import write_glb

    found = three.find_three()  # looked up at call time: tests replace it
    if found is None:
        return None, "no 3D preview: three.js not found (run `npm ci` in the torchmetal repository)"
    try:
        write_glb(material, Path(out_dir) / PREVIEW_GLB)
    except (TorchmetalError, ValueError) as e:
        return None, f"no 3D preview: the glTF export failed ({str(e).splitlines()[0]})"
    return {"glb": PREVIEW_GLB, "three": found[1]}, "3D preview: the glTF export in three.js"


def make_config(material: Material, graphs: dict[str, str], shots: list[dict], *, mode: str,
                title: str = "torchmetal", ort: dict | None = None, threads: int = 1,
                preview: dict | None = None, preview_note: str = "") -> dict:
    """The page's ``config.json`` (see the module docstring)."""
    return {
        "format": CONFIG_FORMAT, "version": CONFIG_VERSION, "mode": mode, "title": title,
        "width": int(material.width), "height": int(material.height),
        "surface": [float(material.size[0]), float(material.size[1])],
        "graphs": dict(graphs), "shots": list(shots), "ort": ort, "threads": int(threads),
        "preview": preview, "preview_note": preview_note,
    }
