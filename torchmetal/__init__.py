"""torchmetal: photos of a coated surface → Phong texture + metallic-flake material → ONNX renderer.

``import torchmetal`` is cheap: the public names below are resolved on first access (PEP 562),
so torch, OpenCV and the rest load only when a name that needs them is used. The exception
classes are plain Python and imported eagerly.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

from torchmetal.errors import CaptureError, ExportError, FitError, InputError, MaterialError, TorchmetalError

__version__ = "0.1.0"

# As before the imports became lazy: any OpenCV loaded after ``import torchmetal`` can read EXR.
os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

# public name -> module that defines it
_LAZY = {
    "Capture": "torchmetal.io.capture", "load_capture": "torchmetal.io.capture", "save_capture": "torchmetal.io.capture_save",
    "FlakeModel": "torchmetal.flakes.model",
    "Material": "torchmetal.material", "load_material": "torchmetal.material", "save_material": "torchmetal.material",
    "MaterialRenderer": "torchmetal.renderer",
    "PhongModel": "torchmetal.phong", "phong_render": "torchmetal.phong", "phong_shading": "torchmetal.phong",
    "specular_lobe": "torchmetal.phong",
    "ShadingGeometry": "torchmetal.geometry", "shading_geometry": "torchmetal.geometry", "surface_points": "torchmetal.geometry",
}

__all__ = [
    "TorchmetalError", "CaptureError", "MaterialError", "InputError", "FitError", "ExportError",
    "Capture", "load_capture", "save_capture",
    "FlakeModel", "Material", "load_material", "save_material", "MaterialRenderer",
    "PhongModel", "phong_render", "phong_shading", "specular_lobe",
    "ShadingGeometry", "shading_geometry", "surface_points",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is not None:
        value = getattr(importlib.import_module(module), name)
    elif not name.startswith("_"):  # a submodule (``torchmetal.io`` …) used without importing it
        try:
            value = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # resolve once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # static analysers see the eager imports
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.geometry import ShadingGeometry, shading_geometry, surface_points
    from torchmetal.io.capture import Capture, load_capture
    from torchmetal.io.capture_save import save_capture
    from torchmetal.material import Material, load_material, save_material
    from torchmetal.phong import PhongModel, phong_render, phong_shading, specular_lobe
    from torchmetal.renderer import MaterialRenderer
