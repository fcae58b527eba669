"""Flat where the photos cannot tell: the last step of :func:`~torchmetal.normals.estimate.estimate_normals`.

A per-pixel normal has two free parameters, so on a flat sample the estimate is the flat normal
plus noise, and the noise costs held-out PSNR (sharp lobes move with it). Each pixel keeps its estimate only when it explains its own shots
significantly better than (0, 0, 1) does — an F-test of the two extra parameters against the
pixel's own residual (noise that grows with the signal, misfit and quantisation included): with
the texture re-solved for both over the estimate's inliers (Cauchy weight > 1/2: glints and
shadows the refinement rejected stay out), Δ = Σ r²(flat) − Σ r²(estimate), c = Σ r²(estimate)
and ν = (inlier shots) − 3,

    F = (Δ/2)/(c/ν),   p = P(F(2, ν) > F) = (1 + Δ/c)^(−ν/2)   (closed form for 2 numerator dof)

and the estimate is kept when p < FLAT_P, or when it is steeper than 5° (where a pixel has few
usable shots the test has no power, e.g. at a sphere's limb; the noise about flat stays well
below that, docs/design.md §4). Tilts the shots resolve pass easily; noise does not.

**What the test could not reject** (:func:`unrejected_tilt_deg`, the floor of the leave-out radius of a pixel set
flat, :mod:`torchmetal.plan.leave_out`): refits that all snap a pixel to (0, 0, 1) agree exactly, and their spread
says nothing of the tilt the test let through. Near flat, an estimate θ̂ that minimises the cost has
Δ = c_flat − c_est ≈ θ̂ᵀAθ̂ (A = JᵀWJ, the Gauss–Newton matrix of the inliers at θ = 0), and with c_flat fixed by
the shots the test keeps flat exactly when Δ/(c_flat − Δ) ≤ FLAT_P^(−2/ν) − 1, i.e. Δ ≤ c_flat·(1 − FLAT_P^(2/ν)).
The estimates it sets flat are then the ellipse θᵀAθ ≤ c_flat·(1 − FLAT_P^(2/ν)), cut at |θ| < FLAT_TILT_MAX
(steeper ones are kept whatever the test): the steepest of them, min(√(c_flat·(1 − FLAT_P^(2/ν))/λ_min(A)),
FLAT_TILT_MAX), is the tilt the snap may have hidden. ν < 1 (the test never keeps anything): the 5° cut.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.normals.core import (
    CAUCHY_C,
    active_blocks,
    cauchy_weights,
    model_state,
    pass_setup,
    robust_scale,
    theta_of,
)

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

FLAT_P = 1e-3  # the test's false-alarm rate on a flat pixel
FLAT_TILT_MAX = 0.0875  # tan 5°: steeper estimates are kept whatever the test (few usable shots: no power)


def flat_where_unresolved(capture: Capture, normals: Tensor, s: Tensor, alpha: Tensor, *,
                          active: Tensor | None = None) -> tuple[Tensor, int]:
    """Normals (3, H, W) with (0, 0, 1) where the test above keeps flat; returns them and the count."""
    dt, spec, act, floor = pass_setup(capture, s, alpha, active)
    w = capture.width
    out = normals.clone()
    count = 0
    for r0, r1, keep, sub in active_blocks(capture, act, dt):
        th = theta_of(normals[:, r0:r1].reshape(3, -1).to(dt))[:, keep]
        st = model_state(sub, th, spec, sub.ok.to(dt), jac=False)
        sigma = robust_scale(st.r, sub.ok, floor)
        for _ in range(2):  # IRLS: a glint must not drag the texture and with it every residual
            st = model_state(sub, th, spec, cauchy_weights(sub, st.r, CAUCHY_C * sigma), jac=False)
        wt = (cauchy_weights(sub, st.r, CAUCHY_C * sigma) > 0.5).to(dt)  # the inliers of the estimate
        c_est = model_state(sub, th, spec, wt, jac=False).cost
        c_flat = model_state(sub, torch.zeros_like(th), spec, wt, jac=False).cost
        nu = wt.sum(0)[0] - 3.0  # shots that count, less D and θ
        gain = (c_flat - c_est).clamp_min(0.0) / c_est.clamp_min(1e-30 * float(sigma) ** 2 + 1e-30)
        flat = ~(0.5 * nu * torch.log1p(gain) > math.log(1.0 / FLAT_P)) | (nu < 1)
        flat &= th.square().sum(0) < FLAT_TILT_MAX ** 2  # a steep estimate is not noise about flat
        idx = keep[flat]
        if idx.numel():
            blk = out[:, r0:r1].reshape(3, -1)
            blk[:, idx] = torch.tensor([0.0, 0.0, 1.0], dtype=out.dtype, device=out.device).view(3, 1)
            out[:, r0:r1] = blk.reshape(3, r1 - r0, w)
        count += int(idx.numel())
    return out, count


def unrejected_tilt_deg(capture: Capture, normals: Tensor, s: Tensor, alpha: Tensor, *,
                        active: Tensor | None = None) -> Tensor:
    """(H, W) float64 degrees: at each ``active`` pixel (default the mask) whose normal in ``normals`` (3, H, W) is
    exactly (0, 0, 1), the steepest estimate the flat test would have set flat there (module docstring: its
    threshold on these shots, at most the 5° cut); 0 elsewhere. ``s``, ``alpha`` (3,): the specular terms the
    test ran with (:class:`~torchmetal.normals.estimate.NormalsEstimate`'s)."""
    dt, spec, act, floor = pass_setup(capture, s, alpha, active)
    h, w = capture.height, capture.width
    out = torch.zeros(h * w, dtype=torch.float64, device=normals.device)
    n64 = normals.double()
    snapped = (n64[0] == 0) & (n64[1] == 0) & (n64[2] == 1)  # (H, W): what the test (or nothing) left at (0, 0, 1)
    cap = math.atan(FLAT_TILT_MAX)
    for r0, r1, keep, sub in active_blocks(capture, act, dt):
        th = theta_of(normals[:, r0:r1].reshape(3, -1).to(dt))[:, keep]
        st = model_state(sub, th, spec, sub.ok.to(dt), jac=False)
        sigma = robust_scale(st.r, sub.ok, floor)  # the block's scale at these normals, as the test's
        for _ in range(2):
            st = model_state(sub, th, spec, cauchy_weights(sub, st.r, CAUCHY_C * sigma), jac=False)
        wt = (cauchy_weights(sub, st.r, CAUCHY_C * sigma) > 0.5).to(dt)
        flat = model_state(sub, torch.zeros_like(th), spec, wt, jac=True)
        j0, j1 = (j.double() for j in flat.jac)
        w64 = wt.double()
        a, b, d = (w64 * j0 * j0).sum(0)[0], (w64 * j0 * j1).sum(0)[0], (w64 * j1 * j1).sum(0)[0]
        lam = 0.5 * (a + d) - torch.sqrt((0.5 * (a - d)) ** 2 + b * b)  # A's smaller eigenvalue: the blind direction
        nu = w64.sum(0)[0] - 3.0
        allowed = flat.cost.double() * -torch.expm1(2.0 / nu.clamp_min(1.0) * math.log(FLAT_P))  # c·(1 − p^(2/ν))
        tan = torch.sqrt(allowed / lam.clamp_min(1e-300))
        tilt = torch.where((nu < 1) | (lam <= 0), torch.full_like(tan, cap), torch.atan(tan).clamp_max(cap))
        idx = keep + r0 * w
        out[idx] = torch.where(snapped.reshape(-1)[idx], torch.rad2deg(tilt), torch.zeros_like(tilt))
    return out.reshape(h, w)
