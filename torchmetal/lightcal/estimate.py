"""The light calibration's parameters from a fit's residuals (:mod:`torchmetal.lightcal`).

Where the calibrated model holds, photo = factor × render, so log(photo / render) = log g_k + p·log cos θ
per observation: a linear least-squares problem in the N log gains and the exponent, solved in closed
form. Observations are weighted by render² (the variance of a log ratio falls with the signal²) and
only where the render is above ``MIN_SIGNAL`` of its maximum (dark ones carry noise, not the light's
shape) and its specular part under ``MAX_SPECULAR`` of it: the light scales the diffuse and the specular
alike, but where a lobe misfits (one global lobe over two materials) the highlights' residuals would
bend the falloff to absorb it (the zoo's two_materials: a falloff "won" the left-out test by 6 % and cost
22 dB against the truth). Saturated and masked-out observations are left out. One step from a fit gives the correction
to that fit's calibration; :func:`calibrate` takes it and refits.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from torchmetal.fit.api import fit_phong
from torchmetal.fit.holdout import valid_pixels
from torchmetal.lightcal.model import LightCalibration, log_axis_cosine
from torchmetal.lightcal.positions import fit_offsets, move_capture

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture

MIN_SIGNAL = 0.02  # observations whose render is under this fraction of the brightest one are left out
MAX_FALLOFF = 40.0  # |p| beyond this is not a flash's beam: clamped (cos 16° ^ 40 ≈ 0.2)
MAX_SPECULAR = 0.05  # only observations whose fitted specular part is under 5 % of the render (module docstring)
POSITION_ROUNDS = 2  # offsets ↔ material alternations of calibrate_positions
MIN_SPREAD = 1e-6  # the log-cosines' weighted variance under which the exponent is not identifiable


def _diffuse_fit(fit: FitResult) -> FitResult:
    """``fit`` without its specular term (s = 0 everywhere)."""
    zero = lambda t: None if t is None else torch.zeros_like(t)  # noqa: E731
    return replace(fit, s=zero(fit.s), cluster_s=zero(fit.cluster_s), gloss_s=zero(fit.gloss_s))


def log_ratio_step(capture: Capture, fit: FitResult, *, gains: bool) -> tuple[float, torch.Tensor]:
    """The weighted least-squares (exponent, (N,) log gains with mean 0) of log(photo / render) on
    ``capture`` (module docstring); log gains all 0 when ``gains`` is False. float64 on the CPU."""
    with torch.no_grad():
        render = fit.render(capture.lights, capture.intensities, capture.cameras).double().cpu()
        diffuse = _diffuse_fit(fit).render(capture.lights, capture.intensities, capture.cameras).double().cpu()
    photo = capture.images.double().cpu()
    v = valid_pixels(capture).cpu() & (photo > 0) & (render > MIN_SIGNAL * render.amax().clamp_min(1e-12))
    v &= render - diffuse <= MAX_SPECULAR * render  # the lobe's misfit is not the light's
    w = torch.where(v, render * render, torch.zeros_like(render))
    y = torch.where(v, torch.log(photo.clamp_min(1e-12)) - torch.log(render.clamp_min(1e-12)), torch.zeros_like(render))
    x = log_axis_cosine(capture).cpu().expand_as(photo)
    n = photo.shape[0]
    sw, sx, sy = w.sum((1, 2, 3)), (w * x).sum((1, 2, 3)), (w * y).sum((1, 2, 3))
    sxx, sxy = (w * x * x).sum(), (w * x * y).sum()
    if gains:  # per-shot intercepts: eliminate them shot by shot
        ok = sw > 0
        mx = torch.where(ok, sx / sw.clamp_min(1e-300), torch.zeros_like(sx))
        my = torch.where(ok, sy / sw.clamp_min(1e-300), torch.zeros_like(sy))
        sxx_c, sxy_c = sxx - (sw * mx * mx).sum(), sxy - (sw * mx * my).sum()
    else:  # one intercept (the level: the texture's)
        tw = sw.sum().clamp_min(1e-300)
        mx, my = sx.sum() / tw, sy.sum() / tw
        sxx_c, sxy_c = sxx - tw * mx * mx, sxy - tw * mx * my
    spread = float(sxx_c / sw.sum().clamp_min(1e-300))
    p = float(sxy_c / sxx_c) if spread > MIN_SPREAD else 0.0
    p = max(-MAX_FALLOFF, min(MAX_FALLOFF, p))
    if not gains:
        return p, torch.zeros(n, dtype=torch.float64)
    b = torch.where(sw > 0, my - p * mx, torch.zeros_like(my))
    return p, b - b[sw > 0].mean() if bool((sw > 0).any()) else b


def calibrate(capture: Capture, fit: FitResult, *, gains: bool, fit_kwargs: dict | None = None,
              base: LightCalibration | None = None, refit: bool = True) -> tuple[LightCalibration, FitResult | None]:
    """One step of :func:`log_ratio_step` from ``fit`` (made on ``base.apply(capture)``), then (``refit``)
    the fit on the capture so calibrated. Returns (calibration, fit or None)."""
    base = base or LightCalibration()
    p, b = log_ratio_step(base.apply(capture), fit, gains=gains)
    log_g = torch.zeros(capture.num_shots, dtype=torch.float64) if base.gains is None else torch.log(
        torch.tensor(base.gains, dtype=torch.float64))
    cal = LightCalibration(base.falloff + p, tuple(torch.exp(log_g + b).tolist()) if gains else base.gains)
    return cal, fit_phong(cal.apply(capture), **(fit_kwargs or {})) if refit else None


def calibrate_positions(capture: Capture, *, fit_kwargs: dict | None = None, rounds: int = POSITION_ROUNDS,
                        base: LightCalibration | None = None, shared: bool = False,
                        first: FitResult | None = None) -> tuple[LightCalibration, FitResult]:
    """Per-shot light offsets (or, ``shared``, the flash's one move of every light:
    :func:`~torchmetal.lightcal.positions.fit_offsets`) alternated ``rounds`` times with the material's fit
    on ``capture`` (each fit on the lights the last offsets moved; the rounds keep the lobe of the first), on
    top of ``base``'s falloff and gains. Returns (calibration, the fit at its offsets)."""
    base = base or LightCalibration()
    kw = fit_kwargs or {}
    cap = base.apply(capture)
    fit, off = first if first is not None else fit_phong(cap, **kw), None
    kw = {**kw, "lobe": fit.lobe}  # the first fit's lobe (chosen there with lobe="auto") for the rounds
    for _ in range(rounds):
        off = fit_offsets(cap, lambda lights: fit.render(lights, cap.intensities, cap.cameras), off, shared=shared)
        fit = fit_phong(move_capture(cap, off), **kw)
    if shared:  # every point light's row holds the one move; added to the base's
        point = (capture.lights[:, 3] > 0).cpu()  # off lives on the CPU (fit_offsets)
        move = off[point][0] if bool(point.any()) else torch.zeros(3, dtype=torch.float64)
        prev = torch.tensor(base.flash or (0.0, 0.0, 0.0), dtype=torch.float64)
        return replace(base, flash=tuple((prev + move).tolist())), fit
    return replace(base, offsets=tuple(tuple(o) for o in off.tolist())), fit
