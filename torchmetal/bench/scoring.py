"""Scoring helpers shared by the benchmark tasks and the zoo: held-out shot choice, PSNR that records
a failed method as NaN, relative errors, the valid-pixel mask, a plain Phong render of parameters and the
left-out sparkle counts (:func:`glint_scores`).

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


#: the real section's scales: full size, ¼ and 1/16 of each side (box averages)
SCALES = (1, 4, 16)


def box_average(x, valid=None, factor: int = 1):
    """``x`` (…, H, W) box-averaged over ``factor``×``factor`` blocks, over its ``valid`` pixels only.

    Returns ``(mean, keep)``: the mean of each block's valid values and a bool of the blocks where at least
    half the pixels are valid (a block of saturated pixels says nothing). The right and bottom edges that do not
    fill a whole block are left out. ``factor`` 1 returns ``x`` and ``valid`` (all True when None)."""
    import torch
    import torch.nn.functional as F

    x = x.detach().double()
    v = torch.ones_like(x, dtype=torch.bool) if valid is None else torch.broadcast_to(valid.bool(), x.shape)
    if factor <= 1:
        return x, v
    h, w = (x.shape[-2] // factor) * factor, (x.shape[-1] // factor) * factor
    if h == 0 or w == 0:
        raise InputError(f"box_average: expected an image of at least {factor}×{factor} pixels, found {tuple(x.shape[-2:])}")
    lead = x.shape[:-2]
    xx = x[..., :h, :w].reshape(-1, 1, h, w)
    vv = v[..., :h, :w].reshape(-1, 1, h, w).double()
    xx = torch.where(vv > 0, xx, torch.zeros((), dtype=xx.dtype))  # NaN or saturated values out of the sums
    wsum = F.avg_pool2d(vv, factor)
    mean = F.avg_pool2d(xx, factor) / wsum.clamp_min(1e-12)
    shape = (*lead, h // factor, w // factor)
    return mean.reshape(shape), (wsum >= 0.5).reshape(shape)


def psnr_scales(pred, ref, valid=None, scales=SCALES, space: str = "srgb") -> dict[str, float]:
    """PSNR of ``pred`` against ``ref`` (linear, …×H×W) at each box-average factor of ``scales``: both images
    averaged alike over their valid pixels (:func:`box_average`, in linear values: what a coarser camera would
    record), then clipped to [0, 1] and compared in ``space`` ("srgb": the encoded values a viewer sees, peak 1).
    Keys are the factors as strings ("1", "4", "16"); NaN where no block is valid or a value is not finite."""
    out = {}
    for f in scales:
        try:
            p, keep = box_average(pred, valid, f)
            r, _ = box_average(ref, valid, f)
        except InputError:
            out[str(f)] = float("nan")
            continue
        out[str(f)] = psnr_or_nan_space(p, r, keep, space)
    return out


def psnr_or_nan_space(pred, ref, valid, space: str) -> float:
    """:func:`psnr_or_nan` in ``space`` ("linear" or "srgb")."""
    from torchmetal.metrics import psnr as _psnr  # torch: imported when a task needs it

    try:
        return _psnr(pred, ref, mask=valid, space=space)
    except InputError:
        return float("nan")


#: Rec. 709 luminance weights of linear RGB
_LUMA = (0.2126, 0.7152, 0.0722)


def extrapolation_share(photo, fitted, mask=None, block: int = 32) -> float:
    """Share of ``block``×``block`` blocks where the left-out ``photo`` (3, H, W, linear) is brighter (mean
    Rec. 709 luminance) than every one of the ``fitted`` photos (M, 3, H, W): where a left-out shot asks the
    material for more than any fitted shot showed it (a highlight no fitted shot saw), the render extrapolates.
    ``mask`` (H, W) bool: a block counts where at least half of it is inside. NaN when no block counts (an image
    smaller than a block included)."""
    import torch

    photo, fitted = photo.detach().double(), fitted.detach().double()
    if min(photo.shape[-2:]) < block:
        return float("nan")
    if fitted.dim() != 4 or fitted.shape[0] == 0 or fitted.shape[1:] != photo.shape:
        raise InputError(f"extrapolation_share: expected fitted photos (M, {', '.join(map(str, photo.shape))}), "
                         f"found {tuple(fitted.shape)}")
    w = torch.tensor(_LUMA, dtype=torch.float64).reshape(3, 1, 1)
    m = None if mask is None else mask.bool().reshape(photo.shape[-2:])
    y, keep = box_average((photo * w).sum(0), m, block)
    y_fit, _ = box_average((fitted * w).sum(1), m, block)
    n = int(keep.sum())
    if n == 0:
        return float("nan")
    return float(((y > y_fit.amax(0)) & keep).sum()) / n


# ---------------------------------------------------------------------------- sparkles

NOISE = 0.005  # σ of the fixed noise the glint residuals are counted in
MATCH_PX = 2.0


def _blobs(res: np.ndarray, k: float = 5.0) -> np.ndarray:
    """(B, 2) centroids (row, col) of the 8-connected blobs of one (3, H, W) residual above k·σ (as sparkle_count)."""
    import cv2

    x = res.max(0)
    sigma = 1.4826 * np.median(np.abs(res - np.median(res)))
    bright = (x - np.median(res) > k * sigma).astype(np.uint8)
    n, _, _, cent = cv2.connectedComponentsWithStats(bright, connectivity=8)
    return cent[1:, ::-1]


def glint_scores(truth: np.ndarray, truth_base: np.ndarray, pred: np.ndarray, pred_base: np.ndarray,
                 seed: int = 0) -> dict:
    """Sparkle count ratio and share of truth glints matched within MATCH_PX, over (S, 3, H, W) shots: each
    image minus its own flake-free render, with the same fixed noise (σ = :data:`NOISE`) added to truth and
    prediction so that ``sparkle_count``'s robust σ is that of a photo; the count pred/truth over all shots and
    the share of the truth's glints (blobs above k·σ) with a predicted glint centroid within :data:`MATCH_PX`."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.metrics import sparkle_count

    rng = np.random.default_rng(seed)
    nt = npred = matched = 0
    for k in range(len(truth)):
        noise = rng.normal(0.0, NOISE, truth[k].shape)
        rt, rp = truth[k] - truth_base[k] + noise, pred[k] - pred_base[k] + noise
        nt += sparkle_count(rt)
        npred += sparkle_count(rp)
        ct, cp = _blobs(rt), _blobs(rp)
        if len(ct) and len(cp):
            d = np.sqrt(((ct[:, None] - cp[None]) ** 2).sum(-1)).min(1)
            matched += int((d <= MATCH_PX).sum())
    return {"truth_sparkles": nt, "pred_sparkles": npred, "count_ratio": npred / max(nt, 1),
            "within_2px": matched / max(nt, 1)}
