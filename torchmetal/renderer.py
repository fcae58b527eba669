"""The material renderer: Phong shading plus deterministic sparkles, as an ``nn.Module``.

``MaterialRenderer(material)(light (B,4), light_intensity (B,3), camera (B,4)) -> (B,3,H,W)``.
All state lives in buffers, so ``.to()``, ``state_dict`` and ONNX export need no extra code.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchmetal.flakes.field import FlakeField, flake_field, sparkle_shading
from torchmetal.geometry import shading_geometry, surface_points
from torchmetal.material import Material
from torchmetal.phong import phong_shading


class MaterialRenderer(nn.Module):
    """Render a :class:`Material` for any batch of lights and cameras."""

    def __init__(self, material: Material, *, flakes: bool = True) -> None:
        super().__init__()
        m = material
        normals = m.flat_normals().float()
        s, alpha = m.specular_maps()
        self.register_buffer("texture", m.texture.detach().float().clone())
        self.register_buffer("s", s.detach().float().clone())
        self.register_buffer("alpha", alpha.detach().float().clone())
        self.register_buffer("normals", normals.clone())
        self.register_buffer("points", surface_points(m.height, m.width, m.size, dtype=torch.float32, device=normals.device))
        self.has_flakes = bool(flakes and m.flakes is not None)
        if self.has_flakes:
            f = flake_field(m.flakes, m.height, m.width, normals)
            self.glint_sigma = f.glint_sigma
            self.register_buffer("flake_weighted_color", f.weight * f.color)
            self.register_buffer("flake_normal", f.normal)

    def forward(self, light: Tensor, light_intensity: Tensor, camera: Tensor) -> Tensor:
        geom = shading_geometry(self.normals, light, light_intensity, camera, points=self.points)
        image = phong_shading(self.texture, self.s, self.alpha, geom)
        if self.has_flakes:
            field = FlakeField(torch.ones_like(self.flake_normal[:1]), self.flake_normal, self.flake_weighted_color, self.glint_sigma, 0)
            image = image + sparkle_shading(field, geom)
        return image
