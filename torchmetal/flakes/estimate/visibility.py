"""Visibility: the probability that a flake is detected in at least one shot.

Flakes that never glint are accounted for by the selection probability

    P_any(p) = ∫dA f_A(A) ∫dΩ p_τ(m) · [1 − Π_k (1 − P_k(m, A))],

evaluated on a coarse grid of cells (:func:`cell_grid`: half vectors, normals, noise σ, pixel area
and the measurable fraction of each cell per shot) and integrated cap by cap with a partition of
unity, Gauss–Legendre in log A over the band where detection switches on and in u = 1 − m·h_k
over each cap's interior and edge band (:func:`log_p_any`). P_k is scaled by the cell's
measurable fraction in that shot: no detection can come from a saturated or masked region.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.flakes.estimate.detect import Detection
from torchmetal.flakes.estimate.glint_model import (
    HEADROOM_SPREAD,
    LOG2PI,
    PROBIT,
    GlintData,
    cap_radius,
    log_amp_floor,
    log_slope_from,
    log_unclipped,
    memo,
    nearest_shots,
    orthonormal_pair,
    overlap_count,
    ring_nodes,
    tail_nodes,
)
from torchmetal.flakes.estimate.shot_geometry import Geometry

#: most shots whose caps share a point through the partition of unity (the nearest first), so the work
#: grows as N·K per cell, not N². Zoo flakes_b (16 shots on a ring) needs all 16: capped at 8 its density
#: came out 16 % high (8 % with all); beyond 16 a capture with shots this close has plenty of them
MAX_OVERLAP = 16


def _gauss_legendre(n: int, dtype, device) -> tuple[Tensor, Tensor]:
    """Gauss–Legendre nodes and weights on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(n)
    return torch.tensor(0.5 * (x + 1), dtype=dtype, device=device), torch.tensor(0.5 * w, dtype=dtype, device=device)


