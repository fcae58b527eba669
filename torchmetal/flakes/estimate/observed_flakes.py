"""Measuring the sample's own flakes (:class:`~torchmetal.flakes.model.observed.ObservedFlakes`) from
the flake stage's detections.

Each associated flake of the flake stage (:class:`~torchmetal.flakes.estimate.results.FlakeStageResult`
``flake_id``) is measured and kept:

- position: the amplitude-weighted mean centroid of its detections (px, pixel i spans [i, i+1));
- footprint: an ellipse of the brightest detection's flux/peak area, aspect and angle, drawn with
  the statistical field's anti-aliased ramp (Σ weight = area);
- normal: the amplitude-weighted mean of the unit half vectors of the shots where it glints, refined
  by their amplitude ratios, then placed by the flakes' known brightness and the shots that missed it
  (:func:`~torchmetal.flakes.estimate.placement.place_normals`: a faint glint is a flake seen at its tail);
- colour: the least-squares glint reflectance c of the detections' peak colours, given the
  footprint's peak weight and each shot's glint factor exp(−|m − h|² / 2σ_g²).

How they are rendered (the statistical field filling what no fit shot observed):
:mod:`torchmetal.flakes.model.observed`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.flakes.estimate.placement import MIN_AMP_STD, place_normals
from torchmetal.flakes.model.observed import ObservedFlakes, footprints
from torchmetal.flakes.model.params import MAX_COLOR, FlakeModel
from torchmetal.geometry import normalize, shading_geometry

if TYPE_CHECKING:
    from torchmetal.flakes.estimate.results import Particles
    from torchmetal.io.capture import Capture

__all__ = ["observed_flakes"]

DENSITY_CELL = 32  # px: cell of the coarse flake-density map
DENSITY_DISPERSION = 2.0  # variance/mean of the cell counts above which the glitter is patchy (Poisson: 1)
MIN_FLAKES_MAP = 20  # fewer observed flakes: no density map


def _ellipse_axes(area: Tensor, aspect: Tensor) -> tuple[Tensor, Tensor]:
    """Semi-axes of the field's footprint with Σ weight = area (the field's anti-aliasing shrink)."""
    a = torch.sqrt(area / (math.pi * aspect))
    b = aspect * a
    k = torch.sqrt((1.0 - 1.0 / (12.0 * b * b)).clamp_min(0.25))
    return a * k, b * k



def _density_map(position: Tensor, height: int, width: int) -> Tensor | None:
    """(gh, gw) counts/mean of the observed flakes in DENSITY_CELL cells (3×3 box smoothed), or None
    when the counts are Poisson-like (variance/mean ≤ DENSITY_DISPERSION) or too few flakes."""
    gh, gw = max(1, -(-height // DENSITY_CELL)), max(1, -(-width // DENSITY_CELL))
    if len(position) < MIN_FLAKES_MAP or gh * gw < 4:
        return None
    ci = (position[:, 0] / DENSITY_CELL).floor().long().clamp(0, gh - 1)
    cj = (position[:, 1] / DENSITY_CELL).floor().long().clamp(0, gw - 1)
    counts = torch.bincount(ci * gw + cj, minlength=gh * gw).double()
    mean = counts.mean()
    if float(counts.var(unbiased=True) / mean) <= DENSITY_DISPERSION:
        return None
    box = torch.nn.functional.avg_pool2d(counts.view(1, 1, gh, gw), 3, 1, 1, count_include_pad=False)[0, 0]
    return (box / box.mean().clamp_min(1e-12)).to(torch.float32)



def _refine_normals(m0: Tensor, hk: Tensor, fid: Tensor, amp: Tensor, snr: Tensor, sigma: float,
                    iters: int = 3, max_step: float = 3.0, max_total: float = 2.0) -> Tensor:
    """Flake normals (J, 3) from the glint amplitudes of their detections, starting at ``m0``.

    log a_k = c₀ − |m − h_k|² / 2σ² is linear in (c₀, δ) for m = m₀ + σ·δ (δ in m₀'s tangent
    plane): Gauss–Newton steps of the weighted least squares (weights snr², the inverse variance
    of log a) with a unit ridge on δ (a flake seen in one shot keeps the half vector of that
    shot; two shots place it between them by their amplitude ratio). Steps are clipped to
    ``max_step``·σ and the normal stays within ``max_total``·σ of ``m0``. ``hk`` (P, 3) half vectors, ``fid`` (P,) flake, ``amp``/``snr`` (P,).
    """
    j = m0.shape[0]
    wt = snr.clamp(1.0, 100.0) ** 2
    y_obs = torch.log(amp)
    m = m0
    for _ in range(iters):
        ref = torch.zeros_like(m)
        ref[:, 0] = 1.0
        alt = torch.zeros_like(m)
        alt[:, 1] = 1.0
        ref = torch.where((m[:, :1].abs() > 0.9), alt, ref)
        t1 = normalize(ref - (ref * m).sum(1, keepdim=True) * m, dim=1)
        t2 = torch.cross(m, t1, dim=1)
        d = m[fid] - hk  # (P, 3)
        x = torch.stack([torch.ones_like(wt), -(d * t1[fid]).sum(1) / sigma, -(d * t2[fid]).sum(1) / sigma], 1)
        y = y_obs + (d * d).sum(1) / (2 * sigma * sigma)
        a = torch.zeros(j, 3, 3, dtype=m.dtype, device=m.device).index_add_(0, fid, wt.view(-1, 1, 1) * x.unsqueeze(2) * x.unsqueeze(1))
        a = a + torch.diag(torch.tensor([1e-9, 1.0, 1.0], dtype=m.dtype, device=m.device))
        rhs = torch.zeros(j, 3, dtype=m.dtype, device=m.device).index_add_(0, fid, (wt * y).unsqueeze(1) * x)
        sol = torch.linalg.solve(a, rhs)
        step = sol[:, 1:]
        norm = step.norm(dim=1, keepdim=True)
        step = step * (max_step / norm.clamp_min(max_step)).clamp(max=1.0)
        m = normalize(m + sigma * (step[:, :1] * t1 + step[:, 1:] * t2), dim=1)
        # never further than max_total·σ from the start: amplitude ratios extrapolate badly
        off = m - m0
        far = off.norm(dim=1, keepdim=True)
        m = normalize(m0 + off * (max_total * sigma / far.clamp_min(max_total * sigma)), dim=1)
    return m



def observed_flakes(capture: Capture, particles: Particles, flake_id: Tensor, model: FlakeModel) -> ObservedFlakes | None:
    """Measure and keep every associated flake of the flake stage.

    Args:
        capture: the fitted :class:`~torchmetal.io.capture.Capture` (normals, lights, cameras, size).
        particles: the stage's :class:`~torchmetal.flakes.estimate.results.Particles` (P rows).
        flake_id: (P,) associated flake of each particle, −1 for particles left out.
        model: the fitted :class:`FlakeModel` (its ``glint_sigma``).

    Returns:
        :class:`ObservedFlakes`, or None when no particle is associated.
    """
    h, w = capture.images.shape[-2:]
    if flake_id is None or len(particles) == 0 or not bool((flake_id >= 0).any()):
        return None
    dt = torch.float64
    keep = torch.nonzero(flake_id >= 0, as_tuple=True)[0]
    p = particles.select(keep)
    fid = torch.unique(flake_id[keep], return_inverse=True)[1]
    j = int(fid.max()) + 1
    amp = p.amp.to(dt).clamp_min(1e-12)
    wsum = torch.zeros(j, dtype=dt, device=fid.device).index_add_(0, fid, amp)
    cy = torch.zeros(j, dtype=dt, device=fid.device).index_add_(0, fid, amp * p.cy.to(dt)) / wsum
    cx = torch.zeros(j, dtype=dt, device=fid.device).index_add_(0, fid, amp * p.cx.to(dt)) / wsum
    b, axes = _brightest_footprint(p, fid, j)
    row, col, half = _half_vectors(capture, cy, cx)
    hk = half[p.shot, :, fid]  # (P, 3)
    normal = normalize(torch.zeros(j, 3, dtype=dt, device=fid.device).index_add_(0, fid, amp.unsqueeze(1) * hk), dim=1)
    sig = float(model.glint_sigma)
    normal = _refine_normals(normal, hk, fid, amp, p.snr.to(dt), sig)
    detect_amp = _detect_amp(particles)
    prior = (model.extra.get("log_amp_mean"), model.extra.get("log_amp_std"))
    if detect_amp is not None and None not in prior:  # the flakes' brightness places tail-seen ones
        normal = _place_by_brightness(capture, p, fid, amp, normal, half, row, col, sig, prior, detect_amp)
    color = _colours(p, fid, amp, normal, hk, sig, torch.stack([cy, cx], 1), axes, b, (h, w),
                     prior if detect_amp is not None and None not in prior else None)
    f32 = torch.float32
    position = torch.stack([cy, cx], 1)
    return ObservedFlakes(
        position=position.to(f32), axes=axes.to(f32), angle=b.angle.to(f32), normal=normal.to(f32),
        color=color.to(f32), probe_lights=capture.lights.to(f32).cpu(), probe_cameras=capture.cameras.to(f32).cpu(),
        shape=(h, w), density=_density_map(position, h, w), detect_amp=detect_amp,
    )


def _brightest_footprint(p: Particles, fid: Tensor, j: int) -> tuple[Particles, Tensor]:
    """Each flake's brightest detection (the least noisy shape) and its footprint's semi-axes (J, 2)."""
    dt = torch.float64
    best = torch.full((j,), -1.0, dtype=dt, device=fid.device).scatter_reduce(0, fid, p.snr.to(dt), "amax")
    is_best = p.snr.to(dt) == best[fid]
    first = torch.full((j,), len(p), dtype=torch.int64, device=fid.device).scatter_reduce(
        0, fid[is_best], torch.arange(len(p), device=fid.device)[is_best], "amin")
    b = p.select(first)
    area = (b.flux.to(dt) / b.amp.to(dt).clamp_min(1e-12)).clamp(0.25, 50.0)
    lam1 = (b.major.to(dt) / 4) ** 2 - 1.0 / 12.0
    lam2 = (b.minor.to(dt) / 4) ** 2 - 1.0 / 12.0
    aspect = torch.sqrt(lam2.clamp_min(1e-3) / lam1.clamp_min(1e-3)).clamp(0.2, 1.0)
    a_ax, b_ax = _ellipse_axes(area, aspect)
    return b, torch.stack([a_ax, b_ax], 1)


def _half_vectors(capture: Capture, cy: Tensor, cx: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The flakes' centre pixels (row, col) and every shot's half vector there (N, 3, J)."""
    dt = torch.float64
    h, w = capture.images.shape[-2:]
    row = cy.floor().long().clamp(0, h - 1)
    col = cx.floor().long().clamp(0, w - 1)
    y = (0.5 - cy / h) * capture.size[1]
    x = (cx / w - 0.5) * capture.size[0]
    pts = torch.stack([x, y, torch.zeros_like(x)]).unsqueeze(1)  # (3, 1, J)
    nrm = capture.normals.to(dt)[:, row, col].unsqueeze(1)
    one = torch.ones_like(capture.intensities, dtype=dt)
    half = shading_geometry(nrm, capture.lights.to(dt), one, capture.cameras.to(dt), points=pts).half[:, :, 0]  # (N, 3, J)
    return row, col, half


