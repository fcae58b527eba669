"""Where the glitter is: a coarse flake-density map (and per-block colour) from the associated detections.

:class:`~torchmetal.flakes.model.FlakeModel`'s ``density`` is one number for the whole sample; a card
with glitter on part of it (glitter in the dark tiles, none on the foil) then sparkles everywhere.
Here the texture is cut into a gh×gw grid of blocks (:func:`map_grid`: as many as keep about
``MIN_COUNT`` associated flakes per block under the uniform model, at most ``MAX_SIDE`` a side, no
block under ``MIN_BLOCK`` px), and per block

- n_r: the associated flakes of the detections (flake stage ``flake_id`` ≥ 0) whose mean centroid
  lies in it;
- E_r = J · D_r / Σ D: the count the uniform model expects there, J the flakes counted and D_r the
  block's detectable area (:func:`detectability`). ``"glint"``: Σ over its pixels of P_any, the
  probability that a flake there glints detectably in at least one shot, in a Gaussian-cap
  approximation: the glint exp(−|m − h_k|²/2σ_g²) of a flake of the typical amplitude A stays
  above the amplitude floor A₀ within s² = σ_g²·ln(A/A₀) of h_k, so with slopes m ~ N(0, τ²)
  P_k = s²/(s² + τ²)·exp(−|μ(h_k)|²/2(s² + τ²)), μ the slope of h_k, times the pixel's measurable
  fraction in the shot (mask, saturation); P_any = 1 − Π_k (1 − P_k). ``"area"``: the measurable
  pixels only (the detections' own spread says the geometry matters little: the real card's
  shots each find flakes all over it, wherever their half vector meets the normal). Irradiance and
  noise differences over the sample are not modelled;
- λ_r = (n_r + a)/(E_r + a): the Poisson–Gamma posterior mean of the block's density relative to
  the global one, λ ~ Gamma(a, a) with a from the counts' overdispersion (method of moments,
  1/a = Σ((n − E)² − n)/Σ E²; no overdispersion → no map), so a block with few counts stays near
  the global value; a block where the uniform model expects ≥ ``ZERO_EXPECTED`` flakes and none
  was found (its 95 % upper limit is then half the average) is 0. The λ are renormalised so that
  Σ λ_r E_r = J (the fitted density is the detectability-weighted mean), then capped at the hash
  field's capacity.

Colour: each flake's mean detected colour (the particles' normalised residual ``rgb``); blocks with
at least ``COLOR_MIN`` flakes are compared with a χ² test of their means against the pooled
within-block covariance (df 3·(R − 1)); when they differ at p < ``COLOR_P`` the colour map is the
model's colour mean scaled channel by channel by each block's (shrunk, ``COLOR_PRIOR``
pseudo-flakes of the global mean) colour over the global one.

Size (:func:`flake_areas`, :func:`_area_map`): each flake's log flux/peak area y_j on its brightest
detection (its particle's flux/amp; flakes with SNR ≥ ``AREA_SNR`` when at least ``MIN_FLAKES`` do, as
:func:`~torchmetal.flakes.estimate.shape_colour.fit_shapes` selects), with fit_shapes's noise model
ν_j = n_pix/(SNR²·area²), n_pix = area + 3√area + 4, and the intrinsic spread s² = the pooled
within-block variance of y minus the median ν. Per block the weighted mean m_r (weights
1/(s² + ν_j)) has standard error 1/W_r; blocks with at least ``AREA_MIN`` flakes are compared by
Cochran's Q = Σ W_r (m_r − m̄)², χ² with R − 1 df. When they differ at p < ``AREA_P`` the area map
holds each block's offset from the global log-mean, shrunk toward 0 by the DerSimonian–Laird
between-block variance τ² = max(0, (Q − df)/(ΣW − ΣW²/ΣW)): offset_r = (m_r − m̄)·τ²/(τ² + 1/W_r)
(a block with few flakes stays near the global size; none: 0), recentred to a flake-weighted mean
of 0 (``area_log_mean`` stays the global log-mean). It is relative: the measurement's common bias
(the particle's flux misses the glint's wings below the detection threshold) cancels. The log-area
spread ``area_log_std`` stays the global one.

Whether the map is used at all is decided on left-out shots: :mod:`torchmetal.flakes.density_choice`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.flakes.estimate.regions import segment_argmax
from torchmetal.flakes.model import MAX_AREA_OFFSET, MAX_COLOR, MAX_DENSITY, FlakeModel
from torchmetal.flakes.model.field import map_blocks
from torchmetal.geometry import normalize, shading_geometry

if TYPE_CHECKING:
    from torchmetal.flakes.estimate.results import Particles
    from torchmetal.io.capture import Capture


MIN_COUNT = 8  # flakes per block expected under the uniform model (the grid's resolution)
MAX_SIDE = 16  # blocks per side at most
MIN_BLOCK = 16  # px: no block smaller than MD's block
MIN_FLAKES = 20  # fewer associated flakes: no map
ZERO_EXPECTED = 6.0  # no flake where the uniform model expects this many: no glitter there (λ = 0)
SAMPLES = 48  # detectability points per side (rounded to a multiple of the grid)
COLOR_MIN = 3
COLOR_P = 0.01
COLOR_PRIOR = 5.0
AREA_MIN = 3  # flakes per block in the area test
AREA_P = 0.01
AREA_SNR = 8.0  # fit_shapes's min_snr


@dataclass
class DensityMap:
    """density (gh, gw) float32 relative to the model's density (as rendered: capped at capacity);
    color (gh, gw, 3) float32 colour means or None; uniform: nothing to change (no overdispersion
    and no area map: density all ones); report: counts, expectations, estimates and tests;
    area (gh, gw) float32 log-area offsets or None."""

    density: Tensor
    color: Tensor | None
    uniform: bool
    report: dict = field(default_factory=dict)
    area: Tensor | None = None

    @property
    def grid(self) -> tuple[int, int]:
        return tuple(self.density.shape)


def map_grid(height: int, width: int, flakes: int) -> tuple[int, int]:
    """(gh, gw): about ``MIN_COUNT`` flakes per block, ≤ ``MAX_SIDE`` a side, blocks ≥ ``MIN_BLOCK`` px."""
    g = max(1, min(MAX_SIDE, int(math.sqrt(max(flakes, 0) / MIN_COUNT))))
    return max(1, min(g, height // MIN_BLOCK)), max(1, min(g, width // MIN_BLOCK))


def flake_positions(particles: Particles, flake_id: Tensor, shots: list[int] | None = None) -> tuple[Tensor, Tensor]:
    """Mean centroid (J, 2) (row, col px) and mean colour (J, 3) of each associated flake, from the
    particles of ``shots`` only (None: all)."""
    keep = flake_id >= 0
    if shots is not None:
        keep &= torch.isin(particles.shot, torch.tensor(shots, dtype=particles.shot.dtype, device=particles.shot.device))
    fid = flake_id[keep]
    if fid.numel() == 0:
        z = torch.zeros(0, dtype=torch.float64)
        return z.view(0, 2), z.view(0, 3)
    ids, inv = torch.unique(fid, return_inverse=True)
    j = ids.numel()
    vals = torch.cat([particles.cy[keep].double().view(-1, 1), particles.cx[keep].double().view(-1, 1),
                      particles.rgb[keep].double()], 1)
    sums = torch.zeros(j, 5, dtype=torch.float64).index_add_(0, inv.cpu(), vals.cpu())
    n = torch.bincount(inv.cpu(), minlength=j).double().view(-1, 1)
    mean = sums / n
    return mean[:, :2], mean[:, 2:]


def flake_areas(particles: Particles, flake_id: Tensor, shots: list[int] | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Log flux/peak area (J,), its measurement noise variance ν (J,) (:func:`~torchmetal.flakes.
    shape_colour.fit_shapes`'s model) and SNR (J,) of each associated flake on its brightest
    detection among ``shots`` (None: all), float64, in :func:`flake_positions`'s order."""
    keep = flake_id >= 0
    if shots is not None:
        keep &= torch.isin(particles.shot, torch.tensor(shots, dtype=particles.shot.dtype, device=particles.shot.device))
    rows = torch.nonzero(keep, as_tuple=True)[0]
    if rows.numel() == 0:
        z = torch.zeros(0, dtype=torch.float64)
        return z, z, z
    ids, inv = torch.unique(flake_id[rows], return_inverse=True)
    snr_all = particles.snr[rows].double()
    best = rows[segment_argmax(inv, snr_all, ids.numel())]
    amp = particles.amp[best].double().cpu()
    area = (particles.flux[best].double().cpu() / amp.clamp_min(1e-12)).clamp_min(0.25)
    snr = particles.snr[best].double().cpu().clamp_min(1e-6)
    npix = area + 3 * torch.sqrt(area) + 4
    return torch.log(area), npix / (snr**2 * area**2), snr


