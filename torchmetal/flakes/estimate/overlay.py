"""Pictures of the flake stage: detections drawn on a shot."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchmetal.checks import check_shape
from torchmetal.errors import InputError
from torchmetal.flakes.estimate.results import Particles
from torchmetal.io.images import linear_to_srgb


def overlay_detections(
    image: Tensor,
    particles: Particles,
    *,
    gain: float = 1.0,
    color: tuple[int, int, int] = (255, 40, 40),
    min_radius: float = 2.5,
) -> np.ndarray:
    """Draw detected particles (ellipses at their moments) on a linear image.

    Args:
        image: (3, H, W) linear RGB; shown sRGB-encoded after multiplying by ``gain``.
        particles: the particles to draw (e.g. ``stage.particles.for_shot(k)``).
        gain: exposure factor; color: RGB of the outlines; min_radius: smallest drawn semi-axis (px).

    Returns:
        (H, W, 3) uint8 RGB picture.
    """
    import cv2  # deferred: OpenCV is heavy to import

    check_shape(image, (3, "H", "W"), "image")
    rgb = (linear_to_srgb((image.detach().float().cpu() * gain).clamp(0.0, 1.0)) * 255 + 0.5).to(torch.uint8)
    canvas = np.ascontiguousarray(rgb.permute(1, 2, 0).numpy()[:, :, ::-1])  # BGR for cv2
    bgr = (int(color[2]), int(color[1]), int(color[0]))
    p = particles.to("cpu")
    for cy, cx, major, minor, angle in zip(p.cy.tolist(), p.cx.tolist(), p.major.tolist(), p.minor.tolist(), p.angle.tolist()):
        axes = (max(min_radius, 0.5 * major), max(min_radius, 0.5 * minor))
        centre = (int(round(cx * 16 - 8)), int(round(cy * 16 - 8)))  # pixel centres → 4-bit fixed point
        ang = -math.degrees(angle)  # our angle is towards image up; cv2's is clockwise in rows-down
        cv2.ellipse(canvas, centre, (int(axes[0] * 16), int(axes[1] * 16)), ang, 0, 360, bgr, 1, cv2.LINE_AA, 4)
    return np.ascontiguousarray(canvas[:, :, ::-1])


def save_detection_overlay(path: str | Path, image: Tensor, particles: Particles, **kwargs) -> Path:
    """Write :func:`overlay_detections` as a PNG; returns the path.

    Raises:
        InputError: the path does not end in ``.png`` or cannot be written (one line, no cv2
            traceback).
    """
    import cv2  # deferred: OpenCV is heavy to import

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"path: expected a .png path, found {str(path)!r}")
    pic = overlay_detections(image, particles, **kwargs)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        ok = cv2.imwrite(str(path), np.ascontiguousarray(pic[:, :, ::-1]))
    except (OSError, cv2.error) as e:
        reason = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise InputError(f"path: expected a writable .png path, found {str(path)!r} ({reason})") from None
    if not ok:
        raise InputError(f"path: expected a writable .png path, found {str(path)!r}")
    return path
