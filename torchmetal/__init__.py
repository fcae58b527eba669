"""torchmetal: photos of a coated surface → Phong texture + metallic-flake material → ONNX renderer."""

from torchmetal.errors import CaptureError, ExportError, FitError, InputError, MaterialError, TorchmetalError
from torchmetal.flakes.model import FlakeModel
from torchmetal.io.capture import Capture, load_capture, save_capture
from torchmetal.geometry import ShadingGeometry, shading_geometry, surface_points
from torchmetal.material import Material, load_material, save_material
from torchmetal.phong import PhongModel, phong_render, phong_shading, specular_lobe
from torchmetal.renderer import MaterialRenderer

__version__ = "0.1.0"

__all__ = [
    "TorchmetalError", "CaptureError", "MaterialError", "InputError", "FitError", "ExportError",
    "Capture", "load_capture", "save_capture",
    "FlakeModel", "Material", "load_material", "save_material", "MaterialRenderer",
    "PhongModel", "phong_render", "phong_shading", "specular_lobe",
    "ShadingGeometry", "shading_geometry", "surface_points",
]
