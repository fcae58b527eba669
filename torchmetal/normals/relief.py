"""``normals="relief"``: a sample's embossing as the fine detail of a height field, fitted to the photos
with the global Phong terms.

Why not per-pixel photometric stereo (:mod:`~torchmetal.normals.estimate`) on a phone-flash capture: the
flash beside the lens barely moves the light, so the diffuse shading leaves the normals undetermined, and
the capture's light positions are off by centimetres per shot, which a free tilt absorbs in the shots a fit
sees and does not carry to others. The relief keeps what is the surface's:

* a height field h on a grid of control points (one every :data:`CELL` pixels at the fit's resolution),
  its slow variations removed (h − G_σ∗h, σ = :data:`SIGMA` cells: a tilt wider than a few cells is the
  lights' error, not the embossing), bicubic to the pixels; normals ∝ (−∂h/∂x, −∂h/∂y, 1)
  (:func:`relief_normals`);
* fitted on the capture box-downsampled to ≤ :data:`RES` pixels a side (``Capture.downsampled``): given the
  normals and the global s, α (per channel), each pixel's texture is the least-squares closed form over its
  valid observations (the projected cost), and L-BFGS (:func:`torchmetal.lbfgs.minimize`) through autograd
  moves h, log s and log α together, from the flat plane's fit (:func:`fit_relief`).

Measured on the shared embossed gold paper (yellow_box, three leave-one-out folds, flat vs relief in this
model, full-resolution renders of the left-out shot): PSNR 17.54 → 17.95 dB, chroma-artifact share 15.0 →
8.4 %; a free (not high-passed) 6 × 6 tilt field instead lost 3.2 dB; σ of 6 cells lost 0.9 dB against 1.5.
Whether a capture takes it is decided on left-out shots (:data:`torchmetal.select.choices.RELIEF`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.fit.holdout import valid_pixels
from torchmetal.geometry import shading_geometry
from torchmetal.lbfgs import minimize
from torchmetal.phong import specular_lobe

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

RES = 128  # the fit's resolution: the capture box-downsampled to at most this many pixels a side
CELL = 2  # pixels (at the fit's resolution) between the height field's control points: 64 a side
SIGMA = 1.5  # cells: the Gaussian whose blur of the heights is removed (slow tilts are the lights' error)
# the fit's penalty on the mean squared slope between control points, per unit of the observations' mean
# square: without it, the relief's in-sample error on yellow_box fell 41 % and its left-out shots lost 0.3-1 dB
SMOOTH = 0.5
ITERS = 100  # L-BFGS iterations of the relief fit
FLAT_ITERS = 60  # … of the flat plane's (6 parameters)
ALPHA_STARTS = (8.0, 64.0)  # the flat fit's starts of α (the lower final cost is kept)
S_START = 0.1


@dataclass
class ReliefFit:
    """A relief (or, without heights, the flat plane) fitted with global Phong terms.

    Attributes:
        heights: (gh, gw) float64 control points in scene units (before the high-pass), or None (flat).
        s, alpha: (3,) float64 specular strength and exponent.
        loss: the fit's cost: the mean squared error over the valid observations it was fitted on, plus the
            relief's slope penalty (:data:`SMOOTH`)
        iterations: L-BFGS iterations.
    """

    heights: Tensor | None
    s: Tensor
    alpha: Tensor
    loss: float
    iterations: int


def factor_for(capture: Capture, res: int = RES) -> int:
    """The integer box factor that brings the capture's longer side to ≤ ``res`` pixels."""
    return max(1, math.ceil(max(capture.height, capture.width) / res))


def grid_shape(h: int, w: int, cell: int = CELL) -> tuple[int, int]:
    """(gh, gw): control points of a height field over an h × w image, one every ``cell`` pixels (≥ 4 a side)."""
    return max(4, round(h / cell)), max(4, round(w / cell))


