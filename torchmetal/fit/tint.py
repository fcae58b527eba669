"""A metal's specular, tinted like its base: s(p) = s_m ⊙ d(p), chosen on shots the fit did not see.

A dielectric coat reflects every colour alike (white s); a metal's highlight has the metal's colour. The
paper's model fits one s per channel for the whole sample, so on the shared embossed gold paper the gold
went into the diffuse and the specular came out bluish (s 0.10 / 0.14 / 0.16): the render's highlights were
white-blue where the photo's are gold (docs/design.md §4). Here every pixel's specular is its own texture
times a global per-channel factor s_m, under the Phong lobe with a global α:

    I_k(p) = E_k(p) · d(p) ⊙ (n·l_k + s_m ⊙ lobe_k(p; α))

Given (α, s_m) the texture is linear: per pixel and channel d = Σ_k w·a_k·y_k / Σ_k w·a_k² with
a_k = E_k·(n·l_k + s_m·lobe_k) (:func:`solve_texture`). The six global numbers (log α, log s_m) are fitted by
L-BFGS through autograd on that projected cost (:func:`fit_tint`), on a pixel grid of the capture
(:func:`~torchmetal.normals.choice.strided_capture`), started from the best of a small grid; the texture is
then solved at full resolution, a band of rows at a time (:func:`tinted_texture`). The result is a
:class:`~torchmetal.fit.result.FitResult` with gloss maps s = s_m ⊙ d, α everywhere the same
(:func:`tinted_fit`), so the material, its renderer, ONNX and every export need nothing new.

Only when asked for (``tint="on"``), not chosen by default: on the gold paper it explains the photos it was
fitted on better (in-sample 18.62 → 19.40 dB) but not the shots left out (leave-one-out 17.48 → 17.46 dB,
chroma-artifact share 10.3 → 13.2 %), although a test on a pixel grid preferred it (per-pixel median
held-out error −11.6 %, z 17.8): docs/design.md §4.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.fit.holdout import valid_pixels
from torchmetal.geometry import shading_geometry, surface_points
from torchmetal.normals.choice import strided_capture
from torchmetal.phong import specular_lobe

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture

TINT_MODES = ("off", "on")
PIXELS = 128 * 128  # the pixel grid of the (α, s_m) fit
ALPHAS = (4.0, 16.0, 64.0, 256.0, 1024.0)  # start grid of α (the fit's own α is tried too)
STRENGTHS = (0.3, 1.0, 3.0, 10.0)  # start grid of s_m
MAX_LOG_ALPHA = math.log(1e4)
ITERS = 100  # L-BFGS iterations
ROWS = 64  # rows per band of the full-resolution texture solve


def _terms(capture: Capture, rows: slice | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """(E (N,3,h,W), n·l ≥ 0 (N,1,h,W), q = 1 − r·v (N,1,h,W), weights (N,3,h,W), photos (N,3,h,W)) in float64,
    for the rows ``rows`` (all by default). Weights: 1 where valid (mask, not saturated) and lit."""
    dt = torch.float64
    rows = rows if rows is not None else slice(None)
    h, w = capture.images.shape[-2:]
    pts = surface_points(h, w, capture.size, dtype=dt, device=capture.images.device)[:, rows]
    geom = shading_geometry(capture.normals.to(dt)[:, rows], capture.lights.to(dt), capture.intensities.to(dt),
                            capture.cameras.to(dt), points=pts)
    lit = geom.n_dot_l > 0
    wts = (valid_pixels(capture)[..., rows, :] & lit).to(dt)
    return geom.irradiance, geom.n_dot_l.clamp_min(0.0), geom.spec_q, wts, capture.images[..., rows, :].to(dt)


def _coefficient(e: Tensor, nl: Tensor, q: Tensor, log_alpha: Tensor, log_sm: Tensor) -> Tensor:
    """a = E·(n·l + s_m·lobe(α)) (N, 3, h, W): the texture's coefficient."""
    lobe = specular_lobe(q, log_alpha.clamp(max=MAX_LOG_ALPHA).exp()) * (nl > 0)
    return e * (nl + log_sm.exp().view(1, -1, 1, 1) * lobe)


def solve_texture(a: Tensor, y: Tensor, wts: Tensor) -> tuple[Tensor, Tensor]:
    """The least-squares texture (3, h, W) ≥ 0 given its coefficients ``a`` (N, 3, h, W), and where a pixel
    had an observation (3, h, W) bool."""
    den = (wts * a * a).sum(0)
    seen = den > 0
    return ((wts * a * y).sum(0) / den.clamp_min(1e-300)).clamp_min(0.0), seen


