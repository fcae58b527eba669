"""The glint likelihood: each flake's numerator f_j and the penalised profile objective.

Each associated flake j contributes its detection pattern b_jk and the amplitude â_j of its
detection in the anchor shot k* (:mod:`~torchmetal.flakes.estimate.association`). Given (A, m) on the
sphere, the anchor amplitude pins m to a ring 1 − m·h_k* = σ_g² ln(A/â) around h_k*; the
density of â there is σ_g²/â (exact change of variables), so

    f_j = σ_g²/â_j ∫dA f_A(A) ∮dφ  p_τ(m) · Π_{k≠k*} P(b_jk | m, A),

with p_τ(m) the slope density (:mod:`~torchmetal.flakes.estimate.glint_model`) (:func:`log_numerator`).
With P_any, the probability of being detected at all (:mod:`~torchmetal.flakes.estimate.visibility`),
the true density is profiled out in closed form (ρ̂ = J / ∫P_any dp), leaving
Σ_j log f_j − J log ∫P_any dp minus the priors' penalty (:func:`objective`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmetal.flakes.estimate.glint_model import (
    GlintData,
    cap_radius,
    log_amp_floor,
    log_detect,
    log_slope_from,
    log_unclipped,
    log_unmeasured,
    memo,
    nearest_shots,
    orthonormal_pair,
    overlap_count,
    ring_nodes,
    tail_nodes,
)
from torchmetal.flakes.estimate.visibility import log_p_any

#: the rate of shots unmeasured at a flake for a reason other than a clip (a neighbour's clipped glint): an
#: unmeasured shot costs at most log(1/ε) (simulated flakes_a geometry: ε = 0.02 left E[A] ×0.92, 1e-4 ×0.96)
UNMEASURED_OUTLIER = 1e-3


def _gather_shots(x: Tensor, idx: Tensor) -> Tensor:
    """x (R, N[, 3]) gathered at idx (R, K) along the shot axis."""
    if x.dim() == 3:
        return x.gather(1, idx[..., None].expand(-1, -1, x.shape[-1]))
    return x.gather(1, idx)


def log_numerator(
    d: GlintData, tau: Tensor, sg: Tensor, la: Tensor, va: Tensor, *, n_a: int = 6, n_phi: int = 16, outlier: float = 0.02,
) -> Tensor:
    """log f_j of every flake (J,) (see the module docstring); ``outlier``: see
    :func:`~torchmetal.flakes.estimate.glint_model.log_detect`."""
    dt, dev = d.half.dtype, d.half.device
    j = d.amp.shape[0]
    qa, phi = memo(d, ("nodes", n_a, n_phi), lambda: ring_nodes(n_a, n_phi, dt, dev))
    h_star, proj, to_shots, order = memo(d, ("numerator",), lambda: _numerator_geometry(d))
    # only shots whose caps can reach the ring matter: keep those (detected first), anchor first
    beta = cap_radius(sg, float((la + 3 * va).detach()), float(d.sigma.min()), max(0.5, d.k_hi - 3.0))
    kk = overlap_count(h_star.unsqueeze(1), d.half, 2.2 * beta + 1e-3)
    kk = max(kk, int(d.detected.sum(1).max()))  # every detected shot stays in the pattern
    detected, sigma, anchor = d.detected, d.sigma, d.anchor
    observed = d.observed if d.observed is not None else torch.ones_like(detected)
    headroom = d.headroom
    if kk < d.half.shape[1]:
        idx = order[:, :kk]
        detected, sigma, anchor = _gather_shots(detected, idx), _gather_shots(sigma, idx), torch.zeros_like(anchor)
        observed = _gather_shots(observed, idx)
        headroom = None if headroom is None else _gather_shots(headroom, idx)
        to_shots = to_shots.gather(2, idx.unsqueeze(1).expand(-1, 3, -1))
    log_amp = torch.log(d.amp.clamp_min(1e-12))
    log_a, log_tail = tail_nodes(la, va, log_amp, qa, log_amp_floor(d))  # A nodes: A > â
    log_tail = log_tail.to(dt)
    cap = sg * sg * (log_a - log_amp.unsqueeze(1))  # 1 − cos β ≥ 0
    inside = cap < 1.9
    cap = cap.clamp(1e-9, 1.9)
    cosb = 1 - cap
    sinb = torch.sqrt(cap * (2 - cap))
    # ring nodes m = cos β·h* + sin β·(cos φ e1 + sin φ e2), (J, nA, nφ), handled through their
    # projections: every dot product m·v is cos β·(h*·v) + sin β·(cos φ e1·v + sin φ e2·v)
    cphi, sphi = torch.cos(phi), torch.sin(phi)
    cosb, sinb = cosb.view(j, n_a, 1), sinb.view(j, n_a, 1)

    def dot_m(b: int) -> Tensor:  # m·(n, t1, t2)[b] (J, nA, nφ)
        ring_v = cphi * proj[:, 1, b : b + 1] + sphi * proj[:, 2, b : b + 1]  # (J, nφ)
        return cosb * proj[:, 0, b].view(j, 1, 1) + sinb * ring_v.unsqueeze(1)

    total = log_slope_from(dot_m(0), dot_m(1), dot_m(2), tau)
    if to_shots.shape[-1] > 1:  # other shots: detection pattern (none when only the anchor's cap reaches the ring)
        rh = cphi.view(1, -1, 1) * to_shots[:, 1].unsqueeze(1) + sphi.view(1, -1, 1) * to_shots[:, 2].unsqueeze(1)  # (J, nφ, K)
        mh = cosb.unsqueeze(-1) * to_shots[:, 0].view(j, 1, 1, -1) + sinb.unsqueeze(-1) * rh.unsqueeze(1)  # (J, nA, nφ, K)
        log_g = -(1 - mh) / (sg * sg)
        a_over_s = torch.exp(log_a.view(j, n_a, 1, 1) + log_g) / sigma.view(j, 1, 1, -1)
        log_m = None  # a measured shot's glint did not clip
        if headroom is not None:
            log_glint = log_a.view(j, n_a, 1, 1) + log_g
            log_m = log_unclipped(log_glint, headroom.view(j, 1, 1, -1))
        ld = log_detect(a_over_s, d.k_hi, detected.view(j, 1, 1, -1), outlier, log_m)
        counted = observed.to(dt)  # the anchor's own detection is the ring
        counted[torch.arange(j, device=dev), anchor] = 0.0
        total = total + (ld * counted.view(j, 1, 1, -1)).sum(-1)
        if headroom is not None:  # an unmeasured shot: its glint clipped (or the coat did: then it says nothing)
            lu = log_unmeasured(log_glint, headroom.view(j, 1, 1, -1), UNMEASURED_OUTLIER)
            total = total + (lu * (~observed).to(dt).view(j, 1, 1, -1)).sum(-1)
    logw = log_tail.view(j, 1, 1) - math.log(n_a) + math.log(2 * math.pi / n_phi)
    total = total + logw
    total = torch.where(inside.view(j, n_a, 1), total, torch.full_like(total, -1e4))
    lse = torch.logsumexp(total.flatten(1), dim=1)
    return lse + 2 * torch.log(sg) - log_amp


def _numerator_geometry(d: GlintData) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each flake's h* (J, 3), its ring frame projected onto the flake's normal frame (J, 3, 3) and onto every
    shot's h (J, 3, N), and the shots nearest its anchor (J, N), detected first."""
    j, dev = d.amp.shape[0], d.half.device
    h_star = d.half[torch.arange(j, device=dev), d.anchor]  # (J, 3)
    e1, e2 = orthonormal_pair(h_star)
    t1, t2 = orthonormal_pair(d.normal)
    basis = torch.stack([h_star, e1, e2], 1)  # (J, 3: h*, e1, e2, 3)
    proj = torch.einsum("jac,jbc->jab", basis, torch.stack([d.normal, t1, t2], 1))  # onto n, t1, t2
    to_shots = torch.einsum("jac,jkc->jak", basis, d.half)  # (J, 3, N) onto every shot's h
    order = nearest_shots(d.half, d.anchor, d.half.shape[1], prefer=d.detected)  # (J, N)
    return h_star, proj, to_shots, order


def objective(d: GlintData, sub: GlintData, theta: Tensor, prior: tuple[Tensor, Tensor], nodes: dict) -> tuple[Tensor, Tensor]:
    """Negative penalised profile log-likelihood (float64) and the expected detected count.

    ``d`` holds the grid, ``sub`` the flakes in the numerator sum (both in the work dtype).
    """
    wd = d.grid_half.dtype
    tau, sg, la, va = torch.exp(theta[0]).to(wd), torch.exp(theta[1]).to(wd), theta[2].to(wd), torch.exp(theta[3]).to(wd)
    lnum = log_numerator(sub, tau, sg, la, va, **nodes.get("num", {})).double()
    log_pa = log_p_any(d, tau, sg, la, va, **nodes.get("any", {}))
    log_expected = torch.logsumexp(log_pa + torch.log(d.grid_area.double().clamp_min(1e-300)), 0)
    ll = lnum.sum() * (d.count / max(1, sub.amp.numel())) - d.count * log_expected
    mean, sd = prior
    pen = 0.5 * (((theta - mean) / sd) ** 2).sum()
    return -(ll - pen), torch.exp(log_expected)
