"""The source paper's section 4.1, batched over pixels and shots.

Initial approximation (4.1.6): T_min = min_k I_k/(E·n·l)_k; s⁰, α⁰ from the control points of
what T_min leaves, with the paper's model s·[(r·v)^α − (r·v*)^α·(n·l)/(n·l*)] (k* the shot of
the minimum); then T⁰ = T_min − X, X = s⁰·(r·v*)^α⁰/(n·l*).
Iteration i:
  4.1.1 specular = image − E·T^{i−1}·(n·l), per unit irradiance;
  4.1.2 control points: observations binned by r·v (bins geometric in q = 1 − r·v, plus one
        bin for the mirror direction and one for r·v ≤ 0) and averaged;
  4.1.3 LM on (s, β = log α) per channel over the control points (all three channels batched,
        per-channel acceptance, closed-form 2×2 steps);
  4.1.4 texture T^i = mean_k (image − specular)/(E·n·l) over the valid observations;
  4.1.5 Err_i = Σ (image − render)²; stop when |Err_{i−1} − Err_i| ≤ tol·Err_{i−1}.
Deviations, all documented (the last three found where a plain numpy implementation of 4.1 converged and this one did not): control points come from bins (the paper's "same r·v" sets are
empty for real data; every non-empty bin is a control point, as in the numpy reference — with a
higher ``min_count`` the few observations near the mirror direction of a sharp lobe are lost and
α = 5000 comes out up to 0.4% low); the 4.1.6 LM starts from the best of a coarse α grid; s is free inside
the LM and clamped to ≥ 0 after it; ε is relative; observations within ~1° of grazing
(n·l < 0.02) are left out of the ratios that divide by n·l; the LM weights each control point by
its observation count (a bin mean of m observations stands for m squares of Err: with equal weights
the few observations of the sparse bins far from the mirror direction weigh as much as the
thousands near it, and on flash-at-the-lens captures they pick 4.1.6's α = 1 solution, where
(r·v)^α − z·(r·v*)^α ≈ α·(L − L*) is a line); T⁰ and T^i are reflectances, ≥ 0 (4.1.4 projected:
the material keeps no negative texture, so the specular is fitted to the texture it will be rendered
with — unprojected, a global s too strong for the dark parts of a spatially varying sample leaves
them negative, and the clamp at the end brought that specular back); and the iteration stops at its
lowest Err when PATIENCE iterations bring no new lowest — the alternation is not a descent method,
and past its minimum it drifted along the diffuse-like direction (with the flash at the lens
(r·v)^α ≈ (n·l)^{4α}: s up, α → 1, texture down) with Err rising by ~10⁻³ per iteration, which the
|ΔErr| ≤ tol·Err rule never stopped (yellow_box: α = 1, s = 0.63/0.94/0.19 after 100 iterations).

One chunked pass per iteration computes T^i, Err_i and the next control points together. Chunks
whose lobe is below e⁻⁴⁰ in every shot (for α above a floor) have a texture that does not depend
on s, α: their texture, error and control-point sums are computed once and cached, so pixels
outside all highlights stop costing work.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

from torchmetal.fit.lm import LMEval, levenberg_marquardt
from torchmetal.fit.problem import ACTIVE_LOG, LOG_OFF, Observations, tmin_chunk
from torchmetal.fit.refine import ALPHA_MAX, ALPHA_MIN, BETA_MAX, BETA_MIN

N_BINS = 254  # + mirror bin + r·v ≤ 0 bin = 256: bin indices fit in uint8
Q_MIN = 1e-6
MIN_COUNT = 1
ALPHA0 = 20.0
ALPHA_GRID = (1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0)  # 4.1.6's LM starts from the best of these and α⁰
DIVERGED = 10.0  # Err above 10× the best so far (plus 1e-6 of Σ y²): the iteration ran away
PATIENCE = 5  # iterations without a new lowest Err before the iteration stops (at its best iterate)
NL_MIN = 0.02  # the paper divides by n·l: observations within ~1° of grazing are left out of its ratios


@dataclass
class PaperFit:
    """Result of the paper's scheme: texture (3, P), s, α (3,), history and status."""

    texture: Tensor
    s: Tensor
    alpha: Tensor
    err: float
    iterations: int
    status: str
    history: list[dict] = field(default_factory=list)


