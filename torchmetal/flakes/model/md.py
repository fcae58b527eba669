"""MD — the paper's *Metallic Difference*: a sparkle-aware image distance in [0, 100].

PSNR compares pixels, so two images of the same glitter with different flake positions score
worse than an image with no glitter at all. MD compares *statistics of blocks* instead
(paper section 4.2):

1. high-frequency image: x − box-mean(x) over 5×5, per channel;
2. sparkle excess e = (hp − t)⁺ above a noise-robust threshold t = k·max(σ_a, σ_b), σ the
   robust (MAD) noise of each image's high-pass, so sensor noise does not count as sparkle;
3. R×R blocks; per block and channel: number of sparkles (local maxima above t), sparkle
   coverage (fraction of pixels above t), mean excess and peak excess;
4. per coarse region (``regions``² of them; default the whole image) the mean and the
   standard deviation of every feature over the blocks — the mean measures how much sparkle
   there is, the spread how it is distributed (few big vs many small, clustering). These are
   alignment-free: a new random placement of the same flakes changes them only by sampling
   noise (~2 MD on a 512² image, ~6 on 256²);
5. each statistic is compared by the normalised difference |a − b| / (a + b) ∈ [0, 1] and
   MD = 100 × their mean. 0 = same sparkle statistics, 100 = sparkle in one image only.
   Lower is better.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmetal.checks import check_float
from torchmetal.errors import InputError
from torchmetal.flakes.model.filters import box_mean, max_filter


def _as_batch(x: Tensor, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise InputError(f"{name}: expected a torch.Tensor, found {type(x).__name__}")
    check_float(x, name)
    if x.dim() == 2:
        x = x[None, None]
    elif x.dim() == 3:
        x = x[None]
    if x.dim() != 4:
        raise InputError(f"{name}: expected shape (H, W), (C, H, W) or (B, C, H, W), found {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise InputError(f"{name}: expected finite values, found NaN/Inf")
    return x


def _robust_sigma(hp: Tensor) -> Tensor:
    """(B, C) robust σ of zero-median high-pass values (MAD on every 2nd pixel)."""
    s = hp[..., ::2, ::2].flatten(2)
    return 1.4826 * s.abs().median(-1).values


def block_features(x: Tensor, threshold: Tensor, window: int) -> Tensor:
    """Per-block sparkle features.

    Args:
        x: (B, C, H, W) high-pass image; threshold: (B, C) sparkle threshold; window: R.

    Returns:
        (B, C, 4, H//R · W//R): sparkle count, coverage, mean excess, peak excess per block.
    """
    b, c, h, w = x.shape
    hb, wb = h // window, w // window
    t = threshold.view(b, c, 1, 1)
    e = (x - t).clamp_min(0.0)
    peaks = ((x >= max_filter(x, 1)) & (e > 0)).to(x.dtype)

    def blocks(v: Tensor) -> Tensor:
        v = v[..., : hb * window, : wb * window]
        return v.reshape(b, c, hb, window, wb, window).permute(0, 1, 2, 4, 3, 5).reshape(b, c, hb, wb, -1)

    eb = blocks(e)
    f = torch.stack([blocks(peaks).sum(-1), (eb > 0).to(x.dtype).mean(-1), eb.mean(-1), eb.amax(-1)], 2)
    return f  # (B, C, 4, hb, wb)


def _region_stats(f: Tensor, regions: int) -> Tensor:
    """(B, C, F, hb, wb) → (B, C, F, r², 2): mean and std of the blocks of each region."""
    b, c, nf, hb, wb = f.shape
    r = max(1, min(regions, hb, wb))
    sh, sw = hb // r, wb // r
    f = f[..., : r * sh, : r * sw].reshape(b, c, nf, r, sh, r, sw).permute(0, 1, 2, 3, 5, 4, 6)
    f = f.reshape(b, c, nf, r * r, sh * sw)
    std = f.std(-1, unbiased=False)
    return torch.stack([f.mean(-1), std], -1)


def metallic_difference(
    img_a: Tensor,
    img_b: Tensor,
    window: int = 16,
    *,
    k: float = 5.0,
    regions: int = 1,
    reduction: str = "mean",
) -> float | Tensor:
    """MD between two images of the same sample (see the module docstring).

    Args:
        img_a, img_b: (H, W), (C, H, W) or (B, C, H, W) linear images of the same shape,
            at least ``window`` pixels per side.
        window: block size R in pixels.
        k: sparkle threshold in units of the larger robust noise σ of the two high-passes.
        regions: the image is split into regions×regions areas compared separately (1 =
            whole image; more regions notice misplaced sparkle but add sampling noise).
        reduction: "mean" → a float over the batch; "none" → (B,) tensor.

    Returns:
        MD in [0, 100]; lower = more similar.
    """
    a = _as_batch(img_a, "img_a")
    b = _as_batch(img_b, "img_b")
    if a.shape != b.shape:
        raise InputError(f"img_b: expected shape {tuple(a.shape)} like img_a, found {tuple(b.shape)}")
    if not isinstance(window, int) or isinstance(window, bool) or window < 2 or min(a.shape[-2:]) < window:
        raise InputError(f"window: expected 2 <= window <= min(H, W) = {min(a.shape[-2:])}, found {window}")
    if not (isinstance(k, (int, float)) and math.isfinite(k) and k > 0):
        raise InputError(f"k: expected a finite number > 0, found {k!r}")
    if not isinstance(regions, int) or isinstance(regions, bool) or regions < 1:
        raise InputError(f"regions: expected an integer >= 1, found {regions!r}")
    if reduction not in ("mean", "none"):
        raise InputError(f"reduction: expected 'mean' or 'none', found {reduction!r}")
    x = torch.cat([a, b]).float()
    hp = x - box_mean(x, 2)
    sig = _robust_sigma(hp)
    n = a.shape[0]
    thr = k * torch.maximum(sig[:n], sig[n:]).clamp_min(1e-6)
    thr = torch.cat([thr, thr])
    f = _region_stats(block_features(hp, thr, window), regions)
    fa, fb = f[:n], f[n:]
    den = fa + fb
    d = torch.where(den > 0, (fa - fb).abs() / den.clamp_min(1e-30), torch.zeros_like(den))
    md = 100.0 * d.flatten(1).mean(1)
    return float(md.mean()) if reduction == "mean" else md
