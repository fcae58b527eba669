"""Flake statistics across shots: association, glint likelihood, and the fitted FlakeModel.

A flake is flat: it glints in shot k only when its normal m lies close to the half vector
h_k(p) at its position, with glint strength g_k = exp(−|m − h_k|²/(2σ_g²)) =
exp(−(1 − m·h_k)/σ_g²). Its slope μ (m ∝ n + μ₁t₁ + μ₂t₂, the :func:`flake_field` draw) is
N(0, τ²I); its peak glint amplitude A (channel mean, reflectance units) is log-normal.
The detector fires when A·g_k exceeds T_k = k_hi·σ_k(p); with pixel noise σ_k that happens
with probability Φ(A·g_k/σ_k − k_hi) (used in its logistic form σ(1.702·z)).

Detections of one flake in several shots are associated by position. Each associated flake j
contributes its detection pattern b_jk and the amplitude â_j of its detection in the anchor
shot k*, its first detected shot (a choice independent of the amplitudes, so the anchor carries
no selection bias; shape and colour are measured on its brightest detection). Given (A, m) on
the sphere, the anchor amplitude pins m to a ring
1 − m·h_k* = σ_g² ln(A/â) around h_k*; the density of â there is σ_g²/â (exact change of
variables), so

    f_j = σ_g²/â_j ∫dA f_A(A) ∮dφ  p_τ(m) · Π_{k≠k*} P(b_jk | m, A),

with p_τ(m) the slope density N(μ; 0, τ²I) times the gnomonic Jacobian 1/(m·n)³. Flakes that
never glint are accounted for by the selection probability

    P_any(p) = ∫dA f_A(A) ∫dΩ p_τ(m) · [1 − Π_k (1 − P_k(m, A))],

integrated cap by cap with a partition of unity. A is LogNormal truncated to A > A₀, the
amplitude floor (:func:`log_amp_floor`): the density counts flakes that some shot could detect
at perfect alignment (flakes that never glinted because of their tilt are counted; flakes
fainter than the noise everywhere are not, as nothing in the data says how many there are).
The true density is profiled out in closed form
(ρ̂ = J / ∫P_any dp) and (τ, σ_g, log-A mean and spread) maximise
Σ_j log f_j − J log ∫P_any dp (L-BFGS, float64, log-normal priors: weak on τ, σ_g and the
log-A mean; on the log-A spread a moderate one, LogNormal(log 0.15, 0.5²), since a hundred
flakes barely constrain it while the colour's E[A] depends on it). σ_g is identified by flakes
seen in more than one shot (with none, it stays at its prior mean 0.03 rad), τ by how the glint
rate falls off as h moves away from the normal; ``report["identified"]`` says when either is not. Shots where a flake is next to a saturated or
masked pixel are missing for that flake (:func:`measurable`), in the numerator and in P_any.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.flakes import regions
from torchmetal.flakes.detect import Detection, Particles
from torchmetal.flakes.model import MAX_DENSITY, MIN_CELL, FlakeModel
from torchmetal.geometry import shading_geometry, surface_points

_LOG2PI = math.log(2.0 * math.pi)


# ---------------------------------------------------------------- association + measurement


def _components(n: int, src: Tensor, dst: Tensor) -> tuple[Tensor, int]:
    """Connected components of an undirected graph on n nodes (min-label propagation)."""
    lab = torch.arange(n, device=src.device)
    if src.numel():
        while True:
            m = torch.minimum(lab[src], lab[dst])
            new = lab.clone()
            new.scatter_reduce_(0, src, m, reduce="amin")
            new.scatter_reduce_(0, dst, m, reduce="amin")
            new = new[new]  # pointer jumping
            if torch.equal(new, lab):
                break
            lab = new
    uniq, inv = torch.unique(lab, return_inverse=True)
    return inv, int(uniq.numel())


def associate(particles: Particles, height: int, width: int, radius: float = 1.5) -> tuple[Tensor, int]:
    """Group detections of the same flake across shots.

    Two detections from different shots whose centroids lie within ``radius`` px are linked;
    detections of one shot are never linked directly (they are different flakes); flakes are
    the connected components of the links. Candidate pairs come from a bucket grid, so the
    cost is O(P log P).

    Returns:
        flake id (P,) int64 in 0..J−1, and J.
    """
    p = len(particles)
    dev = particles.shot.device
    if p == 0:
        return torch.zeros(0, dtype=torch.int64, device=dev), 0
    cell = max(1.0, float(radius))
    bi = torch.floor(particles.cy / cell).long() + 1
    bj = torch.floor(particles.cx / cell).long() + 1
    nbj = int(width / cell) + 4
    key = bi * nbj + bj
    order = torch.argsort(key)
    skey = key[order]
    counts = torch.unique_consecutive(skey, return_counts=True)[1]
    kmax = int(counts.max())
    src, dst = [], []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            nk = key + di * nbj + dj
            lo = torch.searchsorted(skey, nk)
            for t in range(kmax):
                idx = (lo + t).clamp(max=p - 1)
                hit = (lo + t < p) & (skey[idx] == nk)
                other = order[idx]
                mine = torch.arange(p, device=dev)
                ok = hit & (other > mine)
                src.append(mine[ok])
                dst.append(other[ok])
    src_t = torch.cat(src)
    dst_t = torch.cat(dst)
    d2 = (particles.cy[src_t] - particles.cy[dst_t]) ** 2 + (particles.cx[src_t] - particles.cx[dst_t]) ** 2
    keep = (d2 <= radius * radius) & (particles.shot[src_t] != particles.shot[dst_t])
    return _components(p, src_t[keep], dst_t[keep])


@dataclass
class FlakeObservations:
    """Per associated flake j (J rows), over N shots.

    row, col (J,) int64 pixel of the brightest detection; anchor (J,) the likelihood's anchor
    shot, the first shot the flake was detected in; amp (J,) the anchor's peak amplitude
    (channel-mean reflectance units); detected (J, N) bool; sigma (J, N) local pixel noise σ at
    the flake; measured on the brightest detection: area (J,) flux/peak area (px²), aspect (J,)
    minor/major of its ellipse, major (J,) its semi-major axis (px), chroma (J, 3) its colour /
    its channel mean, snr (J,) its amp/σ;
    half (J, N, 3), normal (J, 3): unit half vectors and surface normal at the flake;
    observed (J, N) bool: the flake's neighbourhood is measurable in that shot (:func:`measurable`).
    """

    row: Tensor
    col: Tensor
    anchor: Tensor
    amp: Tensor
    detected: Tensor
    sigma: Tensor
    area: Tensor
    aspect: Tensor
    major: Tensor
    chroma: Tensor
    snr: Tensor
    half: Tensor
    normal: Tensor
    observed: Tensor

    def __len__(self) -> int:
        return int(self.row.numel())


CLIP_RADIUS = 2  # px: a detection this close to an invalid (saturated, masked) pixel is not measured


def measurable(det: Detection, radius: int = CLIP_RADIUS) -> Tensor:
    """(N, H, W) bool: pixels whose (2r+1)² neighbourhood is valid in that shot.

    A glint next to a saturated pixel (a highlight, the mask's edge, or its own clipped peak)
    has its amplitude, area and colour biased low, and whether it was detected says little,
    so such shots are treated as missing (neither a detection nor a miss) instead. Keeping
    self-clipped glints as detections was measured worse: with 3 % of the pixels saturated
    their low amplitudes inflated the density by 17–55 %, against 3–6 % when they are missing.
    """
    n, _, h, w = det.signal.shape
    bad = ~det.valid[:, 0]
    if not bool(bad.any()):
        return torch.ones(n, h, w, dtype=torch.bool, device=bad.device)
    k = 2 * radius + 1  # separable dilation (rows, then columns)
    near = F.max_pool2d(bad.unsqueeze(1).to(torch.float32), (1, k), 1, (0, radius))
    near = F.max_pool2d(near, (k, 1), 1, (radius, 0))[:, 0]
    return (near == 0).expand(n, -1, -1)


def _particle_pixels(p: Particles, h: int, w: int) -> tuple[Tensor, Tensor]:
    """Row and column (P,) of the pixel holding each particle's centroid, inside an H×W image."""
    return p.cy.floor().long().clamp(0, h - 1), p.cx.floor().long().clamp(0, w - 1)


def observe(det: Detection, flake_id: Tensor, count: int, geometry: "Geometry", ok: Tensor | None = None) -> FlakeObservations:
    """Measure every associated flake on its brightest detection, pick its likelihood anchor
    and collect its detection pattern.

    ``flake_id`` (P,): associated flake of each particle, −1 for particles left out;
    ``ok``: :func:`measurable` of ``det`` (computed when None).
    """
    p = det.particles
    n_shots, _, h, w = det.signal.shape
    ok = measurable(det) if ok is None else ok
    rows = torch.nonzero(flake_id >= 0, as_tuple=True)[0]
    fid, shot = flake_id[rows], p.shot[rows]
    anchor_p = rows[regions.segment_argmax(fid, p.snr[rows].double(), count)]
    a = p.select(anchor_p)
    row, col = _particle_pixels(a, h, w)
    detected = torch.zeros(count, n_shots, dtype=torch.bool, device=row.device)
    detected[fid, shot] = True
    # flux/peak area on the anchor, with a ring background around the particle (radius 5 patch)
    r = 4
    sig = regions.patches(det.signal, a.shot, row, col, r)[:, 0]
    lab = regions.patches(det.labels.unsqueeze(1).double(), a.shot, row, col, r)[:, 0]
    own = lab == (anchor_p + 1).view(-1, 1, 1).double()
    other = (lab > 0) & ~own
    own_d = F.max_pool2d(own.double().unsqueeze(1), 3, 1, 1)[:, 0] > 0
    ring = ~F.max_pool2d((own_d | other).double().unsqueeze(1), 3, 1, 1)[:, 0].bool()
    bg = (sig * ring).sum((-2, -1)) / ring.sum((-2, -1)).clamp_min(1)
    flux = ((sig - bg.view(-1, 1, 1)) * own_d).sum((-2, -1))
    area = (flux / a.amp.clamp_min(1e-12)).clamp_min(0.25)
    sigma = det.sigma[:, 0, row, col].t()  # (J, N)
    lam1 = (a.major / 4) ** 2 - 1.0 / 12.0
    lam2 = (a.minor / 4) ** 2 - 1.0 / 12.0
    aspect = torch.sqrt(lam2.clamp_min(1e-3) / lam1.clamp_min(1e-3)).clamp(0.05, 1.0)
    chroma = a.rgb / a.rgb.mean(1, keepdim=True).clamp_min(1e-12)
    half, normal = geometry.at_pixels(row, col)
    # the likelihood's anchor is the flake's first detected shot, a choice independent of the
    # amplitudes: anchoring on the brightest detection (the max of several noisy peaks) biased
    # E[A], and with it the colour, 6-10 % high where flakes glint in many shots (flash layout)
    ring_p = rows[regions.segment_argmax(fid, -shot.double(), count)]
    return FlakeObservations(
        row=row, col=col, anchor=p.shot[ring_p], amp=p.amp[ring_p], detected=detected, sigma=sigma, area=area,
        aspect=aspect, major=0.5 * a.major, chroma=chroma, snr=a.snr, half=half, normal=normal,
        observed=ok[:, row, col].t(),
    )


# ---------------------------------------------------------------- geometry on the sphere


@dataclass
class Geometry:
    """Shot geometry: normals (3, H, W), lights (N, 4), intensities (N, 3), cameras (N, 4), size."""

    normals: Tensor
    lights: Tensor
    intensities: Tensor
    cameras: Tensor
    size: tuple[float, float]

    def _half(self, normals: Tensor, points: Tensor) -> Tensor:
        g = shading_geometry(normals, self.lights, self.intensities, self.cameras, points=points)
        return g.half  # (N, 3, h, w)

    def at_pixels(self, row: Tensor, col: Tensor) -> tuple[Tensor, Tensor]:
        """Unit half vectors (J, N, 3) and normals (J, 3) at pixel centres."""
        h, w = self.normals.shape[-2:]
        dt = torch.float64
        y = (0.5 - (row.to(dt) + 0.5) / h) * self.size[1]
        x = ((col.to(dt) + 0.5) / w - 0.5) * self.size[0]
        pts = torch.stack([x, y, torch.zeros_like(x)]).unsqueeze(1)  # (3, 1, J)
        n = self.normals[:, row, col].to(dt).unsqueeze(1)
        half = self._half(n, pts)[:, :, 0].permute(2, 0, 1)  # (J, N, 3)
        return half, n[:, 0].t()

    def on_grid(self, gh: int, gw: int) -> tuple[Tensor, Tensor]:
        """Half vectors (G, N, 3) and normals (G, 3) at the centre pixels of a gh×gw grid of cells.

        The normal is the centre pixel's own (not a cell average, which would flatten bumps).
        """
        h, w = self.normals.shape[-2:]
        rows = ((torch.arange(gh, device=self.normals.device) + 0.5) * h / gh).long().clamp(max=h - 1)
        cols = ((torch.arange(gw, device=self.normals.device) + 0.5) * w / gw).long().clamp(max=w - 1)
        rr, cc = torch.meshgrid(rows, cols, indexing="ij")
        return self.at_pixels(rr.flatten(), cc.flatten())


def _frame(v: Tensor) -> tuple[Tensor, Tensor]:
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
    return _log_slope_from((m * n).sum(-1), (m * t1).sum(-1), (m * t2).sum(-1), tau)


def _log_slope_from(mn: Tensor, m1: Tensor, m2: Tensor, tau: Tensor) -> Tensor:
    """:func:`_log_slope_density` from the projections m·n, m·t1, m·t2 (all (...,))."""
    ok = mn > 0.05
    mn_s = torch.where(ok, mn, torch.ones_like(mn))
    mu1 = m1 / mn_s
    mu2 = m2 / mn_s
    val = -(mu1 * mu1 + mu2 * mu2) / (2 * tau * tau) - _LOG2PI - 2 * torch.log(tau) - 3 * torch.log(mn_s)
    return torch.where(ok, val, torch.full_like(val, -1e4))


_PROBIT = 1.702  # logistic ≈ probit: |σ(1.702 z) − Φ(z)| < 0.01, and far cheaper than log_ndtr


def _log_detect(a_over_sigma: Tensor, k_hi: float, detected: Tensor, outlier: float = 0.0) -> Tensor:
    """log P(detected or not), P(detected) = Φ(A·g/σ − k_hi) in its logistic form.

    With ``outlier`` = ε the probability is mixed with a coin flip, (1 − ε)·P + ε/2, so one
    mis-associated or merged detection costs at most log(2/ε) instead of dominating the fit.
    Non-detections are divided by their value at P = 0, 1 − ε/2, so a shot whose cap is far
    from the flake adds exactly 0: which far shots the caller includes (a choice that moves
    with the parameters) then cannot make the likelihood jump. (Detected shots are always
    included, so their constant does not depend on the parameters.)
    """
    z = _PROBIT * (a_over_sigma - k_hi)
    lp = F.logsigmoid(torch.where(detected, z, -z))
    if outlier > 0:
        lp = torch.logaddexp(lp + math.log1p(-outlier), torch.full_like(lp, math.log(0.5 * outlier)))
        lp = torch.where(detected, lp, lp - math.log1p(-0.5 * outlier))
    return lp


# ---------------------------------------------------------------- likelihood


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


def _gather_shots(x: Tensor, idx: Tensor) -> Tensor:
    """x (R, N[, 3]) gathered at idx (R, K) along the shot axis."""
    if x.dim() == 3:
        return x.gather(1, idx[..., None].expand(-1, -1, x.shape[-1]))
    return x.gather(1, idx)


def _overlap_count(centres: Tensor, half: Tensor, angle: float) -> int:
    """Largest number of shots (of half (R, N, 3)) within ``angle`` of a centre (R, M, 3)."""
    cos = torch.einsum("rmc,rnc->rmn", centres, half)
    return max(1, int((cos > math.cos(min(angle, math.pi))).sum(-1).max()))


def _cap_radius(sg: Tensor, log_a_max: float, sigma_min: float, level: float) -> float:
    """Largest angular radius of a glint cap: 1 − cos β = σ_g² ln(A_max / (level·σ_min))."""
    u = float(sg.detach()) ** 2 * max(0.0, log_a_max - math.log(level * sigma_min))
    return math.acos(max(-1.0, 1.0 - min(u, 1.9)))


def _ring_nodes(n_a: int, n_phi: int, dtype, device) -> tuple[Tensor, Tensor]:
    qa = (torch.arange(n_a, dtype=dtype, device=device) + 0.5) / n_a
    phi = 2 * math.pi * (torch.arange(n_phi, dtype=dtype, device=device) + 0.5) / n_phi
    return qa, phi


def _memo(d: GlintData, key: tuple, make):
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


def _tail_nodes(la: Tensor, va: Tensor, log_lo: Tensor, qa: Tensor, log_floor: float) -> tuple[Tensor, Tensor]:
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


def truncated_moments(log_amp_mean: float, log_amp_std: float, log_floor: float) -> tuple[float, float]:
    """Mean and variance of A ~ LogNormal(mean, std) truncated to A > exp(log_floor)."""
    mu, v = log_amp_mean, max(log_amp_std, 1e-12)
    zf = (log_floor - mu) / v

    def log_moment(k: int) -> float:  # log E[A^k | A > floor]
        num = torch.special.log_ndtr(torch.tensor(k * v - zf, dtype=torch.float64))
        den = torch.special.log_ndtr(torch.tensor(-zf, dtype=torch.float64))
        return k * mu + 0.5 * (k * v) ** 2 + float(num - den)
    m1 = math.exp(log_moment(1))
    return m1, max(math.exp(log_moment(2)) - m1 * m1, 0.0)


def log_numerator(
    d: GlintData, tau: Tensor, sg: Tensor, la: Tensor, va: Tensor, *, n_a: int = 6, n_phi: int = 16, outlier: float = 0.02,
) -> Tensor:
    """log f_j of every flake (J,) (see the module docstring); ``outlier``: see :func:`_log_detect`."""
    dt, dev = d.half.dtype, d.half.device
    j = d.amp.shape[0]
    qa, phi = _memo(d, ("nodes", n_a, n_phi), lambda: _ring_nodes(n_a, n_phi, dt, dev))

    def geometry() -> tuple[Tensor, Tensor, Tensor]:
        h_star = d.half[torch.arange(j, device=dev), d.anchor]  # (J, 3)
        e1, e2 = _frame(h_star)
        t1, t2 = _frame(d.normal)
        basis = torch.stack([h_star, e1, e2], 1)  # (J, 3: h*, e1, e2, 3)
        proj = torch.einsum("jac,jbc->jab", basis, torch.stack([d.normal, t1, t2], 1))  # onto n, t1, t2
        to_shots = torch.einsum("jac,jkc->jak", basis, d.half)  # (J, 3, N) onto every shot's h
        order = nearest_shots(d.half, d.anchor, d.half.shape[1], prefer=d.detected)  # (J, N)
        return h_star, proj, to_shots, order

    h_star, proj, to_shots, order = _memo(d, ("numerator",), geometry)
    # only shots whose caps can reach the ring matter: keep those (detected first), anchor first
    beta = _cap_radius(sg, float((la + 3 * va).detach()), float(d.sigma.min()), max(0.5, d.k_hi - 3.0))
    kk = _overlap_count(h_star.unsqueeze(1), d.half, 2.2 * beta + 1e-3)
    kk = max(kk, int(d.detected.sum(1).max()))  # every detected shot stays in the pattern
    detected, sigma, anchor = d.detected, d.sigma, d.anchor
    observed = d.observed if d.observed is not None else torch.ones_like(detected)
    if kk < d.half.shape[1]:
        idx = order[:, :kk]
        detected, sigma, anchor = _gather_shots(detected, idx), _gather_shots(sigma, idx), torch.zeros_like(anchor)
        observed = _gather_shots(observed, idx)
        to_shots = to_shots.gather(2, idx.unsqueeze(1).expand(-1, 3, -1))
    log_amp = torch.log(d.amp.clamp_min(1e-12))
    log_a, log_tail = _tail_nodes(la, va, log_amp, qa, log_amp_floor(d))  # A nodes: A > â
    log_tail = log_tail.to(dt)
    cap = sg * sg * (log_a - log_amp.unsqueeze(1))  # 1 − cos β ≥ 0
    inside = cap < 1.9
    cap = cap.clamp(1e-9, 1.9)
    cosb = 1 - cap
    sinb = torch.sqrt(cap * (2 - cap))
    # ring nodes m = cos β·h* + sin β·(cos φ e1 + sin φ e2), (J, nA, nφ), handled through their
    # projections: every dot product m·v is cos β·(h*·v) + sin β·(cos φ e1·v + sin φ e2·v)
    cphi, sphi = torch.cos(phi), torch.sin(phi)
    cosb, sinb = cosb.view(j, n_a, 1), sinb.view(j, n_a, 1)

    def dot_m(b: int) -> Tensor:  # m·(n, t1, t2)[b] (J, nA, nφ)
        ring_v = cphi * proj[:, 1, b : b + 1] + sphi * proj[:, 2, b : b + 1]  # (J, nφ)
        return cosb * proj[:, 0, b].view(j, 1, 1) + sinb * ring_v.unsqueeze(1)

    total = _log_slope_from(dot_m(0), dot_m(1), dot_m(2), tau)
    if to_shots.shape[-1] > 1:  # other shots: detection pattern (none when only the anchor's cap reaches the ring)
        rh = cphi.view(1, -1, 1) * to_shots[:, 1].unsqueeze(1) + sphi.view(1, -1, 1) * to_shots[:, 2].unsqueeze(1)  # (J, nφ, K)
        mh = cosb.unsqueeze(-1) * to_shots[:, 0].view(j, 1, 1, -1) + sinb.unsqueeze(-1) * rh.unsqueeze(1)  # (J, nA, nφ, K)
        log_g = -(1 - mh) / (sg * sg)
        a_over_s = torch.exp(log_a.view(j, n_a, 1, 1) + log_g) / sigma.view(j, 1, 1, -1)
        ld = _log_detect(a_over_s, d.k_hi, detected.view(j, 1, 1, -1), outlier)
        counted = observed.to(dt)  # the anchor's own detection is the ring; unmeasurable shots say nothing
        counted[torch.arange(j, device=dev), anchor] = 0.0
        total = total + (ld * counted.view(j, 1, 1, -1)).sum(-1)
    logw = log_tail.view(j, 1, 1) - math.log(n_a) + math.log(2 * math.pi / n_phi)
    total = total + logw
    total = torch.where(inside.view(j, n_a, 1), total, torch.full_like(total, -1e4))
    lse = torch.logsumexp(total.flatten(1), dim=1)
    return lse + 2 * torch.log(sg) - log_amp


def _gauss_legendre(n: int, dtype, device) -> tuple[Tensor, Tensor]:
    """Gauss–Legendre nodes and weights on [0, 1]."""
    import numpy as np

    x, w = np.polynomial.legendre.leggauss(n)
    return torch.tensor(0.5 * (x + 1), dtype=dtype, device=device), torch.tensor(0.5 * w, dtype=dtype, device=device)


def log_p_any(
    d: GlintData, tau: Tensor, sg: Tensor, la: Tensor, va: Tensor, *,
    n_a: int = 2, n_a_band: int = 4, n_in: int = 2, n_band: int = 3, n_phi: int = 8, margin: float = 3.0,
) -> Tensor:
    """log of the probability (G,) (float64) that a flake in each grid cell is detected in at
    least one shot.

    Amplitudes: Gauss–Legendre in log A (``n_a_band`` nodes) over the band where the cell's
    detection probability rises (from (k_hi − margin)·σ_min to (k_hi + margin)·σ_max of the
    cell), where a steep amplitude tail and a steep detection rate meet and quantile nodes
    would be far off; ``n_a`` quantile nodes of the distribution above it.

    Cap k of shot k (A fixed) is integrated in u = 1 − m·h_k and φ: Gauss–Legendre in u on
    the interior, where A·g ≥ (k_hi + margin)·σ and detection is certain, and on the edge band
    down to (k_hi − margin)·σ, where the detection probability falls from 1 to 0; the
    trapezoid rule in φ. Overlapping caps share each point through a partition of unity
    P_k / Σ_j P_j, so the union is counted once. P_k is scaled by the cell's measurable
    fraction in shot k (``grid_valid``): no detection can come from a saturated region.
    """
    dt, dev = d.grid_half.dtype, d.grid_half.device
    g, n = d.grid_sigma.shape

    def constants():
        qa, phi = _ring_nodes(n_a, n_phi, dt, dev)
        e1, e2 = _frame(d.grid_half)  # (G, N, 3)
        t1, t2 = _frame(d.grid_normal)
        basis = torch.stack([d.grid_half, e1, e2], 2)  # (G, N, 3: h_k, e1_k, e2_k, 3)
        proj = torch.einsum("gnac,gbc->gnab", basis, torch.stack([d.grid_normal, t1, t2], 1))  # onto n, t1, t2
        first = torch.arange(n, device=dev).expand(g, n)
        order = nearest_shots(d.grid_half.unsqueeze(1).expand(g, n, n, 3), first, n)  # (G, N, N) own shot first
        h_near = d.grid_half.gather(1, order.flatten(1)[..., None].expand(-1, -1, 3)).view(g, n, n, 3)
        to_near = torch.einsum("gnac,gnkc->gnak", basis, h_near)  # (G, N, 3, N) onto the nearest shots' h
        s_near = d.grid_sigma.gather(1, order.flatten(1)).view(g, n, n)
        v_near = None if d.grid_valid is None else d.grid_valid.to(dt).gather(1, order.flatten(1)).view(g, n, n)
        return (qa, phi, _gauss_legendre(n_in, dt, dev), _gauss_legendre(n_band, dt, dev),
                torch.log(d.grid_sigma).view(g, 1, n), proj, to_near, s_near, v_near)

    qa, phi, (x_in, w_in), (x_bd, w_bd), lsig, proj, to_near, s_near, v_near = _memo(
        d, ("p_any", n_a, n_in, n_band, n_phi), constants)
    level_lo = max(0.5, d.k_hi - margin)
    log_floor = log_amp_floor(d)

    def band():  # log-A band nodes (G, nAb), log of their width × Gauss–Legendre weight, band top (G,)
        lo = (lsig.amin(-1)[:, 0] + math.log(level_lo)).double().clamp_min(log_floor)
        hi = lsig.amax(-1)[:, 0].double() + math.log(d.k_hi + margin)
        x_ab, w_ab = _gauss_legendre(n_a_band, torch.float64, dev)
        return lo.unsqueeze(1) + (hi - lo).unsqueeze(1) * x_ab, torch.log((hi - lo).unsqueeze(1) * w_ab), hi

    lab, log_width, hi = _memo(d, ("band", n_a_band, margin), band)
    la64, va64 = la.double(), va.double()
    log_wb = (log_width - 0.5 * ((lab - la64) / va64) ** 2 - 0.5 * _LOG2PI
              - torch.log(va64) - torch.special.log_ndtr((la64 - log_floor) / va64))
    lat, log_tail = _tail_nodes(la, va, hi, qa, log_floor)  # (G, nA) above the band
    log_a = torch.cat([lab.to(dt), lat], 1)  # (G, nAb + nA)
    log_wa = torch.cat([log_wb, (log_tail - math.log(n_a)).unsqueeze(1).expand(-1, n_a)], 1)

    def ucap(level: float) -> Tensor:  # 1 − m·h where A·g = level·σ, (G, nA, N)
        return (sg * sg * (log_a.unsqueeze(-1) - lsig - math.log(level))).clamp(0.0, 1.9)

    u_lo = ucap(d.k_hi + margin)
    u_hi = ucap(level_lo)
    uu = torch.cat([u_lo.unsqueeze(-1) * x_in, u_lo.unsqueeze(-1) + (u_hi - u_lo).unsqueeze(-1) * x_bd], -1)
    wu = torch.cat([u_lo.unsqueeze(-1) * w_in, (u_hi - u_lo).unsqueeze(-1) * w_bd], -1)  # (G, nA, N, nR)
    uu = uu.clamp_min(1e-9)
    # nodes m = cos β·h_k + sin β·(cos φ e1_k + sin φ e2_k), (G, nA, N, nR, nφ), handled through
    # their projections m·v = cos β·(h_k·v) + sin β·(cos φ e1_k·v + sin φ e2_k·v)
    cosb = (1 - uu).unsqueeze(-1)
    sinb = torch.sqrt(uu * (2 - uu)).unsqueeze(-1)
    cphi, sphi = torch.cos(phi), torch.sin(phi)

    def dot_m(b: int) -> Tensor:  # m·(n, t1, t2)[b] (G, nA, N, nR, nφ)
        rv = cphi * proj[:, :, 1, b : b + 1] + sphi * proj[:, :, 2, b : b + 1]  # (G, N, nφ)
        return cosb * proj[:, :, 0, b].view(g, 1, n, 1, 1) + sinb * rv.view(g, 1, n, 1, -1)

    logp = _log_slope_from(dot_m(0), dot_m(1), dot_m(2), tau)
    # shots whose caps may overlap cap k (own shot first): caps farther apart never meet
    beta = _cap_radius(sg, float(log_a.max().detach()), float(d.grid_sigma.min()), level_lo)
    kk = _overlap_count(d.grid_half, d.grid_half, 2.2 * beta + 1e-3)
    tn = to_near[..., :kk]  # (G, N, 3, K)
    sn = s_near[..., :kk]  # (G, N, K)
    rh = cphi.view(-1, 1) * tn[:, :, 1].unsqueeze(2) + sphi.view(-1, 1) * tn[:, :, 2].unsqueeze(2)  # (G, N, nφ, K)
    mh = cosb.unsqueeze(-1) * tn[:, :, 0].view(g, 1, n, 1, 1, -1) + sinb.unsqueeze(-1) * rh.view(g, 1, n, 1, -1, kk)  # (G, nA, N, nR, nφ, K)
    a_over_s = torch.exp(log_a.view(g, -1, 1, 1, 1, 1) - (1 - mh) / (sg * sg)) / sn.view(g, 1, n, 1, 1, -1)
    zk = _PROBIT * (a_over_s - d.k_hi)
    pk = torch.sigmoid(zk)
    if v_near is not None:  # a flake can only be detected where its shot is measurable
        pk = pk * v_near[..., :kk].view(g, 1, n, 1, 1, kk)
    any_ = 1.0 - (1.0 - pk).prod(-1)
    own = pk[..., 0]  # (G, nA, N, nR, nφ): P_k at the nodes of cap k
    share = own * any_ / pk.sum(-1).clamp_min(1e-30)
    wts = (wu * (2 * math.pi / n_phi)).unsqueeze(-1)
    val = (torch.exp(logp) * share * wts).sum((2, 3, 4))  # (G, nA)
    return torch.logsumexp(torch.log(val.double().clamp_min(1e-300)) + log_wa, 1)


def _objective(d: GlintData, sub: GlintData, theta: Tensor, prior: tuple[Tensor, Tensor], nodes: dict) -> tuple[Tensor, Tensor]:
    """Negative penalised profile log-likelihood (float64) and the expected detected count.

    ``d`` holds the grid, ``sub`` the flakes in the numerator sum (both in the work dtype).
    """
    wd = d.grid_half.dtype
    tau, sg, la, va = torch.exp(theta[0]).to(wd), torch.exp(theta[1]).to(wd), theta[2].to(wd), torch.exp(theta[3]).to(wd)
    lnum = log_numerator(sub, tau, sg, la, va, **nodes.get("num", {})).double()
    log_pa = log_p_any(d, tau, sg, la, va, **nodes.get("any", {}))
    log_expected = torch.logsumexp(log_pa + torch.log(d.grid_area.double().clamp_min(1e-300)), 0)
    ll = lnum.sum() * (d.count / max(1, sub.amp.numel())) - d.count * log_expected
    mean, sd = prior
    pen = 0.5 * (((theta - mean) / sd) ** 2).sum()
    return -(ll - pen), torch.exp(log_expected)


@dataclass
class GlintFit:
    """Result of :func:`fit_glints`: fitted values, profiled density, loglik at the optimum,
    standard errors and identifiability (by log-parameter name), L-BFGS iterations and
    objective evaluations (L-BFGS runs + curvature)."""

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


_PER_FLAKE = ("half", "normal", "anchor", "amp", "detected", "sigma", "observed")


def _recast(d: GlintData, index: Tensor | None, dtype: torch.dtype, *, flakes: bool, grid: bool) -> GlintData:
    """Copy of ``d`` with the flake rows ``index`` (all when None) and float fields of the
    flake rows and/or the grid cast to ``dtype``."""
    out = {}
    for f in fields(GlintData):
        v = getattr(d, f.name)
        if v is None:
            pass
        elif f.name in _PER_FLAKE:
            if index is not None:
                v = v[index]
            if flakes and v.is_floating_point():
                v = v.to(dtype)
        elif grid and isinstance(v, Tensor) and f.name != "grid_area":
            v = v.to(dtype)
        out[f.name] = v
    return GlintData(**out)


def _even_subsample(j: int, limit: int, device) -> Tensor:
    """min(j, limit) of j rows, evenly spaced (deterministic; all rows when j ≤ limit)."""
    if j <= limit:
        return torch.arange(j, device=device)
    return torch.floor(torch.arange(limit, device=device, dtype=torch.float64) * (j / limit)).long()


@contextmanager
def _one_thread():
    """Run the enclosed torch work (or decorated function) on one intra-op thread, restoring
    the previous count.

    The statistics work on many small tensors (≲ 10⁵ elements): a second thread saves
    nothing there, but every parallel region waits on it, which on a loaded CPU (other
    processes on the cores) made the fit ~7× slower (measured: 1.6 s vs 0.23 s, 1024² shot).
    """
    prev = torch.get_num_threads()
    if prev == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


@_one_thread()
def fit_glints(
    d: GlintData,
    *,
    max_flakes: int = 300,
    max_iter: int = 30,
    tol: float = 3e-3,
    restarts: int = 2,
    init: dict | None = None,
    nodes: dict | None = None,
    work_dtype: torch.dtype = torch.float32,
    uncertainty: bool = True,
) -> GlintFit:
    """Maximum-likelihood (τ, σ_g, A distribution) and the profiled true density.

    L-BFGS (strong Wolfe) from the start below, restarted from its best point while that still
    gains; the curvature for the standard errors is 4 forward differences of the gradient.

    Args:
        d: likelihood data; max_flakes: flakes in the numerator sum (an even subsample);
        max_iter: L-BFGS iterations per run;
        tol: L-BFGS stops when the loss or the (log-)parameters change less than this;
        restarts: at most this many fresh L-BFGS runs from the best point, while a run still
            gains ≥ 0.05 in log-likelihood;
        init: starting values (tau, glint_sigma, log_amp, log_amp_std; not modified);
        nodes: quadrature sizes {"num": {...}, "any": {...}}; work_dtype: dtype of the
        quadrature tensors (sums and parameters stay float64); uncertainty: compute standard
        errors and identifiability from the curvature (4 extra gradients).
    """
    dev = d.half.device
    nodes = nodes or {}
    j = d.amp.shape[0]
    if j == 0:
        raise InputError("fit_glints: expected at least one associated flake, found 0")
    wd = work_dtype
    d = replace(d, log_floor=log_amp_floor(d))  # one floor for the numerator and the float32 grid
    sub = _recast(d, _even_subsample(j, max_flakes, dev), wd, flakes=True, grid=False)
    grid = _recast(d, None, wd, flakes=False, grid=True)
    init = dict(init or {})
    if "tau" not in init:  # detected flakes have m ≈ h*: the RMS slope of h* is a fair start
        h_star = d.half[torch.arange(j, device=dev), d.anchor]
        t1, t2 = _frame(d.normal)
        hn = (h_star * d.normal).sum(-1).clamp_min(0.05)
        sl2 = (((h_star * t1).sum(-1) / hn) ** 2 + ((h_star * t2).sum(-1) / hn) ** 2).mean()
        init["tau"] = float(torch.sqrt(0.5 * sl2).clamp(0.02, 1.0))
    tau0 = init["tau"]
    sg0 = init.get("glint_sigma", 0.03)
    # a glint peaks at A only when h meets m, so the brightest detections bound A: log â is
    # roughly uniform on [log T, log A], and its top quantile is a close start for log A
    la0 = init.get("log_amp", float(torch.quantile(torch.log(d.amp.clamp_min(1e-12)).double(), 0.98)) + 0.1)
    va0 = init.get("log_amp_std", 0.1)
    # the amplitude spread's prior is the one that matters: with ~100 flakes the likelihood is flat
    # in it within 0.3 nats from 0.1 to 0.6 (demo), and E[A] = exp(ℓ + v²/2), hence the colour,
    # followed it up by 20 %; flakes of one paint are alike, so v ~ LogNormal(log 0.15, 0.5²)
    prior_mean = torch.tensor([math.log(0.15), math.log(0.03), la0, math.log(0.15)], dtype=torch.float64, device=dev)
    prior_sd = torch.tensor([2.0, 2.0, 5.0, 0.5], dtype=torch.float64, device=dev)
    prior = (prior_mean, prior_sd)
    evals = [0]

    def value_grad(t: Tensor, data_sub: GlintData) -> tuple[Tensor, Tensor, Tensor]:
        t = t.detach().clone().requires_grad_(True)
        loss, expected = _objective(grid, data_sub, t, prior, nodes)
        evals[0] += 1
        return loss.detach(), expected.detach(), torch.autograd.grad(loss, t)[0]

    # no flake seen in two shots (one shot, or shots far apart): nothing in the data sets the
    # glint width, so it stays at its start (the prior's mean unless ``init`` says otherwise)
    # instead of wandering along a flat valley (one 1024² shot: 10 of 23 evaluations)
    free = torch.ones(4, dtype=torch.bool, device=dev)
    free[1] = bool((d.detected.sum(1) > 1).any())
    idx = torch.nonzero(free, as_tuple=True)[0]

    def hessian(t: Tensor, g0: Tensor) -> Tensor:  # forward differences of the gradient (g0 at t), free block
        eps = 1e-2
        eye = torch.eye(4, dtype=t.dtype, device=dev)
        hess = torch.stack([(value_grad(t + eps * eye[i], sub)[2] - g0)[idx] / eps for i in idx.tolist()])
        return 0.5 * (hess + hess.t())

    th0 = torch.tensor([math.log(tau0), math.log(sg0), la0, math.log(va0)], dtype=torch.float64, device=dev)
    best = [float("inf"), th0.clone(), None, None]  # loss, θ, expected count, gradient
    iters = 0
    # L-BFGS may stop on one short line-search step far from the optimum: restart from the best
    # point (fresh curvature memory) until a run gains less than 0.05 in the loss
    for _ in range(restarts + 1):
        start_loss, start = best[0], best[1]
        z = torch.zeros(4, dtype=torch.float64, device=dev, requires_grad=True)
        opt = torch.optim.LBFGS([z], lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe", tolerance_grad=1e-5, tolerance_change=tol)

        def closure():
            opt.zero_grad()
            theta = start + z
            loss, expected = _objective(grid, sub, theta, prior, nodes)
            evals[0] += 1
            loss.backward()
            z.grad.masked_fill_(~free, 0.0)
            if float(loss.detach()) < best[0]:  # keep the best point visited (line searches may end off it)
                best[:] = [float(loss.detach()), theta.detach().clone(), float(expected.detach()), z.grad.detach().clone()]
            return loss

        opt.step(closure)
        iters += int(opt.state[opt._params[0]].get("n_iter", 0))
        if start_loss - best[0] < 0.05:
            break
    loss, th, expected, grad = best
    prior_h = torch.diag(1.0 / prior_sd**2)
    se = torch.full((4,), float("nan"), dtype=th.dtype, device=dev)
    data_h = torch.full((4,), float("nan"), dtype=th.dtype, device=dev)
    if uncertainty:  # curvature → standard errors of log τ, log σ_g, ℓ, log v (free ones)
        hess = hessian(th, grad)
        cov, info = torch.linalg.inv_ex(hess)
        if int(info) == 0 and bool(torch.isfinite(cov).all()):
            se[idx] = torch.sqrt(torch.diagonal(cov).clamp_min(0.0))
        data_h[idx] = torch.diagonal(hess - prior_h[idx][:, idx])
    total_area = float(d.grid_area.sum())
    names = ("log_tilt_sigma", "log_glint_sigma", "log_amp_mean", "log_amp_std")
    # a parameter is identified when the data, not the prior, sets its curvature
    ident = {nm: bool(data_h[i] > 4.0 * prior_h[i, i]) and bool(se[i] < 0.15) for i, nm in enumerate(names)}
    return GlintFit(
        tilt_sigma=float(torch.exp(th[0])), glint_sigma=float(torch.exp(th[1])), log_amp_mean=float(th[2]),
        log_amp_std=float(torch.exp(th[3])), density=d.count / expected if expected > 0 else math.inf,
        expected_fraction=expected / max(total_area, 1.0), loglik=-loss,
        std_err={nm: float(se[i]) for i, nm in enumerate(names)}, identified=ident, iterations=iters,
        evaluations=evals[0], log_amp_floor=log_amp_floor(d),
    )


# ---------------------------------------------------------------- shape, size, colour


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
    q = torch.quantile(resid, torch.tensor([0.05, 0.95], dtype=resid.dtype))
    lines = (float(b0 + q[0]), float(k), float(b0 + q[1]), float(k))
    return {
        "area_log_mean": med, "area_log_std": math.sqrt(var),
        "aspect_mean": float(asp.mean().clamp(0.05, 1.0)), "aspect_std": float(asp.std().clamp(0.0, 1.0)) if asp.numel() > 1 else 0.0,
        "shape_lines": lines, "n": int(sel.sum()),
    }


def fit_colour(obs: FlakeObservations, fit: GlintFit, *, min_snr: float = 8.0) -> tuple[tuple, tuple]:
    """Colour mean and covariance of the glint reflectance.

    The peak glint of a detection is A·g with g ≤ 1, so raw peaks underestimate the flake's
    colour; the glint falloff is corrected through the fitted amplitude distribution:
    mean = E[A | A > floor] × mean chroma (chroma = colour / channel mean is independent of g).
    Chroma outside [0, 3] per channel (a detection whose mean colour is ≈ 0 or negative: a
    texture edge, not a glint) is left out.
    """
    plausible = ((obs.chroma >= 0) & (obs.chroma <= 3)).all(1)
    sel = (obs.snr >= min_snr) & plausible
    if int(sel.sum()) < 10:
        sel = plausible if int(plausible.sum()) >= 1 else torch.ones_like(sel)
    ch = obs.chroma[sel].double()
    mean_a, var_a = truncated_moments(fit.log_amp_mean, fit.log_amp_std, fit.log_amp_floor)
    cm = ch.mean(0)
    mean = (mean_a * cm).clamp_min(0.0)
    # chroma covariance minus its measurement noise (per channel ≈ √3·σ/(amp·√area)), PSD-clipped
    dev_ch = ch - ch.mean(0)  # covariance by element-wise sums, not a BLAS product (see fit_shapes)
    cov_ch = (dev_ch.unsqueeze(2) * dev_ch.unsqueeze(1)).sum(0) / max(ch.shape[0] - 1, 1)
    noise = (3.0 / (obs.snr[sel].double() ** 2 * obs.area[sel].double().clamp_min(1.0))).median()
    cov_ch = cov_ch - noise * torch.eye(3, dtype=ch.dtype)
    ev, evec = torch.linalg.eigh(cov_ch)
    cov_ch = evec @ torch.diag(ev.clamp_min(0.0)) @ evec.t()
    cov = mean_a**2 * cov_ch + var_a * torch.outer(cm, cm)
    return tuple(float(v) for v in mean), tuple(tuple(float(v) for v in r) for r in cov)


# ---------------------------------------------------------------- all together


@dataclass
class StatsResult:
    """model: the fitted FlakeModel or None; observations; flake_id (P,); report dict."""

    model: FlakeModel | None
    observations: FlakeObservations | None
    flake_id: Tensor
    report: dict = field(default_factory=dict)


def _grid(det: Detection, geometry: Geometry, max_cells: int, ok: Tensor) -> tuple[Tensor, ...]:
    """Half vectors (G, N, 3), normals (G, 3), noise σ (G, N), pixel area (G,) and measurable
    fraction (G, N) (of ``ok`` (N, H, W)) of a grid of at most ``max_cells`` cells."""
    n, _, h, w = det.sigma.shape
    side = max(1, int(math.sqrt(max_cells)))
    gh = min(side, h)
    gw = min(side, w)
    lsig = F.adaptive_avg_pool2d(torch.log(det.sigma.double()), (gh, gw))  # (N, 1, gh, gw)
    valid = F.adaptive_avg_pool2d(ok.unsqueeze(1).to(torch.float32), (gh, gw))[:, 0].double()  # (N, gh, gw)
    area = torch.full((gh * gw,), h * w / (gh * gw), dtype=torch.float64, device=det.sigma.device)
    half, normal = geometry.on_grid(gh, gw)
    return half, normal, torch.exp(lsig).flatten(1).t(), area, valid.flatten(1).t()


@_one_thread()
def flake_statistics(
    det: Detection,
    geometry: Geometry,
    *,
    seed: int = 0,
    assoc_radius: float = 1.5,
    min_flakes: int = 20,
    max_cells: int = 36,
    max_flakes: int = 300,
) -> StatsResult:
    """Fit a :class:`FlakeModel` to the detections of a capture (None when they look like noise).

    Args:
        det: detector output for N shots; geometry: the shots' normals/lights/cameras.
        seed: seed stored in the model (the render field's hash seed).
        assoc_radius: association radius in px (raise it for poorly registered shots).
        min_flakes: fewer associated flakes than this (or than 5× the Gaussian false-alarm
            expectation) means "consistent with noise" and the stage is skipped.
        max_cells, max_flakes: work limits of the likelihood (grid cells, flakes in the sum).
    """
    import time

    times = {}
    t0 = time.perf_counter()
    n, _, h, w = det.signal.shape
    if geometry.lights.shape[0] != n:
        raise InputError(f"geometry: expected {n} shots to match the detection, found {geometry.lights.shape[0]}")
    p = det.particles
    ok = measurable(det)
    row, col = _particle_pixels(p, h, w)
    keep = ok[p.shot, row, col]
    flake_id = torch.full((len(p),), -1, dtype=torch.int64, device=p.shot.device)
    flake_id[keep], count = associate(p.select(keep), h, w, assoc_radius)
    times["associate"] = time.perf_counter() - t0
    valid_px = float(det.valid.expand(n, -1, -1, -1).sum()) if det.valid.shape[0] == 1 else float(det.valid.sum())
    false_alarms = valid_px * 0.5 * math.erfc(det.k_hi / math.sqrt(2))
    report = {"particles": len(p), "clipped_particles": int((~keep).sum()), "flakes_detected": count,
              "expected_false_alarms": false_alarms}
    threshold = max(min_flakes, 5.0 * false_alarms)
    if count < threshold:
        report["skipped"] = f"{count} associated detections, fewer than {threshold:.3g} expected from real flakes (consistent with noise)"
        report["times"] = times
        return StatsResult(None, None, flake_id, report)
    t1 = time.perf_counter()
    obs = observe(det, flake_id, count, geometry, ok)
    times["measure"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    g_half, g_normal, g_sigma, g_area, g_valid = _grid(det, geometry, max_cells, ok)
    data = GlintData(
        half=obs.half.double(), normal=obs.normal.double(), anchor=obs.anchor, amp=obs.amp.double(),
        detected=obs.detected, sigma=obs.sigma.double(), grid_half=g_half, grid_normal=g_normal,
        grid_sigma=g_sigma, grid_area=g_area, k_hi=det.k_hi, count=count, observed=obs.observed,
        grid_valid=g_valid,
    )
    gfit = fit_glints(data, max_flakes=max_flakes)
    times["likelihood"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    if not (math.isfinite(gfit.density) and gfit.density <= 1.0):
        # the likelihood ran off to a spike or tail that explains the detections with almost no
        # flakes expected anywhere (more flakes than pixels): no trustworthy model (reported, not rendered)
        report["skipped"] = (f"glint likelihood degenerate (density {gfit.density:.3g}/px > 1, tilt σ "
                             f"{gfit.tilt_sigma:.3g}, glint σ {gfit.glint_sigma:.3g}): no flake model")
        report["times"] = times
        return StatsResult(None, obs, flake_id, report)
    shapes = fit_shapes(obs)
    cmean, ccov = fit_colour(obs, gfit)
    times["shape_colour"] = time.perf_counter() - t3
    density = min(gfit.density, MAX_DENSITY)
    if gfit.density > MAX_DENSITY:  # a near-solid layer of flakes: drawn as dense as the hash field can
        report["density_clamped"] = (f"fitted density {gfit.density:.3g}/px exceeds the flake field's capacity "
                                     f"{MAX_DENSITY:.3g}/px (one flake per {MIN_CELL}×{MIN_CELL} px cell): rendered at capacity")
    report.update({
        "density": gfit.density, "density_rendered": density, "tilt_sigma": gfit.tilt_sigma, "glint_sigma": gfit.glint_sigma,
        "detected_fraction": count / max(1.0, gfit.density * valid_px / n),
        "std_err": gfit.std_err, "identified": gfit.identified, "iterations": gfit.iterations,
        "multi_shot_flakes": int((obs.detected.sum(1) > 1).sum()), "times": times,
    })
    model = FlakeModel(
        density=density, area_log_mean=shapes["area_log_mean"], area_log_std=min(shapes["area_log_std"], 5.0),
        aspect_mean=shapes["aspect_mean"], aspect_std=shapes["aspect_std"], color_mean=cmean, color_cov=ccov,
        tilt_sigma=min(gfit.tilt_sigma, 1.5), glint_sigma=min(max(gfit.glint_sigma, 1e-4), 1.5),
        shape_lines=shapes["shape_lines"], seed=seed,
        extra={"flakes_detected": count, "density_fitted": gfit.density, "log_amp_mean": gfit.log_amp_mean, "log_amp_std": gfit.log_amp_std,
               "log_amp_floor": gfit.log_amp_floor,
               "std_err": gfit.std_err, "identified": gfit.identified},
    )
    return StatsResult(model, obs, flake_id, report)
