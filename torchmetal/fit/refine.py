"""Joint refinement of texture and specular terms by variable projection.

Given α, the model I = a·d + s·b(α) is linear in the texture d (per pixel) and in s (per
element: channel, or channel × specular cluster). Both are eliminated in closed form, and LM
runs on β = log α alone, one scalar per element:

    d(s, α) = d0 − s·e_b,   e_b = Σ w·a·b / Σ w·a²          (per pixel, the Schur complement)
    b⊥ = b − a·e_b,  c⊥ = ∂b/∂β − a·e_c                      (orthogonal to the texture basis)
    s(α) = max(0, B/C),  B = Σ w·y·b⊥,  C = Σ w·b⊥²           (global sums, float64)
    cost(α) = A − 2sB + s²C,  A = Σ w·(y − a·d0)²            (A exact, from residuals)
    g = −s·(Σ w·y·c⊥ − s·Σ w·b⊥·c⊥),  H = s²·(Σ w·c⊥² − (Σ w·b⊥·c⊥)²/C)

g and H are the Gauss–Newton terms of the projected problem (Kaufman's variable projection),
equal to the Schur complement of the full (texture, s, β) normal equations at the optimal
texture. Everything per pixel is one chunked pass over the observations in the working dtype
(orthogonalised inside the chunk, so no normal-equation cancellation); only the per-element sums
are float64. Chunks × shots whose lobe is below e⁻⁴⁰ for the smallest α are skipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Iterator

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.fit.lm import LMEval, levenberg_marquardt
from torchmetal.fit.lobes import lobe_factor, lobe_terms
from torchmetal.fit.problem import VARIANCE_W_MIN, Observations
from torchmetal.fit.projected_sums import add_skipped_shots, chunk_stats, reduce_stats

ALPHA_MIN = 1.0
ALPHA_MAX = 1.0e4
BETA_MIN = 0.0
BETA_MAX = math.log(ALPHA_MAX)
IDENT_REL = 1e-9  # C below this fraction of Σ w·b² → s and the texture are not separable
STATS = ("B", "C", "Bc", "Cc", "Yc", "Sbb")


@dataclass
class SpecFit:
    """Specular terms of a fit on one set of observations.

    Attributes:
        s, alpha: (K, 3) per element.
        eb: (3, P) e_b at ``alpha``; the texture is d0 − s·e_b.
        cost: (K, 3) float64 cost per element; ``A`` the diffuse-only cost, ``Y`` Σ w·y².
        iterations, status: of the LM.
        active: fraction of (shot, pixel) observations the last pass processed.
    """

    s: Tensor
    alpha: Tensor
    eb: Tensor
    cost: Tensor
    A: Tensor
    Y: Tensor
    iterations: int = 0
    status: str = "converged"
    active: float = 1.0
    pinned: Tensor | None = None  # (K, 3) bool: elements held at given (global) terms
    lobe: str = "phong"  # the observations' lobe (torchmetal.fit.lobes)

    @property
    def k(self) -> int:
        return int(self.s.shape[0])

    def explained(self) -> Tensor:
        """(K, 3) fraction of the diffuse-only residual energy the specular term explains."""
        return ((self.A - self.cost) / self.A.clamp_min(1e-300)).clamp(0.0, 1.0)


def pixel_map(x: Tensor, labels: Tensor | None) -> Tensor:
    """Per-element (K, 3) → per pixel (3, P), or (3, 1) for K = 1."""
    if x.shape[0] == 1 or labels is None:
        return x[0].view(3, 1)
    return x[labels].T


def chunk_terms(obs: Observations, s: Tensor, alpha: Tensor,
                labels: Tensor | None) -> Iterator[tuple[int, tuple[int, int], tuple[Tensor, ...], Tensor, Tensor]]:
    """Per chunk j of ``obs``: (j, (p0, p1), obs.chunk(j), s (1, 3, c|1), α (1, 3, c|1)) for elements s, α (K, 3)
    on pixel ``labels`` (P,) (ignored for K = 1)."""
    lab = labels if s.shape[0] > 1 else None
    s_pix, a_pix = pixel_map(s.to(obs.dtype), lab), pixel_map(alpha.to(obs.dtype), lab)
    for j, (p0, p1) in enumerate(obs.chunks):
        sp = s_pix if s_pix.shape[1] == 1 else s_pix[:, p0:p1]
        ap = a_pix if a_pix.shape[1] == 1 else a_pix[:, p0:p1]
        yield j, (p0, p1), obs.chunk(j), sp.unsqueeze(0), ap.unsqueeze(0)


def chunk_model(obs: Observations, texture: Tensor, s: Tensor, alpha: Tensor,
                labels: Tensor | None) -> Iterator[tuple[Tensor, Tensor, Tensor, Tensor]]:
    """Per chunk of ``obs``: (y, w, a·d, s·b) (N, 3, c) each — the photos, weights, diffuse and specular terms of
    the texture d (3, P) and the elements s, α (K, 3) on pixel ``labels`` (P,) (ignored for K = 1): what the
    residual scale, the noise model and the held-out errors are taken from (residual y − a·d − s·b)."""
    for j, (p0, p1), (y, g, u, L, w, inten), sp, ap in chunk_terms(obs, s, alpha, labels):
        yield y, w, inten * g * texture[:, p0:p1], sp * (inten * u) * lobe_factor(L, ap, obs.geo_chunk(j), obs.lobe)


def spec_sums(obs: Observations, alpha: Tensor, *, per_pixel: bool = False) -> tuple[Tensor, Tensor, float]:
    """One pass: per-element stats (6, K, 3) float64 and e_b (3, P) for α (K, 3).

    With ``per_pixel`` the stats are returned per pixel instead, (6, 3, P) in the working dtype.

    Returns (stats, e_b, fraction of observations processed).
    """
    k = int(alpha.shape[0])
    p = obs.num_pixels
    eb = torch.zeros(3, p, dtype=obs.dtype, device=alpha.device)
    acc = torch.zeros(6, 3, k, dtype=torch.float64, device=alpha.device)
    pix = torch.zeros(6, 3, p, dtype=obs.dtype, device=alpha.device) if per_pixel else None
    active = obs.active_shots(float(alpha.min()))
    done = 0
    a_glob = alpha[0].to(obs.dtype).view(1, 3, 1)
    for j, (p0, p1) in enumerate(obs.chunks):
        act = active[:, j]
        n_act = int(act.sum())
        if n_act == 0:
            continue
        shots = None if n_act == obs.num_shots else act.nonzero().squeeze(1)
        y, g, u, L, w, inten = obs.chunk(j, shots)
        lab = obs.labels[p0:p1] if (k > 1 and obs.labels is not None) else None
        al = a_glob if lab is None else alpha[lab].T.to(obs.dtype).unsqueeze(0)
        a, b, t = lobe_terms(g, u, L, inten, al, obs.geo_chunk(j, shots), obs.lobe)
        wa = w * a
        e, ec, st = chunk_stats(y, a, b, t, w, obs.isaa(p0, p1), wa=wa)
        if shots is not None:  # the left-out shots still couple through the texture
            st = add_skipped_shots(st, e, ec, y, a, wa, obs.saa[:, p0:p1], obs.d0[:, p0:p1])
        eb[:, p0:p1] = e
        if pix is not None:
            pix[:, :, p0:p1] = st
            continue
        reduce_stats(st, lab, k, acc)
        done += n_act * (p1 - p0)
    frac = done / max(1, obs.num_shots * p)
    return (pix if pix is not None else acc.permute(0, 2, 1).contiguous()), eb, frac


def element_terms(stats: Tensor, A: Tensor, s_fixed: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Optimal s, cost, g, H per element from the stats (6, K, 3) and A (K, 3).

    ``s_fixed`` (K, 3) pins s where finite (NaN = free).
    """
    B, C, Bc, Cc, Yc, Sbb = stats.unbind(0)
    ident = C > IDENT_REL * Sbb
    safe_c = torch.where(ident, C, torch.ones_like(C))
    s = torch.where(ident & (B > 0), B / safe_c, torch.zeros_like(B))
    reduced = torch.where(ident, (Cc - Bc * Bc / safe_c).clamp_min(0.0), torch.zeros_like(Cc))
    if s_fixed is not None:
        fixed = ~torch.isnan(s_fixed)
        s = torch.where(fixed, s_fixed, s)
        reduced = torch.where(fixed, Cc, reduced)  # s not eliminated: plain Gauss–Newton term
    cost = (A - 2.0 * s * B + s * s * C).clamp_min(0.0)
    grad = -s * (Yc - s * Bc)
    hess = s * s * reduced
    return s, cost, grad, hess