def log_p_any(
    d: GlintData, tau: Tensor, sg: Tensor, la: Tensor, va: Tensor, *,
    n_a: int = 2, n_a_band: int = 4, n_in: int = 2, n_band: int = 3, n_phi: int = 8, margin: float = 3.0,
) -> Tensor:
    """log of the probability (G,) (float64) that a flake in each grid cell is detected in at
    least one shot.

    Amplitudes: Gauss–Legendre in log A (``n_a_band`` nodes) over the band where the cell's
    detection probability rises (from (k_hi − margin)·σ_min to (k_hi + margin)·σ_max of the
    cell), where a steep amplitude tail and a steep detection rate meet and quantile nodes
    would be far off; ``n_a`` quantile nodes of the distribution above it.

    Cap k of shot k (A fixed) is integrated in u = 1 − m·h_k and φ: Gauss–Legendre in u on
    the interior, where A·g ≥ (k_hi + margin)·σ and detection is certain, and on the edge band
    down to (k_hi − margin)·σ, where the detection probability falls from 1 to 0; the
    trapezoid rule in φ. Overlapping caps share each point through a partition of unity
    P_k / Σ_j P_j, so the union is counted once. P_k is scaled by the cell's measurable
    fraction in shot k (``grid_valid``): no detection can come from a saturated region.
    """
    g, n = d.grid_sigma.shape
    qa, phi, (x_in, w_in), (x_bd, w_bd), lsig, proj, to_near, s_near, v_near, u_near = memo(
        d, ("p_any", n_a, n_in, n_band, n_phi), lambda: _p_any_constants(d, n_a, n_in, n_band, n_phi))
    level_lo = max(0.5, d.k_hi - margin)
    log_floor = log_amp_floor(d)
    lab, log_width, hi = memo(d, ("band", n_a_band, margin),
                              lambda: _amplitude_band(d, lsig, level_lo, log_floor, n_a_band, margin))
    log_a, log_wa = _amplitude_nodes(d, la, va, lab, log_width, hi, qa, log_floor, n_a)

    def ucap(level: float) -> Tensor:  # 1 − m·h where A·g = level·σ, (G, nA, N)
        return (sg * sg * (log_a.unsqueeze(-1) - lsig - math.log(level))).clamp(0.0, 1.9)

    u_lo = ucap(d.k_hi + margin)
    u_hi = ucap(level_lo)
    edge = [u_lo.unsqueeze(-1) + (u_hi - u_lo).unsqueeze(-1) * x_bd], [(u_hi - u_lo).unsqueeze(-1) * w_bd]
    if u_near is None:
        uu = torch.cat([u_lo.unsqueeze(-1) * x_in, *edge[0]], -1)
        wu = torch.cat([u_lo.unsqueeze(-1) * w_in, *edge[1]], -1)  # (G, nA, N, nR)
    else:  # the interior split where the glint stops clipping (A·g = the cell's headroom): a step the nodes must see
        u_c = torch.minimum((sg * sg * (log_a.unsqueeze(-1) - d.grid_headroom.to(u_lo.dtype).view(g, 1, n))).clamp_min(0.0), u_lo)
        uu = torch.cat([u_c.unsqueeze(-1) * x_in, u_c.unsqueeze(-1) + (u_lo - u_c).unsqueeze(-1) * x_in, *edge[0]], -1)
        wu = torch.cat([u_c.unsqueeze(-1) * w_in, (u_lo - u_c).unsqueeze(-1) * w_in, *edge[1]], -1)
    uu = uu.clamp_min(1e-9)
    # nodes m = cos β·h_k + sin β·(cos φ e1_k + sin φ e2_k), (G, nA, N, nR, nφ), handled through
    # their projections m·v = cos β·(h_k·v) + sin β·(cos φ e1_k·v + sin φ e2_k·v)
    cosb = (1 - uu).unsqueeze(-1)
    sinb = torch.sqrt(uu * (2 - uu)).unsqueeze(-1)
    cphi, sphi = torch.cos(phi), torch.sin(phi)

    def dot_m(b: int) -> Tensor:  # m·(n, t1, t2)[b] (G, nA, N, nR, nφ)
        rv = cphi * proj[:, :, 1, b : b + 1] + sphi * proj[:, :, 2, b : b + 1]  # (G, N, nφ)
        return cosb * proj[:, :, 0, b].view(g, 1, n, 1, 1) + sinb * rv.view(g, 1, n, 1, -1)

    logp = log_slope_from(dot_m(0), dot_m(1), dot_m(2), tau)
    share = _union_share(d, sg, log_a, level_lo, cosb, sinb, cphi, sphi, to_near, s_near, v_near, u_near)
    wts = (wu * (2 * math.pi / n_phi)).unsqueeze(-1)
    val = (torch.exp(logp) * share * wts).sum((2, 3, 4))  # (G, nA)
    return torch.logsumexp(torch.log(val.double().clamp_min(1e-300)) + log_wa, 1)


