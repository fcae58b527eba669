"""A cheap first look for glints: is the flake stage worth running at all?

The flake stage's own null test (:func:`torchmetal.flakes.stage.glint_excess`) detects particles in
the residual and in its mirror and compares them location by location — two full detections.
On a flake-free sample that is most of the stage's cost. This screen asks the same question on
pixels, on a strided grid: noise and a Phong misfit give outliers of both signs, glints only
positive ones. With z = residual / (local robust σ), a pixel is *positive* when its largest z over
the shots exceeds its largest −z (a glint's peak is higher than the dips it leaves where the
texture absorbed part of it), *negative* otherwise, at level max(|z|). P(t) and M(t) count the
positive and negative pixels above level t; the screen passes (run the stage) when, at some t of the ladder,
P − M ≥ max(min_excess, 3·√(P + M)): a significant excess of positive outliers. The full test also
asks P ≥ 2·M of its locations; the screen does not (a sample with both glints and a strong misfit,
such as embossed foil beside glitter, must reach the full test).

Pixels are sampled every ``SCREEN_STRIDE``-th row and column (a glint wider than that is always
sampled; the pipeline renders only those pixels), the channel-summed residual loses its local
(clipped) mean over a small box (what is wider than a flake is misfit, not a glint), and σ is
1.4826·MAD over ``tile``×``tile`` sampled pixels of each shot, so a bright highlight's noise does
not hide a glint in the shade nor the reverse. Outliers are counted once per local peak.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmetal.flakes.stage import SNR_LADDER, MIN_EXCESS, glint_rule

SCREEN_STRIDE = 2  # the pipeline renders and screens every 2nd row and column
TILE = 16
BACKGROUND = 2
MAD_TO_SIGMA = 1.4826


CLIP = 3.0  # the background box averages the residual clipped to med ± CLIP·σ of its tile


def _tile_stats(x: Tensor, ok: Tensor, tile: int) -> tuple[Tensor, Tensor]:
    """Median and 1.4826·MAD of the valid values of each tile×tile tile, per pixel: (N, h, w) each."""
    n, h, w = x.shape
    th, tw = -(-h // tile), -(-w // tile)
    pad = (0, tw * tile - w, 0, th * tile - h)
    xp = torch.nn.functional.pad(torch.where(ok, x, torch.nan), pad, value=float("nan"))
    blocks = xp.reshape(n, th, tile, tw, tile).permute(0, 1, 3, 2, 4).reshape(n, th, tw, tile * tile)
    med = blocks.nanmedian(-1).values
    sigma = MAD_TO_SIGMA * (blocks - med[..., None]).abs().nanmedian(-1).values

    def expand(t: Tensor) -> Tensor:
        return torch.nan_to_num(t, nan=0.0).repeat_interleave(tile, 1).repeat_interleave(tile, 2)[:, :h, :w]

    return expand(med), expand(sigma).clamp_min(torch.finfo(x.dtype).tiny)


def _high_pass(r: Tensor, ok: Tensor, med: Tensor, sigma: Tensor, radius: int) -> Tensor:
    """r minus its (2·radius+1)² box mean over valid pixels, the box averaging r clipped to
    med ± CLIP·σ — a bright glint must not dig a negative halo around itself: (N, h, w)."""
    k = 2 * radius + 1
    okf = ok.to(r.dtype)
    clipped = torch.minimum(torch.maximum(r, med - CLIP * sigma), med + CLIP * sigma) * okf

    def pool(x: Tensor) -> Tensor:
        return torch.nn.functional.avg_pool2d(x.unsqueeze(1), k, stride=1, padding=radius, count_include_pad=False)[:, 0]

    return r - pool(clipped) / pool(okf).clamp_min(1e-12)


def glint_screen(images: Tensor, phong_images: Tensor, valid: Tensor, *, stride: int = 1, tile: int = TILE,
                 background: int = BACKGROUND,
                 ladder: tuple[float, ...] = SNR_LADDER, min_excess: int = MIN_EXCESS) -> tuple[bool, dict]:
    """Do positive residual outliers exceed negative ones, pixel by pixel?

    Args:
        images, phong_images: (N, 3, H, W) photos and the Phong renders of the same shots.
        valid: (N, 1|3, H, W) bool, pixels to look at (mask, not saturated).
        stride: sample every ``stride``-th row and column of the inputs (the pipeline passes inputs
            already sampled every :data:`SCREEN_STRIDE`-th, rendered only there).
        tile: edge of the tiles (in sampled pixels) over which σ is estimated.
        background: radius (sampled pixels) of the box whose (clipped) mean is taken off first: a
            misfit wider than the box (a highlight of the wrong width or place) is not an outlier.

    Returns:
        (passed, {"snr": [t…], "positive": [P…], "negative": [M…], "pixels": sampled pixel-shots valid}).
    """
    y = images[..., ::stride, ::stride]
    r = (y - phong_images[..., ::stride, ::stride].to(y.dtype)).sum(1)  # (N, h, w)
    ok = valid[..., ::stride, ::stride].all(1)
    r = torch.where(ok, r, torch.zeros_like(r))
    hp = _high_pass(r, ok, *_tile_stats(r, ok, tile), background)
    med, sigma = _tile_stats(hp, ok, tile)
    z = torch.where(ok, (hp - med) / sigma, torch.zeros_like(hp))  # masked pixels count nowhere
    hi, lo = z.amax(0), -z.amin(0)  # per sampled pixel, over the shots
    top, glint = torch.maximum(hi, lo), hi >= lo
    peak = torch.nn.functional.max_pool2d(top[None, None], 3, stride=1, padding=1)[0, 0] == top
    top = torch.where(peak, top, torch.zeros_like(top))  # one count per local peak: a blob is one outlier
    pos = [int(((top > t) & glint).sum()) for t in ladder]
    neg = [int(((top > t) & ~glint).sum()) for t in ladder]
    passed = glint_rule(pos, neg, min_excess, ratio=1.0)
    return passed, {"snr": list(ladder), "positive": pos, "negative": neg, "pixels": int(ok.sum())}