def fit_specular(
    obs: Observations,
    beta0: Tensor,
    *,
    tol: float = 1e-6,
    max_iters: int = 100,
    on_iter: Callable[[int, float, float], None] | None = None,
    s_fixed: Tensor | None = None,
    beta_fixed: Tensor | None = None,
    first: tuple[Tensor, Tensor] | None = None,
) -> SpecFit:
    """LM on β = log α (K, 3) with texture and s projected out; K from ``beta0``.

    Args:
        obs: observations (``obs.labels`` (P,) in [0, K) when K > 1).
        beta0: (K, 3) start.
        tol: relative cost change / β step at which an element stops.
        max_iters: LM iteration cap.
        on_iter: (iteration, rmse, active fraction) after each iteration.
        s_fixed, beta_fixed: (K, 3), finite entries pin s / β of that element (NaN = free).
        first: (stats (6, K, 3), e_b (3, P)) already computed at ``beta0`` (e.g. by
            :func:`~torchmetal.fit.problem.build_observations`), saving one pass.
    """
    k = int(beta0.shape[0])
    A = obs.element_sum(obs.A, k)
    Y = obs.energy(k)
    n_total = obs.n_obs
    labels = obs.labels if k > 1 else None
    state = {"active": 1.0}
    floor = (0.01 * torch.finfo(obs.dtype).eps * A).reshape(-1)  # cost resolution of the working dtype

    def evaluate(stats: Tensor, eb: Tensor) -> LMEval:
        s, cost, g, h = element_terms(stats, A, s_fixed=s_fixed)
        return LMEval(cost.reshape(-1), g.reshape(-1, 1), h.reshape(-1, 1, 1), aux=(eb, s.reshape(-1)), floor=floor)

    def oracle(x: Tensor) -> LMEval:
        stats, eb, frac = spec_sums(obs, torch.exp(x.view(k, 3)))
        state["active"] = frac
        return evaluate(stats, eb)

    def report(it: int, x: Tensor, ev: LMEval, done: Tensor) -> None:
        if on_iter is not None:
            on_iter(it, math.sqrt(float(ev.cost.sum()) / n_total), state["active"])

    lo, hi, x0 = beta_bounds(beta0, beta_fixed)
    if first is not None and bool((x0 == beta0.reshape(-1, 1).to(torch.float64)).all()):
        ev0 = evaluate(first[0].to(A.device), first[1])
    else:
        ev0 = oracle(x0)
    report(0, x0, ev0, torch.zeros(0))
    res = levenberg_marquardt(oracle, x0, lower=lo, upper=hi, tol=tol, xtol=tol, max_iters=max_iters,
                              merge=_merge_aux(k, labels), first=ev0, on_iter=report)
    eb, s = res.eval.aux
    return SpecFit(
        s=s.view(k, 3), alpha=torch.exp(res.x.view(k, 3)), eb=eb, cost=res.eval.cost.view(k, 3), A=A, Y=Y,
        iterations=res.iterations, status=res.status, active=state["active"], lobe=obs.lobe,
    )


