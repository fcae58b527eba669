"""The flake stage of the pipeline: detect → associate → fit statistics, in one call.

``flake_stage(capture, phong_images)`` is what :func:`torchmetal.pipeline.fit_material` runs
after the Phong fit. It returns the fitted :class:`FlakeModel` (or None when the detections are
consistent with noise alone — the stage is then skipped and the material stores
``flakes: null``), the particle table of every shot, and a report with the time of each
sub-step, the counts, the fitted values with their standard errors, and the skip reason.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchmetal.checks import check_shape
from torchmetal.flakes.detect import Detection, Particles, detect_flakes
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.shot_geometry import Geometry
from torchmetal.flakes.stats import flake_statistics
from torchmetal.geometry import grid_distance2, pixel_axes


@dataclass
class FlakeStageResult:
    """model: fitted FlakeModel or None (skipped); particles: per-shot detections;
    report: times (s) per sub-step, counts, fitted values, ``skipped`` reason when skipped;
    flake_id: (P,) associated flake of each particle (−1 when the stage stopped before, or for a
    particle next to a saturated or masked pixel, which the statistics leave out)."""

    model: FlakeModel | None
    particles: Particles
    report: dict = field(default_factory=dict)
    flake_id: Tensor | None = None


def irradiance_maps(capture, *, dtype: torch.dtype = torch.float32) -> Tensor:
    """Irradiance E of every shot, (N, 3, H, W): intensity/dist² (point) or intensity."""
    n, _, h, w = capture.images.shape
    x, y = pixel_axes(h, w, capture.size, dtype=dtype, device=capture.images.device)
    dist2 = grid_distance2(capture.lights.to(dtype), x, y)  # (N, H, W), separably
    return capture.intensities.to(dtype)[:, :, None, None] / dist2.unsqueeze(1)


def detect_capture(capture, phong_images: Tensor, *, mirrored: bool = False, **detect) -> Detection:
    """:func:`~torchmetal.flakes.detect.detect_flakes` on every shot of ``capture``: residual
    against ``phong_images`` (N, 3, H, W), irradiance from the shots' lights, and only mask pixels
    that are not saturated in any channel.

    ``mirrored``: detect in the residual's mirror image instead, photo' = 2·Phong − photo — the
    empirical null of :func:`glint_excess`. Noise and a misfit of the Phong model (texture edges,
    an imperfect lobe, quantisation) give residuals of both signs; glints are positive only, so
    what the detector finds in the mirror is what misfit alone produces at each SNR.
    """
    images = capture.images
    n, _, h, w = images.shape
    check_shape(phong_images, (n, 3, h, w), "phong_images")
    irr = irradiance_maps(capture, dtype=images.dtype)
    valid = capture.mask.unsqueeze(0) & ~capture.saturated.any(1, keepdim=True)
    ph = phong_images.to(images.dtype)
    return detect_flakes(2.0 * ph - images if mirrored else images, ph, irr, valid=valid, **detect)


SNR_LADDER = (5.0, 7.0, 10.0, 15.0, 20.0, 30.0)  # detection SNRs at which glints and their mirror are compared
MIN_EXCESS = 10  # glint detections beyond the mirrored ones needed at some SNR (and 3 σ of Poisson noise)


def _locations(h: int, w: int, *parts: Particles) -> list[Tensor]:
    """A location label per particle of each part: centres within 1 px (any shot, any part) join."""
    import cv2
    import numpy as np

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


def glint_rule(positive: list[int], negative: list[int], min_excess: int = MIN_EXCESS, ratio: float = 2.0) -> bool:
    """Glints rather than misfit: at some rung, P − M ≥ max(min_excess, 3·√(P + M)) and P ≥ ratio·M."""
    return any(p - m >= max(min_excess, 3.0 * math.sqrt(p + m)) and p >= ratio * m for p, m in zip(positive, negative))


def flake_stage(
    capture,
    phong_images: Tensor,
    *,
    seed: int = 0,
    detect: dict | None = None,
    stats: dict | None = None,
    detection: Detection | None = None,
) -> FlakeStageResult:
    """Fit the flake model of a capture, given the Phong renders of its shots.

    Args:
        capture: a :class:`~torchmetal.io.capture.Capture` (images, normals, mask, lights,
            intensities, cameras, size, saturated).
        phong_images: (N, 3, H, W) Phong render of every shot (same geometry as the photos).
        seed: hash seed stored in the fitted model (the render's flake field).
        detect: extra keyword arguments of :func:`~torchmetal.flakes.detect.detect_flakes`
            (k_hi, k_lo, tile, background, close, open, min_area, cc_backend, chunk).
        stats: extra keyword arguments of :func:`~torchmetal.flakes.stats.flake_statistics`
            (assoc_radius, min_flakes, max_cells, max_flakes).
        detection: :func:`detect_capture` of these renders when the caller already has it
            (``detect`` is then unused).

    Returns:
        :class:`FlakeStageResult`.
    """
    n, _, h, w = capture.images.shape
    check_shape(phong_images, (n, 3, h, w), "phong_images")
    t0 = time.perf_counter()
    det = detect_capture(capture, phong_images, **(detect or {})) if detection is None else detection
    t2 = time.perf_counter()
    geo = Geometry(capture.normals, capture.lights, capture.intensities, capture.cameras, capture.size)
    res = flake_statistics(det, geo, seed=seed, **(stats or {}))
    t3 = time.perf_counter()
    report = dict(res.report)
    times = {"detect": t2 - t0}
    times.update({f"detect.{k}": v for k, v in det.times.items()})
    times["statistics"] = t3 - t2
    times.update({f"statistics.{k}": v for k, v in report.pop("times", {}).items()})
    times["total"] = t3 - t0
    report["times"] = times
    report["particles_per_shot"] = torch.bincount(det.particles.shot, minlength=n).tolist()
    if res.model is None and "skipped" not in report:
        report["skipped"] = "no flake model"
    return FlakeStageResult(res.model, det.particles, report, res.flake_id)
