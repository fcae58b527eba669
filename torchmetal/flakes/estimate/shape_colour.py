"""Flake shape, size and colour from the flakes' brightest detections: the area log-normal,
the aspect and the paper's limit lines (:func:`fit_shapes`), and the colour mean and covariance
of the glint reflectance, its falloff corrected through the fitted amplitude distribution
(:func:`fit_colour`).
"""

from __future__ import annotations

import math

import torch

from torchmetal.errors import InputError
from torchmetal.flakes.estimate.association import FlakeObservations
from torchmetal.flakes.estimate.glint_model import GlintFit, truncated_moments


def fit_shapes(obs: FlakeObservations, *, min_snr: float = 8.0) -> dict:
    """Area log-normal, aspect normal and the paper's limit lines from the anchor detections.

    Uses flakes whose anchor SNR ≥ ``min_snr`` (all flakes when fewer than 20 pass).
    The flux/peak area of the rendered footprint is unbiased; its noise variance is removed
    from the log-area spread.
    """
    sel = obs.snr >= min_snr
    if int(sel.sum()) < 20:
        sel = torch.ones_like(sel)
    area = obs.area[sel].double()
    la = torch.log(area)
    # noise of flux/peak ≈ σ·√(n_pix)/amp with n_pix ≈ area + 3·√area (1-px dilation)
    npix = area + 3 * torch.sqrt(area) + 4
    noise_rel2 = npix / (obs.snr[sel].double() ** 2 * area**2)
    med = float(la.median())
    mad = float((la - med).abs().median()) * 1.4826
    var = max(mad**2 - float(noise_rel2.median()), 1e-4)
    asp = obs.aspect[sel].double()
    semi_major = obs.major[sel].double()
    # semi-major = b + k·√area by least squares in closed form (element-wise sums only: LAPACK's
    # lstsq changed the last bits from call to call with the memory alignment, so the same
    # inputs gave different models)
    x = torch.sqrt(area)
    xc = x - x.mean()
    k = (xc * (semi_major - semi_major.mean())).sum() / (xc * xc).sum().clamp_min(1e-300)
    b0 = semi_major.mean() - k * x.mean()
    resid = semi_major - (b0 + k * x)
    q = torch.quantile(resid, torch.tensor([0.05, 0.95], dtype=resid.dtype, device=resid.device))
    lines = (float(b0 + q[0]), float(k), float(b0 + q[1]), float(k))
    return {
        "area_log_mean": med, "area_log_std": math.sqrt(var),
        "aspect_mean": float(asp.mean().clamp(0.05, 1.0)), "aspect_std": float(asp.std().clamp(0.0, 1.0)) if asp.numel() > 1 else 0.0,
        "shape_lines": lines, "n": int(sel.sum()),
    }


def fit_colour(obs: FlakeObservations, fit: GlintFit, *, min_snr: float = 8.0,
               peak_weight: float = 1.0) -> tuple[tuple, tuple]:
    """Colour mean and covariance of the glint reflectance.

    The peak glint of a detection is A·g with g ≤ 1, so raw peaks underestimate the flake's
    colour; the glint falloff is corrected through the fitted amplitude distribution, and A itself is
    the colour times the brightest pixel's footprint weight (``peak_weight``, its mean:
    :func:`~torchmetal.flakes.model.field.mean_peak_weight`; below 1 for fine flakes, which the field
    renders with the same weights): mean = E[A | floor < A < ceiling] / peak_weight × mean chroma
    (chroma = colour / channel mean is independent of g; the ceiling, the brightest amplitude the
    detections support, bounds the colour by the data).
    Chroma outside [0, 3] per channel (a detection whose mean colour is ≈ 0 or negative: a
    texture edge, not a glint) is left out.
    """
    if not (math.isfinite(peak_weight) and 0.0 < peak_weight <= 1.0):
        raise InputError(f"fit_colour: expected a peak_weight in (0, 1], found {peak_weight!r}")
    plausible = ((obs.chroma >= 0) & (obs.chroma <= 3)).all(1)
    sel = (obs.snr >= min_snr) & plausible
    if int(sel.sum()) < 10:
        sel = plausible if int(plausible.sum()) >= 1 else torch.ones_like(sel)
    ch = obs.chroma[sel].double()
    mean_a, var_a = truncated_moments(fit.log_amp_mean, fit.log_amp_std, fit.log_amp_floor, fit.log_amp_ceiling)
    mean_a, var_a = mean_a / peak_weight, var_a / peak_weight**2
    cm = ch.mean(0)
    mean = (mean_a * cm).clamp_min(0.0)
    # chroma covariance minus its measurement noise (per channel ≈ √3·σ/(amp·√area)), PSD-clipped
    dev_ch = ch - ch.mean(0)  # covariance by element-wise sums, not a BLAS product (see fit_shapes)
    cov_ch = (dev_ch.unsqueeze(2) * dev_ch.unsqueeze(1)).sum(0) / max(ch.shape[0] - 1, 1)
    noise = (3.0 / (obs.snr[sel].double() ** 2 * obs.area[sel].double().clamp_min(1.0))).median()
    cov_ch = cov_ch - noise * torch.eye(3, dtype=ch.dtype, device=ch.device)
    ev, evec = torch.linalg.eigh(cov_ch)
    cov_ch = evec @ torch.diag(ev.clamp_min(0.0)) @ evec.t()
    cov = mean_a**2 * cov_ch + var_a * torch.outer(cm, cm)
    return tuple(float(v) for v in mean), tuple(tuple(float(v) for v in r) for r in cov)
