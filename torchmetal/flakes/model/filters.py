"""Local filters of the flake stage: box means by running sums (cost independent of the radius),
maximum filters by shifted maxima, and binary closing/opening by shifted ORs and ANDs.

Light to import (torch only): the glint screen (:mod:`torchmetal.flakes.estimate.prescreen`) uses them on
every capture, detection and MD on flake captures.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

SHIFT_MAX_RADIUS = 12  # up to here shifted adds beat the two cumsums on CPU (r = 7: 7 vs 18 ms at 8×512²)


def _axis_sum(v: Tensor, radius: int, dim: int) -> Tensor:
    """Sums over 2r+1 neighbours along ``dim`` (-1 or -2), clipped at the border: shifted adds of a
    zero-padded copy for small r (a CPU cumsum costs several adds), running sums otherwise (cost
    independent of r; float32 sums: absolute error ~1e-7 × max|v| × length)."""
    r, n = radius, v.shape[dim]
    pad = (r, r) if dim == -1 else (0, 0, r, r)
    if r <= SHIFT_MAX_RADIUS:
        p = F.pad(v, pad)
        out = p.narrow(dim, 0, n).clone()
        for k in range(1, 2 * r + 1):
            out += p.narrow(dim, k, n)
        return out
    c = F.pad(v, (r + 1, r) if dim == -1 else (0, 0, r + 1, r)).cumsum(dim)
    return c.narrow(dim, 2 * r + 1, n) - c.narrow(dim, 0, n)


def _window_sum(v: Tensor, radius: int) -> Tensor:
    """Sums over (2r+1)² windows (clipped at the border), separably."""
    return _axis_sum(_axis_sum(v, radius, -1), radius, -2)


def box_mean(x: Tensor, radius: int, weight: Tensor | None = None) -> Tensor:
    """Mean over a (2r+1)² window, separably (shifted adds for r ≤ :data:`SHIFT_MAX_RADIUS`, running
    sums beyond: cost independent of r).

    Args:
        x: (B, C, H, W) values; weight: optional (B, 1|C, H, W) weights (e.g. a valid mask):
            the result is then Σ w·x / Σ w over the window (0 where Σ w = 0).

    Returns:
        (B, C, H, W); windows are clipped at the border. Running sums are float32: the
        absolute error is ~1e-7 × max|x| × W, far below the noise of 8/16-bit photos.
    """
    h, w = x.shape[-2:]
    if weight is None:
        ones_h = torch.ones(1, 1, h, 1, dtype=x.dtype, device=x.device)
        ones_w = torch.ones(1, 1, 1, w, dtype=x.dtype, device=x.device)
        den = _window_sum(ones_h, radius) * _window_sum(ones_w, radius)
        return _window_sum(x, radius) / den
    wt = weight.to(x.dtype)
    den = _window_sum(wt, radius)
    num = _window_sum(x * wt, radius)
    return torch.where(den > 0.5, num / den.clamp_min(0.5), torch.zeros_like(num))


def axis_max(v: Tensor, radius: int, dim: int) -> Tensor:
    """Maximum over 2r+1 neighbours along ``dim`` (-1 or -2), −inf beyond the border."""
    n = v.shape[dim]
    p = F.pad(v, (radius, radius) if dim == -1 else (0, 0, radius, radius), value=-torch.inf)
    out = p.narrow(dim, 0, n)
    for k in range(1, 2 * radius + 1):
        out = torch.maximum(out, p.narrow(dim, k, n))
    return out


def _axis_binary(m: Tensor, radius: int, dim: int, dilate: bool) -> Tensor:
    """OR (``dilate``) or AND of 2r+1 neighbours of a bool ``m`` along ``dim`` (-1 or -2), outside pixels ignored."""
    n = m.shape[dim]
    p = F.pad(m.to(torch.uint8), (radius, radius) if dim == -1 else (0, 0, radius, radius), value=0 if dilate else 1).bool()
    out = p.narrow(dim, 0, n).clone()
    for k in range(1, 2 * radius + 1):
        if dilate:
            out |= p.narrow(dim, k, n)
        else:
            out &= p.narrow(dim, k, n)
    return out


def binary_morph(mask: Tensor, close: int, open_: int) -> Tensor:
    """Closing by a ``close``×``close`` square, then opening by an ``open_``×``open_`` one, of a bool mask.

    The values of ``kornia.morphology.closing`` / ``opening`` with ``torch.ones(k, k)`` and their default
    geodesic border (pixels outside the image ignored), by OR/AND of shifted bool copies: 11× faster on CPU
    (4 × 1024², 3×3: 25 vs 275 ms).

    Args:
        mask: (..., H, W) bool; close, open_: odd square sizes (≤ 1: that step off).

    Returns:
        (..., H, W) bool.
    """
    x = mask.bool()
    if close > 1:
        r = close // 2
        x = _axis_binary(_axis_binary(x, r, -1, True), r, -2, True)
        x = _axis_binary(_axis_binary(x, r, -1, False), r, -2, False)
    if open_ > 1:
        r = open_ // 2
        x = _axis_binary(_axis_binary(x, r, -1, False), r, -2, False)
        x = _axis_binary(_axis_binary(x, r, -1, True), r, -2, True)
    return x


def max_filter(x: Tensor, radius: int) -> Tensor:
    """Maximum over a (2r+1)² window, separably by shifted maxima — the values of
    ``F.max_pool2d(x, 2r+1, stride=1, padding=r)``, at a third to a tenth of its CPU time (1024², r = 1: 61 vs
    120 ms; r = 7: 77 vs 938 ms).

    Args:
        x: (..., H, W) floating values (a mask: ``mask.float()``); radius: r ≥ 0.

    Returns:
        (..., H, W); windows are clipped at the border.
    """
    return axis_max(axis_max(x, radius, -1), radius, -2) if radius > 0 else x