def bin_index(L: Tensor, n_bins: int = N_BINS, q_min: float = Q_MIN) -> Tensor:
    """Control-point bin of each observation from L = log r·v, int64, same shape.

    Bin 0: q < q_min; 1…n_bins: geometric in q on [q_min, 1); n_bins + 1: r·v ≤ 0.
    """
    off = L <= LOG_OFF * 0.5
    q = -torch.expm1(torch.where(off, torch.full_like(L, -1.0), L))
    t = (torch.log(q.clamp_min(q_min * 0.5)) - math.log(q_min)) / (-math.log(q_min)) * n_bins
    b = (torch.floor(t).long() + 1).clamp(0, n_bins)
    b = torch.where(q < q_min, torch.zeros_like(b), b)
    return torch.where(off, torch.full_like(b, n_bins + 1), b)


class BinSums:
    """Per-channel control-point sums over bins: count, Σ target, Σ L, and optional Σ z, Σ L*."""

    def __init__(self, n_bins: int, device: torch.device, star: bool = False) -> None:
        self.nb = n_bins + 2
        self.star = star
        self.sums = torch.zeros(5 if star else 3, 3 * self.nb, dtype=torch.float64, device=device)

    def add(self, b: Tensor, ok: Tensor, target: Tensor, L: Tensor, z: Tensor | None = None, lstar: Tensor | None = None) -> None:
        """b (n, 1, c) bins; ok (n, 3, c) bool; target (n, 3, c); L (n, 1, c); z, lstar (n, 3, c).

        Sums in the working dtype per chunk (scatter_add, no masked copies), totals in float64.
        """
        chan = torch.arange(3, device=b.device).view(1, 3, 1) * self.nb
        idx = (b + chan).reshape(-1)
        zero = torch.zeros((), dtype=target.dtype, device=target.device)
        vals = [ok.to(target.dtype), torch.where(ok, target, zero), torch.where(ok, L, zero)]
        if self.star:
            vals += [torch.where(ok, z, zero), torch.where(ok, lstar, zero)]
        v = torch.stack([x.reshape(-1) for x in vals])
        buf = torch.zeros(v.shape[0], 3 * self.nb, dtype=v.dtype, device=v.device)
        buf.scatter_add_(1, idx.unsqueeze(0).expand(v.shape[0], -1), v)
        self.sums += buf.double()

    def __iadd__(self, other: "BinSums") -> "BinSums":
        self.sums += other.sums
        return self

    def control_points(self, min_count: int = MIN_COUNT) -> tuple[Tensor, ...]:
        """(3, nb) weights (observation count of the used bins, 0 elsewhere) and the bin means: target,
        L (and z, L*). The LM weights each control point by its count (module docstring)."""
        s = self.sums.view(self.sums.shape[0], 3, self.nb)
        cnt = s[0]
        use = cnt >= min_count
        den = cnt.clamp_min(1.0)
        return (torch.where(use, cnt, torch.zeros_like(cnt)),) + tuple(s[i] / den for i in range(1, s.shape[0]))


def _lobe(L: Tensor, alpha: Tensor) -> Tensor:
    return torch.exp(alpha * L)


def control_model(cp: tuple[Tensor, ...], alpha: Tensor) -> tuple[Tensor, Tensor]:
    """The control points' model per unit s and its β derivative, each (3, nb); alpha (3, 1).

    e = (r·v)^α, or with the 4.1.6 terms e = (r·v)^α − z̄·(r·v*)^α; de = ∂e/∂β (β = log α).
    """
    L = cp[2]
    e = _lobe(L, alpha)
    de = alpha * L * e
    if len(cp) == 5:
        z, ls = cp[3], cp[4]
        es = _lobe(ls, alpha)
        e, de = e - z * es, de - z * alpha * ls * es
    return e, de


def visible(m: Tensor, e: Tensor) -> Tensor:
    """(3,) bool: the lobe e (3, nb) reaches e⁻⁴⁰ on some used control point (m (3, nb) weights, > 0 when used).

    Below that it counts as zero (as everywhere in the fit): s is not identifiable, and s = Σc̄·e/Σe²
    would be absurdly large (1e68 on a lobe of e⁻¹⁹⁰).
    """
    return ((m > 0) * e.abs()).amax(-1) > math.exp(ACTIVE_LOG)


