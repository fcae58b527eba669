"""Writers that take a fitted material out of torchmetal (docs/design.md §2.5 ``export --format``).

``FORMATS`` maps each format name to ``"module:function"``; the function is
``write(material: Material, path: str | os.PathLike, **options) -> Path`` and writes atomically.
The modules are imported only when their format is asked for, so the command line stays fast
and a missing optional package fails only the format that needs it.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import TYPE_CHECKING

from torchmetal.errors import ExportError

if TYPE_CHECKING:
    from torchmetal.material import Material


FORMATS: dict[str, str] = {
    "onnx": "torchmetal.formats.onnx:write",
    "gltf": "torchmetal.formats.gltf:write_gltf",
    "glb": "torchmetal.formats.gltf:write_glb",
    "mtlx": "torchmetal.formats.mtlx:write",
    "usd": "torchmetal.formats.usd:write",
    "web": "torchmetal.formats.web:write",
}


def default_output(material_dir: str | os.PathLike, fmt: str) -> Path:
    """Where ``export`` writes when ``-o`` is not given: inside the material directory."""
    names = {"onnx": "renderer.onnx", "gltf": "material.gltf", "glb": "material.glb",
             "mtlx": "material.mtlx", "usd": "material.usda", "web": "web"}
    return Path(material_dir) / names.get(fmt, f"material.{fmt}")


def writer(fmt: str):
    """The write function of ``fmt``; raises :class:`ExportError` naming the known formats."""
    if fmt not in FORMATS:
        raise ExportError(f"format: expected one of {', '.join(FORMATS)}, found {fmt!r}")
    module, func = FORMATS[fmt].split(":")
    return getattr(importlib.import_module(module), func)


def export_material(material: Material, fmt: str, path: str | os.PathLike, **options) -> Path:
    """Write ``material`` (a :class:`Material`) as ``fmt`` at ``path``; returns the written path."""
    return writer(fmt)(material, path, **options)
