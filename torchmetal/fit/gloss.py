"""Gloss maps: per-pixel s(p), α(p) with an edge-aware smoothness prior — kept only when it helps.

Why per pixel and not soft clusters: on the real card (cards_blue) the gloss changes with the
embossing and the foil's edges at the scale of a few pixels, and clusters (hard, on colour or
specular features) are never kept there (held-out shots prefer global); on the zoo's
``two_materials`` scene the two materials are separated by a sharp edge that hard clusters
already capture. A per-pixel fit whose neighbourhood is *edge-aware* (weights from the colour of
T_min, the paper's highlight-free texture bound) covers both: inside a material it pools a
window of pixels (the smoothness prior), across a colour edge it does not.

The model per pixel p and channel c (docs/design.md §2.2 with s, α maps):

    I_k(p) = E·[d(p)·max(n·l, 0) + s(p)·lobe(α(p))]

For each pixel the variable-projection problem of :mod:`torchmetal.fit.refine` (texture
eliminated per pixel, s in closed form, LM on β = log α) is solved on the bilateral-weighted sum
of its neighbours' per-pixel normal equations (each neighbour's sums taken at its own current α —
a Jacobi sweep per LM iteration), plus a ridge prior towards the base fit (global or clustered):

    cost_p(s, β) = Σ_q w_pq·[A_q − 2s·B_q + s²·C_q] + μ·C_ref·(s − s₀)² + μ·H_ref·(β − β₀)²

with C_ref, H_ref the median pooled curvatures at the base, so pixels with much less highlight
evidence than typical (no mirror direction seen, outside the mask) keep the base terms.
:func:`choose_maps` fits the base and the maps on all shots but one, for each of :data:`HOLDS` shots in turn, and
keeps the maps only when they lower those shots' errors beyond noise (the paired rule of :mod:`torchmetal.select.rule`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.fit.cluster_features import colour_features
from torchmetal.fit.clusters import heldout_errors, mean_square
from torchmetal.fit.lm import LMEval, levenberg_marquardt
from torchmetal.fit.problem import Observations, Reference, Weighting, build_observations
from torchmetal.fit.refine import (
    ALPHA_MAX,
    ALPHA_MIN,
    BETA_MAX,
    BETA_MIN,
    SpecFit,
    fit_specular,
    pinned_terms,
    pixel_map,
    spec_sums,
    texture_map,
)
from torchmetal.select.rule import MIN_GAIN_ABS, Decision, paired_choice, z_min_for

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

__all__ = ["GlossMaps", "fit_gloss_maps", "choose_maps", "MapsSelection", "RADIUS", "PRIOR", "SIGMA_GUIDE", "HOLDS"]

#: shots left out in turn by the maps' test (the shot plan's first, most predicted specular energy first): one
#: held-out shot's highlight covers a few of its pixels, too few for per-pixel gloss to show beyond noise, and with one
#: the test missed most random scenes where the maps gain ≥ 1 dB (docs/measurements.md, ninth session)
HOLDS = 3

RADIUS = 3  # neighbourhood radius in full-resolution pixels (7×7 window)
SIGMA_GUIDE = 0.5  # bilateral range σ on the standardised T_min colour features
PRIOR = 0.05  # μ: ridge towards the base, relative to the median pooled curvature
MAX_ITERS = 20
EARLY_ITERS = 3  # choose_maps: maps that do worse than their base on the held-out shot after this many iterations stop


@dataclass
class GlossMaps:
    """Per-pixel specular terms of one set of observations.

    Attributes:
        s, alpha: (3, P) maps on the observations' grid; eb: (3, P) e_b at ``alpha``
            (texture = d0 − s·e_b); iterations, status: of the LM.
    """

    s: Tensor
    alpha: Tensor
    eb: Tensor
    iterations: int = 0
    status: str = "converged"

    def texture(self, obs: Observations) -> Tensor:
        """(3, P) closed-form texture at the maps."""
        d = obs.d0 - self.s.to(obs.dtype) * self.eb
        return torch.where(obs.saa > 0, d, obs.fallback)

    def per_pixel(self) -> tuple[Tensor, Tensor, Tensor]:
        """(P, 3) s, α and labels arange(P): the maps as "one cluster per pixel"."""
        p = self.s.shape[1]
        return self.s.T.contiguous(), self.alpha.T.contiguous(), torch.arange(p, device=self.s.device)


def grid_radius(stride: int, radius: int = RADIUS) -> int:
    """Window radius in grid units for a pixel grid of ``stride`` (≥ 1)."""
    return max(1, int(round(radius / max(1, stride))))


def bilateral_weights(guide: Tensor, radius: int, sigma: float = SIGMA_GUIDE) -> list[tuple[int, int, Tensor]]:
    """Neighbour weights of an (F, h, w) guide: [(dy, dx, (h, w) weight)], 0 outside the image.

    w_pq = exp(−|o|²/(2·(radius/2 + 0.5)²)) · exp(−|f_p − f_q|²/(2σ²)).
    """
    f, h, w = guide.shape
    gp = F.pad(guide.unsqueeze(0), (radius,) * 4, mode="replicate")[0]
    inside = F.pad(torch.ones(1, 1, h, w, dtype=guide.dtype, device=guide.device), (radius,) * 4)[0, 0]
    rs = radius / 2.0 + 0.5
    out = []
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            sl = (slice(radius + dy, radius + dy + h), slice(radius + dx, radius + dx + w))
            d2 = ((gp[:, sl[0], sl[1]] - guide) ** 2).sum(0)
            wt = math.exp(-(dy * dy + dx * dx) / (2 * rs * rs)) * torch.exp(-d2 / (2 * sigma * sigma)) * inside[sl]
            out.append((dy, dx, wt))
    return out


def pool(x: Tensor, weights: list[tuple[int, int, Tensor]], radius: int) -> Tensor:
    """Σ_q w_pq·x_q of (C, h, w) sums (zero padded): the pooled normal equations."""
    c, h, w = x.shape
    xp = F.pad(x.unsqueeze(0), (radius,) * 4)[0]
    out = torch.zeros_like(x)
    for dy, dx, wt in weights:  # in place: no (C, h, w) temporary per offset
        out.addcmul_(xp[:, radius + dy:radius + dy + h, radius + dx:radius + dx + w], wt.to(x.dtype))
    return out


def _guide(obs: Observations) -> Tensor:
    """(3, h, w) standardised colour features of T_min (or d0 without T_min)."""
    t = obs.tmin if obs.tmin is not None else obs.d0
    t = torch.where(torch.isfinite(t), t, torch.zeros_like(t)).double()
    used = obs.n.sum(0) > 0
    eps = 0.05 * float(t.clamp_min(0).mean(0)[used].median()) + 1e-12 if bool(used.any()) else 1e-12
    f = colour_features(t, eps)  # (P, 3)
    ref = f[used] if int(used.sum()) > 1 else f
    f = (f - ref.mean(0)) / ref.std(0).clamp_min(1e-6)
    return f.T.reshape(3, obs.height, obs.width)


def _prior_terms(st: Tensor, beta: Tensor, A: Tensor, s0: Tensor, b0: Tensor, prior: float,
                 ref: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(s, cost, gradient, Hessian) (3, P) at β of the pooled stats ``st`` (6, 3, P) with the ridge prior
    centred on the base (``s0``, ``b0``); ``ref`` holds the prior's scale, the reference curvatures at the base
    (filled at the first call)."""
    B, C, Bc, Cc, Yc, _ = st.unbind(0)
    if not ref:  # reference curvatures at the base: the prior's scale
        e = s0 * s0 * (Cc - Bc * Bc / C.clamp_min(1e-300)).clamp_min(0.0)
        for name, v in (("C", C), ("H", e)):
            pos = v > 0
            ref[name] = torch.stack([v[c][pos[c]].median() if bool(pos[c].any()) else v.new_ones(()) for c in range(3)]).view(3, 1)
    ms, mb = prior * ref["C"], prior * ref["H"]
    s = ((B + ms * s0) / (C + ms)).clamp_min(0.0)
    cost = (A - 2.0 * s * B + s * s * C + ms * (s - s0) ** 2 + mb * (beta - b0) ** 2).clamp_min(0.0)
    grad = -s * (Yc - s * Bc) + mb * (beta - b0)
    hess = s * s * (Cc - Bc * Bc / (C + ms)).clamp_min(0.0) + mb
    return s, cost, grad, hess


