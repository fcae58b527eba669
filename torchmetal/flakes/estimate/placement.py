"""Flake normals from the glint amplitudes *and* the flakes' known brightness.

A flake seen in one or two fit shots only, far off its glint peak, shows a faint glint a = A·g_k.
The amplitude ratios of :func:`torchmetal.flakes.estimate.observed_flakes._refine_normals` cannot tell a faint flake
seen head-on from a bright one seen at its tail, and their ridge keeps it at the detections' half
vectors: such a flake renders dim everywhere, and a new view between the fit shots, where it truly
glints at full brightness, misses it. The flake statistics know the brightness distribution
(log A ~ N(μ, s²), ``FlakeModel.extra``), and the shots that did *not* detect the flake bound its
normal away from their half vectors (A·g_j below the detector's amplitude ``detect_amp`` T).
:func:`place_normals` minimises, over a fixed polar grid of candidate normals around the start,

    Σ_k∈det w_k (log a_k − log A + |m − h_k|²/2σ²)² + (log A − μ)²/s² + Σ_j∉det W (log(A·g_j/T))₊²

with log A profiled in closed form from the first two terms (w_k = snr², W = MISS_WEIGHT); the start
is kept unless a candidate is better by ``GAIN``. The grid (and the first minimum on ties) keeps it
deterministic.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmetal.geometry import normalize

MISS_WEIGHT = 25.0  # a miss weighs like a detection at SNR 5 (the detector's threshold)
GAIN = 2.0  # the start is kept unless a candidate lowers the cost by more (≈ 1.4 σ of evidence)
MIN_AMP_STD = 0.25  # floor on the brightness spread s (a narrow fitted s is often not identified)
RADII = 15  # candidate rings: 0 … 3.5 σ
ANGLES = 24


def _candidates(m0: Tensor, sigma: float) -> Tensor:
    """(J, C, 3) unit candidate normals on a polar grid in m0's tangent plane (candidate 0 = m0)."""
    ref = torch.zeros_like(m0)
    ref[:, 0] = 1.0
    alt = torch.zeros_like(m0)
    alt[:, 1] = 1.0
    ref = torch.where(m0[:, :1].abs() > 0.9, alt, ref)
    t1 = normalize(ref - (ref * m0).sum(1, keepdim=True) * m0, dim=1)
    t2 = torch.cross(m0, t1, dim=1)
    r = torch.linspace(0.0, 3.5, RADII, dtype=m0.dtype, device=m0.device)[1:]
    phi = torch.arange(ANGLES, dtype=m0.dtype, device=m0.device) * (2 * math.pi / ANGLES)
    u = torch.cat([m0.new_zeros(1), (r.view(-1, 1) * torch.cos(phi)).reshape(-1)])
    v = torch.cat([m0.new_zeros(1), (r.view(-1, 1) * torch.sin(phi)).reshape(-1)])
    off = sigma * (u.view(1, -1, 1) * t1.unsqueeze(1) + v.view(1, -1, 1) * t2.unsqueeze(1))
    return normalize(m0.unsqueeze(1) + off, dim=2)


def place_normals(m0: Tensor, half: Tensor, detected: Tensor, valid: Tensor, log_a: Tensor, weight: Tensor,
                  sigma: float, log_amp_mean: float, log_amp_std: float, detect_amp: float) -> Tensor:
    """Flake normals (J, 3) of least cost (module docstring) among the grid around ``m0``.

    Args:
        m0: (J, 3) unit start normals; half: (N, 3, J) unit half vector of every shot at each flake;
        detected: (N, J) bool, shot k detected flake j; valid: (N, J) bool, shot k could have
            (pixel on the sample, not clipped); log_a: (N, J) log glint amplitude where detected
            (ignored elsewhere); weight: (N, J) its inverse variance (snr²) where detected.
        sigma: glint width σ_g; log_amp_mean, log_amp_std: the flakes' brightness distribution;
        detect_amp: the amplitude the detector fires at.
    """
    cand = _candidates(m0, sigma)  # (J, C, 3)
    hv = half.permute(2, 0, 1)  # (J, N, 3)
    q = ((cand.unsqueeze(2) - hv.unsqueeze(1)) ** 2).sum(-1) / (2 * sigma * sigma)  # (J, C, N) = −log g
    det = detected.t().unsqueeze(1).to(q.dtype)  # (J, 1, N)
    w = weight.t().unsqueeze(1) * det
    y = log_a.t().unsqueeze(1).where(det > 0, torch.zeros_like(det)) + q  # log A implied by each detection
    s2 = max(log_amp_std, MIN_AMP_STD) ** 2
    log_amp = ((w * y).sum(-1) + log_amp_mean / s2) / (w.sum(-1) + 1.0 / s2)  # (J, C)
    cost = (w * (y - log_amp.unsqueeze(-1)) ** 2).sum(-1) + (log_amp - log_amp_mean) ** 2 / s2
    miss = (valid & ~detected).t().unsqueeze(1).to(q.dtype)
    over = (log_amp.unsqueeze(-1) - q - math.log(detect_amp)).clamp_min(0.0)
    cost = cost + MISS_WEIGHT * (miss * over * over).sum(-1)
    best = cost.argmin(1)  # first minimum on ties
    best = torch.where(cost.gather(1, best.view(-1, 1))[:, 0] < cost[:, 0] - GAIN, best, torch.zeros_like(best))
    return cand[torch.arange(cand.shape[0], device=cand.device), best]