def high_pass(heights: Tensor, sigma: float = SIGMA) -> Tensor:
    """(gh, gw) heights minus their Gaussian blur (σ in cells, edges replicated)."""
    r = max(1, math.ceil(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=heights.dtype, device=heights.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    blur = F.pad(heights[None, None], (r, r, r, r), mode="replicate")
    blur = F.conv2d(blur, k.view(1, 1, 1, -1))
    blur = F.conv2d(blur, k.view(1, 1, -1, 1))[0, 0]
    return heights - blur


def relief_normals(heights: Tensor, shape: tuple[int, int], size: tuple[float, float], sigma: float = SIGMA) -> Tensor:
    """(3, H, W) unit normals of the high-passed height field ``heights`` (gh, gw), bicubic to ``shape``
    (H, W) over a surface of ``size`` (width, height): ∝ (−∂h/∂x, −∂h/∂y, 1), central differences
    (one-sided at the edges); x along the columns, y up the rows (:func:`~torchmetal.geometry.pixel_axes`)."""
    h, w = shape
    z = F.interpolate(high_pass(heights, sigma)[None, None], size=(h, w), mode="bicubic", align_corners=True)
    z = F.pad(z, (1, 1, 1, 1), mode="replicate")[0, 0]
    dx, dy = size[0] / w, size[1] / h
    gx = (z[1:-1, 2:] - z[1:-1, :-2]) / (2 * dx)
    gy = (z[:-2, 1:-1] - z[2:, 1:-1]) / (2 * dy)  # row 0 is the top: y falls down the rows
    n = torch.stack([-gx, -gy, torch.ones_like(gx)])
    return n / n.norm(dim=0, keepdim=True)


def _slope_square(heights: Tensor, size: tuple[float, float]) -> Tensor:
    """The mean squared slope between neighbouring control points of ``heights`` (gh, gw) spread over ``size``."""
    gh, gw = heights.shape
    sx = (heights[:, 1:] - heights[:, :-1]) * ((gw - 1) / size[0])
    sy = (heights[1:] - heights[:-1]) * ((gh - 1) / size[1])
    return sx.square().mean() + sy.square().mean()


@dataclass
class _Rays:
    """What a relief fit's shading needs that no parameter moves, formed once per fit: (N, 3, H, W) float64 unit
    directions to the light ``l`` and ``l + v`` (v to the camera), and the irradiance E (N, 3, H, W)."""

    l: Tensor
    lv: Tensor
    irradiance: Tensor

    @classmethod
    def of(cls, capture: Capture) -> _Rays:
        g = shading_geometry(_flat_normals(capture), capture.lights.double(), capture.intensities.double(),
                             capture.cameras.double(), capture.size)
        return cls(g.l, g.l + g.v, g.irradiance)

    def shading(self, normals: Tensor, s: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
        """(a, b) (N, 3, H, W) for ``normals`` (3, H, W): the diffuse factor E·max(n·l, 0) and the specular term
        E·s·lobe (0 where n·l ≤ 0), n·l and q = |r − v|²/2 from the stored rays (r − v = 2(n·l)n − (l + v))."""
        n = normals.unsqueeze(0)
        nl = (n * self.l).sum(1, keepdim=True)
        rv = 2.0 * nl * n - self.lv
        q = 0.5 * rv.square().sum(1, keepdim=True)
        a = self.irradiance * nl.clamp_min(0.0)
        b = torch.where(nl > 0, self.irradiance * s.view(1, 3, 1, 1) * specular_lobe(q, alpha), torch.zeros_like(a))
        return a, b


def _texture(a: Tensor, b: Tensor, y: Tensor, weight: Tensor) -> Tensor:
    """(3, H, W) ≥ 0: per pixel and channel the least-squares texture of y ≈ a·T + b over the weighted shots."""
    return ((weight * a * (y - b)).sum(0) / (weight * a * a).sum(0).clamp_min(1e-300)).clamp_min(0.0)


def _flat_normals(capture: Capture) -> Tensor:
    """(3, H, W) float64 (0, 0, 1) at the resolution of ``capture``."""
    return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(3, 1, 1).expand(3, capture.height, capture.width)


def fit_normals(fit: ReliefFit, capture: Capture) -> Tensor:
    """(3, H, W) float64 normals of ``fit`` at the resolution and surface of ``capture``."""
    if fit.heights is None:
        return _flat_normals(capture)
    return relief_normals(fit.heights, (capture.height, capture.width), capture.size)


def render_heldout(fit: ReliefFit, train: Capture, hold: Capture) -> Tensor:
    """(M, 3, H, W): ``hold``'s shots rendered with ``fit`` and the texture solved on ``train``'s shots
    (both captures of one sample, at the resolution the fit's normals are wanted)."""
    with torch.no_grad():
        n = fit_normals(fit, train)
        a, b = _Rays.of(train).shading(n, fit.s, fit.alpha)
        tex = _texture(a, b, train.images.double(), valid_pixels(train).double())
        a, b = _Rays.of(hold).shading(n, fit.s, fit.alpha)
        return a * tex + b


def fit_relief(capture: Capture, *, start: ReliefFit | None = None, relief: bool = True, iters: int = ITERS,
               cell: int = CELL) -> ReliefFit:
    """The relief (``relief=True``) or the flat plane fitted to ``capture`` (already at the fit's resolution,
    ``Capture.downsampled``) with global s, α; from ``start``'s s, α (and heights), else from the flat fit's
    (:data:`ALPHA_STARTS`). Module docstring."""
    if relief and start is None:
        start = fit_relief(capture, relief=False)
    if start is None:
        fits = [_fit(capture, None, torch.full((3,), S_START, dtype=torch.float64), torch.full((3,), a0, dtype=torch.float64),
                     FLAT_ITERS, cell) for a0 in ALPHA_STARTS]
        return min(fits, key=lambda f: f.loss)
    heights = start.heights
    if relief and heights is None:
        heights = torch.zeros(grid_shape(capture.height, capture.width, cell), dtype=torch.float64)
    return _fit(capture, heights if relief else None, start.s, start.alpha, iters if relief else FLAT_ITERS, cell)


def _fit(capture: Capture, heights: Tensor | None, s: Tensor, alpha: Tensor, iters: int, cell: int) -> ReliefFit:
    y = capture.images.double()
    valid = valid_pixels(capture)
    flat = _flat_normals(capture)
    rays = _Rays.of(capture)  # the lights and cameras do not move: their directions are formed once, not per step
    shape = None if heights is None else heights.shape
    x0 = torch.cat([s.clamp_min(1e-6).log(), alpha.clamp_min(1e-3).log()] + ([] if heights is None else [heights.reshape(-1)]))
    weight = valid.double()
    count = float(valid.sum().clamp_min(1))
    smooth = SMOOTH * float(y[valid].square().mean()) if bool(valid.any()) else 0.0

    def value_grad(x: Tensor) -> tuple[float, Tensor]:
        x = x.detach().requires_grad_(True)
        n = flat if shape is None else relief_normals(x[6:].view(shape), (capture.height, capture.width), capture.size)
        a, b = rays.shading(n, x[:3].exp(), x[3:6].exp())
        # an unlit observation counts (its render is 0): else tilting a pixel away from the light would drop it
        r = (y - a * _texture(a, b, y, weight) - b) * weight
        loss = r.square().sum() / count
        if shape is not None:
            loss = loss + smooth * _slope_square(x[6:].view(shape), capture.size)
        (g,) = torch.autograd.grad(loss, x)
        return float(loss.detach()), g

    x, iterations = minimize(value_grad, x0, max_iter=iters, tolerance_grad=1e-12, tolerance_change=1e-14, history_size=20)
    loss, _ = value_grad(x)
    return ReliefFit(None if shape is None else x[6:].view(shape).clone(), x[:3].exp(), x[3:6].exp(), loss, iterations)


def with_relief(capture: Capture, *, res: int = RES) -> tuple[Capture, dict]:
    """The capture with its relief's normals (fitted on all its shots at ≤ ``res`` pixels a side), and a
    report entry."""
    ds = capture.downsampled(factor_for(capture, res))
    fit = fit_relief(ds)
    normals = relief_normals(fit.heights, (capture.height, capture.width), capture.size).to(capture.images.dtype)
    tilt = torch.rad2deg(torch.acos(fit_normals(fit, ds)[2].clamp(-1.0, 1.0)))  # at the fit's resolution
    report = {"mode": "relief", "fit_resolution": [ds.height, ds.width], "grid": list(fit.heights.shape),
              "iterations": fit.iterations, "cost": fit.loss, "s": fit.s.tolist(), "alpha": fit.alpha.tolist(),
              "tilt_mean_deg": float(tilt.mean()), "tilt_p99_deg": float(tilt.flatten().quantile(0.99))}
    return replace(capture, normals=normals), report


__all__ = ["ReliefFit", "factor_for", "fit_relief", "relief_normals", "render_heldout", "with_relief"]