def chi2_sf(x: float | Tensor, df: int) -> float:
    """P(X > x) for X ~ χ²(df): the regularised upper incomplete gamma Q(df/2, x/2) (torch, no scipy)."""
    x = torch.as_tensor(x, dtype=torch.float64).clamp_min(0.0)
    return float(torch.special.gammaincc(torch.tensor(df / 2, dtype=torch.float64), x / 2))


def _area_map(block: Tensor, y: Tensor, nu: Tensor, snr: Tensor, grid: tuple[int, int]) -> tuple[Tensor | None, dict]:
    """Per-block log-area offsets (gh, gw) when the blocks' mean log areas differ beyond their
    standard errors (module docstring), else None; and the test's report."""
    r = grid[0] * grid[1]
    sel = snr >= AREA_SNR
    if int(sel.sum()) < MIN_FLAKES:
        sel = torch.ones_like(sel)
    block, y, nu = block[sel], y[sel], nu[sel]
    n = torch.bincount(block, minlength=r).double()
    big = n >= AREA_MIN
    rep = {"flakes": int(sel.sum()), "blocks_tested": int(big.sum()), "kept": False}
    if int(big.sum()) < 2:
        rep["reason"] = f"fewer than 2 blocks with {AREA_MIN}+ flakes"
        return None, rep
    plain = torch.zeros(r, dtype=torch.float64).index_add_(0, block, y) / n.clamp_min(1)
    dof = int(n[n >= 1].sum()) - int((n >= 1).sum())
    if dof < 2:
        rep["reason"] = "too few flakes for the within-block spread"
        return None, rep
    within = float(((y - plain[block]) ** 2).sum()) / dof
    s2 = max(within - float(nu.median()), 1e-4)
    w = 1.0 / (s2 + nu)
    wsum = torch.zeros(r, dtype=torch.float64).index_add_(0, block, w)
    m = torch.zeros(r, dtype=torch.float64).index_add_(0, block, w * y) / wsum.clamp_min(1e-300)
    wb = wsum[big]
    grand = float((wb * m[big]).sum() / wb.sum())
    q = float((wb * (m[big] - grand) ** 2).sum())
    df = int(big.sum()) - 1
    p = chi2_sf(q, df)
    tau2 = max(0.0, (q - df) / float(wb.sum() - (wb * wb).sum() / wb.sum()))
    rep.update({"within_var": within, "intrinsic_var": s2, "noise_var_median": float(nu.median()), "Q": q, "df": df,
                "p": p, "between_var": tau2, "log_mean": m.view(grid).tolist(), "counts": n.view(grid).tolist()})
    if not p < AREA_P:
        rep["reason"] = f"block areas within their standard errors (Q {q:.1f}, df {df}, p {p:.3g} >= {AREA_P})"
        return None, rep
    has = n >= 1
    off = torch.where(has, (m - grand) * tau2 / (tau2 + 1.0 / wsum.clamp_min(1e-300)), torch.zeros_like(m))
    off = off - float((n * off).sum() / n.sum())  # flake-weighted mean 0: area_log_mean stays the global one
    off = off.clamp(-MAX_AREA_OFFSET, MAX_AREA_OFFSET)
    rep.update({"kept": True, "area_map": off.view(grid).tolist(),
                "reason": f"block areas differ (Q {q:.1f}, df {df}, p {p:.3g} < {AREA_P})"})
    return off.view(grid).float(), rep


