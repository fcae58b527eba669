"""ONNX writer for ``export --format onnx`` (the renderer itself lives in ``torchmetal.onnx_export``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torchmetal.material import Material



def write(material: Material, path: str | os.PathLike, *, opset: int = 20) -> Path:
    """Export ``material``'s renderer to one self-contained ONNX file (docs/design.md §2.4)."""
    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.onnx_export import export_onnx

    return export_onnx(material, path, opset=opset)
