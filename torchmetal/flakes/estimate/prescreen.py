"""A cheap first look for glints: is the flake stage worth running at all?

The flake stage's own null test (:func:`torchmetal.flakes.estimate.null_test.glint_excess`) detects particles in
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
1.4826·MAD over ``tile``×``tile`` sampled pixels of each shot (from every ``SUB``-th of them), so a
bright highlight's noise does not hide a glint in the shade nor the reverse. Outliers are counted
once per local peak, and only where they are spots: above twice the largest value on a ring half of
:data:`~torchmetal.flakes.estimate.null_test.EXTENT` away (a flake glints as a spot; the shared uw_gray_sphere's
sheen bands, 200 px long, had passed the screen).

Cost, skipped flake stage / Phong fit (CPU seconds of a fresh process, one thread, 3 runs each;
:func:`sampled_residual` renders the strided grid separably in float32, the tile statistics are
applied per tile without full-size copies): 6.3–7.4 % at 1024² × 8 shots (zoo few_highlight),
7.0–7.6 % at 512² × 16 (bumpy_lin16), 6.3–7.0 % at 384² × 12 (photo_srgb8), 5.5–7.1 % on the 256²
scenes whose fit skips the specular (≈ 0.1 s of fit, 7–8 ms of screen; the pipeline imports this
module with itself).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.flakes.estimate.lobe_core import CORE_LEVEL, LOG_CORE
from torchmetal.flakes.estimate.null_test import EXTENT, MIN_EXCESS, SNR_LADDER, glint_rule
from torchmetal.flakes.estimate.rim import interior
from torchmetal.flakes.model.filters import axis_max, box_mean, max_filter
from torchmetal.geometry import grid_shading_terms, is_flat, pixel_axes
from torchmetal.lobes import ggx_lobe, grid_half_terms
from torchmetal.phong import exp_normal

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture


SCREEN_STRIDE = 2  # the pipeline renders and screens every 2nd row and column
TILE = 32
BACKGROUND = 2
MAD_TO_SIGMA = 1.4826
SUB = 2  # tile statistics from every 2nd sampled row and column of the tile
CHUNK_ELEMENTS = 1 << 19  # sampled pixel-shots per pass of the screen (2 MiB per float32 temporary, ~12 of them)
CLIP = 3.0  # the background box averages the residual clipped to med ± CLIP·σ of its tile


def _tile_stats(x: Tensor, ok: Tensor, tile: int, sub: int = SUB) -> tuple[Tensor, Tensor]:
    """Median and 1.4826·MAD of the valid values of each tile×tile tile: (N, ⌈h/tile⌉, ⌈w/tile⌉) each
    (0 and the smallest normal σ for a tile without valid values; :func:`_per_tile` applies them).

    Taken over every ``sub``-th row and column of the tile ((tile/sub)² values; σ the same for both
    signs of the residual)."""
    n, h, w = x.shape
    th, tw = -(-h // tile), -(-w // tile)
    xs = torch.where(ok[:, ::sub, ::sub], x[:, ::sub, ::sub], torch.nan)
    t = tile // sub
    pad = (0, tw * t - xs.shape[2], 0, th * t - xs.shape[1])
    xp = torch.nn.functional.pad(xs, pad, value=float("nan"))
    blocks = xp.reshape(n, th, t, tw, t).permute(0, 1, 3, 2, 4).reshape(n, th, tw, t * t)
    med = blocks.nanmedian(-1).values
    sigma = MAD_TO_SIGMA * (blocks - med[..., None]).abs().nanmedian(-1).values
    return torch.nan_to_num(med, nan=0.0), torch.nan_to_num(sigma, nan=0.0).clamp_min(torch.finfo(x.dtype).tiny)


def _per_tile(fn, x: Tensor, tile: int, *stats: Tensor) -> Tensor:
    """``fn(x, *stats)`` with each (N, th, tw) tile statistic broadcast over its tile×tile pixels of
    the (N, h, w) ``x`` — no full-size copies of the statistics: (N, h, w)."""
    n, h, w = x.shape
    th, tw = stats[0].shape[1:]
    if h != th * tile or w != tw * tile:
        x = torch.nn.functional.pad(x, (0, tw * tile - w, 0, th * tile - h))
    out = fn(x.reshape(n, th, tile, tw, tile), *(v[:, :, None, :, None] for v in stats))
    return out.reshape(n, th * tile, tw * tile)[:, :h, :w]


def _ring_max(z: Tensor, radius: int) -> Tensor:
    """Largest value of (N, h, w) ``z`` on the square ring at Chebyshev distance ``radius`` around each pixel
    (−inf off the image), from one row- and one column-wise running maximum: (N, h, w)."""
    rows, cols = axis_max(z, radius, -1), axis_max(z, radius, -2)  # along each row, along each column
    p = torch.nn.functional.pad(rows, (0, 0, radius, radius), value=-torch.inf)
    q = torch.nn.functional.pad(cols, (radius, radius), value=-torch.inf)
    h, w = z.shape[-2:]
    return torch.maximum(torch.maximum(p[:, :h], p[:, 2 * radius:]), torch.maximum(q[..., :w], q[..., 2 * radius:]))


def _compact(z: Tensor, radius: int) -> Tensor:
    """``z`` (N, h, w) where a pixel is a spot — above twice the largest value on the ring ``radius`` sampled
    px around it (a glint no longer than :data:`~torchmetal.flakes.estimate.null_test.EXTENT`), 0 elsewhere (a band of
    misfit crossing the ring: a sheen, the streak of a highlight)."""
    return torch.where(z > 2.0 * _ring_max(z, radius), z, torch.zeros_like(z))


def _high_pass(r: Tensor, ok: Tensor | None, med: Tensor, sigma: Tensor, radius: int, tile: int) -> Tensor:
    """r minus its (2·radius+1)² box mean over valid pixels (:func:`~torchmetal.flakes.model.filters.box_mean`),
    the box averaging r clipped to med ± CLIP·σ of its tile (``med``, ``sigma``: (N, th, tw) from
    :func:`_tile_stats`) — a bright glint must not dig a negative halo around itself: (N, h, w).
    ``ok`` None: every pixel valid."""
    spread = sigma * CLIP
    clipped = _per_tile(torch.clamp, r, tile, med - spread, med + spread)
    return r - box_mean(clipped.unsqueeze(1), radius, None if ok is None else ok.unsqueeze(1))[:, 0]


def sampled_residual(fit: FitResult, capture: Capture, stride: int = SCREEN_STRIDE, *, chunk: int | None = None) -> Tensor:
    """Channel-summed residual Σ_c (photo − render) of every shot on the pixels (i·stride, j·stride):
    (N, ⌈H/stride⌉, ⌈W/stride⌉) float32 (a noise-level decision needs no more; the fit's float64
    would cost 8× in the exponentials).

    The render is formed on the grid separably (:func:`~torchmetal.geometry.grid_shading_terms`,
    :func:`~torchmetal.lobes.grid_half_terms`: no per-pixel vectors) and summed over channels as it
    goes, Σ_c I_c (T_c·max(n·l, 0) + [n·l > 0]·s_c·lobe_c)/d² — the screen looks at nothing else.
    Equal to ``(images − fit.render(...))[..., ::stride, ::stride].sum(1)`` to rounding. ``chunk``
    shots at a time (default: up to :data:`CHUNK_ELEMENTS` sampled pixel-shots, at least one shot —
    a small capture in one pass, not many small operations).
    """
    parts = [r for _, r, _ in residual_groups(fit, capture, stride, chunk)]
    return parts[0] if len(parts) == 1 else torch.cat(parts)


def residual_groups(fit: FitResult, capture: Capture, stride: int = SCREEN_STRIDE, chunk: int | None = None):
    """:func:`sampled_residual` ``chunk`` shots at a time: yields (shot range, (B, h, w) residual,
    (B, h, w) bool core of the fit's highlight or None without a specular) — the core as
    :func:`~torchmetal.flakes.estimate.lobe_core.lobe_core_at` defines it, from the lobe the render forms anyway."""
    dt = torch.float32
    h, w = fit.texture.shape[-2:]
    grid = (..., slice(None, None, stride), slice(None, None, stride))
    tex = fit.texture[grid].to(dt)
    xs, ys = pixel_axes(h, w, fit.size, rows=grid[1], cols=grid[2], dtype=dt, device=tex.device)
    normals = fit.normals[grid].to(dt)
    nrm = None if is_flat(normals) else normals
    s, alpha = fit.specular_maps()
    s, alpha = ((x[grid] if x.dim() == 3 else x).to(dt) for x in (s, alpha))
    chunk = max(1, CHUNK_ELEMENTS // (xs.numel() * ys.numel())) if chunk is None else chunk
    shiny = bool((s != 0).any())  # no specular fitted (no highlight, an unidentifiable lobe): no lobe to render
    for k in range(0, capture.num_shots, chunk):
        k1 = min(k + chunk, capture.num_shots)
        light, cam = capture.lights[k:k1].to(dt), capture.cameras[k:k1].to(dt)
        inten = capture.intensities[k:k1].to(dt)  # (B, 3)
        nl, q, d2 = grid_shading_terms(light, cam, xs, ys, nrm)  # (B, h, w) each
        core = None
        if not shiny:
            spec = torch.zeros_like(nl)
        elif fit.lobe == "ggx":
            hq, nv, vh = (t.unsqueeze(1) for t in grid_half_terms(light, cam, xs, ys, nrm))
            lobe = ggx_lobe(hq, nl.unsqueeze(1), nv, vh, alpha)
            core = (lobe.amax(1) >= CORE_LEVEL) & (nl > 0)
            spec = (inten[:, :, None, None] * (s.view(1, 3, 1, 1) if s.dim() == 1 else s) * lobe).sum(1)
            spec.masked_fill_(nl <= 0, 0.0)
        else:  # Σ_c I_c s_c (1 − q)^α_c, q = 1 − r·v (phong) or 1 − n·h (blinn), one channel at a time
            if fit.lobe == "blinn":
                q = grid_half_terms(light, cam, xs, ys, nrm)[0]
            dark = (q >= 1.0) | (nl <= 0)  # r·v ≤ 0 or unlit: no highlight
            log_cos = q.clamp_max(1.0 - 2.0**-20).neg_().log1p_()  # finite where dark (masked below)
            spec = torch.zeros_like(q)
            for c in range(3):
                spec.addcmul_(exp_normal(log_cos * alpha[c]), s[c] * inten[:, c, None, None])
            spec.masked_fill_(dark, 0.0)
            core = (log_cos * alpha.amin(0) >= LOG_CORE) & ~dark  # the widest channel's lobe ≥ CORE_LEVEL
        diffuse = torch.einsum("bc,chw->bhw", inten, tex)  # Σ_c I_c T_c
        shade = spec.addcmul_(diffuse, nl.clamp_min(0.0)).div_(d2)
        img = capture.images[k:k1, :, ::stride, ::stride].to(dt)  # a view for float32 photos
        photo = img[:, 0] + img[:, 1] + img[:, 2]  # cheaper than .sum(1) on a strided view
        yield range(k, k1), photo.sub_(shade), core


def sampled_valid(capture: Capture, stride: int = SCREEN_STRIDE) -> Tensor:
    """(N, ⌈H/stride⌉, ⌈W/stride⌉) bool: inside the sample's mask, off its rim
    (:func:`~torchmetal.flakes.estimate.rim.interior`), and saturated in no channel."""
    mask = interior(capture.mask)[..., ::stride, ::stride]
    if not bool(capture.saturated.view(torch.uint8).amax()):  # 10× cheaper than Tensor.any; then no strided ORs
        return mask.expand(capture.num_shots, -1, -1)
    sat = capture.saturated[..., ::stride, ::stride]
    return mask & ~(sat[:, 0] | sat[:, 1] | sat[:, 2])


def _extremes(r: Tensor, ok: Tensor, tile: int, background: int, radius: int) -> tuple[Tensor, Tensor, int]:
    """Largest compact z and largest compact −z (:func:`_compact`, ring ``radius``) over the shots of
    (n, h, w) residuals ``r`` (valid where ``ok``): (h, w) each, and the number of valid pixel-shots. Every
    statistic is per shot, so shot groups combine by maxima."""
    every = bool(ok.view(torch.uint8).amin())  # Tensor.all, cheaper
    r = r if every else torch.where(ok, r, torch.zeros_like(r))
    hp = _high_pass(r, None if every else ok, *_tile_stats(r, ok, tile, sub=2 * SUB), background, tile)
    z = _per_tile(lambda x, med, sigma: (x - med) / sigma, hp, tile, *_tile_stats(hp, ok, tile))
    z = z if every else torch.where(ok, z, torch.zeros_like(z))  # masked pixels count nowhere
    return _compact(z, radius).amax(0), _compact(-z, radius).amax(0), ok.numel() if every else int(ok.sum())


def _counts(hi: Tensor, lo: Tensor, pixels: int, ladder: tuple[float, ...], min_excess: int) -> tuple[bool, dict]:
    top, glint = torch.maximum(hi, lo), hi >= lo
    peak = max_filter(top, 1) == top
    top = torch.where(peak, top, torch.zeros_like(top))  # one count per local peak: a blob is one outlier
    pos = [int(((top > t) & glint).sum()) for t in ladder]
    neg = [int(((top > t) & ~glint).sum()) for t in ladder]
    passed = glint_rule(pos, neg, min_excess, ratio=1.0)
    return passed, {"snr": list(ladder), "positive": pos, "negative": neg, "pixels": pixels}


def glint_screen(residual: Tensor, valid: Tensor, *, stride: int = 1, pitch: int = 1, tile: int = TILE,
                 background: int = BACKGROUND,
                 ladder: tuple[float, ...] = SNR_LADDER, min_excess: int = MIN_EXCESS) -> tuple[bool, dict]:
    """Do positive residual outliers exceed negative ones, pixel by pixel?

    Args:
        residual: (N, H, W) channel-summed photo − Phong render (:func:`sampled_residual`).
        valid: (N, H, W) bool, pixels to look at (mask, not saturated).
        stride: sample every ``stride``-th row and column of the inputs.
        pitch: capture pixels per input pixel (:data:`SCREEN_STRIDE` for :func:`sampled_residual`'s grid):
            sets the ring a spot must stand above (:func:`ring_radius`).
        tile: edge of the tiles (in sampled pixels) over which σ is estimated.
        background: radius (sampled pixels) of the box whose (clipped) mean is taken off first: a
            misfit wider than the box (a highlight of the wrong width or place) is not an outlier.

    Returns:
        (passed, {"snr": [t…], "positive": [P…], "negative": [M…], "pixels": sampled pixel-shots valid}).
    """
    hi, lo, pixels = _extremes(residual[..., ::stride, ::stride], valid[..., ::stride, ::stride], tile, background,
                               ring_radius(pitch * stride))
    return _counts(hi, lo, pixels, ladder, min_excess)


def ring_radius(stride: int) -> int:
    """Sampled px from a spot's centre to the ring it must stand above: half of
    :data:`~torchmetal.flakes.estimate.null_test.EXTENT`, rounded up, at sampling ``stride``."""
    return max(1, math.ceil(EXTENT / 2 / stride))


def screen_fit(fit: FitResult, capture: Capture, stride: int = SCREEN_STRIDE, *, shots_per_pass: int | None = None) -> tuple[bool, dict]:
    """:func:`glint_screen` of the fit's :func:`sampled_residual` on the pixels (i·stride, j·stride),
    a few shots at a time (``shots_per_pass``, default ~:data:`CHUNK_ELEMENTS` sampled pixel-shots):
    its memory is a few sampled planes, not the capture's. The same result as in one pass."""
    valid = sampled_valid(capture, stride)
    hi = lo = None
    pixels = 0
    for shots, r, core in residual_groups(fit, capture, stride, shots_per_pass):
        ok = valid[shots.start:shots.stop]
        h_k, l_k, p_k = _extremes(r, ok if core is None else ok & ~core, TILE, BACKGROUND, ring_radius(stride))
        hi, lo = (h_k, l_k) if hi is None else (torch.maximum(hi, h_k), torch.maximum(lo, l_k))
        pixels += p_k
    return _counts(hi, lo, pixels, SNR_LADDER, MIN_EXCESS)
