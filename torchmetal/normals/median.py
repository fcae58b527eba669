"""The neighbourhood's normal where it explains a pixel as well: a step of
:func:`~torchmetal.normals.estimate.estimate_normals` before the flat test.

A glint (a flake, a speck of dust) lit in one shot can be explained by tilting the pixel's
normal until the Phong highlight falls on that shot; noise in a dark pixel can pull its normal
far off too. Both leave a normal that differs from its neighbours'. Each pixel is compared with
the component-wise median gradient of its 5×5 neighbourhood under a truncated quadratic
(min((r/σ)², K²) per shot: one glint costs at most K², however bright), the texture re-solved by
IRLS for both; the median is taken where it costs no more. On a smooth surface the median is the
pixel's own normal up to noise, so little changes there.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.normals.core import (
    CAUCHY_C,
    active_blocks,
    cauchy_weights,
    model_state,
    normals_of,
    pass_setup,
    robust_scale,
    theta_of,
)

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

WINDOW = 5
TRUNC_K = 3.0  # the truncated quadratic's cap, in units of σ


def _median_theta(theta: Tensor, valid: Tensor) -> Tensor:
    """Component-wise median of θ (2, H, W) over WINDOW×WINDOW neighbourhoods of ``valid`` (H, W) pixels."""
    h, w = theta.shape[1:]
    pad = WINDOW // 2
    x = torch.where(valid.unsqueeze(0), theta, torch.full_like(theta, float("nan")))
    cols = F.unfold(x.unsqueeze(0), WINDOW, padding=pad)[0]  # (2·K², H·W), zero padding → treat as missing
    ones = F.unfold(valid.to(theta.dtype).view(1, 1, h, w), WINDOW, padding=pad)[0]  # (K², H·W)
    cols = cols.view(2, WINDOW * WINDOW, h * w)
    cols = torch.where(ones.unsqueeze(0) > 0, cols, torch.full_like(cols, float("nan")))
    med = torch.nanmedian(cols, dim=1).values
    return torch.where(torch.isnan(med), theta.reshape(2, -1), med).view(2, h, w)


def _truncated_cost(sub, th: Tensor, spec, sigma: Tensor) -> Tensor:
    st = model_state(sub, th, spec, sub.ok.to(sub.y.dtype), jac=False)
    for _ in range(2):
        st = model_state(sub, th, spec, cauchy_weights(sub, st.r, CAUCHY_C * sigma), jac=False)
    u2 = (st.r / sigma).square().clamp_max(TRUNC_K * TRUNC_K)
    return torch.where(sub.ok, u2, torch.zeros_like(u2)).sum(0)[0]


def median_where_as_good(capture: Capture, normals: Tensor, s: Tensor, alpha: Tensor, *,
                         active: Tensor | None = None) -> tuple[Tensor, int]:
    """Normals (3, H, W) with the neighbourhood median taken where it costs no more; and the count."""
    dt, spec, act, floor = pass_setup(capture, s, alpha, active)
    h, w = capture.height, capture.width
    theta = theta_of(normals.to(dt).reshape(3, -1)).view(2, h, w)
    med = _median_theta(theta, act)
    out = normals.clone()
    count = 0
    for r0, r1, keep, sub in active_blocks(capture, act, dt):
        own = theta[:, r0:r1].reshape(2, -1)[:, keep]
        cand = med[:, r0:r1].reshape(2, -1)[:, keep]
        sigma = robust_scale(model_state(sub, own, spec, sub.ok.to(dt), jac=False).r, sub.ok, floor)
        take = (_truncated_cost(sub, cand, spec, sigma) <= _truncated_cost(sub, own, spec, sigma)) & (cand != own).any(0)
        idx = keep[take]
        if idx.numel():
            n, _ = normals_of(cand[:, take])
            blk = out[:, r0:r1].reshape(3, -1)
            blk[:, idx] = n.to(out.dtype)
            out[:, r0:r1] = blk.reshape(3, r1 - r0, w)
        count += int(idx.numel())
    return out, count
