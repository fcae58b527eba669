"""How well a capture's shots are registered: each shot's residual shift against the others (the fit report's
measurement), and the capture with its shots moved back by it (:func:`with_registration`, the registration choice's
extension: :mod:`torchmetal.select.choices`).

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

import math
import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.errors import InputError

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

__all__ = ["MAX_WIDTH", "MIN_REGISTER_SIDE", "moved", "registered", "registration_shifts", "shifts_against", "shot_shifts",
           "unregistrable", "valid_observations", "with_registration"]

REFINE_PX = 0.1  # refine a shift while the last step moved it by more (px of the measured images)
REFINE_STEPS = 2
MIN_REGISTER_SIDE = 16  # a phase correlation needs a window and some texture: smaller captures are not registered
PASSES = 3  # measurements of the shifts, each on the shots moved back by the ones before (registration_shifts)
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
    norm, f = _prepared(images, valid, max_width)
    n = norm.shape[0]
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


def _prepared(images: Tensor, valid: Tensor | None, max_width: int) -> tuple[np.ndarray, int]:
    """(N, H', W') float64 texture-normalised luminance (step 1) at ≤ ``max_width`` wide, and the box factor."""
    x = images.detach().float().cpu()
    h, w = x.shape[-2:]
    v = None if valid is None else torch.broadcast_to(valid.bool().cpu(), x.shape).all(1, keepdim=True)
    f = max(1, -(-w // max_width))
    if f > 1:
        hh, ww = (h // f) * f, (w // f) * f
        x = F.avg_pool2d(x[..., :hh, :ww], f)
        if v is not None:
            v = F.avg_pool2d(v[..., :hh, :ww].float(), f) > 0.999
    window = max(17, int(round(x.shape[-1] / 32)) | 1)
    return _normalised(x, v, window).numpy().astype(np.float64), f


def shifts_against(reference: Tensor, images: Tensor, *, max_width: int = MAX_WIDTH) -> list[list[float]]:
    """[[dx, dy], …]: each of ``images`` (K, 3, H, W)'s shift against the mean of ``reference`` (M, 3, H, W)'s
    normalised luminance (a registered set of shots), in full-size pixels: where a new shot sits in their frame."""
    import cv2  # on use

    ref, f = _prepared(reference, None, max_width)
    img, _ = _prepared(images, None, max_width)
    hann = cv2.createHanningWindow((ref.shape[-1], ref.shape[-2]), cv2.CV_64F)
    mean = np.ascontiguousarray(ref.mean(0))
    return [[float(c) * f for c in _correlate(cv2, mean, np.ascontiguousarray(k), hann)[0]] for k in img]


def moved(images: Tensor, shifts, *, sign: float = -1.0) -> Tensor:
    """(N, C, H, W) ``images`` each moved by ``sign`` × its shift (``shifts`` [[dx, dy], …] in pixels; −1: back
    into the others' frame, +1: from it into the shot's), bilinear in their own float dtype (a float32 grid
    places a 1 MP image's samples within 1e-4 px); NaN where the moved image has no source pixel."""
    n, c, h, w = images.shape
    x = images if images.is_floating_point() else images.float()
    out = F.grid_sample(torch.cat([x, torch.ones_like(x[:, :1])], 1), _shift_grid(shifts, n, h, w, sign, x),
                        mode="bilinear", padding_mode="zeros", align_corners=True)
    out, inside = out[:, :c], out[:, c:]
    return torch.where(inside > 1.0 - 1e-5, out, torch.full_like(out, math.nan))


def _shift_grid(shifts, n: int, h: int, w: int, sign: float, like: Tensor) -> Tensor:
    """(N, H, W, 2) grid_sample coordinates (align_corners) that read pixel p − ``sign`` × shift of each image."""
    d = torch.as_tensor(shifts, dtype=torch.float64).reshape(n, 2) * sign
    xs = torch.arange(w, dtype=torch.float64)
    ys = torch.arange(h, dtype=torch.float64)
    gx = ((xs[None] - d[:, :1]) * (2.0 / max(w - 1, 1)) - 1.0).to(like.dtype)  # (N, W)
    gy = ((ys[None] - d[:, 1:]) * (2.0 / max(h - 1, 1)) - 1.0).to(like.dtype)  # (N, H)
    return torch.stack(torch.broadcast_tensors(gx[:, None, :], gy[:, :, None]), -1).to(like.device)


def registered(capture: Capture, shifts) -> Capture:
    """``capture`` with each shot moved back by its shift (``shifts``, full-size pixels); a pixel moved in from
    outside the photo counts as clipped in every channel (no observation there). Photos and clip flags move in
    one resampling."""
    imgs = capture.images
    both = moved(torch.cat([imgs, capture.saturated.to(imgs.dtype)], 1), shifts)
    images, sat = both[:, :3], both[:, 3:]
    outside = torch.isnan(images)
    return replace(capture, images=torch.nan_to_num(images, nan=0.0), saturated=(sat > 0) | outside)


def with_registration(capture: Capture, mode: str) -> tuple[Capture, dict]:
    """The capture as ``mode`` says: "off" as captured; "shift": each shot moved back by its measured shift
    (:func:`shot_shifts`). Returns (capture, report entry)."""
    if mode == "off":
        return capture, {"chosen": "off"}
    if mode != "shift":
        raise InputError(f"registration: expected one of ['off', 'shift'], found {mode!r}")
    why = unregistrable(capture)
    if why is not None:
        return capture, {"chosen": "off", "reason": why}
    shifts = registration_shifts(capture)
    mag = [float(np.hypot(*d)) for d in shifts]
    return registered(capture, shifts), {"chosen": "shift", "shifts": shifts, "max": max(mag)}


def unregistrable(capture: Capture) -> str | None:
    """Why ``capture``'s shots cannot be measured against each other (None: they can)."""
    if capture.num_shots < 2:
        return "one shot: nothing to register against"
    if min(capture.height, capture.width) < MIN_REGISTER_SIDE:
        return f"{capture.height}x{capture.width} px: too small to measure a shift (< {MIN_REGISTER_SIDE} px a side)"
    return None


def registration_shifts(capture: Capture, *, max_width: int = MAX_WIDTH, passes: int = PASSES) -> list[list[float]]:
    """[[dx, dy], …] per shot: :func:`shot_shifts`, measured again on the shots moved back and added up, ``passes``
    times. The reference (the others' mean) is itself misregistered on the first pass, and shading that the
    normalisation leaves pulls the peak: one pass left a synthetic capture's shots 1–2 px apart where they had been
    3–6 px; a pass on the moved shots measures what is left."""
    # each pass moves the box-averaged shots it measures, not the full-size ones: resampling the full size cost
    # more than the measurement (docs/measurements.md, 2026-12-07)
    f = max(1, -(-capture.width // max_width))
    small = capture.downsampled(f)
    total = [[0.0, 0.0] for _ in range(capture.num_shots)]
    for _ in range(passes):
        cur = registered(small, total) if any(any(d) for d in total) else small
        step = shot_shifts(cur.images, valid_observations(cur), max_width=max_width)["shifts"]
        total = [[a + b for a, b in zip(t, d)] for t, d in zip(total, step)]
    mean = [sum(d[i] for d in total) / len(total) for i in (0, 1)]  # the shots' mean frame: the geometry's
    return [[(d[0] - mean[0]) * f, (d[1] - mean[1]) * f] for d in total]


def valid_observations(capture: Capture) -> Tensor:
    """(N, 3, H, W) bool: on the mask, not clipped, finite."""
    v = torch.isfinite(capture.images) & capture.mask.bool().reshape(1, 1, *capture.images.shape[-2:])
    return v & ~capture.saturated.bool()