def grid_start(cp: tuple[Tensor, ...], alphas: tuple[float, ...] = ALPHA_GRID) -> tuple[Tensor, Tensor]:
    """Best (s, β) per channel over a coarse α grid, s projected: max(0, Σ c̄·e / Σ e²) (3,) each."""
    use, c = cp[0], cp[1]
    m = use.double()
    best_cost = torch.full((3,), math.inf, dtype=torch.float64, device=c.device)
    best_s = torch.zeros(3, dtype=torch.float64, device=c.device)
    best_b = torch.zeros(3, dtype=torch.float64, device=c.device)
    for a in alphas:
        e, _ = control_model(cp, torch.full((3, 1), float(a), dtype=torch.float64, device=c.device))
        ee = (m * e * e).sum(-1)
        ok = visible(m, e)
        s = torch.where(ok, (m * c * e).sum(-1) / torch.where(ok, ee, torch.ones_like(ee)), torch.zeros_like(ee))
        s = s.clamp_min(0.0)
        cost = (m * (c - s.unsqueeze(-1) * e) ** 2).sum(-1)
        better = cost < best_cost
        best_cost = torch.where(better, cost, best_cost)
        best_s = torch.where(better, s, best_s)
        best_b = torch.where(better, torch.full_like(best_b, math.log(a)), best_b)
    return best_s, best_b


def fit_control_points(
    cp: tuple[Tensor, ...], s0: Tensor, beta0: Tensor, *, tol: float = 1e-10, max_iters: int = 100
) -> tuple[Tensor, Tensor]:
    """LM on (s, β) per channel over control points (4.1.3, 4.1.6).

    s is free during the LM and clamped to ≥ 0 at the end (as ``least_squares`` in the numpy
    reference): a bound s ≥ 0 inside the LM is absorbing, since at s = 0 the β derivative
    −s·∂e/∂β vanishes, and a first step from a broad start that overshoots s below zero would
    leave a strong sharp highlight at s = 0.

    Args:
        cp: (use, c̄, L̄) or (use, c̄, L̄, z̄, L̄*) from :meth:`BinSums.control_points`, each (3, nb).
        s0, beta0: (3,) start.

    Returns:
        s (3,) ≥ 0 (0 where the lobe is not :func:`visible`), β (3,) float64.
    """
    use, c = cp[0], cp[1]
    m = use.double()

    def oracle(x: Tensor) -> LMEval:
        s, beta = x[:, :1], x[:, 1:]
        e, de = control_model(cp, torch.exp(beta))
        r = c - s * e
        j_s, j_b = -e, -s * de
        cost = (m * r * r).sum(-1)
        grad = torch.stack([(m * j_s * r).sum(-1), (m * j_b * r).sum(-1)], -1)
        h12 = (m * j_s * j_b).sum(-1)
        hess = torch.stack([torch.stack([(m * j_s * j_s).sum(-1), h12], -1),
                            torch.stack([h12, (m * j_b * j_b).sum(-1)], -1)], -2)
        return LMEval(cost, grad, hess)

    x0 = torch.stack([s0.double().clamp_min(0.0), beta0.double().clamp(BETA_MIN, BETA_MAX)], -1)
    lo = torch.tensor([-math.inf, BETA_MIN], dtype=torch.float64, device=x0.device)
    hi = torch.tensor([math.inf, BETA_MAX], dtype=torch.float64, device=x0.device)
    res = levenberg_marquardt(oracle, x0, lower=lo, upper=hi, tol=tol, xtol=tol, max_iters=max_iters)
    x = torch.where(torch.isfinite(res.x), res.x, x0)
    s, beta = x[:, 0].clamp_min(0.0), x[:, 1]
    seen = visible(m, control_model(cp, torch.exp(beta).unsqueeze(-1))[0])
    return torch.where(seen, s, torch.zeros_like(s)), beta


def _ok(w: Tensor, g: Tensor, u: Tensor) -> Tensor:
    """Observations the paper's ratios may use: valid and n·l ≥ NL_MIN (g/u = n·l), bool."""
    return (w > 0) & (g >= NL_MIN * u)


def bins_of(obs: Observations, n_bins: int = N_BINS) -> Tensor:
    """(N, 1, P) uint8/int16 control-point bins of every observation (computed once per fit)."""
    dt = torch.uint8 if n_bins + 2 <= 256 else torch.int16
    out = torch.empty(obs.num_shots, 1, obs.num_pixels, dtype=dt, device=obs.device)
    for j, (p0, p1) in enumerate(obs.chunks):
        out[:, :, p0:p1] = bin_index(obs.L[:, :, p0:p1] if obs.source is None else obs.chunk(j)[3], n_bins).to(dt)
    return out


