"""Flake detection per shot: residual → adaptive binarisation → components → particle table.

For shot k the residual photo − Phong is divided by the irradiance E_k, so a glint of
reflectance c reads c·w·g whatever the light distance or exposure (bright and dark regions
compare). The channel mean of that normalised residual is high-passed (minus a 15×15 box mean)
and compared with a *local* noise level σ: the robust MAD of the high-passed residual in
32×32 tiles, smoothed by a 3×3 box over the tile grid and interpolated bilinearly.
Hysteresis binarisation keeps the 8-connected regions of ``signal > k_lo·σ`` that reach
``0.85·k_hi·σ`` somewhere (positive residuals only; invalid/saturated pixels never count); a
region is a particle when its peak above the local ring background (the amplitude the
statistics use) reaches ``k_hi·σ``.
A morphological closing closes 1-px gaps (3×3; :func:`~torchmetal.flakes.model.filters.binary_morph`: the
values of ``kornia.morphology.closing``, 11× faster on bool masks); opening is available but off by default,
since it erases the 1–3 px glints real glitter makes. Properties come from :mod:`torchmetal.flakes.estimate.regions`, measured on
the residual minus a local background (the mean of the non-detected pixels in a ring around
each particle, so a flake never lowers its own amplitude), and the mean Lab colour of each particle from ``kornia.color.rgb_to_lab`` on its clamped,
sRGB-encoded residual colour (computed on foreground pixels only).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.checks import check_finite, check_float, check_shape
from torchmetal.errors import InputError
from torchmetal.flakes.estimate import regions
from torchmetal.flakes.estimate.results import Particles
from torchmetal.flakes.model.filters import binary_morph, box_mean, max_filter
from torchmetal.io.images import linear_to_srgb

_CANDIDATE = 0.85  # hysteresis seeds at 0.85·k_hi on the box high-pass; the final cut is k_hi on the ring peak


def tile_noise(x: Tensor, valid: Tensor, tile: int = 32, *, floor: float = 1e-6) -> Tensor:
    """Robust local noise σ of zero-median data, per pixel.

    σ = 1.4826·median|x| over the valid pixels of each tile (every second pixel in each
    direction), smoothed by a 3×3 box over the tile grid and interpolated bilinearly. Tiles with
    too few valid pixels take the median of the others; σ ≥ max(floor, 0.2·median tile σ).

    Args:
        x: (B, 1, H, W) high-passed residual; valid: (B, 1, H, W) bool.

    Returns:
        (B, 1, H, W) σ.
    """
    b, _, h, w = x.shape
    th, tw = -(-h // tile), -(-w // tile)
    pad = (0, tw * tile - w, 0, th * tile - h)
    v = F.pad(torch.where(valid, x.abs(), torch.full_like(x, float("nan"))), pad, value=float("nan"))
    step = 2 if tile >= 8 else 1
    t = v[..., ::step, ::step].reshape(b, th, tile // step, tw, tile // step).permute(0, 1, 3, 2, 4)
    t = t.reshape(b, th, tw, -1)
    nvalid = (~torch.isnan(t)).sum(-1)
    med = t.nanmedian(-1).values * 1.4826
    ok = nvalid >= max(8, t.shape[-1] // 8)
    glob = torch.stack([m[o].median() if bool(o.any()) else x.new_tensor(floor) for m, o in zip(med, ok)])
    glob = glob.clamp_min(floor).view(b, 1, 1)
    med = torch.where(ok & torch.isfinite(med), med, glob.expand_as(med))
    med = torch.maximum(med, 0.2 * glob).unsqueeze(1)
    med = F.avg_pool2d(F.pad(med, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
    full = F.interpolate(med, size=(th * tile, tw * tile), mode="bilinear", align_corners=False)
    return full[..., :h, :w].clamp_min(floor)


@dataclass
class Detection:
    """Detector output for N shots.

    particles: the particle table; signal (N, 1, H, W): channel-mean normalised residual,
    high-passed (minus the 15×15 box mean, detected pixels included); sigma (N, 1, H, W): local
    noise σ; labels (N, H, W) int64: 0 or 1 + row of ``particles``; valid (N|1, 1, H, W);
    k_hi, k_lo: thresholds in σ; times: seconds per sub-step.
    """

    particles: Particles
    signal: Tensor
    sigma: Tensor
    labels: Tensor
    valid: Tensor
    k_hi: float
    k_lo: float
    times: dict
    headroom: Tensor | None = None  # (N, 1, H, W) the brightest measurable glint peak (:func:`glint_headroom`); None: nothing clipped, or not measured (detect_flakes(headroom=False))


def _check_inputs(photos: Tensor, phong: Tensor, irradiance: Tensor, valid: Tensor | None) -> None:
    check_shape(photos, ("N", 3, "H", "W"), "photos")
    check_float(photos, "photos")
    check_shape(phong, tuple(photos.shape), "phong")
    check_shape(irradiance, ("N", 3, "*", "*"), "irradiance")
    n, _, h, w = photos.shape
    if irradiance.shape[0] != n or irradiance.shape[-2:] not in ((1, 1), (h, w)):
        raise InputError(f"irradiance: expected shape ({n}, 3, {h}|1, {w}|1), found {tuple(irradiance.shape)}")
    if valid is not None:
        check_shape(valid, ("*", 1, h, w), "valid")
        if valid.dim() != 4 or valid.shape[0] not in (1, n):
            raise InputError(f"valid: expected shape ({n}|1, 1, {h}, {w}), found {tuple(valid.shape)}")
        if valid.dtype != torch.bool:
            raise InputError(f"valid: expected a bool tensor, found dtype {valid.dtype}")
    check_finite(photos, "photos")
    check_finite(phong, "phong")
    low = float(irradiance.min())
    if not low > 0 or not bool(torch.isfinite(irradiance.sum())):
        raise InputError(f"irradiance: expected finite values > 0, found minimum {low:.4g}")


def _detect_chunk(res: Tensor, valid: Tensor, all_valid: bool, *, k_hi, k_lo, tile, background, close, open_, min_area, backend, times):
    t0 = time.perf_counter()
    s = res.mean(1, keepdim=True)
    hp = s - box_mean(s, background, None if all_valid else valid)
    if not all_valid:
        hp = torch.where(valid, hp, torch.zeros_like(hp))
    sigma = tile_noise(hp, valid, tile)
    t1 = time.perf_counter()
    lo = hp > k_lo * sigma
    if not all_valid:
        lo &= valid
    lo = binary_morph(lo, close, open_)
    if not all_valid:
        lo &= valid
    t2 = time.perf_counter()
    labels, count = regions.label_components(lo, backend=backend)
    t3 = time.perf_counter()
    px = regions.pixel_list(labels, count)
    z = hp[px.b, 0, px.i, px.j] / sigma[px.b, 0, px.i, px.j]
    zmax = regions.segment_max(px.ids, z, count)
    area = regions.segment_sum(px.ids, torch.ones_like(z), count)
    keep = (zmax >= _CANDIDATE * k_hi) & (area >= min_area)
    newid = torch.cumsum(keep.long(), 0) - 1
    sel = keep[px.ids]
    px = regions.PixelList(newid[px.ids[sel]], px.b[sel], px.i[sel], px.j[sel], int(keep.sum()))
    lab_map = torch.zeros(res.shape[0], *res.shape[-2:], dtype=torch.int64, device=res.device)
    lab_map[px.b, px.i, px.j] = px.ids + 1
    t4 = time.perf_counter()
    table = _measure(px, res, hp, sigma, valid, lab_map, background)
    # final decision on the ring-background peak (the amplitude the statistics model uses)
    final = table.snr >= k_hi
    if not bool(final.all()):
        lut = torch.where(final, torch.cumsum(final.long(), 0), torch.zeros_like(final, dtype=torch.int64))
        lut = torch.cat([lut.new_zeros(1), lut])
        lab_map = lut[lab_map]
        table = table.select(final)
    t5 = time.perf_counter()
    for key, dt in (("noise", t1 - t0), ("binarise", t2 - t1), ("components", t3 - t2), ("hysteresis", t4 - t3), ("properties", t5 - t4)):
        times[key] = times.get(key, 0.0) + dt
    return table, hp, sigma, lab_map


def ring_background(x: Tensor, fg: Tensor, valid: Tensor, b: Tensor, ci: Tensor, cj: Tensor, radius: int) -> Tensor:
    """Mean of ``x`` over the valid, non-foreground pixels of a patch around each centre.

    Args:
        x: (N, C, H, W); fg, valid: (N, 1, H, W) bool; b, ci, cj: (P,) centres; radius: patch
            half-size. Foreground is dilated by 1 px before it is excluded.

    Returns:
        (P, C) local background (0 where a patch has no usable pixel).
    """
    xp = regions.patches(x, b, ci, cj, radius)
    fp = regions.patches(fg.to(x.dtype), b, ci, cj, radius, fill=1.0)
    vp = regions.patches(valid.to(x.dtype), b, ci, cj, radius, fill=0.0)
    fp = max_filter(fp, 1)
    w = vp * (1.0 - fp)
    return (xp * w).sum((-2, -1)) / w.sum((-2, -1)).clamp_min(1.0)


def _measure(px, res, hp, sigma, valid, lab_map, radius) -> "Particles":
    """Particle table of the kept components (background from a ring around each particle)."""
    n = px.count
    w_hp = hp[px.b, 0, px.i, px.j]
    mom = regions.region_moments(px, w_hp)
    if n == 0:
        z = res.new_zeros(0)
        return Particles(px.b, z, z, z, z, z, z, res.new_zeros(0, 3), res.new_zeros(0, 3), res.new_zeros(0, 3), z, z, z, z)
    first = torch.zeros(n, dtype=torch.int64, device=res.device)
    first[px.ids] = px.b
    ci = mom["cy"].floor().long()
    cj = mom["cx"].floor().long()
    fg = (lab_map > 0).unsqueeze(1)
    if valid.shape[0] != res.shape[0]:
        valid = valid.expand(res.shape[0], -1, -1, -1)
    bg = ring_background(res, fg, valid, first, ci, cj, radius)  # (P, 3)
    rgb_px = res[px.b, :, px.i, px.j] - bg[px.ids]
    w = rgb_px.mean(1)
    arg = regions.segment_argmax(px.ids, w, n)
    area = mom["area"]
    sig = sigma[px.b, 0, px.i, px.j][arg]
    amp = w[arg]
    return Particles(
        shot=first, area=area, cy=mom["cy"], cx=mom["cx"], major=mom["major"], minor=mom["minor"],
        angle=mom["angle"], rgb=regions.segment_sum(px.ids, rgb_px, n) / area[:, None],
        lab=regions.segment_sum(px.ids, _lab(rgb_px), n) / area[:, None], peak=rgb_px[arg],
        amp=amp, snr=amp / sig, flux=regions.segment_sum(px.ids, w, n), sigma=sig,
    )


def _lab(rgb_px: Tensor) -> Tensor:
    """Lab (M, 3) of linear residual colours (M, 3), clamped to [0, 1] and sRGB-encoded."""
    if rgb_px.shape[0] == 0:
        return rgb_px.new_zeros(0, 3)
    from kornia.color import rgb_to_lab  # deferred: kornia is heavy to import

    img = linear_to_srgb(rgb_px.clamp(0.0, 1.0)).t().reshape(1, 3, -1, 1)
    return rgb_to_lab(img).reshape(3, -1).t()


def detect_flakes(
    photos: Tensor,
    phong: Tensor,
    irradiance: Tensor,
    *,
    valid: Tensor | None = None,
    k_hi: float = 5.0,
    k_lo: float = 2.5,
    tile: int = 32,
    background: int = 7,
    close: int = 3,
    open: int = 0,
    min_area: int = 1,
    cc_backend: str = "auto",
    chunk: int = 4,
    headroom: bool = True,
) -> Detection:
    """Detect glinting flakes in every shot.

    Args:
        photos: (N, 3, H, W) linear photos; phong: (N, 3, H, W) the Phong renders of the same shots.
        irradiance: (N, 3, H, W) or (N, 3, 1, 1) irradiance E of each shot (> 0).
        valid: optional (N|1, 1, H, W) bool, False for masked-out or saturated pixels.
        k_hi, k_lo: hysteresis thresholds in units of the local noise σ (k_hi ≥ k_lo > 0).
        tile: noise-tile edge in pixels; background: radius of the high-pass box.
        close, open: odd kernel sizes of the morphological closing / opening (≤ 1 = off).
        min_area: smallest region kept, in pixels; cc_backend: see :func:`regions.label_components`.
        chunk: shots processed at once (bounds memory).
        headroom: measure :attr:`Detection.headroom` (what the flake statistics need only where they model
            clipped glints).

    Returns:
        :class:`Detection` (particle table, signal, σ and label maps).
    """
    _check_inputs(photos, phong, irradiance, valid)
    _check_options(k_hi=k_hi, k_lo=k_lo, close=close, open_=open, tile=tile, background=background,
                   min_area=min_area, chunk=chunk)
    n, _, h, w = photos.shape
    if valid is None:
        valid = torch.ones(1, 1, h, w, dtype=torch.bool, device=photos.device)
    times: dict[str, float] = {}
    tables, signals, sigmas, label_maps = [], [], [], []
    offset = 0
    with torch.no_grad():
        for k0 in range(0, n, max(1, chunk)):
            k1 = min(n, k0 + max(1, chunk))
            res, v, all_valid = _chunk_residual(photos, phong, irradiance, valid, k0, k1)
            tab, sig, sgm, lab = _detect_chunk(
                res, v, all_valid, k_hi=k_hi, k_lo=k_lo, tile=tile, background=background, close=close, open_=open,
                min_area=min_area, backend=cc_backend, times=times,
            )
            tab.shot = tab.shot + k0
            label_maps.append(torch.where(lab > 0, lab + offset, lab))
            offset += len(tab)
            tables.append(tab)
            signals.append(sig)
            sigmas.append(sgm)
    particles = Particles.cat(tables)
    t0 = time.perf_counter()
    room = None
    if headroom:
        with torch.no_grad():
            room = glint_headroom(photos, phong, irradiance, valid, particles, chunk=chunk)
        times["headroom"] = time.perf_counter() - t0
    return Detection(
        particles=particles, signal=torch.cat(signals), sigma=torch.cat(sigmas),
        labels=torch.cat(label_maps), valid=valid, k_hi=float(k_hi), k_lo=float(k_lo), times=times, headroom=room,
    )


HEADROOM_RADIUS = 2  # px: association.CLIP_RADIUS, a glint is unmeasured when a pixel this close clips
_MIN_HEADROOM = 1e-6


def clip_level(photos: Tensor, valid: Tensor) -> float | None:
    """The encoding's top (linear), when some invalid pixels sit at it: the brightest value of any channel at
    an invalid pixel, if no valid pixel is brighter (saturated pixels are the capture's brightest); None when
    nothing clipped (no invalid pixel, float files, or only a mask)."""
    top = photos.amax(1, keepdim=True)  # (N, 1, H, W)
    bad = ~valid.expand_as(top)
    if not bool(bad.any()):
        return None
    clip = float(top[bad].max())
    good = ~bad
    if clip <= 0 or (bool(good.any()) and float(top[good].max()) > clip):
        return None
    return clip


def glint_headroom(photos: Tensor, phong: Tensor, irradiance: Tensor, valid: Tensor, particles: Particles, *,
                   chunk: int = 4, min_snr: float = 8.0) -> Tensor | None:
    """(N, 1, H, W) the brightest glint peak (channel-mean reflectance, the particles' amplitude units) each pixel
    can hold without a pixel within :data:`HEADROOM_RADIUS` clipping: min over channels of (clip − Phong)/(E·chroma),
    the chroma the detections' median (a glint is brightest in its strongest channel); ≈ 0 where the coat clips
    or the pixel is masked (nothing measurable). None when nothing in the capture clipped (:func:`clip_level`).

    The likelihood needs it: a glint that clips is never measured (:func:`~torchmetal.flakes.estimate.association.measurable`),
    so the brightest glints are missing from the data, and a model unaware of it puts the amplitude low."""
    clip = clip_level(photos, valid)
    if clip is None:
        return None
    sel = particles.snr >= min_snr
    chroma = torch.ones(3, dtype=photos.dtype, device=photos.device)
    if int(sel.sum()) >= 5:
        rgb = particles.rgb[sel].to(photos.dtype)
        ch = rgb / rgb.mean(1, keepdim=True).clamp_min(1e-12)
        ok = ((ch >= 0) & (ch <= 3)).all(1)
        if int(ok.sum()) >= 5:
            chroma = ch[ok].median(0).values.clamp_min(0.05)
    n = photos.shape[0]
    out = []
    for k0 in range(0, n, max(1, chunk)):
        k1 = min(n, k0 + max(1, chunk))
        v = valid[k0:k1] if valid.shape[0] == n else valid.expand(k1 - k0, -1, -1, -1)
        u = ((clip - phong[k0:k1]) / (irradiance[k0:k1] * chroma.view(1, 3, 1, 1))).amin(1, keepdim=True)
        masked = ~v & (photos[k0:k1].amax(1, keepdim=True) < clip)  # invalid but not at the top: masked out
        u = torch.where(masked, torch.zeros_like(u), u).clamp_min(_MIN_HEADROOM)
        out.append(-max_filter(-u, HEADROOM_RADIUS))
    return torch.cat(out)


def _check_options(*, k_hi: float, k_lo: float, close: int, open_: int, tile: int, background: int, min_area: int,
                   chunk: int) -> None:
    """Raise :class:`InputError` on thresholds, kernel sizes or work sizes :func:`detect_flakes` cannot use."""
    if not (0 < k_lo <= k_hi):
        raise InputError(f"k_lo, k_hi: expected 0 < k_lo <= k_hi, found k_lo={k_lo}, k_hi={k_hi}")
    for name, k in (("close", close), ("open", open_)):
        if k > 1 and k % 2 == 0:
            raise InputError(f"{name}: expected an odd kernel size, found {k}")
    for name, k, lo in (("tile", tile, 2), ("background", background, 1), ("min_area", min_area, 0), ("chunk", chunk, 1)):
        if not isinstance(k, int) or isinstance(k, bool) or k < lo:
            raise InputError(f"{name}: expected an integer >= {lo}, found {k!r}")


def _chunk_residual(photos: Tensor, phong: Tensor, irradiance: Tensor, valid: Tensor, k0: int,
                    k1: int) -> tuple[Tensor, Tensor, bool]:
    """Shots k0..k1's residual over irradiance (0 where not valid), their valid mask, and whether all of it is."""
    n = photos.shape[0]
    e = irradiance[k0:k1]
    v = valid[k0:k1] if valid.shape[0] == n else valid.expand(k1 - k0, -1, -1, -1)
    res = (photos[k0:k1] - phong[k0:k1]) / e
    all_valid = bool(v.all())
    if not all_valid:
        res = torch.where(v, res, torch.zeros_like(res))
    return res, v, all_valid