def block_pixels(height: int, width: int, grid: tuple[int, int]) -> Tensor:
    """(gh, gw) float64 pixel count of each block (:func:`~torchmetal.flakes.model.field.map_blocks`)."""
    bi, _ = map_blocks(grid[0], 1, torch.arange(height), torch.zeros(1, dtype=torch.long), height, 1)
    _, bj = map_blocks(1, grid[1], torch.zeros(1, dtype=torch.long), torch.arange(width), 1, width)
    return torch.outer(torch.bincount(bi, minlength=grid[0]).double(), torch.bincount(bj, minlength=grid[1]).double())


DETECT_MODES = ("glint", "area")


def detectability(capture: Capture, model: FlakeModel, shots: list[int], grid: tuple[int, int], mode: str = "glint") -> Tensor:
    """(gh, gw) float64 detectable area D_r of each block (px): Σ of P_any over its pixels, ``mode``
    "glint" or "area" (module docstring)."""
    if mode not in DETECT_MODES:
        raise InputError(f"mode: expected one of {DETECT_MODES}, found {mode!r}")
    h, w = capture.images.shape[-2:]
    gh, gw = grid
    sh, sw = gh * max(1, SAMPLES // gh), gw * max(1, SAMPLES // gw)
    sh, sw = min(sh, h), min(sw, w)
    dt = torch.float64
    nrm = normalize(F.adaptive_avg_pool2d(capture.normals.to(dt).unsqueeze(0), (sh, sw))[0], dim=0)
    idx = torch.tensor(shots, dtype=torch.long, device=capture.lights.device)
    ok = capture.mask.unsqueeze(0) & ~capture.saturated[idx].any(1, keepdim=True)  # (K, 1, H, W)
    valid = F.adaptive_avg_pool2d(ok.to(dt), (sh, sw))[:, 0]
    geo = shading_geometry(nrm, capture.lights[idx].to(dt), capture.intensities[idx].to(dt), capture.cameras[idx].to(dt),
                           capture.size)
    half = normalize(geo.l + geo.v, dim=1)
    cos = (half * nrm.unsqueeze(0)).sum(1).clamp(1e-6, 1.0)  # (K, sh, sw)
    slope2 = (1.0 - cos * cos) / (cos * cos)
    tau2 = max(model.tilt_sigma, 1e-3) ** 2
    ex = model.extra or {}
    log_ratio = float(ex.get("log_amp_mean", 0.0)) - float(ex.get("log_amp_floor", -1.0))
    s2 = model.glint_sigma**2 * max(1.0, log_ratio if math.isfinite(log_ratio) else 1.0)
    lit = ((geo.n_dot_l[:, 0] > 0) & ((geo.v * nrm.unsqueeze(0)).sum(1) > 0)).to(dt)
    if mode == "area":
        pk = valid * lit
    else:
        pk = (s2 / (s2 + tau2) * torch.exp(-slope2 / (2.0 * (s2 + tau2))) * valid * lit).clamp(0.0, 1.0)
    p_any = 1.0 - torch.prod(1.0 - pk, 0)  # (sh, sw)
    mean = F.adaptive_avg_pool2d(p_any.view(1, 1, sh, sw), (gh, gw))[0, 0]
    return mean.cpu() * block_pixels(h, w, grid)


def _shrink(n: Tensor, e: Tensor) -> tuple[Tensor, float, Tensor]:
    """Poisson–Gamma posterior means λ (gh, gw), the dispersion 1/a, and the zeroed blocks (bool)."""
    phi = float((((n - e) ** 2 - n).sum() / (e * e).sum().clamp_min(1e-30)).clamp_min(0.0))
    if phi <= 0.0:
        return torch.ones_like(n), 0.0, torch.zeros_like(n, dtype=torch.bool)
    a = 1.0 / phi
    lam = (n + a) / (e + a)
    zero = (n == 0) & (e >= ZERO_EXPECTED)
    lam = torch.where(zero, torch.zeros_like(lam), lam)
    total = float((lam * e).sum())
    if total > 0:
        lam = lam * float(n.sum()) / total
    return lam, phi, zero


def _colour_map(model: FlakeModel, block: Tensor, colours: Tensor, grid: tuple[int, int]) -> tuple[Tensor | None, dict]:
    """Per-block colour means (gh, gw, 3) when the blocks' colours differ beyond their standard errors."""
    r = grid[0] * grid[1]
    n = torch.bincount(block, minlength=r).double()
    sums = torch.zeros(r, 3, dtype=torch.float64).index_add_(0, block, colours)
    means = sums / n.clamp_min(1).view(-1, 1)
    big = n >= COLOR_MIN
    rep = {"blocks_tested": int(big.sum()), "kept": False}
    if int(big.sum()) < 2:
        rep["reason"] = f"fewer than 2 blocks with {COLOR_MIN}+ flakes"
        return None, rep
    sel = big[block]
    dev = colours[sel] - means[block[sel]]
    dof = int(sel.sum()) - int(big.sum())
    if dof < 3:
        rep["reason"] = "too few flakes for the within-block covariance"
        return None, rep
    cov = dev.T @ dev / dof + 1e-12 * torch.eye(3, dtype=torch.float64)
    grand = (means[big] * n[big].view(-1, 1)).sum(0) / n[big].sum()
    d = means[big] - grand
    stat = float((n[big] * (d @ torch.linalg.inv(cov) * d).sum(1)).sum())
    df = 3 * (int(big.sum()) - 1)
    p = chi2_sf(stat, df)
    rep.update({"chi2": stat, "df": df, "p": p})
    if not p < COLOR_P:
        rep["reason"] = f"block colours within their standard errors (chi2 {stat:.1f}, df {df}, p {p:.3g} >= {COLOR_P})"
        return None, rep
    shrunk = (sums + COLOR_PRIOR * grand) / (n + COLOR_PRIOR).view(-1, 1)
    ratio = shrunk / grand.clamp_min(1e-6)
    cmap = (torch.tensor(model.color_mean, dtype=torch.float64) * ratio).clamp(0.0, MAX_COLOR)
    rep.update({"kept": True, "reason": f"block colours differ (chi2 {stat:.1f}, df {df}, p {p:.3g} < {COLOR_P})"})
    return cmap.view(*grid, 3).float(), rep


def estimate_map(capture: Capture, model: FlakeModel, particles: Particles, flake_id: Tensor, shots: list[int] | None = None,
                 grid: tuple[int, int] | None = None, mode: str = "glint") -> DensityMap | None:
    """The density map of ``model`` from the detections of ``shots`` (None: all), detectability
    ``mode`` ("glint" or "area"), or None when there are fewer than ``MIN_FLAKES`` associated flakes or
    the grid is one block (module docstring)."""
    h, w = capture.images.shape[-2:]
    shots = list(range(capture.num_shots)) if shots is None else list(shots)
    pos, col = flake_positions(particles, flake_id, shots)
    j = pos.shape[0]
    if j < MIN_FLAKES:
        return None
    grid = map_grid(h, w, j) if grid is None else tuple(grid)
    if grid[0] * grid[1] < 2:
        return None
    bi, bj = map_blocks(grid[0], grid[1], pos[:, 0].floor().long().clamp(0, h - 1),
                        pos[:, 1].floor().long().clamp(0, w - 1), h, w)
    block = bi * grid[1] + bj
    n = torch.bincount(block, minlength=grid[0] * grid[1]).double().view(grid)
    d = detectability(capture, model, shots, grid, mode)
    e = j * d / d.sum().clamp_min(1e-30)
    lam, phi, zero = _shrink(n, e)
    fitted = float(model.extra.get("density_fitted", model.density)) if model.density > 0 else 0.0
    cap = MAX_DENSITY / model.density if model.density > 0 else 1.0
    rendered = (lam * (fitted / model.density if model.density > 0 else 1.0)).clamp(max=cap)
    report = {"mode": mode, "grid": list(grid), "flakes": j, "shots": shots, "counts": n.tolist(), "expected": e.tolist(),
              "raw": (n / e.clamp_min(1e-12)).tolist(), "dispersion": phi, "zero_blocks": int(zero.sum()),
              "capped_blocks": int((lam * fitted / max(model.density, 1e-30) > cap).sum()) if model.density > 0 else 0}
    la, nu, snr = flake_areas(particles, flake_id, shots)
    amap, report["area"] = _area_map(block, la, nu, snr, grid)
    if phi <= 0.0:
        report["reason"] = "block counts no more dispersed than Poisson around the uniform model"
        if amap is None:
            return DensityMap(torch.ones(grid), None, True, report)
        report["density_map"] = torch.ones(grid).tolist()  # sizes differ: a map of ones carries their grid
        return DensityMap(torch.ones(grid), None, False, report, amap)
    cmap, report["color"] = _colour_map(model, block, col, grid)
    report["density_map"] = rendered.tolist()
    return DensityMap(rendered.float(), cmap, False, report, amap)


def with_map(model: FlakeModel, dm: DensityMap | None) -> FlakeModel:
    """``model`` with the map's density (and colour, and area offsets) when it is not uniform, else ``model``."""
    if dm is None or dm.uniform:
        return model
    return replace(model, density_map=dm.density, color_map=dm.color, area_map=dm.area)