def tmin_control_points(
    obs: Observations, bidx: Tensor, *, n_bins: int = N_BINS, min_count: int = MIN_COUNT
) -> tuple[tuple[Tensor, ...], Tensor, Tensor, Tensor]:
    """4.1.6's first half: T_min and the control points of what it leaves.

    Args:
        bidx: (N, 1, P) bins from :func:`bins_of`.
        min_count: observations a bin needs to be a control point.

    Returns:
        control points (use, c̄, L̄, z̄, L̄*) each (3, nb); T_min, L* and (n·l)* (3, P) (the
        log r·v and n·l of the shot of the minimum).
    """
    dev = obs.device
    p = obs.num_pixels
    tmin = torch.empty(3, p, dtype=obs.dtype, device=dev)
    lstar = torch.empty(3, p, dtype=obs.dtype, device=dev)
    nlstar = torch.empty(3, p, dtype=obs.dtype, device=dev)
    bins = BinSums(n_bins, dev, star=True)
    for j, (p0, p1) in enumerate(obs.chunks):
        y, g, u, L, w, inten = obs.chunk(j)
        a, iu = inten * g, inten * u
        t, kstar = tmin_chunk(y, a, _ok(w, g, u).to(a.dtype))
        ok = w > 0
        nl = torch.where(u > 0, g / torch.where(u > 0, u, torch.ones_like(u)), torch.zeros_like(u))
        ls = L.expand(-1, 3, -1).gather(0, kstar.unsqueeze(0))[0]
        ns = nl.expand(-1, 3, -1).gather(0, kstar.unsqueeze(0))[0]
        ns = torch.where(ns > 0, ns, torch.ones_like(ns))
        tmin[:, p0:p1], lstar[:, p0:p1], nlstar[:, p0:p1] = t, ls, ns
        target = (y - t * a) / torch.where(ok, iu, torch.ones_like(iu))
        bins.add(bidx[:, :, p0:p1].long(), ok, target, L, nl / ns, ls.unsqueeze(0).expand_as(target))
    return bins.control_points(min_count), tmin, lstar, nlstar


def initial_approximation(
    obs: Observations, bidx: Tensor, *, n_bins: int = N_BINS, alpha0: float = ALPHA0
) -> tuple[Tensor, Tensor, Tensor]:
    """4.1.6: T_min, then s⁰, α⁰ from its control points, then T⁰ = T_min − X.

    The LM on the control points starts from the best of α⁰ and a coarse α grid
    (:func:`grid_start`): the lobe fit is far from convex, and one fixed start can end in a
    distant local minimum (e.g. α = 1 for a sharp α = 5000 highlight).

    Args:
        bidx: (N, 1, P) bins from :func:`bins_of`.

    Returns (T⁰ (3, P), s⁰ (3,), β⁰ (3,)).
    """
    cp, tmin, lstar, nlstar = tmin_control_points(obs, bidx, n_bins=n_bins)
    s0, beta0 = fit_control_points(cp, *grid_start(cp, (alpha0, *ALPHA_GRID)))
    al = torch.exp(beta0).to(obs.dtype).view(3, 1)
    x = s0.to(obs.dtype).view(3, 1) * torch.exp(al * lstar) / nlstar
    t0 = torch.where(obs.saa > 0, tmin - x, obs.fallback).clamp_min(0.0)
    return t0, s0, beta0


@dataclass
class _Cache:
    alpha_lo: float
    static: Tensor  # (n_chunks,) bool: chunk whose lobe is negligible in every shot
    filled: bool = False
    bins: BinSums | None = None
    err: float = 0.0


