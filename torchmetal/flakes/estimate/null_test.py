"""The flake stage's null test: are the detections glints, or what misfit alone produces?

Noise and a misfit of the Phong model (texture edges, an imperfect lobe, quantisation) give
residual outliers of both signs; glints give positive ones. Both tests here count positive and
negative outliers at each SNR of :data:`SNR_LADDER` and keep the glints by :func:`glint_rule`:
:func:`glint_excess` on detections of the residual and of its mirror (two full detections), and
the pixel screen of :mod:`torchmetal.flakes.estimate.prescreen` (no detection) before it. Only compact
detections count (:func:`drop_extended`): glints are spots, misfit of the shading can be a band. This module is
light to import: the screen loads it on a flake-free capture, where nothing else of the flake
stage runs.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from torchmetal.flakes.estimate.results import Particles

SNR_LADDER = (5.0, 7.0, 10.0, 15.0, 20.0, 30.0)  # detection SNRs at which glints and their mirror are compared
MIN_EXCESS = 10  # glint detections beyond the mirrored ones needed at some SNR (and 3 σ of Poisson noise)
#: px: the longest ellipse axis of a glint the test counts — the detector's high-pass box (radius 7, the
#: default ``background`` of :func:`~torchmetal.flakes.estimate.detect.detect_flakes`), 2·7 + 1 px across
EXTENT = 15.0


def drop_extended(particles: Particles, extent: float = EXTENT) -> tuple[Particles, int]:
    """``particles`` without the extended ones (major axis > ``extent`` px); returns (particles, number dropped).

    A flake glints as a spot no larger than the detector's high-pass box; a longer detection is a structure
    of the shading the coating misfits (a sheen band, the streak of a highlight). On the shared
    uw_gray_sphere (matte, no flakes) the locations above SNR 15 were 17 positive (median major axis
    196 px) vs 3 mirrored: with the extended ones left out of both sides, 0 vs 1. The zoo's flake scenes
    keep every positive location (their glints' major axes: median 3 px, at most 15)."""
    keep = particles.major <= extent
    return particles.select(torch.nonzero(keep, as_tuple=True)[0]), int((~keep).sum())


def _locations(h: int, w: int, *parts: Particles) -> list[Tensor]:
    """A location label per particle of each part: centres within 1 px (any shot, any part) join."""
    import cv2  # deferred: OpenCV is heavy to import (the screen loads this module on every capture)

    occupied = np.zeros((h, w), np.uint8)
    rows, cols = [], []
    for p in parts:
        r = p.cy.round().long().clamp(0, h - 1)
        c = p.cx.round().long().clamp(0, w - 1)
        rows.append(r)
        cols.append(c)
        occupied[r.cpu().numpy(), c.cpu().numpy()] = 1
    occupied = cv2.dilate(occupied, np.ones((3, 3), np.uint8))
    _, labels = cv2.connectedComponents(occupied, connectivity=8)
    lab = torch.from_numpy(labels.astype(np.int64))
    return [lab[r.cpu(), c.cpu()].to(p.cy.device) for r, c, p in zip(rows, cols, parts)]


def glint_excess(positive: Particles, mirrored: Particles, shape: tuple[int, int],
                 ladder: tuple[float, ...] = SNR_LADDER, min_excess: int = MIN_EXCESS) -> tuple[bool, dict]:
    """Do the detections exceed what the mirrored residual gives, location by location?

    Detections of the residual and of its mirror are pooled into locations (centres within 1 px,
    any shot). A location is *positive* when its brightest detection is in the residual, *mirrored*
    when it is in the mirror. Misfit makes both equally often; a flake is positive, even where the
    texture has absorbed part of its glints (the dips this leaves in the other shots are shallower
    than its peak). At each SNR t of ``ladder``, over the locations whose brightest detection
    exceeds t: P positive, M mirrored. Glints are kept when, for some t,
    P − M ≥ max(min_excess, 3·√(P + M)) and P ≥ 2·M.

    Returns (kept, {"snr": [t…], "positive": [P…], "mirrored": [M…]}).
    """
    h, w = shape
    lp, lm = _locations(h, w, positive, mirrored)
    n = int(max(int(lp.max()) if len(lp) else 0, int(lm.max()) if len(lm) else 0)) + 1
    best_p = torch.zeros(n, dtype=torch.float64).scatter_reduce_(0, lp.cpu(), positive.snr.double().cpu(), "amax")
    best_m = torch.zeros(n, dtype=torch.float64).scatter_reduce_(0, lm.cpu(), mirrored.snr.double().cpu(), "amax")
    pos, neg = [], []
    for t in ladder:
        top = torch.maximum(best_p, best_m)
        pos.append(int(((top > t) & (best_p >= best_m)).sum()))
        neg.append(int(((top > t) & (best_m > best_p)).sum()))
    return glint_rule(pos, neg, min_excess), {"snr": list(ladder), "positive": pos, "mirrored": neg}


#: the largest share of mirrored locations (the misfit's estimate) among the positive ones at the SNR the flake
#: statistics detect at: their detections are then at least ~95 % glints by the mirror's count
MAX_MIRRORED_SHARE = 0.05


def glint_snr(counts: dict, k_hi: float, max_share: float = MAX_MIRRORED_SHARE) -> float:
    """The detection threshold (SNR) for the flake statistics: ``k_hi`` (the detector's) unless the
    mirrored residual's locations exceed ``max_share`` of the positive ones there; then the lowest rung of
    ``counts`` (:func:`glint_excess`) above it where they do not (``k_hi`` when none: the stage's rule
    already said glints).

    Misfit of the coating near texture detail makes faint positive spots too, and the statistics read each
    detection as a flake: on the zoo's flakes_orange (a photo texture) 73 of the 98 detections below SNR 7
    lay on no flake (the procedural flakes_a: 0 of 9) and the density came out ~6× the truth's."""
    for t, p, m in zip(counts["snr"], counts["positive"], counts["mirrored"]):
        if t >= k_hi and p > 0 and m <= max_share * p:
            return float(t)
    return float(k_hi)


def glint_rule(positive: list[int], negative: list[int], min_excess: int = MIN_EXCESS, ratio: float = 2.0) -> bool:
    """Glints rather than misfit: at some rung, P − M ≥ max(min_excess, 3·√(P + M)) and P ≥ ratio·M."""
    return any(p - m >= max(min_excess, 3.0 * math.sqrt(p + m)) and p >= ratio * m for p, m in zip(positive, negative))