def _cost(terms, log_alpha: Tensor, log_sm: Tensor) -> Tensor:
    e, nl, q, wts, y = terms
    a = _coefficient(e, nl, q, log_alpha, log_sm)
    d, _ = solve_texture(a, y, wts)
    r = (y - a * d) * wts
    return (r * r).sum()


def fit_tint(capture: Capture, alpha0: Tensor | None = None, *, iters: int = ITERS) -> tuple[Tensor, Tensor]:
    """(α (3,), s_m (3,)) float64 of the tinted model on ``capture`` (use a pixel grid: every pixel's
    geometry is held at once). One s_m for the three channels: the highlight has the texture's hue (a free
    s_m per channel made the gold paper's highlights blue, s_m 0.49 / 1.18 / 10.9). Started from the best
    of :data:`ALPHAS` (and ``alpha0``) × :data:`STRENGTHS`."""
    terms = _terms(capture)
    dev = capture.images.device
    alphas = list(ALPHAS) + ([float(a) for a in alpha0.flatten()[:3].tolist()] if alpha0 is not None else [])
    best = None
    with torch.no_grad():
        for a0 in alphas:
            for s0 in STRENGTHS:
                la = torch.full((3,), math.log(max(a0, 1e-3)), dtype=torch.float64, device=dev)
                ls = torch.full((1,), math.log(s0), dtype=torch.float64, device=dev)
                c = float(_cost(terms, la, ls))
                if best is None or c < best[0]:
                    best = (c, la, ls)
    la, ls = (t.clone().requires_grad_(True) for t in best[1:])
    opt = torch.optim.LBFGS([la, ls], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        c = _cost(terms, la, ls)
        c.backward()
        return c

    opt.step(closure)
    la, ls = la.detach(), ls.detach()
    if not (torch.isfinite(la).all() and torch.isfinite(ls).all()):  # keep the grid's best
        la, ls = best[1], best[2]
    return la.clamp(max=MAX_LOG_ALPHA).exp(), ls.exp().expand(3).contiguous()


def tinted_texture(capture: Capture, alpha: Tensor, s_m: Tensor, *, rows: int = ROWS) -> Tensor:
    """The full-resolution texture (3, H, W) float64 under (α, s_m), solved a band of ``rows`` rows at a
    time; a pixel no shot saw gets the median of the seen ones (per channel)."""
    h = int(capture.images.shape[-2])
    la, ls = torch.log(alpha.double()), torch.log(s_m.double())
    bands, seen = [], []
    for r0 in range(0, h, rows):
        e, nl, q, wts, y = _terms(capture, slice(r0, min(h, r0 + rows)))
        d, ok = solve_texture(_coefficient(e, nl, q, la, ls), y, wts)
        bands.append(d)
        seen.append(ok)
    d, ok = torch.cat(bands, 1), torch.cat(seen, 1)
    for c in range(3):
        fill = d[c][ok[c]].median() if bool(ok[c].any()) else d.new_zeros(())
        d[c] = torch.where(ok[c], d[c], fill)
    return d


def tinted_fit(capture: Capture, fit: FitResult, *, max_pixels: int = PIXELS) -> FitResult:
    """``fit`` with the tinted specular (module docstring): (α, s_m) fitted on the capture's pixel grid from
    ``fit``'s α, the texture at full resolution, s = s_m ⊙ d as gloss maps (s, α hold their means)."""
    t0 = time.perf_counter()
    alpha, s_m = fit_tint(strided_capture(capture, max_pixels), fit.alpha.detach().double())
    texture = tinted_texture(capture, alpha, s_m)
    dt = fit.texture.dtype
    gloss_s = (s_m.view(3, 1, 1) * texture).to(dt)
    inside = capture.mask.bool().reshape(-1)
    s_mean = gloss_s.reshape(3, -1)[:, inside].mean(1) if bool(inside.any()) else gloss_s.reshape(3, -1).mean(1)
    a = alpha.to(dt)
    return replace(fit, texture=texture.to(dt), s=s_mean, alpha=a, gloss_s=gloss_s,
                   gloss_alpha=a.view(3, 1, 1).expand_as(gloss_s).contiguous(), spec_labels=None, cluster_s=None,
                   cluster_alpha=None, lobe="phong", specular="tinted",
                   stage_times={**fit.stage_times, "tint": time.perf_counter() - t0})


def tint_factor(fit: FitResult) -> list[float] | None:
    """The fitted s_m (3,) of a tinted fit (gloss_s / texture where the texture is not 0), else None."""
    if fit.specular != "tinted" or fit.gloss_s is None:
        return None
    d, s = fit.texture.reshape(3, -1).double(), fit.gloss_s.reshape(3, -1).double()
    ok = d > 1e-6
    return [float((s[c][ok[c]] / d[c][ok[c]]).median()) if bool(ok[c].any()) else 0.0 for c in range(3)]