def paper_pass(
    obs: Observations, bidx: Tensor, s: Tensor, alpha: Tensor, *, texture: Tensor | None = None,
    prev: Tensor | None = None, cache: _Cache | None = None, n_bins: int = N_BINS,
) -> tuple[Tensor, float, BinSums, float]:
    """T^i (4.1.4) when ``texture`` is None, Err_i (4.1.5) and the control points of T^i (4.1.1–2).

    With a ``cache``, chunks it marks static are processed once (the first pass with this cache)
    and later read from it; their texture is taken from ``prev`` (the last pass's texture).

    Returns (texture (3, P), Err, control-point sums, fraction of pixels processed).
    """
    dev = obs.device
    if texture is not None:
        cache = None  # a given texture is not the iteration's own: nothing to cache
    tex = (texture if texture is not None else prev if prev is not None else obs.fallback).clone()
    s3 = s.to(obs.dtype).view(1, 3, 1)
    a3 = alpha.to(obs.dtype).view(1, 3, 1)
    bins = BinSums(n_bins, dev)
    fill = cache is not None and not cache.filled
    static_bins = BinSums(n_bins, dev) if fill else None
    err = torch.zeros((), dtype=torch.float64, device=dev)
    static_err = torch.zeros((), dtype=torch.float64, device=dev)
    done = 0
    zero = torch.zeros((), dtype=obs.dtype, device=dev)
    for j, (p0, p1) in enumerate(obs.chunks):
        skip = cache is not None and bool(cache.static[j])
        if skip and cache.filled:
            continue
        y, g, u, L, w, inten = obs.chunk(j)
        a, iu = inten * g, inten * u
        spec = s3 * iu * torch.exp(a3 * L)
        if texture is None:
            ok = _ok(w, g, u)  # 4.1.4 divides by n·l: not within ~1° of grazing
            n = ok.sum(0)
            t = (torch.where(ok, y - spec, zero) / torch.where(ok, a, torch.ones_like(a))).sum(0) / n.clamp_min(1)
            t = torch.where(n > 0, t, obs.fallback[:, p0:p1])
            t = t.clamp_min(0.0)  # a texture is a reflectance: the projected 4.1.4 (module docstring)
            tex[:, p0:p1] = t
        else:
            t = tex[:, p0:p1]
        ok = w > 0
        d = y - t * a
        r = (d - spec) * w
        e = (r * r).sum(0).double().sum()
        target = d / torch.where(ok, iu, torch.ones_like(iu))
        b = bidx[:, :, p0:p1].long()
        if skip:
            static_bins.add(b, ok, target, L)
            static_err += e
        else:
            bins.add(b, ok, target, L)
            err += e
        done += p1 - p0
    if cache is not None:
        if fill:
            cache.bins, cache.err, cache.filled = static_bins, float(static_err), True
        bins += cache.bins
        err += cache.err
    return tex, float(err), bins, done / max(1, obs.num_pixels)


def _new_cache(obs: Observations, alpha: Tensor) -> _Cache:
    lo = max(ALPHA_MIN, 0.5 * float(alpha.min()))
    static = ~(obs.active_shots(lo).any(0))
    return _Cache(alpha_lo=lo, static=static)


def paper_scheme(
    obs: Observations,
    *,
    tol: float = 1e-6,
    max_iters: int = 100,
    n_bins: int = N_BINS,
    on_iter: Callable[[str, int, float, float], None] | None = None,
) -> PaperFit:
    """Run 4.1.6 then iterations 4.1.1–4.1.5 until |ΔErr| ≤ tol·Err or ``max_iters``.

    The paper's alternation is not a descent method: if Err runs away (non-finite, or above
    10× the best so far) it stops with status "diverged" and returns the best iterate.

    ``on_iter(stage, iteration, rmse, active)`` reports "init" once, then "paper" per iteration.
    """
    n_obs = obs.n_obs
    bidx = bins_of(obs, n_bins)
    t0, s, beta = initial_approximation(obs, bidx, n_bins=n_bins)
    alpha = torch.exp(beta)
    cache = _new_cache(obs, alpha)
    tex, err, bins, frac = paper_pass(obs, bidx, s, alpha, texture=t0, n_bins=n_bins)
    history = [{"stage": "init", "iter": 0, "rmse": math.sqrt(err / n_obs), "active": frac}]
    if on_iter is not None:
        on_iter("init", 0, history[-1]["rmse"], frac)
    status, it, rising = "max_iters", 0, 0
    best = (tex, s, beta, err)
    energy = float(obs.energy().sum())
    for it in range(1, max_iters + 1):
        s, beta = fit_control_points(bins.control_points(), s, beta)
        alpha = torch.exp(beta)
        if float(alpha.min()) < cache.alpha_lo:
            cache = _new_cache(obs, alpha)
        tex, err_new, bins, frac = paper_pass(obs, bidx, s, alpha, prev=tex, cache=cache, n_bins=n_bins)
        if not math.isfinite(err_new) or err_new > DIVERGED * best[3] + 1e-6 * energy:
            # the alternation is not a descent method; stop when it runs away and keep the best iterate
            status = "diverged"
            tex, s, beta, err = best
            break
        history.append({"stage": "paper", "iter": it, "rmse": math.sqrt(err_new / n_obs), "active": frac})
        if on_iter is not None:
            on_iter("paper", it, history[-1]["rmse"], frac)
        change = abs(err - err_new)
        err = err_new
        if err <= best[3]:
            best, rising = (tex, s, beta, err), 0
        else:
            rising += 1
        if change <= tol * max(err, 1e-300):
            status = "converged"
            break
        if rising >= PATIENCE:
            # past its Err minimum the alternation drifts along the diffuse-like direction (module docstring)
            status = "converged"
            break
    if err > best[3]:
        tex, s, beta, err = best
    alpha = torch.exp(beta)
    return PaperFit(texture=tex, s=s, alpha=alpha.clamp(ALPHA_MIN, ALPHA_MAX), err=err, iterations=it, status=status,
                    history=history)
