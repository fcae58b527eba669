"""Texture encoding shared by the engine writers: 8-bit PNGs, sRGB curves, the specular encoding.

The specular encoding (:func:`specular_encoding`) is the one of glTF's KHR_materials_specular,
reused by OpenPBR and UsdPreviewSurface: F0 = F0_ior·colour·colour_factor·F90 and F90 = k·map, with
the IOR chosen so that the colour map stays in [0, 1].
"""

from __future__ import annotations

import io
import math
import os
from pathlib import Path

import numpy as np
import torch

from torchmetal.formats.engine import EngineMaterial
from torchmetal.io.capture_save import replace_dir
from torchmetal.io.images import atomic_write_bytes, linear_to_srgb, srgb_to_linear

MIN_F0_IOR = 0.01  # ior ≈ 1.22
MAX_F0_IOR = 0.9  # ior ≈ 36.9


def png_bytes(planes: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, C) float array in [0, 1], C = 3 or 4, 8 bits."""
    from PIL import Image

    q = np.rint(np.clip(planes, 0.0, 1.0) * 255.0).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(q, mode="RGBA" if q.shape[2] == 4 else "RGB").save(buf, format="PNG")
    return buf.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data))).astype(np.float64) / 255.0


def hwc(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().double().permute(1, 2, 0).numpy()


def to_srgb(x: np.ndarray) -> np.ndarray:
    return linear_to_srgb(torch.from_numpy(np.clip(x, 0.0, 1.0))).numpy()


def to_linear(x: np.ndarray) -> np.ndarray:
    return srgb_to_linear(torch.from_numpy(x)).numpy()


def is_constant(x: torch.Tensor) -> bool:
    return bool((x == x.reshape(x.shape[0], -1)[:, :1].reshape(-1, 1, 1)).all())


def specular_encoding(em: EngineMaterial) -> dict:
    """glTF specular parameters: ior, specularFactor k, specularColorFactor, and the per-texel
    F90/k (1, H, W) and colour (3, H, W) in [0, 1] such that F0 = F0_ior·colour·factor·F90."""
    f0 = em.f0.double()
    f90 = em.f90.double()
    k = float(f90.max())
    ratio = torch.where(f90 > 0, f0 / f90.clamp_min(1e-30), torch.zeros_like(f0)).clamp(0.0, 1.0)
    top = float(ratio.max())
    f0_ior = min(max(top, MIN_F0_IOR), MAX_F0_IOR)
    sq = math.sqrt(f0_ior)
    ior = (1.0 + sq) / (1.0 - sq)
    colour = ratio / f0_ior
    factor = max(float(colour.max()), 1e-30) if top > MAX_F0_IOR else 1.0
    return {"ior": ior, "f0_ior": f0_ior, "specular_factor": k, "color_factor": factor,
            "f90_map": f90 / k if k > 0 else torch.zeros_like(f90), "color_map": (colour / factor).clamp(0.0, 1.0)}


def f0_to_ior(f0: float) -> float:
    """The IOR whose normal-incidence Fresnel reflectance is ``f0`` (clamped to [MIN_F0_IOR, MAX_F0_IOR])."""
    sq = math.sqrt(min(max(float(f0), MIN_F0_IOR), MAX_F0_IOR))
    return (1.0 + sq) / (1.0 - sq)


def write_png(path: str | os.PathLike, planes: np.ndarray) -> Path:
    """Write an (H, W, 3|4) float array in [0, 1] as an 8-bit PNG, atomically."""
    atomic_write_bytes(path, png_bytes(planes))
    return Path(path)


def gray(x: np.ndarray) -> np.ndarray:
    """(H, W, 1) → (H, W, 3) by repetition (grey PNGs that every reader takes)."""
    return np.repeat(x, 3, 2)


def write_texture_dir(tex_dir: Path, textures: dict[str, np.ndarray]) -> None:
    """Write ``{name: planes}`` as ``tex_dir/name.png``, the folder replaced as a whole (atomic)."""
    import shutil
    import tempfile

    tex_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{tex_dir.name}.", dir=tex_dir.parent))
    try:
        for name, planes in textures.items():
            (tmp / f"{name}.png").write_bytes(png_bytes(planes))
        replace_dir(tmp, tex_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
