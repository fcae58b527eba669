"""Shot geometry at the flakes (:class:`Geometry`): the shots' normals, lights, intensities and
cameras, sampled as unit half vectors and surface normals at pixel centres (the associated
flakes) and at the centre pixels of a grid of cells (the visibility integral's grid).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchmetal.geometry import shading_geometry


@dataclass
class Geometry:
    """Shot geometry: normals (3, H, W), lights (N, 4), intensities (N, 3), cameras (N, 4), size."""

    normals: Tensor
    lights: Tensor
    intensities: Tensor
    cameras: Tensor
    size: tuple[float, float]

    def _half(self, normals: Tensor, points: Tensor) -> Tensor:
        g = shading_geometry(normals, self.lights, self.intensities, self.cameras, points=points)
        return g.half  # (N, 3, h, w)

    def at_pixels(self, row: Tensor, col: Tensor) -> tuple[Tensor, Tensor]:
        """Unit half vectors (J, N, 3) and normals (J, 3) at pixel centres."""
        h, w = self.normals.shape[-2:]
        dt = torch.float64
        y = (0.5 - (row.to(dt) + 0.5) / h) * self.size[1]
        x = ((col.to(dt) + 0.5) / w - 0.5) * self.size[0]
        pts = torch.stack([x, y, torch.zeros_like(x)]).unsqueeze(1)  # (3, 1, J)
        n = self.normals[:, row, col].to(dt).unsqueeze(1)
        half = self._half(n, pts)[:, :, 0].permute(2, 0, 1)  # (J, N, 3)
        return half, n[:, 0].t()

    def on_grid(self, gh: int, gw: int) -> tuple[Tensor, Tensor]:
        """Half vectors (G, N, 3) and normals (G, 3) at the centre pixels of a gh×gw grid of cells.

        The normal is the centre pixel's own (not a cell average, which would flatten bumps).
        """
        h, w = self.normals.shape[-2:]
        rows = ((torch.arange(gh, device=self.normals.device) + 0.5) * h / gh).long().clamp(max=h - 1)
        cols = ((torch.arange(gw, device=self.normals.device) + 0.5) * w / gw).long().clamp(max=w - 1)
        rr, cc = torch.meshgrid(rows, cols, indexing="ij")
        return self.at_pixels(rr.flatten(), cc.flatten())
