"""What the flake stage produces: the particle table of the detections and the stage's result.

Light to import (torch and the model only): the pipeline builds a :class:`FlakeStageResult` when the
glint screen skips the stage, before anything else of the stage is loaded.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

from torchmetal.flakes.model import FlakeModel


@dataclass
class Particles:
    """Ragged table of detected particles of a capture; every field has P rows.

    shot (P,) int64 shot index; area (P,) pixel count; cy, cx (P,) signal-weighted centroid
    (pixel-centre coordinates, row/col); major, minor (P,) ellipse axis lengths (4·√λ);
    angle (P,) radians from +col towards up; rgb (P, 3) mean normalised residual colour
    (reflectance units); lab (P, 3) mean Lab of the clamped sRGB-encoded residual colour;
    peak (P, 3) residual colour at the brightest pixel; amp (P,) peak of the channel-mean signal;
    snr (P,) amp / local σ; flux (P,) signal summed over the region; sigma (P,) local σ.
    """

    shot: Tensor
    area: Tensor
    cy: Tensor
    cx: Tensor
    major: Tensor
    minor: Tensor
    angle: Tensor
    rgb: Tensor
    lab: Tensor
    peak: Tensor
    amp: Tensor
    snr: Tensor
    flux: Tensor
    sigma: Tensor

    def __len__(self) -> int:
        return int(self.shot.numel())

    def select(self, index: Tensor) -> "Particles":
        """Rows ``index`` (bool mask or int64 indices) of every field."""
        return Particles(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def for_shot(self, k: int) -> "Particles":
        """The particles of shot ``k``."""
        return self.select(self.shot == k)

    def to(self, *args, **kwargs) -> "Particles":
        return Particles(**{f.name: getattr(self, f.name).to(*args, **kwargs) for f in fields(self)})

    @staticmethod
    def empty(device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> "Particles":
        """A table with no rows (a stage that stopped before detecting)."""
        widths = {"rgb": 3, "lab": 3, "peak": 3}
        return Particles(**{f.name: torch.zeros((0, widths[f.name]) if f.name in widths else (0,),
                                                dtype=torch.int64 if f.name == "shot" else dtype, device=device)
                            for f in fields(Particles)})

    @staticmethod
    def cat(parts: list["Particles"]) -> "Particles":
        return Particles(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Particles)})



@dataclass
class FlakeStageResult:
    """model: fitted FlakeModel or None (skipped); particles: per-shot detections;
    report: times (s) per sub-step, counts, fitted values, ``skipped`` reason when skipped;
    flake_id: (P,) associated flake of each particle (−1 when the stage stopped before, or for a
    particle next to a saturated or masked pixel, which the statistics leave out)."""

    model: FlakeModel | None
    particles: Particles
    report: dict = field(default_factory=dict)
    flake_id: Tensor | None = None
