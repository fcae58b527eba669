"""Where the model is not trusted at all: the rim of the sample's mask.

Pixels at the edge of a mask (a sphere's silhouette, a cut-out sample) mix the sample with what lies
beyond it and have the least reliable normals; the Phong fit misses them both ways, but the bright side
makes compact positive blobs that pass for glints. On the shared uw_gray_sphere (a matte sphere, no
flakes) 65 of 145 positive detections lay within 2 px of the mask's edge against 8 of 89 in the mirrored
residual: an excess that is the mask's edge, not glints. The screen and the null test therefore look only
at the mask's interior (on uw_gray_sphere the sheen still left an excess, 17 vs 3 above SNR 15, of bands
~200 px long, which :func:`~torchmetal.flakes.estimate.null_test.drop_extended` leaves out):
pixels more than :data:`RIM` px from a pixel outside the mask (the image border does not count). A
sample's glints elsewhere are counted as before; a full mask has no rim.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

if TYPE_CHECKING:
    from torchmetal.flakes.estimate.results import Particles
    from torchmetal.io.capture import Capture


RIM = 2  # px: the band along the mask's edge left out of the screen and the null test


def interior(mask: Tensor, rim: int = RIM) -> Tensor:
    """(1, H, W) bool: ``mask`` (1, H, W) without the pixels within ``rim`` px (Chebyshev) of a pixel outside it."""
    m = mask.bool()
    if rim <= 0 or bool(m.all()):
        return m
    outside = (~m).to(torch.float32).unsqueeze(0)  # (1, 1, H, W)
    near = F.max_pool2d(outside, 2 * rim + 1, stride=1, padding=rim)[0] > 0  # zero padding: the border is not outside
    return m & ~near


def drop_rim(capture: Capture, particles: Particles) -> tuple[Particles, int]:
    """``particles`` without those whose centre lies on the mask's rim; returns (particles, number dropped)."""
    inner = interior(capture.mask)[0]
    h, w = inner.shape
    row = particles.cy.floor().long().clamp(0, h - 1)
    col = particles.cx.floor().long().clamp(0, w - 1)
    keep = inner[row.to(inner.device), col.to(inner.device)]
    return particles.select(torch.nonzero(keep, as_tuple=True)[0]), int((~keep).sum())
