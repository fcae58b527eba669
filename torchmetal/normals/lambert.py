"""The first step of :func:`~torchmetal.normals.estimate_normals`: robust Lambertian photometric stereo.

Per pixel, the channel sum of y/E is g·l_k (g = (Σ_c d_c)·n), solved by weighted least squares over
the shots that are lit, unsaturated and not dark (``DARK``), then again without the shots the fit
predicts in attached shadow (n·l below ``SHADOW``) or whose residual exceeds ``INIT_K``·σ
(highlights, glints, cast shadows); σ is the chunk's robust scale. A pixel needs ``MIN_SHOTS``
usable shots.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.normals.core import Chunk, normals_of, robust_scale, row_blocks, row_chunk, theta_of

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

DARK = 0.02  # shots darker than this fraction of the pixel's brightest are left out
SHADOW = 0.05  # shots with predicted n·l below this are attached shadow
INIT_K = 3.0  # |residual| > INIT_K·σ leaves a shot out (highlights, glints, cast shadows)
INIT_ROUNDS = 4
MIN_SHOTS = 3


def _solve3(l: Tensor, z: Tensor, w: Tensor) -> Tensor:
    """Per-pixel weighted least squares z_k = g·l_k: l (N, 3, P), z, w (N, P) → g (3, P)."""
    wl = l * w.unsqueeze(1)
    a = torch.einsum("nip,njp->pij", wl, l).double()
    b = torch.einsum("nip,np->pi", wl, z).double()
    tr = a.diagonal(dim1=1, dim2=2).sum(-1)
    ridge = torch.where(tr > 0, 1e-9 * tr, torch.ones_like(tr))  # no observation: g = 0
    a = a + ridge.view(-1, 1, 1) * torch.eye(3, dtype=a.dtype, device=a.device)
    return torch.linalg.solve(a, b).T.to(z.dtype)


def _lambert_init(ch: Chunk) -> tuple[Tensor, Tensor]:
    """Robust Lambertian photometric stereo: θ (2, P) and the pixels with ≥ MIN_SHOTS usable shots (P,)."""
    ok = ch.ok[:, 0]
    z = torch.where(ok, ch.y[:, 0] / torch.where(ok, ch.e[:, 0], torch.ones_like(ch.y[:, 0])), torch.zeros_like(ch.y[:, 0]))
    zmax = z.amax(0)
    w = ok & (z > DARK * zmax)
    for _ in range(INIT_ROUNDS):
        g = _solve3(ch.l, z, w.to(z.dtype))
        rho = g.norm(dim=0).clamp_min(1e-30)
        zh = (g.unsqueeze(0) * ch.l).sum(1)
        res = (z - zh) / rho
        sig = robust_scale(res, w, 1e-6)
        keep = ok & (zh > SHADOW * rho) & (res.abs() <= INIT_K * sig)
        w = torch.where((keep.sum(0) >= MIN_SHOTS).unsqueeze(0), keep, w)
    g = _solve3(ch.l, z, w.to(z.dtype))
    return theta_of(g), (w.sum(0) >= MIN_SHOTS) & ch.pix


def lambertian_normals(capture: Capture, dt: torch.dtype) -> tuple[Tensor, Tensor]:
    """:func:`_lambert_init` over the capture's row chunks in the work dtype ``dt``: unit normals
    (3, H, W), (0, 0, 1) where a pixel is not solvable, and the solvable pixels (H, W)."""
    h, w = capture.height, capture.width
    normals = torch.zeros(3, h, w, dtype=dt, device=capture.images.device)
    normals[2] = 1.0
    solvable = torch.zeros(h, w, dtype=torch.bool, device=normals.device)
    for r0, r1 in row_blocks(capture):
        theta, good = _lambert_init(row_chunk(capture, r0, r1, dt))
        n, _ = normals_of(theta)
        normals[:, r0:r1] = torch.where(good.unsqueeze(0), n, normals[:, r0:r1].reshape(3, -1)).reshape(3, r1 - r0, w)
        solvable[r0:r1] = good.reshape(r1 - r0, w)
    return normals, solvable
