"""How sure is each fitted number: intervals for s, α (per channel, per cluster) and the texture (per pixel).

``fit_uncertainty(fit, capture, UncertaintyOptions()) -> dict`` (JSON-able, the material report's
``"uncertainty"``); :func:`estimate_uncertainty` returns the same as an :class:`Uncertainty` with the
texture's standard deviation kept as a tensor (on the pass's grid; ``texture_map=True`` for every pixel).

**Curvature (Gauss–Newton / Laplace).** The model I = a·d + s·b(β), β = log α (docs/design.md §2.2), is
linear in the texture d (one unknown per pixel and channel) and in s. With the texture profiled out —
the Schur complement the solver itself uses (:mod:`torchmetal.fit.refine`) — each element (channel,
cluster) keeps two unknowns θ = (s, β) with the projected Jacobian columns

    b⊥ = b − a·e_b,   c⊥ = s·(∂b/∂β − a·e_c),   e_x = Σ w·a·x / Σ w·a²   (per pixel),

whose normal matrix H = Σ w·[b⊥ c⊥]ᵀ[b⊥ c⊥] is the LM's own at the solution. The covariance is the
sandwich H⁻¹·(Σ w²·v·[b⊥ c⊥]ᵀ[b⊥ c⊥])·H⁻¹, with v the noise variance of each observation: exact to first
order whatever weights w the fit used (uniform, or its noise weights), and equal to v·H⁻¹ when w = 1/v.
The texture's own part is its per-pixel normal equation, Σ w²·a²·v / (Σ w·a²)², plus the globals'
uncertainty carried by d = d0 − s·e_b: eᵀ·Cov(θ)·e with e = (e_b, s·e_c).

**Noise variance from the residuals.** v is a function of the model value ŷ per channel (shot noise, an
8-bit sRGB step that grows with the value: the same dependence as :func:`~torchmetal.fit.refine.noise_model`),
estimated from the fit's residuals r in quantile bins of ŷ as the bin's mean of r²/(1 − h), where
h = w·a²/Σ w·a² is the observation's leverage on its pixel's texture: a pixel seen by N shots spends one
of its N residual degrees of freedom on its texture, so plain r² would understate v by about 1/N (25 % at
4 shots) and the intervals would not cover. Between bins v is interpolated linearly (clamped at the ends).
The mean, not a median: a glint's residual is part of the error the texture really has there.

**A pixel budget.** The pass runs on a strided grid of at most ``max_pixels`` (2^15) pixels; H and M are sums
over pixels, so the grid's are scaled by each element's full/grid pixel count (the sandwich covariance shrinks
by that factor: the information of the whole capture). The texture's standard deviation is per pixel and
does not depend on the stride; it is known on the grid (the report keeps its median and p90), and
``texture_map=True`` runs the pass on every pixel for the exact map (on 1 MP × 7, 2026-12-06, load 7.3 on 2
cores: 0.13–0.18 s on the grid against 1.5–1.7 s for the fit, 8.5–11 %; 3–6 s for every pixel).

**Where curvature is not valid**, refits with shots left out (jackknife over shots): an element at a
bound (α at 1 or 10⁴, s at 0) or with a singular H. Each refit is the variable-projection LM
(:func:`~torchmetal.fit.refine.fit_specular`) on a subsample with the fit's clusters held, started at the
fit's α; the variance is (N−1)/N·Σ(θ_i − θ̄)² and the interval uses Student's t with N−1 degrees of
freedom (N shots give N−1 independent differences). An estimate at a bound keeps the bound as that side
of its interval (a mirror's α is "at least"). ``jackknife="always"`` reports both for every element.

Not covered here: the normals where estimated, the flake statistics (their likelihood is not a least
squares; a jackknife over the flake stage is the way, not done yet), and gloss maps (per-pixel s, α with
a smoothness prior: only the texture's local part is given, ``globals`` is None).
Intervals assume the model is right: a lobe the fit cannot represent biases s and α beyond them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.fit.lobes import lobe_terms
from torchmetal.fit.problem import build_observations, grid_stride
from torchmetal.fit.refine import ALPHA_MAX, ALPHA_MIN, BETA_MAX, BETA_MIN, fit_specular

if TYPE_CHECKING:
    from torchmetal.fit.problem import Observations
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture

JACKKNIFE_MODES = ("bounds", "always", "off")
BOUND_TOL = 1e-4  # β within this of a bound, or s below this fraction of its channel's largest: at a bound
SINGULAR_REL = 1e-9  # det H / (H_ss·H_ββ) below this: s and β not separable, curvature not valid
KEEP_OBSERVATIONS = 1 << 21  # pixels × shots up to which the grid's per-chunk terms are kept for both passes (~120 MB)


@dataclass(frozen=True)
class UncertaintyOptions:
    """level: two-sided probability of the intervals; max_pixels: pixel budget of the curvature pass (a
    stride beyond it: the global sums H, M are scaled to the full pixel count, the texture's standard
    deviation is known on the grid — its summary is the grid's, its map spreads each grid pixel to its
    stride block); texture_map: run the pass on every pixel instead (the exact per-pixel map of the
    texture's standard deviation, at the cost of a pass over the whole capture: 5 s on 1 MP × 7, twice the
    fit); bins: quantile bins of the noise variance's model; jackknife: "bounds" (refits where curvature
    is not valid), "always", "off"; jackknife_pixels: pixel budget of each refit; samples: residuals kept
    per channel for the variance model.

    Why 2^15 pixels: the pipeline runs this after every fit and issue 41 wants every extra stage cheap
    (≤ ~10 % of the fit). The curvature of s and α is a sum over the pixels the highlight crosses; a
    uniform grid of 2^15 of them estimates it (scaled by full/grid pixels) to well under its own interval
    (1 MP × 7, 2026-12-06: s and log α std within 2 % of the every-pixel pass at 2^14–2^16; calibration
    holds at 2^10, bench ``uncertainty``), and the texture's std is a smooth function of the local shading
    and value, so its median and p90 from the grid are the image's."""

    level: float = 0.9
    max_pixels: int = 1 << 15
    texture_map: bool = False
    bins: int = 16
    jackknife: str = "bounds"
    jackknife_pixels: int = 1 << 14
    samples: int = 1 << 16

    def checked(self) -> UncertaintyOptions:
        if not 0.0 < self.level < 1.0:
            raise InputError(f"UncertaintyOptions.level: expected a probability in (0, 1), found {self.level}")
        if self.jackknife not in JACKKNIFE_MODES:
            raise InputError(f"UncertaintyOptions.jackknife: expected one of {JACKKNIFE_MODES}, found {self.jackknife!r}")
        if self.max_pixels < 1 or self.jackknife_pixels < 1 or self.bins < 2:
            raise InputError(f"UncertaintyOptions: expected max_pixels, jackknife_pixels >= 1 and bins >= 2, found "
                             f"{self.max_pixels}, {self.jackknife_pixels}, {self.bins}")
        return self


