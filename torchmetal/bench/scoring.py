"""Scoring helpers shared by the benchmark tasks and the zoo: held-out shot choice, PSNR that records
a failed method as NaN, relative errors, the valid-pixel mask and a plain Phong render of parameters.

torch is imported inside the functions that need it, so a task pays for it only when it runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from torchmetal.errors import InputError

if TYPE_CHECKING:  # annotations only: a real import would load torch (this module imports numpy only)
    from torchmetal.io.capture import Capture


def holdout_indices(n_total: int, n_hold: int) -> list[int]:
    """``n_hold`` shot indices spread evenly over ``n_total`` (never the same one twice)."""
    if n_hold <= 0:
        return []
    idx = sorted({min(n_total - 1, int((i + 0.5) * n_total / n_hold)) for i in range(n_hold)})
    return idx


def psnr_or_nan(pred, ref, valid=None) -> float:
    """:func:`torchmetal.metrics.psnr` (linear values clipped to [0, 1], peak 1) over ``valid``.

    A benchmark records a failed method instead of stopping: NaN when ``valid`` selects nothing
    or a compared value of ``pred`` is not finite.
    """
    from torchmetal.metrics import psnr as _psnr  # torch: imported when a task needs it

    try:
        return _psnr(pred, ref, mask=valid)
    except InputError:
        return float("nan")


def rel_err(est, true) -> float:
    """max over channels of |est − true| / |true| (absolute where true is 0); NaN if shapes differ."""
    e = np.asarray(est, np.float64).reshape(-1)
    t = np.asarray(true, np.float64).reshape(-1)
    if e.shape != t.shape:
        return float("nan")
    den = np.where(np.abs(t) > 0, np.abs(t), 1.0)
    return float(np.max(np.abs(e - t) / den))


def to_numpy(x):
    """float64 numpy copy of a tensor or array-like (None stays None)."""
    if x is None:
        return None
    if hasattr(x, "detach"):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, np.float64)


def valid_mask(capture: Capture):
    """(N, 3, H, W) bool: finite, inside the mask and not saturated."""
    import torch

    img = capture.images
    v = torch.isfinite(img)
    mask = getattr(capture, "mask", None)
    if mask is not None:
        v = v & mask.bool().reshape(1, 1, *img.shape[-2:])
    sat = getattr(capture, "saturated", None)
    if sat is not None:
        sat = sat.bool()
        if sat.dim() == 3:
            sat = sat[:, None]
        v = v & ~sat.expand_as(img)
    return v


def capture_nbytes_f32(capture: Capture) -> int:
    return int(capture.images.numel()) * 4


def _normals(capture):
    import torch

    n = getattr(capture, "normals", None)
    h, w = capture.images.shape[-2:]
    if n is None:
        n = torch.zeros(3, h, w)
        n[2] = 1.0
    if n.dim() == 4:
        n = n[0]
    if n.shape[-1] == 3 and n.shape[0] != 3:
        n = n.permute(2, 0, 1)
    return n.float()


def render_params(texture, s, alpha, capture: Capture):
    """torch Phong render of all shots of ``capture`` for plain (texture, s, α) parameters."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.phong import phong_render

    t = torch.as_tensor(np.asarray(texture), dtype=torch.float32) if not hasattr(texture, "detach") else texture.detach().float()
    s_ = torch.as_tensor(np.asarray(s), dtype=torch.float32) if not hasattr(s, "detach") else s.detach().float()
    a_ = torch.as_tensor(np.asarray(alpha), dtype=torch.float32) if not hasattr(alpha, "detach") else alpha.detach().float()
    with torch.no_grad():
        return phong_render(t, s_, a_, _normals(capture), capture.lights.float(), capture.intensities.float(),
                            capture.cameras.float(), tuple(float(v) for v in capture.size))
