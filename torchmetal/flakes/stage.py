"""The flake stage of the pipeline: detect → associate → fit statistics, in one call.

``flake_stage(capture, phong_images)`` is what :func:`torchmetal.pipeline.fit_material` runs
after the Phong fit. It returns the fitted :class:`FlakeModel` (or None when the detections are
consistent with noise alone — the stage is then skipped and the material stores
``flakes: null``), the particle table of every shot, and a report with the time of each
sub-step, the counts, the fitted values with their standard errors, and the skip reason.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.checks import check_shape
from torchmetal.flakes.estimate import stats as _stats
from torchmetal.flakes.estimate.detect import Detection, detect_flakes
from torchmetal.flakes.estimate.results import FlakeStageResult
from torchmetal.flakes.estimate.shot_geometry import Geometry
from torchmetal.flakes.estimate.stats import flake_statistics
from torchmetal.geometry import grid_distance2, pixel_axes

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture



def irradiance_maps(capture: Capture, *, dtype: torch.dtype = torch.float32) -> Tensor:
    """Irradiance E of every shot, (N, 3, H, W): intensity/dist² (point) or intensity."""
    n, _, h, w = capture.images.shape
    x, y = pixel_axes(h, w, capture.size, dtype=dtype, device=capture.images.device)
    dist2 = grid_distance2(capture.lights.to(dtype), x, y)  # (N, H, W), separably
    return capture.intensities.to(dtype)[:, :, None, None] / dist2.unsqueeze(1)


def detect_capture(capture: Capture, phong_images: Tensor, *, mirrored: bool = False, irradiance: Tensor | None = None,
                   **detect) -> Detection:
    """:func:`~torchmetal.flakes.estimate.detect.detect_flakes` on every shot of ``capture``: residual
    against ``phong_images`` (N, 3, H, W), irradiance from the shots' lights, and only mask pixels
    that are not saturated in any channel.

    ``mirrored``: detect in the residual's mirror image instead, photo' = 2·Phong − photo — the
    empirical null of :func:`~torchmetal.flakes.estimate.null_test.glint_excess`. Noise and a misfit of the Phong model (texture edges,
    an imperfect lobe, quantisation) give residuals of both signs; glints are positive only, so
    what the detector finds in the mirror is what misfit alone produces at each SNR.
    The glints' headroom is measured only where the statistics model clipped glints
    (:data:`~torchmetal.flakes.estimate.stats.MODEL_CLIPS`).

    ``irradiance``: :func:`irradiance_maps` of the capture in its images' dtype, where the caller detects
    more than once (formed here otherwise).
    """
    images = capture.images
    n, _, h, w = images.shape
    check_shape(phong_images, (n, 3, h, w), "phong_images")
    irr = irradiance_maps(capture, dtype=images.dtype) if irradiance is None else irradiance
    valid = capture.mask.unsqueeze(0) & ~capture.saturated.any(1, keepdim=True)
    ph = phong_images.to(images.dtype)
    detect = {"headroom": _stats.MODEL_CLIPS and not mirrored, **detect}
    return detect_flakes(2.0 * ph - images if mirrored else images, ph, irr, valid=valid, **detect)


def flake_stage(
    capture: Capture,
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
        detect: extra keyword arguments of :func:`~torchmetal.flakes.estimate.detect.detect_flakes`
            (k_hi, k_lo, tile, background, close, open, min_area, cc_backend, chunk).
        stats: extra keyword arguments of :func:`~torchmetal.flakes.estimate.stats.flake_statistics`
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
