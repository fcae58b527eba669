"""Leave-one-out evaluation: fit on all shots but one, render the one left out."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable

import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.fit.api import fit_phong
from torchmetal.metrics import psnr

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture


def valid_pixels(capture: Capture) -> Tensor:
    """(N, 3, H, W) bool: inside the mask and not saturated."""
    v = capture.mask.bool().unsqueeze(0).expand_as(capture.images)
    if capture.saturated is not None:
        v = v & ~capture.saturated
    return v


def valid_mean_square(capture: Capture) -> float:
    """Mean square of the capture's valid observations (:func:`valid_pixels`; 0.0 without one): the scale of a
    held-out signal, against which a decision's gain is float rounding below :data:`~torchmetal.select.rule.MIN_GAIN_ABS`."""
    v = valid_pixels(capture)
    return float(capture.images.double()[v].square().mean()) if bool(v.any()) else 0.0


def leave_one_out(capture: Capture, specular: str = "auto", *, peak: float = 1.0, **fit_kwargs: Any) -> list[float]:
    """PSNR of each shot rendered from a :func:`~torchmetal.fit.fit_phong` fit on all the other shots.

    Args:
        capture: a Capture with N ≥ 2 shots.
        specular: passed to :func:`~torchmetal.fit.fit_phong` ("global", "clustered", ...).
        peak: PSNR peak (:func:`torchmetal.metrics.psnr`: linear values clipped to [0, 1]).
        fit_kwargs: more :func:`fit_phong` arguments.

    Returns:
        N PSNR values (dB), over mask pixels that are not saturated (NaN for a shot with none).
    """
    def fit_render(train, one):
        fit = fit_phong(train, specular=specular, **fit_kwargs)
        with torch.no_grad():
            return fit.render(one.lights, one.intensities, one.cameras)

    return leave_one_out_with(capture, fit_render, peak=peak)


def leave_one_out_with(capture: Capture, fit_render: Callable[[Capture, Capture], Tensor], *,
                       peak: float = 1.0) -> list[float]:
    """PSNR of each shot k rendered by ``fit_render(capture without k, capture of k)`` → (1, 3, H, W).

    Any fit (the whole pipeline, another scheme) scored like :func:`leave_one_out`: N values (dB) over
    mask pixels that are not saturated (NaN for a shot with none). The fit may use autograd: render
    under ``torch.no_grad`` inside ``fit_render``.
    """
    n = int(capture.images.shape[0])
    if n < 2:
        raise InputError(f"leave-one-out: expected a capture with at least 2 shots, found {n}")
    out = []
    for k in range(n):
        one = capture.subset([k])
        pred = fit_render(capture.subset([i for i in range(n) if i != k]), one).detach()
        v = valid_pixels(one)
        out.append(psnr(pred, one.images, mask=v, peak=peak) if bool(v.any()) else math.nan)
    return out
