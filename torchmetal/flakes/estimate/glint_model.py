"""The glint model's parts shared by the likelihood numerator and the visibility integral.

A flake is flat: it glints in shot k only when its normal m lies close to the half vector
h_k(p) at its position, with glint strength g_k = exp(−|m − h_k|²/(2σ_g²)) =
exp(−(1 − m·h_k)/σ_g²). Its slope μ (m ∝ n + μ₁t₁ + μ₂t₂, the :func:`flake_field` draw) is
N(0, τ²I); its peak glint amplitude A (channel mean, reflectance units) is log-normal.
The detector fires when A·g_k exceeds T_k = k_hi·σ_k(p); with pixel noise σ_k that happens
with probability Φ(A·g_k/σ_k − k_hi) (used in its logistic form σ(1.702·z), :func:`log_detect`).

Held here: the data the likelihood reads (:class:`GlintData`) and the fitted parameters
(:class:`GlintFit`); the slope density p_τ(m), N(μ; 0, τ²I) times the gnomonic Jacobian
1/(m·n)³, and the frame it is measured in; the detection probability; the amplitude
distribution, LogNormal truncated to A > A₀, the amplitude floor (:func:`log_amp_floor`: the
density counts flakes that some shot could detect at perfect alignment; flakes that never
glinted because of their tilt are counted, flakes fainter than the noise everywhere are not, as
nothing in the data says how many there are), its quantile nodes and truncated moments; and the
quadrature helpers both integrals use (ring nodes, shot order, cap radius, per-data memo).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

LOG2PI = math.log(2.0 * math.pi)


def orthonormal_pair(v: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors orthogonal to unit v (..., 3) and to each other."""
    ex = torch.zeros_like(v)
    ex[..., 0] = 1.0
    ey = torch.zeros_like(v)
    ey[..., 1] = 1.0
    ref = torch.where(v[..., :1].abs() < 0.9, ex, ey)
    t1 = ref - (ref * v).sum(-1, keepdim=True) * v
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    return t1, torch.cross(v, t1, dim=-1)


def _log_slope_density(m: Tensor, n: Tensor, t1: Tensor, t2: Tensor, tau: Tensor) -> Tensor:
    """log of N(μ; 0, τ²I)/(m·n)³ for unit m (..., 3); −inf where m·n ≤ 0.05."""
    return log_slope_from((m * n).sum(-1), (m * t1).sum(-1), (m * t2).sum(-1), tau)


def log_slope_from(mn: Tensor, m1: Tensor, m2: Tensor, tau: Tensor) -> Tensor:
    """:func:`_log_slope_density` from the projections m·n, m·t1, m·t2 (all (...,))."""
    ok = mn > 0.05
    mn_s = torch.where(ok, mn, torch.ones_like(mn))
    mu1 = m1 / mn_s
    mu2 = m2 / mn_s
    val = -(mu1 * mu1 + mu2 * mu2) / (2 * tau * tau) - LOG2PI - 2 * torch.log(tau) - 3 * torch.log(mn_s)
    return torch.where(ok, val, torch.full_like(val, -1e4))


PROBIT = 1.702  # logistic ≈ probit: |σ(1.702 z) − Φ(z)| < 0.01, and far cheaper than log_ndtr


def log_detect(a_over_sigma: Tensor, k_hi: float, detected: Tensor, outlier: float = 0.0,
               log_measurable: Tensor | None = None) -> Tensor:
    """log P(detected or not), P(detected) = Φ(A·g/σ − k_hi) in its logistic form.

    ``log_measurable``: log of the probability that the glint does not clip (:func:`log_unclipped`); either
    state of a measurable shot needs it (a clipped glint leaves the shot unmeasured, neither).

    With ``outlier`` = ε the probability is mixed with a coin flip, (1 − ε)·P + ε/2, so one
    mis-associated or merged detection costs at most log(2/ε) instead of dominating the fit.
    Non-detections are divided by their value at P = 0, 1 − ε/2, so a shot whose cap is far
    from the flake adds exactly 0: which far shots the caller includes (a choice that moves
    with the parameters) then cannot make the likelihood jump. (Detected shots are always
    included, so their constant does not depend on the parameters.)
    """
    z = PROBIT * (a_over_sigma - k_hi)
    lp = F.logsigmoid(torch.where(detected, z, -z))
    if log_measurable is not None:
        lp = lp + log_measurable
    if outlier > 0:
        lp = torch.logaddexp(lp + math.log1p(-outlier), torch.full_like(lp, math.log(0.5 * outlier)))
        lp = torch.where(detected, lp, lp - math.log1p(-0.5 * outlier))
    return lp


#: spread (log units) of a glint's clipping level about the headroom of :attr:`GlintData.headroom`: the flakes'
#: own colour varies about the mean chroma the headroom is measured with (≈ 10 % per channel)
HEADROOM_SPREAD = 0.1