def _place_by_brightness(capture: Capture, p: Particles, fid: Tensor, amp: Tensor, normal: Tensor, half: Tensor,
                         row: Tensor, col: Tensor, sig: float, prior: tuple, detect_amp: float) -> Tensor:
    """The normals placed by the flakes' known brightness and the shots that missed them
    (:func:`~torchmetal.flakes.estimate.placement.place_normals`)."""
    dt = torch.float64
    j = normal.shape[0]
    n_shot = half.shape[0]
    flat = p.shot * j + fid  # a flake detected twice in a shot: its brightest detection
    det = torch.zeros(n_shot * j, dtype=torch.bool, device=flat.device).index_fill_(0, flat, True).view(n_shot, j)
    log_a = torch.full((n_shot * j,), -50.0, dtype=dt, device=flat.device).scatter_reduce(0, flat, torch.log(amp), "amax").view(n_shot, j)
    wt = torch.zeros(n_shot * j, dtype=dt, device=flat.device).scatter_reduce(0, flat, p.snr.to(dt).clamp(1.0, 100.0) ** 2, "amax")
    valid = (capture.mask[0, row, col].unsqueeze(0) & ~capture.saturated[:, :, row, col].any(1)).to(det.device)
    return place_normals(normal, half, det, valid, log_a, wt.view(n_shot, j), sig, float(prior[0]),
                         float(prior[1]), detect_amp)


