"""Tiny synthetic captures for the fit tests."""

from __future__ import annotations

import math

import torch

from torchmetal.io.capture import Capture
from torchmetal.synth import synth_capture


def synth(size: int = 48, shots: int = 12, seed: int = 0, **kw):
    return synth_capture(size=size, shots=shots, seed=seed, texture="procedural", **kw)


def psnr(pred: torch.Tensor, ref: torch.Tensor, valid: torch.Tensor | None = None, peak: float = 1.0) -> float:
    err = pred.double() - ref.double()
    if valid is not None:
        err = err[valid.expand_as(err)]
    mse = float(err.square().mean())
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)


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