def beta_bounds(beta0: Tensor, beta_fixed: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """(lower, upper, start) (K·3, 1) float64 of the LM on β: [BETA_MIN, BETA_MAX], pinned where ``beta_fixed``
    is finite; the start ``beta0`` clamped into them."""
    k = int(beta0.shape[0])
    lo = torch.full((k * 3, 1), BETA_MIN, dtype=torch.float64, device=beta0.device)
    hi = torch.full_like(lo, BETA_MAX)
    if beta_fixed is not None:
        bf = beta_fixed.reshape(-1, 1).to(torch.float64)
        pin = ~torch.isnan(bf)
        lo, hi = torch.where(pin, bf, lo), torch.where(pin, bf, hi)
    x0 = torch.minimum(torch.maximum(beta0.reshape(-1, 1).to(torch.float64), lo), hi)
    return lo, hi, x0


def _merge_aux(k: int, labels: Tensor | None) -> Callable[[tuple, tuple, Tensor], tuple]:
    """The LM's ``merge`` of the aux parts (e_b (3, P), s (K·3,)): e_b from the new evaluation on the pixels of
    accepted elements."""

    def merge(new, old, accepted: Tensor):
        if bool(accepted.all()):  # no full-size copy when every element moves (or none does)
            return new
        if not bool(accepted.any()):
            return old
        acc_pix = pixel_map(accepted.view(k, 3).to(torch.uint8), labels).bool()
        return torch.where(acc_pix, new[0], old[0]), torch.where(accepted, new[1], old[1])

    return merge


def pinned_terms(pinned: Tensor | None, s: Tensor, alpha: Tensor) -> tuple[Tensor | None, Tensor | None]:
    """``s_fixed``, ``beta_fixed`` (K, 3) of :func:`fit_specular` holding the ``pinned`` (K, 3) elements
    at s and log α (K, 3), NaN (free) elsewhere; (None, None) when nothing is pinned."""
    if pinned is None or not bool(pinned.any()):
        return None, None
    nan = torch.full_like(s, math.nan)
    return torch.where(pinned, s, nan), torch.where(pinned, torch.log(alpha), nan)


def evaluate_specular(obs: Observations, s: Tensor | None, alpha: Tensor) -> SpecFit:
    """Cost and e_b at fixed α (K, 3); s optimal per element, or fixed where ``s`` is given."""
    k = int(alpha.shape[0])
    A = obs.element_sum(obs.A, k)
    stats, eb, frac = spec_sums(obs, alpha.to(torch.float64))
    s_opt, cost, _, _ = element_terms(stats, A, s_fixed=s)
    return SpecFit(s=s_opt, alpha=alpha.to(torch.float64), eb=eb, cost=cost, A=A, Y=obs.energy(k), active=frac,
                   lobe=obs.lobe)


SHARED_ALPHA_P = 3.09  # share_alpha: z of the χ² test (p = 0.001, one-sided)


def share_alpha(obs: Observations, fit: SpecFit) -> tuple[SpecFit, dict]:
    """One α for the three channels of each element — a GGX roughness — where the data cannot
    tell the channels' α apart.

    Candidates per element: the mean of the three log α and each channel's own; the best shared
    one (s re-solved per channel, :func:`evaluate_specular`) is kept when it raises the cost by
    less than the χ²(2K) quantile at p = 0.001 (Wilson–Hilferty) times the fit's mean cost per
    observation: two parameters per element removed, the likelihood-ratio test of the simpler
    model. (Zoo ggx_truth, one true α: 101.30 / 101.27 / 101.37 → shared; the real grey sphere,
    1.44 / 1.33 / 1.00 → kept per channel.) A shared α renders as one GGX fraction instead of three
    (:meth:`~torchmetal.renderer.MaterialRenderer._ggx_spec`). Elements pinned to other terms keep
    theirs. Returns (fit, report)."""
    if fit.pinned is not None and bool(fit.pinned.any()):
        return fit, {"shared": False, "reason": "elements pinned to the global terms"}
    k = fit.k
    beta = torch.log(fit.alpha.to(torch.float64))
    best = None
    for cand in (beta.mean(1, keepdim=True), *beta.split(1, dim=1)):
        trial = evaluate_specular(obs, None, torch.exp(cand).expand(k, 3).contiguous())
        if best is None or float(trial.cost.sum()) < float(best.cost.sum()):
            best = trial
    n_obs = obs.n_obs
    nu = 2.0 * k
    chi2 = nu * (1.0 - 2.0 / (9.0 * nu) + SHARED_ALPHA_P * math.sqrt(2.0 / (9.0 * nu))) ** 3
    rise = float(best.cost.sum() - fit.cost.sum())
    bound = chi2 * float(fit.cost.sum()) / n_obs
    report = {"cost_rise": rise, "bound": bound, "shared": rise <= bound}
    if rise > bound:
        return fit, report
    return replace(best, iterations=fit.iterations, status=fit.status), report


def grid_beta(
    obs: Observations, k: int, extra: Tensor | None = None, grid: tuple[float, ...] = (1, 4, 16, 64, 256, 1024, 4096)
) -> Tensor:
    """Best β per element (K, 3) over a coarse α grid (plus ``extra`` (K, 3) or (M, K, 3): M α candidates)."""
    dev = obs.device
    cands = [torch.full((k, 3), float(a), dtype=torch.float64, device=dev) for a in grid]
    if extra is not None:
        cands += list(extra.to(device=dev, dtype=torch.float64).clamp(ALPHA_MIN, ALPHA_MAX).reshape(-1, k, 3))
    best_cost = torch.full((k, 3), math.inf, dtype=torch.float64, device=dev)
    best = cands[0]
    for alpha in cands:
        fit = evaluate_specular(obs, None, alpha)
        better = fit.cost < best_cost
        best_cost = torch.where(better, fit.cost, best_cost)
        best = torch.where(better, alpha, best)
    return torch.log(best)


def texture_map(obs: Observations, s: Tensor, eb: Tensor) -> Tensor:
    """Texture (3, P): d0 − s·e_b, and the fallback where a pixel has no valid observation."""
    d = torch.addcmul(obs.d0, pixel_map(s.to(obs.dtype), obs.labels if s.shape[0] > 1 else None), eb, value=-1.0)
    unseen = obs.saa <= 0
    if bool(unseen.view(torch.uint8).amax()):
        d[unseen] = obs.fallback.expand_as(d)[unseen]
    return d


def residual_scale(obs: Observations, s: Tensor, alpha: Tensor, eb: Tensor, max_samples: int = 1 << 20) -> Tensor:
    """Robust residual scale σ (3,) = 1.4826·median |r| over valid observations (subsampled)."""
    d = texture_map(obs, s, eb)
    parts: list[list[Tensor]] = [[], [], []]
    budget = max(1, max_samples // max(1, len(obs.chunks)))
    for y, w, diffuse, spec in chunk_model(obs, d, s, alpha, obs.labels):
        r = y - diffuse - spec
        ok = w > 0
        for c in range(3):
            v = r[:, c][ok[:, c]].abs()
            if v.numel() > budget:
                v = v[:: max(1, v.numel() // budget)]
            parts[c].append(v)
    out = []
    for c in range(3):
        v = torch.cat(parts[c]) if parts[c] else torch.zeros(0, dtype=obs.dtype, device=d.device)
        out.append(1.4826 * v.median() if v.numel() else torch.zeros((), dtype=obs.dtype, device=d.device))
    return torch.stack(out)


NOISE_BINS = 16  # noise_model: quantile bins of the model value
MEDIAN_CHI2_1 = 0.45493642311957283  # median of χ²(1): median r² = 0.4549·variance for Gaussian noise


def noise_model(obs: Observations, s: Tensor, alpha: Tensor, eb: Tensor, *, floor: float = 0.0,
                max_samples: int = 1 << 18) -> Tensor:
    """The observations' noise variance as a function of the model value ŷ, var = a + b·ŷ per channel
    (read noise and quantisation a; shot noise, and an 8-bit sRGB step growing with the value, b):
    (2, 3) float64 rows a, b.

    Fitted to the residuals of the fit (s, α (K, 3), e_b (3, P)): ŷ cut into :data:`NOISE_BINS`
    quantile bins, each bin's variance its median r² / :data:`MEDIAN_CHI2_1` (glints and a misfit
    highlight do not move a median), then a, b ≥ 0 by least squares relative to each bin's variance.
    a is at least ``floor`` (a variance below which residuals are rounding, not noise: a noise-free capture gets
    uniform weights) and :data:`~torchmetal.fit.problem.VARIANCE_W_MIN` of the brightest bin's variance.

    The residuals also hold the model's misfit, which can grow with the value; that is why the weights are
    chosen on a held-out shot (``weights="auto"``, the pipeline's default) and never forced: a noise-free
    capture with a black patch weighted its highlights 500× down (s 17 % off; uniform 3.7 %), and capping the
    range at 10× (4.2 %) let two_materials' misfit choose other clusters and GGX (CI zoo 45.3 dB; uniform 54.5)."""
    d = texture_map(obs, s, eb)
    preds: list[list[Tensor]] = [[], [], []]
    sq: list[list[Tensor]] = [[], [], []]
    budget = max(1, max_samples // max(1, len(obs.chunks)))
    for y, w, diffuse, spec in chunk_model(obs, d, s, alpha, obs.labels):
        pred = diffuse + spec
        ok = w > 0
        for c in range(3):
            m = ok[:, c]
            v, r = pred[:, c][m], (y[:, c] - pred[:, c])[m]
            step = max(1, v.numel() // budget)
            preds[c].append(v[::step])
            sq[c].append((r * r)[::step])
    out = torch.zeros(2, 3, dtype=torch.float64, device=d.device)
    for c in range(3):
        v = torch.cat(preds[c]).double() if preds[c] else torch.zeros(0, dtype=torch.float64, device=d.device)
        if v.numel() < 4 * NOISE_BINS:
            out[0, c] = 1.0  # too few observations to model: every observation alike
            continue
        r2 = torch.cat(sq[c]).double()
        order = torch.argsort(v)
        v, r2 = v[order], r2[order]
        bins = torch.tensor_split(torch.arange(v.numel(), device=v.device), NOISE_BINS)
        x = torch.stack([v[i].median() for i in bins])
        var = torch.stack([r2[i].median() for i in bins]) / MEDIAN_CHI2_1
        if not bool(var.max() > 0) or not bool(torch.isfinite(var).all()):
            out[0, c] = 1.0  # residuals all zero (one shot fitted exactly): nothing to model, every observation alike
            continue
        var = var.clamp_min(VARIANCE_W_MIN * float(var.max()))
        rel = 1.0 / var  # least squares relative to each bin's variance
        design = torch.stack([torch.ones_like(x), x.clamp_min(0.0)], 1) * rel[:, None]
        a, b = torch.linalg.lstsq(design, torch.ones_like(var)).solution.tolist()
        if not b >= 0.0:
            a, b = float(var.numel() / rel.sum()), 0.0
        top = max(a, 0.0) + b * float(x.clamp_min(0.0).max())
        out[0, c], out[1, c] = max(a, VARIANCE_W_MIN * top, floor, 1e-300), b
    return out


def model_terms(obs: Observations, alpha: Tensor, labels: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Dense per-observation model terms (N, 3, P) — the analytic Jacobian of I = a·d + s·b(β):

    ∂I/∂d = a,  ∂I/∂s = b,  ∂I/∂β = s·t·b (returned without the factor s; t = α·L for
    phong/blinn, :func:`torchmetal.fit.lobes.lobe_terms`'s t for ggx).
    For small problems (tests, diagnostics); α (K, 3) with ``labels`` (P,) when K > 1.
    """
    a_pix = pixel_map(alpha.to(obs.dtype), labels if alpha.shape[0] > 1 else None).unsqueeze(0)
    g, u, L, geo = obs.dense()
    if obs.lobe != "phong":
        a, b, t = lobe_terms(g, u, L, obs.inten, a_pix, geo, obs.lobe)
        return a, b, t * b
    t = a_pix * L
    a = obs.inten * g
    b = obs.inten * u * torch.exp(t)
    return a, b, t * b


WEAK_REL = 1e-3  # Σ w·a² below 1e-3 of the median pixel: the texture is not observed (grazing only)


def unobserved(obs: Observations, inside: Tensor) -> Tensor:
    """(3, P) bool: pixels inside the mask whose texture the observations do not determine.

    No valid observation, or only grazing ones: Σ w·a² < 1e-3 × its median over observed pixels.
    """
    seen = obs.saa > 0
    med = torch.stack([obs.saa[c][seen[c]].median() if bool(seen[c].any()) else obs.saa.new_zeros(()) for c in range(3)])
    return inside.view(1, -1) & (obs.saa < WEAK_REL * med.view(3, 1))


def fill_unobserved(tex: Tensor, bad: Tensor, max_iters: int = 64) -> Tensor:
    """Inpaint ``bad`` (3, H, W) texels from observed neighbours (normalised 3×3 box filter, grown
    ring by ring), then the per-channel median; tex (3, H, W)."""
    if not bool(bad.any()):
        return tex
    tex = tex.clone()
    known = (~bad).to(tex.dtype)
    for _ in range(max_iters):
        if bool((known > 0).all()):
            break
        num = F.avg_pool2d((tex * known).unsqueeze(0), 3, stride=1, padding=1)[0]
        den = F.avg_pool2d(known.unsqueeze(0), 3, stride=1, padding=1)[0]
        grow = (known == 0) & (den > 0)
        tex = torch.where(grow, num / den.clamp_min(1e-12), tex)
        known = torch.where(grow, torch.ones_like(known), known)
    for c in range(3):
        rest = known[c] == 0
        if bool(rest.any()):
            ref = tex[c][known[c] > 0]
            tex[c][rest] = ref.median() if ref.numel() else 0.0
    return tex