@dataclass
class Uncertainty:
    """The intervals of one fit.

    Attributes:
        level: the intervals' probability.
        s, alpha: (K, 3) the fitted elements (clusters × channels; K = 1 for a global specular).
        s_std, beta_std, cov_sb: (K, 3) standard deviations of s and β = log α, and their covariance
            (curvature; NaN where not valid).
        s_lo, s_hi, alpha_lo, alpha_hi: (K, 3) the intervals (α's from β's, so asymmetric).
        method: K × 3 nested lists of "curvature" | "jackknife" | "bound" (at a bound, jackknife off or under
            3 shots: the interval is the curvature's where it exists, else the point) | "unseen" (no highlight
            evidence: s in [0, ∞), α anywhere; JSON null for ∞).
        jack_s_std, jack_beta_std: (K, 3) jackknife standard deviations, or None when none ran.
        texture_grid: (3, h, w) standard deviation of the texture on the pass's grid (every ``stride``-th
            pixel from ``stride // 2``; inf where no shot saw it); :attr:`texture_std` is the (3, H, W) map.
        stride: the grid's stride (1: every pixel, ``UncertaintyOptions.texture_map``).
        size_hw: (H, W) of the capture.
        noise: {"y": (3, B) bin values, "var": (3, B) variance} — the model of v(ŷ).
        shots: shots the fit saw.
    """

    level: float
    s: Tensor
    alpha: Tensor
    s_std: Tensor
    beta_std: Tensor
    cov_sb: Tensor
    s_lo: Tensor
    s_hi: Tensor
    alpha_lo: Tensor
    alpha_hi: Tensor
    method: list
    texture_grid: Tensor
    noise: dict
    shots: int
    stride: int = 1
    size_hw: tuple[int, int] | None = None
    jack_s_std: Tensor | None = None
    jack_beta_std: Tensor | None = None
    globals_: bool = True

    @property
    def z(self) -> float:
        return NormalDist().inv_cdf(0.5 + 0.5 * self.level)

    @property
    def texture_std(self) -> Tensor:
        """(3, H, W) float32 standard deviation of the texture per pixel: exact with ``stride`` 1, else each grid
        pixel's value spread over its stride block (made on each call: 1 MP is 12 MB)."""
        return _full_resolution(self.texture_grid, self.stride, *(self.size_hw or self.texture_grid.shape[-2:]))

    def texture_interval(self, texture: Tensor) -> tuple[Tensor, Tensor]:
        """(lo, hi) (3, H, W) of the fitted ``texture`` (3, H, W)."""
        half = self.z * self.texture_std.to(texture.dtype)
        return texture - half, texture + half

    def to_dict(self) -> dict:
        """JSON-able: per element value, interval and ± (half its width), the texture's summary."""
        r = lambda t, n=6: [[round(float(v), n) if math.isfinite(v) else None for v in row] for row in t.tolist()]  # noqa: E731
        # the summary from the grid: each grid pixel stands for its stride block (unseen counted in full pixels)
        grid = self.texture_grid.reshape(3, -1)
        fin = torch.isfinite(grid)
        tex = {}
        for c, name in enumerate("rgb"):
            v = grid[c][fin[c]]
            q = None if v.numel() == 0 else torch.quantile(v.float()[:: max(1, v.numel() // 16384)],
                                                           torch.tensor([0.5, 0.9])).tolist()
            tex[name] = None if q is None else {"std_median": q[0], "std_p90": q[1], "unseen": int((~fin[c]).sum()) * self.stride**2}
        out = {"level": self.level, "shots": self.shots, "texture": tex, "stride": self.stride,
               "noise": {"y": r(self.noise["y"], 6), "var": r(self.noise["var"], 9)}}
        if not self.globals_:
            out["globals"] = None
            return out
        out["globals"] = {
            "s": {"value": r(self.s), "lo": r(self.s_lo), "hi": r(self.s_hi), "std": r(self.s_std),
                  "pm": r((self.s_hi - self.s_lo) / 2)},
            "alpha": {"value": r(self.alpha, 3), "lo": r(self.alpha_lo, 3), "hi": r(self.alpha_hi, 3),
                      "std_log": r(self.beta_std), "pm": r((self.alpha_hi - self.alpha_lo) / 2, 3)},
            "cov_s_log_alpha": r(self.cov_sb, 9),
            "method": self.method,
            "jackknife": None if self.jack_s_std is None else {"s_std": r(self.jack_s_std), "std_log_alpha": r(self.jack_beta_std)},
        }
        return out


def fit_uncertainty(fit: FitResult, capture: Capture, options: UncertaintyOptions | None = None) -> dict:
    """JSON-able intervals of ``fit`` on ``capture`` (the capture it was fitted to): :meth:`Uncertainty.to_dict`."""
    return estimate_uncertainty(fit, capture, options).to_dict()


def estimate_uncertainty(fit: FitResult, capture: Capture, options: UncertaintyOptions | None = None) -> Uncertainty:
    """The intervals of ``fit`` (module docstring): curvature with the texture profiled out, a jackknife over
    shots where curvature is not valid. ``capture`` must be the one fitted (same size, shots, normals)."""
    o = (options or UncertaintyOptions()).checked()
    if tuple(fit.texture.shape[-2:]) != (capture.height, capture.width):
        raise InputError(f"fit_uncertainty: expected a capture of the fit's size {tuple(fit.texture.shape[-2:])}, "
                         f"found {(capture.height, capture.width)}")
    stride = 1 if o.texture_map else grid_stride(capture.height, capture.width, o.max_pixels)
    # every pixel: streamed (stored geometry would weigh as much as the capture); a grid: stored, and its chunks'
    # terms kept between the two passes (noise model, curvature) when they are small
    obs = build_observations(capture, stride=stride, lobe=fit.lobe, stream=stride == 1)
    grid = _grid_fit(fit, obs, stride)
    small = obs.num_pixels * obs.num_shots <= KEEP_OBSERVATIONS
    chunks = list(_chunks(obs, grid)) if small else None
    noise = _noise_model(obs, grid, o, chunks)
    sums = _scaled(_curvature_sums(obs, grid, noise, chunks), _pixel_scale(fit, capture, grid, stride))
    k = grid["k"]
    s_el, a_el = _elements(fit)
    beta = torch.log(a_el.double())
    cov = _sandwich(sums["H"], sums["M"])  # (K, 3, 2, 2)
    var_s_only = sums["M"][..., 0, 0] / sums["H"][..., 0, 0].clamp_min(1e-300) ** 2  # β held: s alone
    at_bound = (beta <= BETA_MIN + BOUND_TOL) | (beta >= BETA_MAX - BOUND_TOL) | (
        s_el.double() <= BOUND_TOL * s_el.double().amax(0, keepdim=True).clamp_min(1e-12))
    valid = ~at_bound & torch.isfinite(cov).all(-1).all(-1) & (cov[..., 0, 0] >= 0) & (cov[..., 1, 1] >= 0)
    s_std = torch.where(valid, cov[..., 0, 0].clamp_min(0).sqrt(), torch.full_like(beta, math.nan))
    b_std = torch.where(valid, cov[..., 1, 1].clamp_min(0).sqrt(), torch.full_like(beta, math.nan))
    cov_sb = torch.where(valid, cov[..., 0, 1], torch.full_like(beta, math.nan))
    z = NormalDist().inv_cdf(0.5 + 0.5 * o.level)
    jack = None
    if fit.specular == "none":  # no highlight evidence: the photos bound neither s from above nor α
        return _unseen(capture, o, sums, grid, obs, stride, noise, s_el, a_el)
    if grid["globals"] and o.jackknife != "off" and capture.num_shots >= 3 and (o.jackknife == "always" or not bool(valid.all())):
        jack = _jackknife(fit, capture, o)
    half_s, half_b = z * s_std, z * b_std
    method = [["curvature" if bool(valid[i, c]) else "bound" for c in range(3)] for i in range(k)]
    if jack is not None:
        t = _student_t(0.5 + 0.5 * o.level, capture.num_shots - 1)
        use = ~valid
        half_s = torch.where(use, t * jack[0], half_s)
        half_b = torch.where(use, t * jack[1], half_b)
        for i in range(k):
            for c in range(3):
                if bool(use[i, c]):
                    method[i][c] = "jackknife"
    s64 = s_el.double()
    half_s0 = torch.nan_to_num(half_s, nan=0.0)
    half_b0 = torch.nan_to_num(half_b, nan=0.0)
    s_lo, s_hi = (s64 - half_s0).clamp_min(0.0), s64 + half_s0
    lo_b, hi_b = beta - half_b0, beta + half_b0
    lo_b = torch.where(beta <= BETA_MIN + BOUND_TOL, torch.full_like(beta, BETA_MIN), lo_b)
    hi_b = torch.where(beta >= BETA_MAX - BOUND_TOL, torch.full_like(beta, BETA_MAX), hi_b)
    s_lo = torch.where(s64 <= BOUND_TOL * s64.amax(0, keepdim=True).clamp_min(1e-12), torch.zeros_like(s64), s_lo)
    a_lo, a_hi = torch.exp(lo_b).clamp(ALPHA_MIN, ALPHA_MAX), torch.exp(hi_b).clamp(ALPHA_MIN, ALPHA_MAX)
    # the texture: its local part plus the globals' part carried through d = d0 − s·e_b
    var_s = torch.where(valid, cov[..., 0, 0], torch.where(torch.isfinite(var_s_only), var_s_only, torch.zeros_like(beta)))
    var_b = torch.where(valid, cov[..., 1, 1], torch.zeros_like(beta))
    c_sb = torch.where(valid, cov[..., 0, 1], torch.zeros_like(beta))
    if jack is not None:
        var_s = torch.where(valid, var_s, jack[0] ** 2)
        var_b = torch.where(valid, var_b, jack[1] ** 2)
    tex_std = _texture_variance(sums, grid, var_s, var_b, c_sb).sqrt().float().view(3, obs.height, obs.width)
    return Uncertainty(
        level=o.level, s=s64, alpha=a_el.double(), s_std=s_std, beta_std=b_std, cov_sb=cov_sb, s_lo=s_lo, s_hi=s_hi,
        alpha_lo=a_lo, alpha_hi=a_hi, method=method, texture_grid=tex_std, noise=noise, shots=capture.num_shots,
        stride=stride, size_hw=(capture.height, capture.width), jack_s_std=None if jack is None else jack[0], jack_beta_std=None if jack is None else jack[1],
        globals_=grid["globals"],
    )


def _unseen(capture: Capture, o: UncertaintyOptions, sums: dict, grid: dict, obs: Observations, stride: int,
            noise: dict, s_el: Tensor, a_el: Tensor) -> Uncertainty:
    """The intervals of a fit that found no highlight (``specular="none"``, s = 0): s in [0, ∞) and α anywhere in
    its range — a specular term whose highlight no shot saw is not measured, and saying so is the honest
    answer (the capture plan's job is the shot that sees it). The texture keeps its local part."""
    k = int(s_el.shape[0])
    nan = torch.full((k, 3), math.nan, dtype=torch.float64)
    zeros = torch.zeros(k, 3, dtype=torch.float64)
    tex_std = _texture_variance(sums, grid, zeros, zeros, zeros).sqrt().float().view(3, obs.height, obs.width)
    return Uncertainty(
        level=o.level, s=s_el.double(), alpha=a_el.double(), s_std=nan, beta_std=nan, cov_sb=nan, s_lo=zeros,
        s_hi=torch.full_like(zeros, math.inf), alpha_lo=torch.full_like(zeros, ALPHA_MIN),
        alpha_hi=torch.full_like(zeros, ALPHA_MAX), method=[["unseen"] * 3 for _ in range(k)], texture_grid=tex_std,
        noise=noise, shots=capture.num_shots, stride=stride, size_hw=(capture.height, capture.width),
        globals_=grid["globals"])


# --------------------------------------------------------------------------------------- the passes


def _elements(fit: FitResult) -> tuple[Tensor, Tensor]:
    """(s, α) (K, 3) of the fit's elements: clusters, or the global terms (K = 1)."""
    if fit.spec_labels is not None and fit.cluster_s is not None:
        return fit.cluster_s.detach(), fit.cluster_alpha.detach()
    return fit.s.detach().view(1, 3), fit.alpha.detach().view(1, 3)


def _grid_fit(fit: FitResult, obs: Observations, stride: int) -> dict:
    """The fit on the observations' grid: texture, s and α per pixel (3, P) or (3, 1), labels (P,) or None."""
    off = stride // 2 if stride > 1 else 0
    on = lambda t: t[..., off::stride, off::stride].reshape(*t.shape[:-2], -1)  # noqa: E731
    tex = on(fit.texture.detach()).double()
    s_map, a_map = fit.specular_maps()
    gloss = fit.gloss_s is not None
    labels = None
    if s_map.dim() == 1:
        s_pix, a_pix = s_map.detach().double().view(3, 1), a_map.detach().double().view(3, 1)
    else:
        s_pix, a_pix = on(s_map.detach()).double(), on(a_map.detach()).double()
        if not gloss:
            labels = on(fit.spec_labels).long()
    k = 1 if labels is None else int(fit.cluster_s.shape[0])
    return {"tex": tex, "s": s_pix, "alpha": a_pix, "labels": labels, "k": k, "globals": not gloss,
            "noise_w": fit.noise}


def _chunks(obs: Observations, grid: dict):
    """Per chunk: (p0, p1, y, a, b, t, w, pred) in float64, (n, 3, c) each; w the fit's weights (validity, times
    its noise weights when it used them)."""
    nw = grid["noise_w"]
    for j, (p0, p1) in enumerate(obs.chunks):
        y, g, u, L, w, inten = obs.chunk(j)
        geo = obs.geo_chunk(j)
        sl = lambda t: t if t.shape[-1] == 1 else t[:, p0:p1]  # noqa: E731
        s, al = sl(grid["s"]).unsqueeze(0), sl(grid["alpha"]).unsqueeze(0)
        a, b, t = lobe_terms(g.double(), u.double(), L.double(), inten.double(), al, None if geo is None else geo.double(),
                             obs.lobe)
        pred = a * grid["tex"][:, p0:p1].unsqueeze(0) + s * b
        w = w.double()
        if nw is not None:  # the fit's noise weights a/(a + b·ŷ) (torchmetal.fit.problem.Weighting.noise_weight)
            va = torch.as_tensor(nw["a"], dtype=torch.float64).view(1, 3, 1)
            vb = torch.as_tensor(nw["b"], dtype=torch.float64).view(1, 3, 1)
            w = w * (va / (va + vb * pred.clamp_min(0.0))).clamp_min(1e-3)
        yield p0, p1, y.double(), a, b, t, w, pred, s


def _noise_model(obs: Observations, grid: dict, o: UncertaintyOptions, chunks: list | None = None) -> dict:
    """v(ŷ) per channel: bins of the model value, each bin's mean of r²/(1 − h) (module docstring). ``chunks``:
    :func:`_chunks`'s output kept (else recomputed)."""
    xs: list[list[Tensor]] = [[], [], []]
    rs: list[list[Tensor]] = [[], [], []]
    budget = max(64, o.samples // max(1, len(obs.chunks)))
    for _, _, y, a, _, _, w, pred, _ in chunks if chunks is not None else _chunks(obs, grid):
        # a subsample of whole pixels (every step-th column: a pixel's leverage needs all its shots), drawn
        # before any arithmetic — the variance model needs ~samples residuals, not the grid's millions
        step = max(1, y.shape[0] * y.shape[-1] // budget)
        y, a, w, pred = (x[..., ::step] for x in (y, a, w, pred))
        saa = (w * a * a).sum(0, keepdim=True)
        h = torch.where(saa > 0, w * a * a / saa.clamp_min(1e-300), torch.ones_like(a))
        r2 = (y - pred) ** 2 / (1.0 - h).clamp_min(1e-3)
        ok = (w > 0) & (h < 0.99)
        for c in range(3):
            m = ok[:, c]
            xs[c].append(pred[:, c][m])
            rs[c].append(r2[:, c][m])
    ys, vs = [], []
    for c in range(3):
        x = torch.cat(xs[c]) if xs[c] else torch.zeros(0, dtype=torch.float64)
        e = torch.cat(rs[c]) if rs[c] else torch.zeros(0, dtype=torch.float64)
        if x.numel() < 2 * o.bins:
            ys.append(torch.tensor([0.0, 1.0], dtype=torch.float64).repeat_interleave(o.bins // 2 + o.bins % 2)[: o.bins])
            vs.append(torch.full((o.bins,), float(e.mean()) if e.numel() else 0.0, dtype=torch.float64))
            continue
        order = torch.argsort(x)
        parts = torch.tensor_split(order, o.bins)
        ys.append(torch.stack([x[i].mean() for i in parts]))
        vs.append(torch.stack([e[i].mean() for i in parts]))
    return {"y": torch.stack(ys), "var": torch.stack(vs).clamp_min(0.0)}


def noise_variance(noise: dict, pred: Tensor) -> Tensor:
    """v(ŷ) for model values ``pred`` (n, 3, c): the piecewise-linear model of :func:`_noise_model`, clamped at
    its end bins."""
    out = torch.empty_like(pred)
    for c in range(3):
        x, v = noise["y"][c].to(pred).contiguous(), noise["var"][c].to(pred)
        dx = x[1:] - x[:-1]
        slope = torch.where(dx > 0, (v[1:] - v[:-1]) / dx.clamp_min(1e-300), torch.zeros_like(dx))  # per segment
        p = pred[:, c].clamp(float(x[0]), float(x[-1])).contiguous()
        i = (torch.searchsorted(x, p) - 1).clamp(0, x.numel() - 2)  # the segment [x_i, x_i+1] holding p
        out[:, c] = v[i] + slope[i] * (p - x[i])
    return out


def _curvature_sums(obs: Observations, grid: dict, noise: dict, chunks: list | None = None) -> dict:
    """Per element H and M (K, 3, 2, 2) (module docstring) and per pixel: the texture's local variance, e_b and
    s·e_c (3, P) and each pixel's element (P,) or None. ``chunks``: :func:`_chunks`'s output kept."""
    k, labels = grid["k"], grid["labels"]
    p = obs.num_pixels
    H = torch.zeros(3, k, 3, dtype=torch.float64)  # (channel, element, [bb, bc, cc])
    M = torch.zeros_like(H)
    local = torch.zeros(3, p, dtype=torch.float64)
    eb_all, ec_all = torch.zeros_like(local), torch.zeros_like(local)
    for p0, p1, _, a, b, t, w, pred, s in chunks if chunks is not None else _chunks(obs, grid):
        v = noise_variance(noise, pred)
        wa = w * a
        saa = (wa * a).sum(0)
        inv = torch.where(saa > 0, 1.0 / saa.clamp_min(1e-300), torch.zeros_like(saa))
        tb = t * b
        eb, ec = (wa * b).sum(0) * inv, (wa * tb).sum(0) * inv
        bp = b - a * eb
        cp = s * (tb - a * ec)
        ww = w * w * v
        h = torch.stack([(w * bp * bp).sum(0), (w * bp * cp).sum(0), (w * cp * cp).sum(0)], -1)  # (3, c, 3)
        m = torch.stack([(ww * bp * bp).sum(0), (ww * bp * cp).sum(0), (ww * cp * cp).sum(0)], -1)
        local[:, p0:p1] = torch.where(saa > 0, (ww * a * a).sum(0) * inv * inv, torch.full_like(saa, math.inf))
        eb_all[:, p0:p1] = eb
        ec_all[:, p0:p1] = s[0] * ec
        if labels is None:
            H[:, 0] += h.sum(1)
            M[:, 0] += m.sum(1)
        else:
            H.index_add_(1, labels[p0:p1], h)
            M.index_add_(1, labels[p0:p1], m)
    mat = lambda x: torch.stack([torch.stack([x[..., 0], x[..., 1]], -1), torch.stack([x[..., 1], x[..., 2]], -1)], -2)  # noqa: E731
    return {"H": mat(H.permute(1, 0, 2)), "M": mat(M.permute(1, 0, 2)), "local": local, "eb": eb_all, "sec": ec_all}


def _sandwich(H: Tensor, M: Tensor) -> Tensor:
    """H⁻¹·M·H⁻¹ for (..., 2, 2) symmetric H (NaN where H is singular), in closed form."""
    det = H[..., 0, 0] * H[..., 1, 1] - H[..., 0, 1] ** 2
    ok = det > SINGULAR_REL * (H[..., 0, 0] * H[..., 1, 1]).abs()
    inv = torch.stack([torch.stack([H[..., 1, 1], -H[..., 0, 1]], -1), torch.stack([-H[..., 0, 1], H[..., 0, 0]], -1)], -2)
    inv = inv / torch.where(ok, det, torch.ones_like(det))[..., None, None]
    cov = inv @ M @ inv
    return torch.where(ok[..., None, None], cov, torch.full_like(cov, math.nan))


def _texture_variance(sums: dict, grid: dict, var_s: Tensor, var_b: Tensor, c_sb: Tensor) -> Tensor:
    """(3, P): local part plus e_pᵀ·Cov(θ)·e_p of each pixel's element."""
    labels = grid["labels"]
    pick = (lambda x: x[0].view(3, 1)) if labels is None else (lambda x: x[labels].T)  # noqa: E731
    eb, sec = sums["eb"], sums["sec"]
    glob = eb * eb * pick(var_s) + 2.0 * eb * sec * pick(c_sb) + sec * sec * pick(var_b)
    if not grid["globals"]:
        glob = torch.zeros_like(glob)
    return sums["local"] + glob.clamp_min(0.0)


def _pixel_scale(fit: FitResult, capture: Capture, grid: dict, stride: int) -> Tensor:
    """(K,) float64: per element, its pixels inside the mask at full resolution over those on the grid — the
    factor that turns the grid's sums H, M into the whole image's (1 with stride 1). Both H and M grow with
    it, so the sandwich covariance H⁻¹MH⁻¹ shrinks by it: the full capture's information, not the grid's."""
    k = grid["k"]
    if stride == 1:
        return torch.ones(k, dtype=torch.float64)
    off = stride // 2
    inside = torch.ones(capture.height, capture.width, dtype=torch.bool) if capture.mask is None else \
        capture.mask.reshape(capture.height, capture.width).bool()
    on = inside[off::stride, off::stride]
    if grid["labels"] is None:
        full, sub = inside.sum().double().view(1), on.sum().double().view(1)
    else:
        full = torch.bincount(fit.spec_labels.long()[inside], minlength=k).double()
        sub = torch.bincount(grid["labels"][on.reshape(-1)], minlength=k).double()
    return torch.where(sub > 0, full / sub.clamp_min(1.0), torch.ones_like(full))


def _scaled(sums: dict, scale: Tensor) -> dict:
    """``sums`` with H and M (K, 3, 2, 2) times ``scale`` (K,) (:func:`_pixel_scale`); the per-pixel parts as they are."""
    f = scale.view(-1, 1, 1, 1)
    return {**sums, "H": sums["H"] * f, "M": sums["M"] * f}


def _full_resolution(std: Tensor, stride: int, height: int, width: int) -> Tensor:
    """(3, h, w) on the grid → (3, H, W) float32; each grid pixel's value spread over its stride block."""
    m = std.float()
    if stride == 1:
        return m
    big = m.repeat_interleave(stride, 1).repeat_interleave(stride, 2)
    off = stride // 2
    big = torch.cat([big[:, :1].expand(3, off, -1), big], 1) if off else big
    big = torch.cat([big[:, :, :1].expand(-1, -1, off), big], 2) if off else big
    return big[:, :height, :width].contiguous()


def _jackknife(fit: FitResult, capture: Capture, o: UncertaintyOptions) -> tuple[Tensor, Tensor]:
    """Jackknife standard deviations (K, 3) of s and β: the variable-projection refit with each shot left out,
    on a subsample, the fit's clusters held."""
    s_el, a_el = _elements(fit)
    k = int(s_el.shape[0])
    stride = grid_stride(capture.height, capture.width, o.jackknife_pixels)
    full = None if k == 1 else fit.spec_labels.long()
    labeler = None if full is None else (lambda tmin, rc: full[rc[0].long(), rc[1].long()])
    beta0 = torch.log(a_el.double().clamp(ALPHA_MIN, ALPHA_MAX))
    ss, bs = [], []
    n = capture.num_shots
    for i in range(n):
        keep = [j for j in range(n) if j != i]
        obs = build_observations(capture, stride=stride, shots=keep, lobe=fit.lobe, labeler=labeler)
        sf = fit_specular(obs, beta0)
        ss.append(sf.s.double())
        bs.append(torch.log(sf.alpha.double()))
    s_j, b_j = torch.stack(ss), torch.stack(bs)
    f = (n - 1) / n
    return (f * ((s_j - s_j.mean(0)) ** 2).sum(0)).sqrt(), (f * ((b_j - b_j.mean(0)) ** 2).sum(0)).sqrt()


def _student_t(q: float, dof: int) -> float:
    """The q-quantile of Student's t with ``dof`` degrees of freedom: the Cornish–Fisher expansion around the
    normal's (q = 0.95: 2.912 for 2 dof, exact 2.920; 2.3523 for 3, exact 2.3534; closer beyond)."""
    z = NormalDist().inv_cdf(q)
    d = float(max(1, dof))
    g1 = (z**3 + z) / 4
    g2 = (5 * z**5 + 16 * z**3 + 3 * z) / 96
    g3 = (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384
    g4 = (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160
    return z + g1 / d + g2 / d**2 + g3 / d**3 + g4 / d**4
