"""Light positions as nuisance parameters (:mod:`torchmetal.lightcal`): per shot, or one offset shared by
every shot (the flash).

A phone capture's light positions come from its marker board and a guess of where the flash sits beside
the lens; on the shared gold paper they put the flash's mirror point 1.7–3.1 cm away from the photo's
hotspot (docs/measurements.md), and a fit then explains the hotspot with a broad lobe that veils the whole
sample. Here each point light gets an offset (x, y, z) in the capture's units, fitted to the shot's photo
with the material held fixed: a Levenberg–Marquardt step per shot on the squared error over its valid
observations, the Jacobian by central differences (three numbers per shot, independent across shots).
:func:`~torchmetal.lightcal.estimate.calibrate_positions` alternates it with the material's fit.

An offset is bounded by ``MAX_MOVE`` × the light's distance to the surface centre; a directional light
has none. A phone's flash sits beside the lens at the same place in every shot: where the capture put it
elsewhere, one offset shared by every shot (``shared=True``) says so, and it carries over to shots the
fit did not see (the shared card: y −0.85 cm in every leave-one-out fold, docs/design.md §4).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor

from torchmetal.fit.holdout import valid_pixels

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture
    from torchmetal.material import Material

PIXELS = 128 * 128  # material_offsets' pixel grid: a flash hotspot spans a few of its pixels
ITERS = 15  # LM iterations per call
MAX_MOVE = 0.5  # an offset's length is at most this fraction of the light's distance to the centre
STEP = 1e-3  # the central differences' step, as a fraction of that distance
LAMBDA0 = 1e-3  # the damping's start (relative to the diagonal of JᵀJ)
#: a shot's search stops once an accepted step lowers its squared error by less than this fraction. Without it the
#: iterations after convergence were rejected steps or gains of 1e-10 relative (the shared card: converged in 2–4 of 15
#: iterations each call). A stop on the linearised model's predicted gain was tried and dropped: far from the optimum
#: (a hotspot far from its photo's) it predicts little, and random scene 252's flash test fell from z 16.5 to 9.9
#: (docs/measurements.md)
FTOL = 1e-6


def moved_lights(lights: Tensor, offsets: Tensor | None) -> Tensor:
    """(N, 4) lights with ``offsets`` (N, 3) added to the point lights' positions (directional ones kept)."""
    if offsets is None:
        return lights
    point = (lights[:, 3] > 0).to(lights.dtype)[:, None]
    return torch.cat([lights[:, :3] + offsets.to(lights) * point, lights[:, 3:]], 1)


def move_capture(capture: Capture, offsets: Tensor | None) -> Capture:
    """``capture`` with its point lights moved by ``offsets`` (N, 3)."""
    return capture if offsets is None else replace(capture, lights=moved_lights(capture.lights, offsets))


