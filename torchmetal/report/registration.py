"""How well a capture's shots are registered: each shot's residual shift against the others (a measurement for
the fit report; nothing is resampled).

The shots of a capture from photos are rectified to the sample plane (from markers); what is left of a
misregistration moves the texture between shots, and no material explains a texture that moves. Per shot k:

1. texture-normalised luminance: Y / (its local mean over about 1/32 of the width) − 1, clipped to ±1 and 0
   where the observation is invalid (saturated, outside the mask): the light's falloff and a broad highlight
   divide out, the texture stays;
2. the reference: the mean of the other shots' normalised images;
3. ``cv2.phaseCorrelate(reference, shot k)`` under a Hann window: the sub-pixel translation (dx, dy) of shot k
   against the others, in pixels of the full image (x to the right, y down), and the correlation peak's
   response (near 1: one clear shift; near 0: no texture to register by). The sub-pixel part is refined by
   measuring again with the shot moved back (:func:`_correlate`): still about ±0.3 px at half-pixel shifts
   (cv2's centroid under-reads small shifts): enough to find a shot off by a pixel or more.

A global translation only: parallax (3-D relief seen from moving cameras) shifts parts of the image by different
amounts, which the disagreement map (:mod:`torchmetal.report.disagreement`) shows instead.
"""

from __future__ import annotations

import time

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.errors import InputError

__all__ = ["shot_shifts", "MAX_WIDTH"]

REFINE_PX = 0.1  # refine a shift while the last step moved it by more (px of the measured images)
REFINE_STEPS = 2
MAX_WIDTH = 512  # wider images are box-averaged by a whole factor first (shifts reported in full-size pixels):
# a 1 MP capture measures at a quarter of the cost, and ±0.6 full-size px still finds a shot off by a pixel or more
_LUMA = (0.2126, 0.7152, 0.0722)


def _normalised(images: Tensor, valid: Tensor | None, window: int) -> Tensor:
    """(N, H, W) texture-normalised luminance (module docstring, step 1)."""
    y = (images.nan_to_num(0.0).clamp_min(0.0) * torch.tensor(_LUMA).reshape(1, 3, 1, 1)).sum(1, keepdim=True)
    v = torch.ones_like(y, dtype=torch.bool) if valid is None else valid
    b = max(1, window // 2)
    h, w = y.shape[-2:]
    ph, pw = (-h) % b, (-w) % b
    vy = F.pad(y * v, (0, pw, 0, ph), mode="replicate")
    vf = F.pad(v.float(), (0, pw, 0, ph), mode="replicate")
    mean = F.avg_pool2d(vy, b) / F.avg_pool2d(vf, b).clamp_min(1e-6)
    mean = F.interpolate(mean, size=(h + ph, w + pw), mode="bilinear", align_corners=False)[..., :h, :w]
    n = (y / mean.clamp_min(1e-6) - 1.0).clamp(-1.0, 1.0)
    return torch.where(v, n, torch.zeros(()))[:, 0]


def _correlate(cv2, ref: np.ndarray, img: np.ndarray, hann: np.ndarray) -> tuple[tuple[float, float], float]:
    """cv2.phaseCorrelate(ref, img), refined: its sub-pixel centroid is off by up to 0.3 px for half-pixel
    shifts, so while the shift found exceeds :data:`REFINE_PX`, ``img`` is moved back by it (cubic, a copy for the
    measurement only) and the remainder measured, up to :data:`REFINE_STEPS` times. Returns ((dx, dy), the first
    correlation's response)."""
    (dx, dy), resp = cv2.phaseCorrelate(ref, img, hann)
    total = np.array([dx, dy])
    step = total.copy()
    for _ in range(REFINE_STEPS):
        if float(np.hypot(*step)) <= REFINE_PX:
            break
        back = np.float64([[1, 0, -total[0]], [0, 1, -total[1]]])
        moved = cv2.warpAffine(img, back, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        step = np.array(cv2.phaseCorrelate(ref, moved, hann)[0])
        total += step
    return (float(total[0]), float(total[1])), float(resp)


def shot_shifts(images: Tensor, valid: Tensor | None = None, *, max_width: int = MAX_WIDTH) -> dict:
    """Each shot's residual shift against the mean of the others (module docstring).

    Args:
        images: (N, 3, H, W) linear RGB shots of one capture (N ≥ 2).
        valid: (N, 3, H, W) or (N, 1, H, W) (or broadcastable) bool, the observations that count; default all.
        max_width: wider images are box-averaged by a whole factor first.

    Returns:
        dict: ``shifts`` [[dx, dy], …] per shot in full-size pixels, ``magnitude`` (px), ``response`` per shot,
        ``max`` (the largest magnitude), ``factor`` (the box average used), ``time`` (seconds).
    """
    import cv2  # on use: the fit report's measurements load it only when run

    t0 = time.perf_counter()
    if images.dim() != 4 or images.shape[1] != 3 or images.shape[0] < 2:
        raise InputError(f"shot_shifts: expected (N, 3, H, W) images with N ≥ 2, found {tuple(images.shape)}")
    x = images.detach().float().cpu()
    n, _, h, w = x.shape
    v = None if valid is None else torch.broadcast_to(valid.bool().cpu(), x.shape).all(1, keepdim=True)
    f = max(1, -(-w // max_width))
    if f > 1:
        hh, ww = (h // f) * f, (w // f) * f
        x = F.avg_pool2d(x[..., :hh, :ww], f)
        if v is not None:
            v = F.avg_pool2d(v[..., :hh, :ww].float(), f) > 0.999
    window = max(17, int(round(x.shape[-1] / 32)) | 1)
    norm = _normalised(x, v, window).numpy().astype(np.float64)
    hann = cv2.createHanningWindow((norm.shape[-1], norm.shape[-2]), cv2.CV_64F)
    total = norm.sum(0)
    shifts, response = [], []
    for k in range(n):
        ref = np.ascontiguousarray((total - norm[k]) / (n - 1))
        (dx, dy), resp = _correlate(cv2, ref, np.ascontiguousarray(norm[k]), hann)
        shifts.append([float(dx) * f, float(dy) * f])
        response.append(float(resp))
    mag = [float(np.hypot(*s)) for s in shifts]
    return {"shifts": shifts, "magnitude": mag, "response": response, "max": max(mag), "factor": int(f),
            "time": time.perf_counter() - t0}
