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

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.fit.holdout import valid_pixels
from torchmetal.geometry import shading_geometry
from torchmetal.lbfgs import minimize
from torchmetal.phong import lobe_from_log, lobe_log

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
    return n / _length(n)


class _Length(torch.autograd.Function):
    """``n.norm(dim=0, keepdim=True)`` of a CPU (3, H, W) float64 ``n``, bit for bit, values and gradient: the
    reduction over the leading dimension costs 40× the elementwise steps (7 ms at 128², a third of a relief
    fit's step). As torch's kernel: √(x·x + y·y + z·z), the square root correctly rounded (numpy's; torch's
    vectorised float64 ``sqrt`` is not, on 1 % of values); the backward is torch's p = 2 norm backward."""

    @staticmethod
    def forward(ctx, n: Tensor) -> Tensor:
        square = n[0] * n[0] + n[1] * n[1] + n[2] * n[2]
        length = torch.from_numpy(np.sqrt(square.numpy())).unsqueeze(0)
        ctx.save_for_backward(n, length)
        return length

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        n, length = ctx.saved_tensors
        return grad * (n / length).masked_fill_(length == 0, 0)


def _length(n: Tensor) -> Tensor:
    """(1, H, W) Euclidean length of ``n`` (3, H, W) over its first dimension (:class:`_Length` on CPU float64)."""
    if n.device.type == "cpu" and n.dtype == torch.float64 and n.shape[0] == 3:
        return _Length.apply(n)
    return n.norm(dim=0, keepdim=True)


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

    def terms(self, normals: Tensor) -> _Terms:
        """The shading terms of ``normals`` (3, H, W) that s and α do not move: n·l and q = |r − v|²/2 from the
        stored rays (r − v = 2(n·l)n − (l + v))."""
        n = normals.unsqueeze(0)
        nl = (n * self.l).sum(1, keepdim=True)
        rv = 2.0 * nl * n - self.lv
        q = 0.5 * rv.square().sum(1, keepdim=True)
        return _Terms(self.irradiance, nl, q)

    def shading(self, normals: Tensor, s: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
        """(a, b) (N, 3, H, W) for ``normals`` (3, H, W): the diffuse factor E·max(n·l, 0) and the specular term
        E·s·lobe (0 where n·l ≤ 0)."""
        return self.terms(normals).shading(s, alpha)


class _Terms:
    """n·l (N, 1, H, W), q (N, 1, H, W) and what follows from them alone: the diffuse factor a = E·max(n·l, 0) and
    the lobe's log1p(−q) (:func:`~torchmetal.phong.specular_lobe` in its two steps). On the flat plane they are
    formed once per fit, not per step: only s and α move (values and gradients bit for bit as per step)."""

    def __init__(self, irradiance: Tensor, nl: Tensor, q: Tensor):
        self.irradiance = irradiance
        self.a = irradiance * nl.clamp_min(0.0)
        self.unlit = ~(nl > 0)
        self.inside = q < 1.0
        self.log = lobe_log(q, self.inside)

    def shading(self, s: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
        """(a, b): b = E·s·lobe, 0 where n·l ≤ 0 (``masked_fill`` rather than ``where`` against zeros: the same
        values and gradients)."""
        lobe = lobe_from_log(self.log, self.inside, alpha)
        return self.a, (self.irradiance * s.view(1, 3, 1, 1) * lobe).masked_fill(self.unlit, 0.0)


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
    data = _Data(capture)
    if relief and start is None:
        start = _flat_fit(data, cell)
    if start is None:
        return _flat_fit(data, cell)
    heights = start.heights
    if relief and heights is None:
        heights = torch.zeros(grid_shape(capture.height, capture.width, cell), dtype=torch.float64)
    return _fit(data, heights if relief else None, start.s, start.alpha, iters if relief else FLAT_ITERS, cell)


def _flat_fit(data: _Data, cell: int) -> ReliefFit:
    """The flat plane's fit from each of :data:`ALPHA_STARTS`, the lower final cost kept."""
    fits = [_fit(data, None, torch.full((3,), S_START, dtype=torch.float64), torch.full((3,), a0, dtype=torch.float64),
                 FLAT_ITERS, cell) for a0 in ALPHA_STARTS]
    return min(fits, key=lambda f: f.loss)


class _Data:
    """A capture's observations, weights and rays as each of its fits (flat starts, relief) reads them, formed once
    (the lights and cameras do not move: their directions are formed once, not per step); with the flat plane's
    shading terms and the texture's weighted diffuse factor and denominator, which no parameter of a flat fit moves."""

    def __init__(self, capture: Capture):
        self.capture = capture
        self.y = capture.images.double()
        valid = valid_pixels(capture)
        self.weight = valid.double()
        self.count = float(valid.sum().clamp_min(1))
        self.smooth = SMOOTH * float(self.y[valid].square().mean()) if bool(valid.any()) else 0.0
        self.rays = _Rays.of(capture)
        self._flat: tuple[_Terms, Tensor, Tensor] | None = None

    def flat(self) -> tuple[_Terms, Tensor, Tensor]:
        """The flat plane's :class:`_Terms`, w·a and Σ w·a² (clamped), as :func:`_texture` forms them."""
        if self._flat is None:
            terms = self.rays.terms(_flat_normals(self.capture))
            wa = self.weight * terms.a
            self._flat = terms, wa, (wa * terms.a).sum(0).clamp_min(1e-300)
        return self._flat


def _fit(data: _Data, heights: Tensor | None, s: Tensor, alpha: Tensor, iters: int, cell: int) -> ReliefFit:
    capture, y, weight, count, smooth = data.capture, data.y, data.weight, data.count, data.smooth
    shape = None if heights is None else heights.shape
    x0 = torch.cat([s.clamp_min(1e-6).log(), alpha.clamp_min(1e-3).log()] + ([] if heights is None else [heights.reshape(-1)]))
    flat = data.flat() if shape is None else None

    # the texture is each pixel's least-squares optimum given the shading (clamped at 0 where that is below): the
    # cost's derivative with respect to it is 0 there, or it is held at 0, so the gradient needs no path through
    # it (the envelope theorem; yellow_box's relief fit: heights equal to 3e-10 relative, loss to 1e-13, −20 % CPU)
    def value_grad(x: Tensor) -> tuple[float, Tensor]:
        x = x.detach().requires_grad_(True)
        if flat is None:
            n = relief_normals(x[6:].view(shape), (capture.height, capture.width), capture.size)
            a, b = data.rays.shading(n, x[:3].exp(), x[3:6].exp())
            texture = _texture(a.detach(), b.detach(), y, weight)
        else:  # the flat plane: only b moves (the same steps as _texture's on it)
            terms, wa, den = flat
            a, b = terms.shading(x[:3].exp(), x[3:6].exp())
            texture = ((wa * (y - b.detach())).sum(0) / den).clamp_min(0.0)
        # an unlit observation counts (its render is 0): else tilting a pixel away from the light would drop it
        r = (y - a * texture - b) * weight
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