def log_unclipped(log_glint: Tensor, log_headroom: Tensor, spread: Tensor | float = HEADROOM_SPREAD) -> Tensor:
    """log P(a glint of peak amplitude exp(``log_glint``) does not clip) = log Φ((log U − log A·g)/s), logistic form.

    A glint whose brightest pixel clips (coat + E·A·g·chroma above the encoding's top) makes its neighbourhood
    unmeasurable (:func:`~torchmetal.flakes.estimate.association.measurable`): the data never hold the brightest
    glints, and a likelihood unaware of it puts the amplitude mean low (zoo flakes_a: colour ×0.78).
    """
    return F.logsigmoid(PROBIT * (log_headroom - log_glint) / spread)


def log_unmeasured(log_glint: Tensor, log_headroom: Tensor, outlier: float) -> Tensor:
    """log P(a shot is unmeasured at the flake) = log(ε + (1 − ε)·P(the glint clips)).

    Where the coat itself clips next to the flake the headroom is ≈ 0 and this is ≈ 0 for any glint (the shot
    says nothing, as before); elsewhere an unmeasured shot says the flake glinted brighter than its headroom
    there. ε (the likelihood's outlier rate) covers the shots unmeasured for other reasons (a neighbour's glint)."""
    clip = F.logsigmoid(PROBIT * (log_glint - log_headroom) / HEADROOM_SPREAD)
    return torch.logaddexp(clip + math.log1p(-outlier), torch.full_like(clip, math.log(outlier)))


@dataclass
class GlintData:
    """Tensors the likelihood needs (float64)."""

    half: Tensor  # (J, N, 3)
    normal: Tensor  # (J, 3)
    anchor: Tensor  # (J,)
    amp: Tensor  # (J,)
    detected: Tensor  # (J, N)
    sigma: Tensor  # (J, N)
    grid_half: Tensor  # (G, N, 3)
    grid_normal: Tensor  # (G, 3)
    grid_sigma: Tensor  # (G, N)
    grid_area: Tensor  # (G,) pixels per cell (what is measurable is in grid_valid)
    k_hi: float
    count: int  # all associated flakes (the numerator may use a subsample)
    log_floor: float | None = None  # log amplitude floor; None: FLOOR_LEVEL·min grid σ (:func:`log_amp_floor`)
    observed: Tensor | None = None  # (J, N) bool, shots measurable at the flake (None: all)
    grid_valid: Tensor | None = None  # (G, N) measurable fraction of each cell per shot (None: all)
    # log of the brightest peak amplitude a glint can have without clipping (channel-mean reflectance units),
    # per flake and shot (J, N), and its mean and spread over each cell's measurable pixels (G, N); None: no clipping
    headroom: Tensor | None = None
    grid_headroom: Tensor | None = None
    grid_headroom_sd: Tensor | None = None


def nearest_shots(half: Tensor, first: Tensor, k: int, prefer: Tensor | None = None) -> Tensor:
    """Indices (..., k) of the shots whose half vectors are closest to shot ``first``.

    Args:
        half: (..., N, 3) unit half vectors; first: (...,) shot that comes first (itself);
        k: how many; prefer: optional (..., N) bool, shots taken before any other (e.g. those
            where the flake was detected).
    """
    h0 = half.gather(-2, first[..., None, None].expand(*first.shape, 1, 3))
    dist = 1.0 - (half * h0).sum(-1)  # (..., N)
    if prefer is not None:
        dist = dist - 10.0 * prefer.to(dist.dtype)
    dist = dist.scatter(-1, first[..., None], -100.0)
    return dist.topk(min(k, half.shape[-2]), dim=-1, largest=False).indices


def overlap_count(centres: Tensor, half: Tensor, angle: float) -> int:
    """Largest number of shots (of half (R, N, 3)) within ``angle`` of a centre (R, M, 3)."""
    cos = torch.einsum("rmc,rnc->rmn", centres, half)
    return max(1, int((cos > math.cos(min(angle, math.pi))).sum(-1).max()))


def cap_radius(sg: Tensor, log_a_max: float, sigma_min: float, level: float) -> float:
    """Largest angular radius of a glint cap: 1 − cos β = σ_g² ln(A_max / (level·σ_min))."""
    u = float(sg.detach()) ** 2 * max(0.0, log_a_max - math.log(level * sigma_min))
    return math.acos(max(-1.0, 1.0 - min(u, 1.9)))


def ring_nodes(n_a: int, n_phi: int, dtype, device) -> tuple[Tensor, Tensor]:
    qa = (torch.arange(n_a, dtype=dtype, device=device) + 0.5) / n_a
    phi = 2 * math.pi * (torch.arange(n_phi, dtype=dtype, device=device) + 0.5) / n_phi
    return qa, phi


def memo(d: GlintData, key: tuple, make):
    """Parameter-free tensors of ``d`` (frames, projections, shot orders), computed once per
    GlintData object (treated as immutable): the fit evaluates the likelihood ~20 times on
    the same data."""
    store = d.__dict__.setdefault("_memo", {})
    if key not in store:
        store[key] = make()
    return store[key]


FLOOR_LEVEL = 2.0  # the faintest flake counted glints at this many σ of the quietest cell


