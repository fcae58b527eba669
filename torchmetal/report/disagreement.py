"""Where the fitted shots disagree with the model beyond the noise: the fit report's disagreement map.

A material explains every fitted shot at a pixel with one texture value and one lobe. Where the photos do
not show the same surface point in every shot (parallax: grout and tile edges that move between views, a
shot not registered to the others), no material can: the shots' residuals there stay large and change sign
from shot to shot. The map marks those pixels:

1. images wider than :data:`MAX_WIDTH` are box-averaged by a whole factor (a parallax of 5–10 px stays a few
   px); a map pixel is valid in a shot where its whole block is (on the mask, not saturated);
2. per shot k, the residual r = photo − render of the luminance encoded as Y^(1/2.2) (close to sRGB, the
   8-bit photos' own steps, and to a shot noise's square root: the noise about alike at every brightness);
3. high-passed: minus its local mean over about ``window`` px (a shot's exposure or a missing broad
   highlight is a misfit of the lights or the lobe, smooth in the image; parallax moves sharp edges);
4. divided by the noise σ: the robust spread (1.4826 · median |·|) of all valid high-passed residuals;
5. per pixel, the **median over the valid shots** of |r| / σ: a highlight or a glint that one or two shots
   show and the model misses does not move it, an edge that moves in every shot does;
6. the pixel disagrees where that median exceeds ``threshold`` (:data:`THRESHOLD`: under Gaussian noise, 4 of 7
   shots beyond 2 σ has a probability below 2e-4).

The noise estimate is the residuals' own typical spread: where most of a capture disagrees, the map shows
the worst of it. One pass over the full-size images, the rest at the map's size: about 0.1 s for seven
1-MP shots on one core.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.metrics import srgb_encode

__all__ = ["disagreement_map", "disagreement_png", "THRESHOLD", "WINDOW"]

THRESHOLD = 2.0  # median over the shots of the noise-normalised residual
WINDOW = 1 / 32  # the high-pass's box, as a fraction of the image width (33 px at 1024)
GAMMA = 2.2  # the residuals' encoding: luminance^(1/2.2), close to sRGB and to a shot noise's square root
MAX_WIDTH = 512  # wider images are box-averaged to at most this width first (parallax of 5-10 px stays 2-5 px)
SIGMA_FLOOR = 1e-3  # σ below a quarter of an 8-bit step is rounding, not noise
_LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709 luminance of linear RGB
_MAD = 1.4826
_SAMPLES = 1 << 16  # residuals sampled per channel for the noise estimate


def disagreement_map(photos: Tensor, renders: Tensor, valid: Tensor | None = None, *, threshold: float = THRESHOLD,
                     window: int | None = None, min_shots: int = 3, max_width: int = MAX_WIDTH) -> tuple[Tensor, dict]:
    """The disagreement map of fitted shots (module docstring).

    Args:
        photos, renders: (N, 3, H, W) linear RGB, the fitted shots and the material's render of each.
        valid: (N, 3, H, W) (or broadcastable) bool: observations that count (mask, not saturated); default all.
        threshold: the median noise-normalised residual above which a pixel disagrees.
        window: the high-pass's box in px of the map (default :data:`WINDOW` of its width, at least 3).
        min_shots: pixels with fewer valid shots are not assessed (never marked).
        max_width: images wider are box-averaged by a whole factor first (the map is that size).

    Returns:
        the (H', W') bool map (H' = H // factor) and a summary dict: ``share`` (of the assessed pixels marked),
        ``assessed`` (share of the pixels with ≥ ``min_shots`` valid shots), ``threshold``, ``window``,
        ``factor``, ``sigma`` (the noise σ at the median brightness, in gamma-encoded luminance), ``shots``,
        ``time`` (seconds).
    """
    t0 = time.perf_counter()
    if photos.dim() != 4 or photos.shape[1] != 3 or renders.shape != photos.shape:
        raise InputError(f"disagreement_map: expected photos and renders (N, 3, H, W) of one shape, found "
                         f"{tuple(photos.shape)} and {tuple(renders.shape)}")
    n, _, h, w = photos.shape
    photos, renders = photos.detach().float().cpu(), renders.detach().float().cpu()
    v = None if valid is None else torch.broadcast_to(valid.bool().cpu(), photos.shape).all(1, keepdim=True)
    f = max(1, -(-w // max_width))
    if f > 1:  # box-average first (one pass over the full images): a map pixel is valid where its whole block is
        hh, ww = (h // f) * f, (w // f) * f
        photos, renders = F.avg_pool2d(photos[..., :hh, :ww], f), F.avg_pool2d(renders[..., :hh, :ww], f)
        if v is not None:
            v = F.avg_pool2d(v[..., :hh, :ww].float(), f) > 0.999
    ok = torch.isfinite(photos).all(1, keepdim=True) & torch.isfinite(renders).all(1, keepdim=True)
    v = ok if v is None else v & ok
    luma = torch.tensor(_LUMA).reshape(1, 3, 1, 1)
    yp = (photos.nan_to_num(0.0).clamp(0.0, 1.0) * luma).sum(1, keepdim=True)  # (N, 1, H', W')
    yr = (renders.nan_to_num(0.0).clamp(0.0, 1.0) * luma).sum(1, keepdim=True)
    yr = yr.clamp_min(0.0).pow(1.0 / GAMMA)
    r = torch.where(v, yp.clamp_min(0.0).pow(1.0 / GAMMA) - yr, torch.zeros(()))
    if window is None:
        window = max(3, int(round(r.shape[-1] * WINDOW)) | 1)
    window = int(window) | 1
    if window > 1:  # high-pass: minus the local mean of the valid residuals
        r = torch.where(v, r - _local_mean(r, v.float(), window), torch.zeros(()))
    sigma = _noise_sigma(r, v)
    z = torch.where(v, r.abs() / sigma, torch.full((), float("nan")))[:, 0]
    counts = v[:, 0].sum(0)
    med = z.nanmedian(0).values  # (H', W')
    assessed = counts >= min_shots
    marked = assessed & (med > threshold)
    a = int(assessed.sum())
    summary = {"share": float(marked.sum()) / a if a else float("nan"), "assessed": a / float(marked.numel()),
               "threshold": float(threshold), "window": int(window), "factor": int(f), "shots": int(n),
               "sigma": sigma, "time": time.perf_counter() - t0}
    return marked, summary


def _local_mean(x: Tensor, weight: Tensor, window: int) -> Tensor:
    """The weighted mean of ``x`` (N, C, H, W) around each pixel over about ``window`` px: block means over
    ``window // 2`` px blocks (edge blocks padded by replication), bilinearly interpolated back to every pixel;
    O(1) per pixel."""
    b = max(1, window // 2)
    h, w = x.shape[-2:]
    ph, pw = (-h) % b, (-w) % b
    xs, ws = F.pad(x * weight, (0, pw, 0, ph), mode="replicate"), F.pad(weight, (0, pw, 0, ph), mode="replicate")
    mean = F.avg_pool2d(xs, b) / F.avg_pool2d(ws, b).clamp_min(1e-6)
    up = F.interpolate(mean, size=(h + ph, w + pw), mode="bilinear", align_corners=False)
    return up[..., :h, :w]


def _noise_sigma(r: Tensor, v: Tensor) -> float:
    """1.4826 · median |r| of a sample of the valid high-passed residuals (at least :data:`SIGMA_FLOOR`)."""
    step = max(1, v.numel() // _SAMPLES)
    rc = r.reshape(-1)[::step][v.reshape(-1)[::step]]
    if rc.numel() == 0:
        return 1.0
    return max(SIGMA_FLOOR, _MAD * float(rc.abs().median()))


def disagreement_png(path: str | Path, marked: Tensor, photo: Tensor) -> Path:
    """The map over a photo: the photo (3, H, W linear) in grey, dimmed, with the disagreeing pixels red; one
    8-bit sRGB PNG of the photo's size."""
    import cv2  # on use: the report's figures load it only when written

    g = srgb_encode(photo.detach().float().cpu().nan_to_num(0.0).clamp(0.0, 1.0)).mean(0)
    g = 0.25 + 0.5 * g  # grey, dimmed: the red reads on dark and bright photos alike
    m = marked.cpu().bool()
    rgb = torch.stack([torch.where(m, torch.ones(()), g), torch.where(m, torch.zeros(()), g),
                       torch.where(m, torch.zeros(()), g)], -1)
    img = (rgb.numpy() * 255.0 + 0.5).astype(np.uint8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1])):
        raise OSError(f"{path}: could not write the disagreement map")
    return path