def fit_gloss_maps(
    obs: Observations,
    s0: Tensor,
    alpha0: Tensor,
    *,
    stride: int = 1,
    radius: int = RADIUS,
    sigma: float = SIGMA_GUIDE,
    prior: float = PRIOR,
    tol: float = 1e-4,
    max_iters: int = MAX_ITERS,
    alpha_start: Tensor | None = None,
) -> GlossMaps:
    """Per-pixel s, α (3, P) of ``obs`` from a base fit ``s0``, ``alpha0`` ((3, P) or (3, 1) per pixel).

    ``stride`` is the grid's pixel stride (the window covers ``radius`` full-resolution pixels).
    ``alpha_start`` (3, P): resume the LM from these α (e.g. a shorter run's); default ``alpha0``.
    The ridge prior stays centred on the base.
    """
    p, h, w = obs.num_pixels, obs.height, obs.width
    dev = obs.device
    f64 = torch.float64
    s0 = s0.to(f64).expand(3, p).contiguous()
    b0 = torch.log(alpha0.to(f64).clamp(ALPHA_MIN, ALPHA_MAX)).expand(3, p).contiguous()
    r = grid_radius(stride, radius)
    wts = bilateral_weights(_guide(obs), r, sigma)
    A = pool(obs.A.to(f64).reshape(3, h, w), wts, r).reshape(3, p)
    labels_before = obs.labels
    obs.labels = torch.arange(p, device=dev)
    ref: dict[str, Tensor] = {}

    def stats_at(beta: Tensor) -> tuple[Tensor, Tensor]:
        st, eb, _ = spec_sums(obs, torch.exp(beta).T.contiguous(), per_pixel=True)  # (6, 3, P)
        return pool(st.to(f64).reshape(18, h, w), wts, r).reshape(6, 3, p), eb

    floor = (0.01 * torch.finfo(obs.dtype).eps * A).reshape(-1)

    def oracle(x: Tensor) -> LMEval:
        beta = x.view(3, p)
        st, eb = stats_at(beta)
        s, cost, g, hh = _prior_terms(st, beta, A, s0, b0, prior, ref)
        return LMEval(cost.reshape(-1), g.reshape(-1, 1), hh.reshape(-1, 1, 1), aux=(eb, s.reshape(-1)), floor=floor)

    def merge(new, old, accepted: Tensor):
        acc = accepted.view(3, p)
        return torch.where(acc, new[0], old[0]), torch.where(accepted, new[1], old[1])

    try:
        x0 = (b0 if alpha_start is None else torch.log(alpha_start.to(f64).clamp(ALPHA_MIN, ALPHA_MAX))).reshape(-1, 1).clone()
        res = levenberg_marquardt(oracle, x0, lower=BETA_MIN, upper=BETA_MAX, tol=tol, xtol=tol, max_iters=max_iters,
                                  merge=merge)
    finally:
        obs.labels = labels_before
    eb, s = res.eval.aux
    return GlossMaps(s=s.view(3, p), alpha=torch.exp(res.x.view(3, p)), eb=eb, iterations=res.iterations,
                     status=res.status)


