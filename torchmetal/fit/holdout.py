"""Leave-one-out evaluation: fit on all shots but one, render the one left out."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def psnr(pred: Tensor, ref: Tensor, valid: Tensor, peak: float | None = None) -> float:
    """PSNR (dB) over ``valid``; peak defaults to the largest reference value there."""
    v = valid.expand_as(ref)
    if not bool(v.any()):
        return math.nan
    err = (pred.double() - ref.double())[v]
    mse = float(err.square().mean())
    pk = float(ref.double()[v].abs().max()) if peak is None else float(peak)
    return math.inf if mse <= 0 else 10.0 * math.log10(pk * pk / mse)


def valid_pixels(capture) -> Tensor:
    """(N, 3, H, W) bool: inside the mask and not saturated."""
    v = capture.mask.bool().unsqueeze(0).expand_as(capture.images)
    if capture.saturated is not None:
        v = v & ~capture.saturated
    return v


def leave_one_out(capture, specular: str = "auto", *, peak: float | None = None, **fit_kwargs) -> list[float]:
    """PSNR of each shot rendered from a fit on all the other shots.

    Args:
        capture: a Capture with N ≥ 2 shots.
        specular: passed to :func:`~torchmetal.fit.fit_phong` ("global", "clustered", ...).
        peak: PSNR peak (default: the largest valid value of the left-out shot).
        fit_kwargs: more :func:`fit_phong` arguments.

    Returns:
        N PSNR values (dB), over mask pixels that are not saturated.
    """
    from torchmetal.fit.api import fit_phong

    n = int(capture.images.shape[0])
    out = []
    for k in range(n):
        fit = fit_phong(capture.subset([i for i in range(n) if i != k]), specular=specular, **fit_kwargs)
        one = capture.subset([k])
        with torch.no_grad():
            pred = fit.render(one.lights, one.intensities, one.cameras)
        out.append(psnr(pred, one.images, valid_pixels(one), peak))
    return out