def fit_offsets(capture: Capture, render: Callable[[Tensor], Tensor], init: Tensor | None = None, *,
                iters: int = ITERS, shared: bool = False) -> Tensor:
    """(N, 3) float64 offsets of ``capture``'s point lights that bring ``render`` (lights (N, 4) →
    (N, 3, H, W), the material held fixed) closest to the photos in squared error over their valid
    observations (module docstring); ``init`` (N, 3) starts the search (zeros by default). ``shared``:
    one offset for every shot (the flash's place beside the lens, where the capture put it elsewhere:
    the normal equations summed over the shots), repeated in each row."""
    lights = capture.lights.double().cpu()
    n = lights.shape[0]
    photo = capture.images.double().cpu().reshape(n, -1)
    valid = valid_pixels(capture).cpu().reshape(n, -1)
    point = lights[:, 3] > 0
    dist = lights[:, :3].norm(dim=1).clamp_min(1e-12)
    d = torch.zeros(n, 3, dtype=torch.float64) if init is None else init.double().cpu().clone()
    d[~point] = 0.0
    if not bool(point.any()) or not bool(valid.any()):
        return d
    h = (STEP * dist)[:, None]
    if shared:  # one set of normal equations, one damping, one bound (the nearest light's)
        dist = dist.min().expand(n)
    pool = (lambda x: x.sum(0, keepdim=True).expand_as(x)) if shared else (lambda x: x)  # noqa: E731

    def residual(off: Tensor) -> Tensor:
        with torch.no_grad():
            pred = render(moved_lights(capture.lights, off.to(capture.lights.dtype))).double().cpu().reshape(n, -1)
        return torch.where(valid, pred - photo, torch.zeros_like(photo))

    r = residual(d)
    cost = (r * r).sum(1)
    lam = torch.full((n,), LAMBDA0, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    live = point.clone()  # shots still searching (a shot's own stop: FTOL)
    for _ in range(iters):
        cols = []
        for j in range(3):
            e = torch.zeros(n, 3, dtype=torch.float64)
            e[:, j] = h[:, 0]
            cols.append((residual(d + e) - residual(d - e)) / (2.0 * h))
        jac = torch.stack(cols, 2)  # (N, M, 3)
        a = pool(jac.transpose(1, 2) @ jac)  # (N, 3, 3)
        g = pool((jac * r[:, :, None]).sum(1))  # (N, 3)
        damp = a + lam[:, None, None] * (torch.diagonal(a, dim1=1, dim2=2)[:, :, None] * eye + 1e-12 * eye)
        step = -torch.linalg.solve(damp, g[:, :, None])[:, :, 0]
        trial = d + step
        length = trial.norm(dim=1, keepdim=True)
        trial = trial * (MAX_MOVE * dist[:, None] / length.clamp_min(1e-300)).clamp(max=1.0)
        trial[~point] = 0.0
        r_t = residual(trial)
        c_t = (r_t * r_t).sum(1)
        before, after = pool(cost[:, None])[:, 0], pool(c_t[:, None])[:, 0]
        take = (after < before) & live
        live &= ~(take & (before - after <= FTOL * before))
        d = torch.where(take[:, None], trial, d)
        r = torch.where(take[:, None], r_t, r)
        cost = torch.where(take, c_t, cost)
        lam = torch.where(take, lam / 3.0, lam * 4.0)
        live &= lam <= 1e8
        if not bool(live.any()):
            break
    return d


def material_offsets(material: Material, capture: Capture, factor: Tensor | None = None, *,
                     max_pixels: int = PIXELS) -> Tensor:
    """(N, 3) offsets of the point lights of ``capture`` (shots of ``material``'s sample it was not fitted
    on) fitted to their photos with the material held fixed: its coating (the lobe's shading, no sparkles)
    on a pixel grid of ≤ ``max_pixels`` (:func:`~torchmetal.io.grid.stride_grid`); ``factor``
    (N, 1, H, W) or (N, 1, 1, 1): a light calibration's factor the render is multiplied by."""
    from torchmetal.io.grid import stride_grid, strided_capture
    from torchmetal.lobes import lobe_render  # on use: lobes → phong → geometry (no circle, fewer imports)

    h, w = int(capture.images.shape[-2]), int(capture.images.shape[-1])
    if (h, w) != (material.height, material.width):
        raise ValueError(f"material_offsets: expected photos of {material.height}x{material.width}, found {h}x{w}")
    sub = strided_capture(capture, max_pixels)
    rows, cols, _, _ = stride_grid(h, w, max_pixels)  # every pixel where the capture is small enough
    pick = lambda t: t[..., rows, cols]  # noqa: E731
    tex = pick(material.texture)
    dt = tex.dtype
    s, alpha = material.specular_maps()
    s, alpha = (pick(s), pick(alpha)) if s.dim() == 3 else (s, alpha)
    normals = pick(material.flat_normals())
    f = 1.0 if factor is None else (pick(factor) if factor.shape[-1] > 1 else factor).to(dt)
    return fit_offsets(sub, lambda lights: f * lobe_render(tex, s, alpha, normals, lights.to(dt), sub.intensities.to(dt),
                                                           sub.cameras.to(dt), sub.size, material.lobe))