def _p_any_constants(d: GlintData, n_a: int, n_in: int, n_band: int, n_phi: int) -> tuple:
    """The parameter-free part of :func:`log_p_any`: ring and Gauss–Legendre nodes, log σ, each cap's frame
    projected onto the cell's normal frame and onto the nearest shots' half vectors (own shot first)."""
    dt, dev = d.grid_half.dtype, d.grid_half.device
    g, n = d.grid_sigma.shape
    qa, phi = ring_nodes(n_a, n_phi, dt, dev)
    e1, e2 = orthonormal_pair(d.grid_half)  # (G, N, 3)
    t1, t2 = orthonormal_pair(d.grid_normal)
    basis = torch.stack([d.grid_half, e1, e2], 2)  # (G, N, 3: h_k, e1_k, e2_k, 3)
    proj = torch.einsum("gnac,gbc->gnab", basis, torch.stack([d.grid_normal, t1, t2], 1))  # onto n, t1, t2
    first = torch.arange(n, device=dev).expand(g, n)
    order = nearest_shots(d.grid_half.unsqueeze(1).expand(g, n, n, 3), first, n)  # (G, N, N) own shot first
    h_near = d.grid_half.gather(1, order.flatten(1)[..., None].expand(-1, -1, 3)).view(g, n, n, 3)
    to_near = torch.einsum("gnac,gnkc->gnak", basis, h_near)  # (G, N, 3, N) onto the nearest shots' h
    s_near = d.grid_sigma.gather(1, order.flatten(1)).view(g, n, n)
    v_near = None if d.grid_valid is None else d.grid_valid.to(dt).gather(1, order.flatten(1)).view(g, n, n)
    u_near = None  # the headroom's mean and spread (log) over the cell, of the nearest shots
    if d.grid_headroom is not None:
        spread = torch.sqrt(d.grid_headroom_sd.to(dt) ** 2 + HEADROOM_SPREAD**2)
        u_near = (d.grid_headroom.to(dt).gather(1, order.flatten(1)).view(g, n, n), spread.gather(1, order.flatten(1)).view(g, n, n))
    return (qa, phi, _gauss_legendre(n_in, dt, dev), _gauss_legendre(n_band, dt, dev),
            torch.log(d.grid_sigma).view(g, 1, n), proj, to_near, s_near, v_near, u_near)


def _amplitude_band(d: GlintData, lsig: Tensor, level_lo: float, log_floor: float, n_a_band: int,
                    margin: float) -> tuple[Tensor, Tensor, Tensor]:
    """log-A band nodes (G, nAb), log of their width × Gauss–Legendre weight, band top (G,)."""
    lo = (lsig.amin(-1)[:, 0] + math.log(level_lo)).double().clamp_min(log_floor)
    hi = lsig.amax(-1)[:, 0].double() + math.log(d.k_hi + margin)
    x_ab, w_ab = _gauss_legendre(n_a_band, torch.float64, d.grid_half.device)
    return lo.unsqueeze(1) + (hi - lo).unsqueeze(1) * x_ab, torch.log((hi - lo).unsqueeze(1) * w_ab), hi


def _amplitude_nodes(d: GlintData, la: Tensor, va: Tensor, lab: Tensor, log_width: Tensor, hi: Tensor, qa: Tensor,
                     log_floor: float, n_a: int) -> tuple[Tensor, Tensor]:
    """log A at the band's and the tail's nodes (G, nAb + nA) and the log of their weights."""
    la64, va64 = la.double(), va.double()
    log_wb = (log_width - 0.5 * ((lab - la64) / va64) ** 2 - 0.5 * LOG2PI
              - torch.log(va64) - torch.special.log_ndtr((la64 - log_floor) / va64))
    lat, log_tail = tail_nodes(la, va, hi, qa, log_floor)  # (G, nA) above the band
    log_a = torch.cat([lab.to(d.grid_half.dtype), lat], 1)  # (G, nAb + nA)
    log_wa = torch.cat([log_wb, (log_tail - math.log(n_a)).unsqueeze(1).expand(-1, n_a)], 1)
    return log_a, log_wa