def _colours(p: Particles, fid: Tensor, amp: Tensor, normal: Tensor, hk: Tensor, sig: float, position: Tensor,
             axes: Tensor, b: Particles, shape: tuple[int, int], prior: tuple | None) -> Tensor:
    """The flakes' glint reflectances (J, 3), bounded (``prior``: the flakes' log-amplitude mean and spread
    when their brightness is known, else None)."""
    dt = torch.float64
    j = normal.shape[0]
    # colour: peak colour = c · w_peak · g_k  →  least squares over the detections
    g = torch.exp(-((normal[fid] - hk) ** 2).sum(1) / (2.0 * sig * sig))  # (P,)
    flake, _, wt = footprints(position, axes, b.angle.to(dt), *shape)
    w_peak = torch.zeros(j, dtype=dt, device=fid.device).scatter_reduce(0, flake, wt, "amax").clamp_min(0.05)
    num = torch.zeros(j, 3, dtype=dt, device=fid.device).index_add_(0, fid, g.unsqueeze(1) * p.peak.to(dt).clamp_min(0.0))
    den = torch.zeros(j, dtype=dt, device=fid.device).index_add_(0, fid, g * g).clamp_min(1e-12)
    color = num / (den * w_peak).unsqueeze(1)
    # a glint factor ≥ 1/2 at the brightest detection: c ≤ 2·peak/w_peak (a normal placed far off
    # the detections' half vectors must not turn a faint detection into a bright flake), or, with the
    # flakes' brightness known, up to its mean + 2 spreads (a flake placed by it)
    top = torch.zeros(j, 3, dtype=dt, device=fid.device).scatter_reduce_(0, fid.view(-1, 1).expand(-1, 3), p.peak.to(dt).clamp_min(0.0), "amax")
    scale = torch.full((j,), 2.0, dtype=dt, device=fid.device)
    if prior is not None:
        a_top = torch.zeros(j, dtype=dt, device=fid.device).scatter_reduce(0, fid, amp, "amax")
        bright = math.exp(float(prior[0]) + 2.0 * max(float(prior[1]), MIN_AMP_STD))
        scale = torch.maximum(scale, bright / a_top)
    return torch.minimum(color, scale.unsqueeze(1) * top / w_peak.unsqueeze(1)).clamp(0.0, MAX_COLOR)



def _detect_amp(particles: Particles) -> float | None:
    """The peak glint amplitude the detector fires at: the least SNR of all the stage's detections
    (its threshold k_hi) × their median local σ; None when there is none to measure."""
    sigma, snr = particles.sigma.double(), particles.snr.double()
    ok = torch.isfinite(sigma) & torch.isfinite(snr) & (sigma > 0) & (snr > 0)
    if not bool(ok.any()):
        return None
    return float(snr[ok].min() * sigma[ok].median())

