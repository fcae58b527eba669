"""Tiny synthetic captures for the fit tests."""

from __future__ import annotations

import torch

from torchmetal.io.capture import Capture
from torchmetal.synth import synth_capture


def synth(size: int = 48, shots: int = 12, seed: int = 0, **kw):
    return synth_capture(size=size, shots=shots, seed=seed, texture="procedural", **kw)


def render_all(fit, cap: Capture) -> torch.Tensor:
    with torch.no_grad():
        return fit.render(cap.lights, cap.intensities, cap.cameras)


def replace(cap: Capture, **changes) -> Capture:
    fields = dict(images=cap.images, normals=cap.normals, mask=cap.mask, lights=cap.lights, intensities=cap.intensities,
                  cameras=cap.cameras, size=cap.size, saturated=cap.saturated, names=cap.names, color_space=cap.color_space)
    fields.update(changes)
    return Capture(**fields)


def rel_err(est: torch.Tensor, true: torch.Tensor) -> float:
    return float(((est.double() - true.double()) / true.double()).abs().max())