@dataclass
class MapsSelection:
    """Outcome of the held-out comparison of gloss maps against their base."""

    kept: bool
    hold: int
    mse: dict = field(default_factory=dict)  # "base" / "maps" → held-out MSE
    reason: str = ""
    decision: Decision | None = None
    iterations: int = 0  # LM iterations of the maps' trial
    stopped_early: bool = False  # the trial lost to its base after EARLY_ITERS iterations and went no further

    def to_dict(self) -> dict:
        return {"kept": self.kept, "hold": self.hold, "mse": dict(self.mse), "reason": self.reason,
                "iterations": self.iterations, "stopped_early": self.stopped_early,
                "decision": None if self.decision is None else self.decision.to_dict()}


def _maps_errors(ho: Observations, obs: Observations, maps: GlossMaps) -> Tensor:
    """Held-out squared errors (M,) of ``maps`` fitted on ``obs``, their texture included."""
    s_p, a_p, ar = maps.per_pixel()
    return heldout_errors(ho, maps.texture(obs), s_p, a_p, ar)


def choose_maps(
    capture: Capture,
    base: Reference,
    *,
    labeler: Callable[[Tensor, Tensor], Tensor] | None = None,
    stride: int,
    hold: int,
    force: bool,
    tol: float,
    max_iters: int,
    dtype: torch.dtype,
    chunk: int,
    weighting: Weighting | None,
    lobe: str = "phong",
    base_errors: Tensor | None = None,
    pinned: Tensor | None = None,
    more_holds: list[int] | None = None,
) -> MapsSelection:
    """Fit the base specular (global, or clustered with ``labeler``) and gloss maps from it on all
    shots but ``hold``, then likewise without each of ``more_holds`` in turn; keep the maps when they lower
    the held-out shots' errors beyond noise (:func:`~torchmetal.select.rule.paired_choice` on every held-out
    shot's errors together; ``base_errors`` (M,): the errors to beat on ``hold``'s observations, default the
    base's own; ``pinned`` (K, 3): base elements held at their terms, as in
    :func:`~torchmetal.fit.clusters.fit_clustered`).

    Decided early when the maps lose: after :data:`EARLY_ITERS` LM iterations without ``hold``, maps whose
    held-out MSE is not below the base's are not kept and not fitted further, nor without the other shots
    (docs/measurements.md, gloss maps' early stop: a trial that loses there has stayed worse to convergence on
    every zoo scene)."""
    n = int(capture.images.shape[0])
    holds = [hold] + [h for h in (more_holds or ()) if h != hold]
    k = base.k
    s_fix, b_fix = pinned_terms(pinned, base.s, base.alpha)  # clusters without evidence keep the global terms
    errors: dict = {"base": [], "maps": []}
    early, iters, ho_ms = False, 0, 0.0
    for i, h in enumerate(holds):
        obs = build_observations(capture, stride=stride, shots=[j for j in range(n) if j != h], dtype=dtype,
                                 chunk=chunk, ref=base, weighting=weighting, want_tmin=True, labeler=labeler, lobe=lobe)
        ho = build_observations(capture, stride=stride, shots=[h], dtype=dtype, chunk=chunk, lobe=lobe)
        ho_ms = max(ho_ms, mean_square(ho))
        g: SpecFit = fit_specular(obs, torch.log(base.alpha), tol=tol, max_iters=max_iters, s_fixed=s_fix,
                                  beta_fixed=b_fix)
        lab = obs.labels if k > 1 else None
        errors["base"].append(heldout_errors(ho, texture_map(obs, g.s, g.eb), g.s, g.alpha, lab)
                              if base_errors is None or i > 0 else base_errors)
        s0, a0 = pixel_map(g.s, lab), pixel_map(g.alpha, lab)
        maps = fit_gloss_maps(obs, s0, a0, stride=stride, tol=tol, max_iters=min(EARLY_ITERS, max_iters))
        err = _maps_errors(ho, obs, maps)
        early = (i == 0 and not force and maps.status != "converged"
                 and float(err.mean()) >= float(errors["base"][-1].mean()))
        if not early and maps.status != "converged" and max_iters > maps.iterations:
            maps = fit_gloss_maps(obs, s0, a0, stride=stride, tol=tol, max_iters=max_iters - maps.iterations,
                                  alpha_start=maps.alpha)
            err = _maps_errors(ho, obs, maps)
        errors["maps"].append(err)
        iters += maps.iterations
        if early:  # lost on the first shot after EARLY_ITERS: not fitted on the others
            holds = holds[:1]
            break
    errors = {c: torch.cat(e) for c, e in errors.items()}
    over = k > 1  # on top of clusters: a calibrated z, reached even where the maps halve the error
    d = paired_choice("gloss maps", errors, "base", floor=MIN_GAIN_ABS * ho_ms,
                      z_min=z_min_for("gloss maps over clusters" if over else "gloss maps"), decisive=not over)
    d.holds, d.pixels = holds, ho.num_pixels
    if early:
        d.reason += f" (stopped early on shot {holds[-1]}, after {maps.iterations} iterations)"
    if force:
        d.chosen, d.reason = "maps", f"forced (specular='maps'); {d.reason}"
    shots = f"shot {hold}" if len(holds) == 1 else f"shots {holds}"
    return MapsSelection(d.chosen == "maps", hold, dict(d.mse), f"held-out {shots}: {d.reason}", d,
                         iterations=iters, stopped_early=early)
