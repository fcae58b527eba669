"""The light calibration's parameters and what they do to a capture (:mod:`torchmetal.lightcal`)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.geometry import direction_to, surface_points
from torchmetal.lightcal.positions import moved_lights

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

MIN_COS = 1e-3  # the falloff's cosine is clamped here (a point beside or behind the light's axis)


def log_axis_cosine(capture: Capture) -> Tensor:
    """(N, 1, H, W) float64: log cos θ per shot and pixel, θ between the direction from shot k's light to
    the pixel's surface point and the direction from the light to the surface centre; 0 for a directional
    light (no falloff) and for a light at the centre itself."""
    h, w = int(capture.images.shape[-2]), int(capture.images.shape[-1])
    lights = capture.lights.to(torch.float64)
    pts = surface_points(h, w, capture.size, dtype=torch.float64, device=lights.device)
    to_light, _ = direction_to(pts, lights)  # (N, 3, H, W), point → light
    pos = lights[:, :3]
    norm = pos.norm(dim=1, keepdim=True)
    axis = -pos / norm.clamp_min(1e-12)  # light → centre (the centre is the origin)
    cos = -(to_light * axis[:, :, None, None]).sum(1, keepdim=True)
    out = torch.log(cos.clamp_min(MIN_COS))
    point = (lights[:, 3] > 0) & (norm[:, 0] > 0)
    return torch.where(point[:, None, None, None], out, torch.zeros_like(out))


@dataclass(frozen=True)
class LightCalibration:
    """Falloff exponent, per-shot gains and per-shot light offsets (:mod:`torchmetal.lightcal`); the
    default is no calibration.

    Attributes:
        falloff: p in cos(θ)^p (0: isotropic lights).
        gains: (N,) per-shot multipliers of the capture it was fitted on, or None (all 1).
        offsets: (N,) (x, y, z) moves of the point lights of the capture it was fitted on, in its units
            (:mod:`~torchmetal.lightcal.positions`), or None.
        flash: one (x, y, z) move of every point light, this capture's or another of the same rig (the
            flash's place beside the lens), or None.
    """

    falloff: float = 0.0
    gains: tuple[float, ...] | None = None
    offsets: tuple[tuple[float, float, float], ...] | None = None
    flash: tuple[float, float, float] | None = None

    @property
    def identity(self) -> bool:
        return self.falloff == 0.0 and self.gains is None and self.offsets is None and self.flash is None

    def for_unseen(self) -> LightCalibration:
        """The calibration for shots it was not fitted on: the falloff and the flash's move (no gain, no
        per-shot offset)."""
        return replace(self, gains=None, offsets=None)

    def lights(self, capture: Capture) -> Tensor:
        """(N, 4) the capture's lights, the point lights moved by the flash's move and the offsets."""
        lights = capture.lights
        if self.flash is not None:
            lights = moved_lights(lights, torch.tensor([self.flash], dtype=torch.float64).expand(capture.num_shots, 3))
        if self.offsets is None:
            return lights
        if len(self.offsets) != capture.num_shots:
            raise InputError(f"light calibration: expected offsets for {capture.num_shots} shots, "
                             f"found {len(self.offsets)}")
        return moved_lights(lights, torch.tensor(self.offsets, dtype=torch.float64))

    def factor(self, capture: Capture) -> Tensor:
        """(N, 1, H, W) in the images' dtype: what the calibration multiplies each shot's irradiance by
        (the falloff's axis from the moved lights where there are offsets)."""
        n = capture.num_shots
        if self.gains is not None and len(self.gains) != n:
            raise InputError(f"light calibration: expected gains for {n} shots, found {len(self.gains)}")
        if (self.offsets is not None or self.flash is not None) and self.falloff != 0.0:
            capture = replace(capture, lights=self.lights(capture))  # the axis from the moved lights
        log_f = self.falloff * log_axis_cosine(capture) if self.falloff != 0.0 else torch.zeros(
            n, 1, 1, 1, dtype=torch.float64, device=capture.images.device)
        if self.gains is not None:
            g = torch.tensor(self.gains, dtype=torch.float64, device=log_f.device)
            log_f = log_f + torch.log(g)[:, None, None, None]
        return torch.exp(log_f).to(capture.images.dtype)

    def apply(self, capture: Capture) -> Capture:
        """The capture as isotropic lights of constant power at the calibrated positions would have
        recorded it: the lights moved, the photos / factor (the falloff's axis from the moved lights)."""
        if self.identity:
            return capture
        moved = replace(capture, lights=self.lights(capture))
        if self.falloff == 0.0 and self.gains is None:
            return moved
        return replace(moved, images=capture.images / self.factor(capture))

    def to_dict(self) -> dict:
        return {"falloff": self.falloff, "gains": None if self.gains is None else list(self.gains),
                "offsets": None if self.offsets is None else [list(o) for o in self.offsets],
                "flash": None if self.flash is None else list(self.flash),
                "axis": "from each point light to the surface centre"}

    @classmethod
    def from_dict(cls, d: dict | None) -> LightCalibration:
        """The calibration a report's ``light`` entry describes (none for None or an empty entry)."""
        if not d:
            return cls()
        gains, offsets, flash = d.get("gains"), d.get("offsets"), d.get("flash")
        return cls(float(d.get("falloff", 0.0)), None if gains is None else tuple(float(g) for g in gains),
                   None if offsets is None else tuple(tuple(float(x) for x in o) for o in offsets),
                   None if flash is None else tuple(float(x) for x in flash))