def _union_share(d: GlintData, sg: Tensor, log_a: Tensor, level_lo: float, cosb: Tensor, sinb: Tensor, cphi: Tensor,
                 sphi: Tensor, to_near: Tensor, s_near: Tensor, v_near: Tensor | None,
                 u_near: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Cap k's share P_k · P_any / Σ_j P_j of the union at its nodes (G, nA, N, nR, nφ) (partition of unity
    over the shots whose caps may overlap it). With a headroom (``u_near``: its log mean and spread over the
    cell), P_k holds only the glints that do not clip (a clipped one is never measured)."""
    g, n = d.grid_sigma.shape
    # shots whose caps may overlap cap k (own shot first): caps farther apart never meet
    beta = cap_radius(sg, float(log_a.max().detach()), float(d.grid_sigma.min()), level_lo)
    kk = min(overlap_count(d.grid_half, d.grid_half, 2.2 * beta + 1e-3), MAX_OVERLAP)
    tn = to_near[..., :kk]  # (G, N, 3, K)
    sn = s_near[..., :kk]  # (G, N, K)
    rh = cphi.view(-1, 1) * tn[:, :, 1].unsqueeze(2) + sphi.view(-1, 1) * tn[:, :, 2].unsqueeze(2)  # (G, N, nφ, K)
    mh = cosb.unsqueeze(-1) * tn[:, :, 0].view(g, 1, n, 1, 1, -1) + sinb.unsqueeze(-1) * rh.view(g, 1, n, 1, -1, kk)  # (G, nA, N, nR, nφ, K)
    log_glint = log_a.view(g, -1, 1, 1, 1, 1) - (1 - mh) / (sg * sg)
    a_over_s = torch.exp(log_glint) / sn.view(g, 1, n, 1, 1, -1)
    zk = PROBIT * (a_over_s - d.k_hi)
    pk = torch.sigmoid(zk)
    if u_near is not None:
        um, us = (x[..., :kk].view(g, 1, n, 1, 1, kk) for x in u_near)
        pk = pk * torch.exp(log_unclipped(log_glint, um, us))
    if v_near is not None:  # a flake can only be detected where its shot is measurable
        pk = pk * v_near[..., :kk].view(g, 1, n, 1, 1, kk)
    any_ = 1.0 - (1.0 - pk).prod(-1)
    own = pk[..., 0]  # (G, nA, N, nR, nφ): P_k at the nodes of cap k
    return own * any_ / pk.sum(-1).clamp_min(1e-30)


def cell_grid(det: Detection, geometry: Geometry, max_cells: int, ok: Tensor) -> tuple[Tensor, ...]:
    """Half vectors (G, N, 3), normals (G, 3), noise σ (G, N), pixel area (G,) and measurable
    fraction (G, N) (of ``ok`` (N, H, W)) of a grid of at most ``max_cells`` cells."""
    n, _, h, w = det.sigma.shape
    side = max(1, int(math.sqrt(max_cells)))
    gh = min(side, h)
    gw = min(side, w)
    lsig = F.adaptive_avg_pool2d(torch.log(det.sigma.double()), (gh, gw))  # (N, 1, gh, gw)
    valid = F.adaptive_avg_pool2d(ok.unsqueeze(1).to(torch.float32), (gh, gw))[:, 0].double()  # (N, gh, gw)
    area = torch.full((gh * gw,), h * w / (gh * gw), dtype=torch.float64, device=det.sigma.device)
    half, normal = geometry.on_grid(gh, gw)
    return half, normal, torch.exp(lsig).flatten(1).t(), area, valid.flatten(1).t()


def cell_headroom(det: Detection, max_cells: int, ok: Tensor) -> tuple[Tensor, Tensor] | None:
    """Mean and spread (G, N) of the log headroom (:attr:`Detection.headroom`) over each cell's measurable pixels
    (``ok`` (N, H, W)), on :func:`cell_grid`'s cells; None without a headroom."""
    if det.headroom is None:
        return None
    n, _, h, w = det.headroom.shape
    side = max(1, int(math.sqrt(max_cells)))
    gh, gw = min(side, h), min(side, w)
    lu = torch.log(det.headroom.double())
    wt = ok.unsqueeze(1).double()
    cnt = F.adaptive_avg_pool2d(wt, (gh, gw)).clamp_min(1e-12)
    mean = F.adaptive_avg_pool2d(lu * wt, (gh, gw)) / cnt
    var = (F.adaptive_avg_pool2d(lu * lu * wt, (gh, gw)) / cnt - mean * mean).clamp_min(0.0)
    return mean.flatten(1).t().contiguous(), torch.sqrt(var).flatten(1).t().contiguous()