def log_amp_floor(d: GlintData) -> float:
    """log of the amplitude floor A₀ = FLOOR_LEVEL·σ_min: the model's amplitude distribution is
    the log-normal truncated to A > A₀, and its density counts those flakes only.

    Fainter flakes are never detected (P < 1% at perfect alignment in the quietest cell), so
    the data cannot say how many there are: without the floor a steep bright tail of a mostly
    invisible population fits many real captures better, and the density runs off to infinity.
    """
    if d.log_floor is not None:
        return d.log_floor
    return math.log(FLOOR_LEVEL * float(d.grid_sigma.double().min()))


def tail_nodes(la: Tensor, va: Tensor, log_lo: Tensor, qa: Tensor, log_floor: float) -> tuple[Tensor, Tensor]:
    """Quantile nodes of log A ~ N(la, va²) truncated to log A > max(log_lo, log_floor).

    Args:
        la, va: log-amplitude mean and spread (scalars); log_lo: (R,) lower bounds;
        qa: (nA,) quantile levels in (0, 1); log_floor: the model's amplitude floor.

    Returns:
        log A nodes (R, nA) in the dtype of ``log_lo``, and log P(A > lo | A > floor) (R,) in
        float64 (it underflows float32 for a far tail).
    """
    dt = log_lo.dtype
    la, va = la.double(), va.double()
    z0 = (log_lo.double().clamp_min(log_floor) - la) / va  # small tensors: float64
    log_tail = torch.special.log_ndtr(-z0)  # log(1 − F(lo))
    # u_i = F(lo) + (1 − F(lo))·q_i, written through the upper tail to keep precision near 1
    tail = torch.exp(log_tail).unsqueeze(1) * (1 - qa.double())  # 1 − u_i
    z = torch.maximum(-torch.special.ndtri(tail.clamp(1e-300, 1.0)), z0.unsqueeze(1))
    log_norm = torch.special.log_ndtr(-(log_floor - la) / va)
    return (la + va * z).to(dt), log_tail - log_norm


def _log_ndtr_diff(a: float, b: float) -> float:
    """log(Φ(b) − Φ(a)) for a < b, without cancellation in either tail (−inf when a ≥ b)."""
    if not a < b:
        return -math.inf
    if a > 0:  # both in the upper tail: Φ(b) − Φ(a) = Φ(−a) − Φ(−b)
        a, b = -b, -a
    lb = float(torch.special.log_ndtr(torch.tensor(b, dtype=torch.float64)))
    la = float(torch.special.log_ndtr(torch.tensor(a, dtype=torch.float64)))
    return lb + math.log1p(-math.exp(min(la - lb, 0.0))) if la < lb else -math.inf


def truncated_moments(log_amp_mean: float, log_amp_std: float, log_floor: float,
                      log_ceiling: float = math.inf) -> tuple[float, float]:
    """Mean and variance of A ~ LogNormal(mean, std) truncated to exp(log_floor) < A < exp(log_ceiling).

    The ceiling is the brightest amplitude the detections support (:attr:`GlintFit.log_amp_ceiling`):
    above it a log-normal's tail is extrapolation, and with an unidentified spread its moments grow as
    exp(2·std²) without bound (a colour of 1e20 from a spread of 6). Both moments lie in [floor, ceiling]
    and [0, (ceiling − floor)²] by construction."""
    mu, v = log_amp_mean, max(log_amp_std, 1e-12)
    zf = (log_floor - mu) / v
    zc = (log_ceiling - mu) / v if math.isfinite(log_ceiling) else math.inf
    den = _log_ndtr_diff(zf, zc)
    if not math.isfinite(den):  # all the mass outside [floor, ceiling]: the nearer end
        a = math.exp(min(max(mu, log_floor), log_ceiling))
        return a, 0.0

    def log_moment(k: int) -> float:  # log E[A^k | floor < A < ceiling]
        return k * mu + 0.5 * (k * v) ** 2 + _log_ndtr_diff(zf - k * v, zc - k * v) - den
    lo, hi = math.exp(log_floor), math.exp(log_ceiling) if math.isfinite(log_ceiling) else math.inf
    m1 = min(max(math.exp(log_moment(1)), lo), hi)
    return m1, max(math.exp(log_moment(2)) - m1 * m1, 0.0)


@dataclass
class GlintFit:
    """Result of :func:`~torchmetal.flakes.estimate.stats.fit_glints`: fitted values, profiled density,
    loglik at the optimum, standard errors and identifiability (by log-parameter name), L-BFGS
    iterations and objective evaluations (L-BFGS runs + curvature)."""

    tilt_sigma: float
    glint_sigma: float
    log_amp_mean: float
    log_amp_std: float
    density: float
    expected_fraction: float
    loglik: float
    std_err: dict
    identified: dict
    iterations: int
    evaluations: int = 0
    log_amp_floor: float = -math.inf
    log_amp_ceiling: float = math.inf  # log of the brightest amplitude the detections support
    degenerate: str | None = None  # why the fit stopped early without a usable model (None: it did not)
