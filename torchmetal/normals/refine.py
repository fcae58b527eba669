"""The per-pixel refinement behind :func:`~torchmetal.normals.estimate.estimate_normals`: observations
of a row chunk, the model and its Jacobian in the surface gradient, and the robust LM.

Per pixel, with n = (−θx, −θy, 1)/√(1 + θx² + θy²) (n·z > 0 by construction) and the channel
sum z_k = Σ_c y_kc of each shot (shots with a clipped channel left out):

    z_k = Ē_k·[D·max(n·l_k, 0) + [n·l_k > 0]·Σ_c κ_kc·s_c·max(r_k·v_k, 0)^α_c]

Ē_k the channel mean of the irradiance, κ_kc = E_kc/Ē_k the light's colour, D = Σ_c κ_c·d_c.
The texture D is eliminated in closed form (variable projection; Kaufman's Jacobian), θ is
solved by a 2-parameter Levenberg–Marquardt per pixel inside Cauchy IRLS rounds; converged
pixels leave the working set. Every term is per pixel, so the work runs in row chunks (memory
only; the robust scale is the chunk's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchmetal.geometry import direction_to, surface_points
from torchmetal.phong import log1p_exact

CAUCHY_C = 5.0  # Cauchy scale in units of σ
SLOPE_MAX = 57.0  # |θ| cap: normals at most ~89° from z
IRLS_ROUNDS = 3  # Cauchy weights recomputed this many times
STEP_TOL = 1e-4  # a pixel stops when its θ step is below this (relative; ~0.006°)
CHUNK_OBS = 1 << 18  # observations (shots × pixels) per chunk
MAD = 1.4826


# ------------------------------------------------------------------------------- per-chunk data


@dataclass
class _Chunk:
    """Channel-summed observations of a block of rows, flattened to P pixels (working dtype)."""

    y: Tensor  # (N, 1, P) z = Σ_c y_c
    e: Tensor  # (N, 1, P) Ē, the channel mean of the irradiance
    kappa: Tensor  # (N, 3, 1) E_c / Ē, the light's colour
    l: Tensor  # (N, 3, P) unit to light
    v: Tensor  # (N, 3, P) unit to camera
    ok: Tensor  # (N, 1, P) bool: in the mask, no channel clipped, E > 0
    pix: Tensor  # (P,) bool: in the mask


def _chunk(capture, r0: int, r1: int, dt: torch.dtype) -> _Chunk:
    h, w = capture.height, capture.width
    dev = capture.images.device
    n = capture.num_shots
    pts = surface_points(h, w, capture.size, rows=(r0, r1), dtype=dt, device=dev)
    l, d2 = direction_to(pts, capture.lights.to(dt))
    v, _ = direction_to(pts, capture.cameras.to(dt))
    inten = capture.intensities.to(dt)
    mean = inten.mean(1, keepdim=True)
    kappa = torch.where(mean > 0, inten / torch.where(mean > 0, mean, torch.ones_like(mean)), torch.ones_like(inten))
    e = (mean[:, :, None, None] / d2).reshape(n, 1, -1)
    pix = capture.mask[0, r0:r1].reshape(-1)
    ok = (~capture.saturated[:, :, r0:r1]).all(1, keepdim=True).reshape(n, 1, -1) & (e > 0) & pix.view(1, 1, -1)
    y = capture.images[:, :, r0:r1].to(dt).sum(1, keepdim=True).reshape(n, 1, -1)
    return _Chunk(y, e, kappa.view(n, 3, 1), l.reshape(n, 3, -1), v.reshape(n, 3, -1), ok, pix)


def _row_blocks(capture):
    rows = max(1, CHUNK_OBS // (capture.num_shots * capture.width))
    return [(r0, min(capture.height, r0 + rows)) for r0 in range(0, capture.height, rows)]


def _active_blocks(capture, act: Tensor, dt: torch.dtype):
    """Per row block with active pixels: (r0, r1, keep (k,) indices into the block, the block's chunk of them)."""
    for r0, r1 in _row_blocks(capture):
        keep = act[r0:r1].reshape(-1).nonzero().squeeze(1)
        if keep.numel():
            yield r0, r1, keep, _subset(_chunk(capture, r0, r1, dt), keep)


def _robust_scale(x: Tensor, keep: Tensor, floor: float) -> Tensor:
    """σ = 1.4826·median|x| over the ``keep`` entries (a 0-d tensor, at least ``floor``)."""
    vals = x[keep].abs()
    sig = MAD * vals.median() if vals.numel() else x.new_tensor(0.0)
    return sig.clamp_min(floor)


# ------------------------------------------------------------------------------- normals ↔ θ


def _normals_of(theta: Tensor) -> tuple[Tensor, Tensor]:
    """θ (2, P) → unit n (3, P) and k = √(1 + |θ|²) (P,)."""
    k = torch.sqrt(1.0 + theta[0] * theta[0] + theta[1] * theta[1])
    return torch.stack([-theta[0], -theta[1], torch.ones_like(k)]) / k, k


def _theta_of(g: Tensor) -> Tensor:
    """Any vectors g (3, P) with g_z > 0 preferred → θ (2, P); g_z is floored so |θ| ≤ SLOPE_MAX."""
    gz = torch.maximum(g[2], torch.hypot(g[0], g[1]) / SLOPE_MAX).clamp_min(1e-30)
    return torch.stack([-g[0] / gz, -g[1] / gz]).clamp(-SLOPE_MAX, SLOPE_MAX)

# ------------------------------------------------------------------------------- 2. refinement


@dataclass
class _State:
    r: Tensor  # (N, 1, P) residual z − model
    d: Tensor  # (1, P) texture D
    cost: Tensor  # (P,) weighted squared residual Σ w·r²
    jac: tuple[Tensor, Tensor]  # ∂model/∂θ projected off the texture, (N, 1, P) each
    gjac: tuple[Tensor, Tensor] | None = None  # ∂model/∂(log s, log α), when asked for

    def merge(self, other: "_State", take: Tensor) -> "_State":
        """Per pixel: ``other`` where ``take`` (P,), else self."""
        pick = lambda a, b: torch.where(take, b, a)  # noqa: E731
        return _State(pick(self.r, other.r), pick(self.d, other.d), pick(self.cost, other.cost),
                      (pick(self.jac[0], other.jac[0]), pick(self.jac[1], other.jac[1])))

    def select(self, keep: Tensor) -> "_State":
        return _State(self.r[..., keep], self.d[..., keep], self.cost[keep], (self.jac[0][..., keep], self.jac[1][..., keep]))


@dataclass
class _Spec:
    """The global specular terms of a refinement: s (3,) > 0 somewhere, α (3,)."""

    s: Tensor
    alpha: Tensor

    def lobe(self, kappa: Tensor, lg: Tensor, inside: Tensor) -> tuple[Tensor, Tensor]:
        """Σ_c κ_c·s_c·lobe_c and Σ_c κ_c·s_c·α_c·lobe_c, (N, 1, P) each, from log(r·v) ``lg`` (N, 1, P)."""
        ks = kappa * self.s.view(1, 3, 1)  # (N, 3, 1)
        a = self.alpha
        if bool(((a - a[0]).abs() <= 1e-6 * a[0]).all()):  # one exponent: one exp
            h = torch.exp(a[0] * lg)
            spec = ks.sum(1, keepdim=True) * h
            dspec = a[0] * spec
        else:
            h = torch.exp(a.view(1, 3, 1) * lg)  # (N, 3, P)
            spec = (ks * h).sum(1, keepdim=True)
            dspec = (ks * a.view(1, 3, 1) * h).sum(1, keepdim=True)
        zero = torch.zeros_like(spec)
        return torch.where(inside, spec, zero), torch.where(inside, dspec, zero)


def _pass_setup(capture, s: Tensor, alpha: Tensor, active: Tensor | None):
    """The common start of a per-pixel pass over the normals: the work dtype, the specular terms
    (None when s = 0 everywhere), the pixels that may change (H, W) (default the mask) and the
    cost floor (1e-6 of the brightest value)."""
    dt = _work_dtype(capture)
    s, alpha = s.to(dt).reshape(3), alpha.to(dt).reshape(3)
    spec = _Spec(s, alpha) if bool((s > 0).any()) else None
    act = capture.mask[0] if active is None else active
    floor = 1e-6 * float(capture.images.detach().abs().amax().clamp_min(1e-30))
    return dt, spec, act, floor


def _model(ch: _Chunk, theta: Tensor, spec: _Spec | None, w: Tensor, jac: bool = True,
           glob: bool = False) -> _State:
    """Residuals, the closed-form texture (weighted least squares with the weights w (N, 1, P)),
    the weighted cost and (``jac``) the Jacobian of the model in θ at θ (2, P); ``spec`` None:
    Lambertian. With ``glob`` (and spec), also the Jacobian in the log-scales of s and α
    (``State.gjac``, projected off the texture like the θ one)."""
    n, k = _normals_of(theta)
    nl = (n.unsqueeze(0) * ch.l).sum(1, keepdim=True)  # (N, 1, P)
    lit = nl > 0
    ea = ch.e * nl.clamp_min(0.0)
    wea = w * ea
    den = (wea * ea).sum(0)
    has = den > 0
    iden = torch.where(has, 1.0 / torch.where(has, den, torch.ones_like(den)), torch.zeros_like(den))
    if spec is None:
        target = ch.y
    else:
        rmv = 2.0 * nl * n.unsqueeze(0) - ch.l - ch.v
        q = 0.5 * (rmv * rmv).sum(1, keepdim=True)
        inside = lit & (q < 1.0)
        lg = log1p_exact(-torch.where(inside, q, torch.full_like(q, 0.5)))
        sh, dsh = spec.lobe(ch.kappa, lg, inside)
        target = ch.y - ch.e * sh
    d = ((wea * target).sum(0) * iden).clamp_min(0.0)
    r = target - ea * d
    cost = (w * r * r).sum(0)[0]
    if not jac:
        return _State(r, d, cost, (r, r))
    if spec is not None:
        rv = 1.0 - q
        pos = inside & (rv > 1e-6)
        slope = torch.where(pos, dsh / torch.where(pos, rv, torch.ones_like(rv)), torch.zeros_like(dsh))
        nv = (n.unsqueeze(0) * ch.v).sum(1, keepdim=True)
    proj = iden * (d > 0)
    jacs = []
    for j in (0, 1):  # ∂n/∂θ_j = (n_j·n − e_j)/k
        dn = n[j] * n / k
        dn[j] -= 1.0 / k
        dnl = (dn.unsqueeze(0) * ch.l).sum(1, keepdim=True)
        dm = d.unsqueeze(0) * torch.where(lit, dnl, torch.zeros_like(dnl))
        if spec is not None:
            dnv = (dn.unsqueeze(0) * ch.v).sum(1, keepdim=True)
            dm = dm + slope * (2.0 * (dnl * nv + nl * dnv))
        dm = ch.e * dm
        dm = dm - ea * ((wea * dm).sum(0) * proj).unsqueeze(0)  # Kaufman: orthogonal to the texture basis
        jacs.append(dm)
    st = _State(r, d, cost, (jacs[0], jacs[1]))
    if glob and spec is not None:
        gj = []
        for dm in (ch.e * sh, ch.e * dsh * lg):  # ∂/∂ log s, ∂/∂ log α
            gj.append(dm - ea * ((wea * dm).sum(0) * proj).unsqueeze(0))
        st.gjac = (gj[0], gj[1])
    return st


def _cauchy_weights(ch: _Chunk, r: Tensor, scale: Tensor) -> Tensor:
    u = r / scale
    return torch.where(ch.ok, 1.0 / (1.0 + u * u), torch.zeros_like(u))


def _subset(ch: _Chunk, keep: Tensor) -> _Chunk:
    return _Chunk(ch.y[..., keep], ch.e[..., keep], ch.kappa, ch.l[..., keep], ch.v[..., keep], ch.ok[..., keep],
                  ch.pix[keep])


def _lm(ch: _Chunk, theta: Tensor, spec: _Spec | None, w: Tensor, iters: int) -> tuple[Tensor, int]:
    """Per-pixel LM on θ (2, P) with fixed weights w (N, 1, P); pixels that converged leave the
    working set. Returns θ and the iterations run."""
    theta = theta.clone()
    st = _model(ch, theta, spec, w)
    idx = torch.arange(theta.shape[1], device=theta.device)
    th, lam = theta, torch.full_like(st.cost, 1e-3)
    live = torch.ones_like(st.cost, dtype=torch.bool)
    it = 0
    for it in range(1, iters + 1):
        j0, j1 = st.jac
        wj0, wj1 = w * j0, w * j1
        a11, a12, a22 = (wj0 * j0).sum(0)[0], (wj0 * j1).sum(0)[0], (wj1 * j1).sum(0)[0]
        g1, g2 = (wj0 * st.r).sum(0)[0], (wj1 * st.r).sum(0)[0]
        tiny = 1e-9 * (a11 + a22) + 1e-30
        b11, b22 = a11 * (1 + lam) + tiny, a22 * (1 + lam) + tiny
        det = b11 * b22 - a12 * a12
        step = torch.stack([(b22 * g1 - a12 * g2) / det, (b11 * g2 - a12 * g1) / det])
        step = torch.where(live.unsqueeze(0) & torch.isfinite(step), step, torch.zeros_like(step))
        trial = (th + step).clamp(-SLOPE_MAX, SLOPE_MAX)
        st_t = _model(ch, trial, spec, w)
        better = live & (st_t.cost < st.cost) & torch.isfinite(st_t.cost)
        th = torch.where(better.unsqueeze(0), trial, th)
        st = st.merge(st_t, better)
        lam = torch.where(better, (lam / 3.0).clamp_min(1e-7), lam * 5.0)
        small = step.abs().amax(0) <= STEP_TOL * (1.0 + th.abs().amax(0))
        live = live & ~small & (lam < 1e8)
        n_live = int(live.sum())
        if n_live == 0 or it == iters or n_live < 0.5 * live.numel():  # write back, then shrink the set
            theta[:, idx] = th
            if n_live == 0:
                break
            keep = live.nonzero().squeeze(1)
            idx, th, lam, live, w, st = idx[keep], th[:, keep], lam[keep], live[keep], w[..., keep], st.select(keep)
            ch = _subset(ch, keep)
    return theta, it


def _robust_cost(ch: _Chunk, theta: Tensor, spec: _Spec | None, scale: Tensor) -> Tensor:
    """Σ_k log(1 + (r_k/scale)²) per pixel (P,) at θ, the texture solved by least squares with
    Cauchy weights of the plain least-squares residual (what selects between candidate normals)."""
    st = _model(ch, theta, spec, ch.ok.to(ch.y.dtype), jac=False)
    st = _model(ch, theta, spec, _cauchy_weights(ch, st.r, scale), jac=False)
    u = st.r / scale
    return torch.where(ch.ok, torch.log1p(u * u), torch.zeros_like(u)).sum(0)[0]


def _irls(ch: _Chunk, theta: Tensor, spec: _Spec | None, scale: Tensor, iters: int) -> tuple[Tensor, int]:
    """IRLS (Cauchy weights, ``IRLS_ROUNDS`` rounds) around a per-pixel LM on θ (2, P)."""
    total = 0
    per_round = max(1, math.ceil(iters / IRLS_ROUNDS))
    w = ch.ok.to(ch.y.dtype)
    for _ in range(IRLS_ROUNDS):
        st = _model(ch, theta, spec, w, jac=False)
        w = _cauchy_weights(ch, st.r, scale)
        theta, it = _lm(ch, theta, spec, w, per_round)
        total += it
    return theta, total


def _best_of(sub: _Chunk, theta: Tensor, cost: Tensor, cands: list, spec: _Spec | None, scale: Tensor,
             gain: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Per pixel the least robust cost among θ (2, P) at ``cost`` (P,) and the candidates (each
    (2, P)), a candidate winning only below (1 − gain) × the cost to beat; returns θ, its cost and
    whether a candidate won (P,)."""
    won = torch.zeros_like(cost, dtype=torch.bool)
    for t in cands:
        c = _robust_cost(sub, t, spec, scale)
        take = c < (1.0 - gain) * cost
        theta, cost, won = torch.where(take, t, theta), torch.where(take, c, cost), won | take
    return theta, cost, won


def _refine_kept(sub: _Chunk, theta: Tensor, cost: Tensor, spec: _Spec | None, scale: Tensor,
                 iters: int) -> tuple[Tensor, Tensor, int]:
    """θ (2, P) refined by :func:`_irls` where that lowers the robust cost (P,); and the LM iterations run."""
    t, it = _irls(sub, theta, spec, scale, iters)
    c = _robust_cost(sub, t, spec, scale)
    better = c < cost
    return torch.where(better, t, theta), torch.where(better, c, cost), it


def _shifted(x: Tensor, width: int, dy: int, dx: int) -> Tensor:
    """A (2, R·W) map moved by (dy, dx) pixels within the chunk (edges repeat)."""
    m = x.reshape(x.shape[0], -1, width)
    r = m.shape[1]
    rows = (torch.arange(r, device=x.device) - dy).clamp(0, r - 1)
    cols = (torch.arange(width, device=x.device) - dx).clamp(0, width - 1)
    return m[:, rows][:, :, cols].reshape(x.shape)


PROPAGATE = tuple((d * sy, d * sx) for d in (1, 3, 9) for sy, sx in ((0, 1), (0, -1), (1, 0), (-1, 0)))
"""Shifts (rows, cols) of the neighbours whose normals a pixel tries: 1, 3 and 9 px in the four
directions, so a patch caught in a wrong minimum near a highlight takes its rim's normals."""


def _solve_chunk(ch: _Chunk, width: int, active: Tensor, candidates: list, iters: int, floor: float,
                 propagate: bool) -> tuple[Tensor, Tensor, int]:
    """Per ``active`` pixel: every candidate start (θ (2, P), spec) refined under its terms, the
    one of least robust cost kept; then (``propagate``) each neighbour's θ is tried under the first candidate's
    terms and the pixels that took one are refined again. Returns θ (2, P), the robust cost (P,)
    and the LM iterations run."""
    keep = active.nonzero().squeeze(1)
    sub = _subset(ch, keep)
    starts = [(th[:, keep], sp) for th, sp in candidates]
    ls = [_model(sub, th, sp, sub.ok.to(sub.y.dtype), jac=False) for th, sp in starts]
    best = torch.stack([st.cost for st in ls]).argmin(0)  # the scale: residuals of the best start
    r0 = torch.stack([st.r for st in ls]).gather(0, best.view(1, 1, 1, -1).expand(1, *ls[0].r.shape))[0]
    scale = CAUCHY_C * _robust_scale(r0, sub.ok, floor)
    del ls, r0
    total, refined = 0, []
    for th, sp in starts:  # each start refined under its terms; per pixel the best kept
        t, it = _irls(sub, th, sp, scale, iters)
        total += it
        refined.append((t, _robust_cost(sub, t, sp, scale)))
    costs = torch.stack([c for _, c in refined])
    best = costs.argmin(0)
    theta = torch.stack([t for t, _ in refined]).gather(0, best.view(1, 1, -1).expand(1, 2, -1))[0]
    cost = costs.gather(0, best.view(1, -1))[0]
    spec = starts[0][1]
    del refined, costs
    if propagate:
        full = candidates[0][0].clone()
        full[:, keep] = theta
        theta, cost, moved = _best_of(sub, theta, cost, [_shifted(full, width, dy, dx)[:, keep] for dy, dx in PROPAGATE],
                                      spec, scale)
        idx = moved.nonzero().squeeze(1)
        if idx.numel():
            theta[:, idx], cost[idx], it = _refine_kept(_subset(sub, idx), theta[:, idx], cost[idx], spec, scale, iters)
            total += it
    out_t = candidates[0][0].clone()
    out_t[:, keep] = theta
    c_full = torch.zeros(out_t.shape[1], dtype=cost.dtype, device=cost.device)
    c_full[keep] = cost
    return out_t, c_full, total


def refine_normals(
    capture, candidates, *, iters: int = 12, active: Tensor | None = None, propagate: bool = True,
) -> tuple[Tensor, dict]:
    """Refine per-pixel normals under global Phong terms (texture eliminated, Cauchy IRLS).

    Args:
        capture: a :class:`~torchmetal.io.capture.Capture`.
        candidates: list of (normals (3, H, W) start, s (3,), α (3,)); s = 0: Lambertian. Per pixel
            the start that explains the shots best (robust cost) is refined under its terms.
        iters: LM iterations per pixel.
        active: (H, W) bool pixels to refine (default: the mask); the others keep the first
            candidate's normals.
        propagate: then try the neighbours' normals too (:data:`PROPAGATE`, under the first
            candidate's terms).

    Returns:
        normals (3, H, W) and a report (LM iterations, mean robust cost per pixel).
    """
    dt = _work_dtype(capture)
    w = capture.width
    cands = []
    for nrm, s, al in candidates:
        s = torch.as_tensor(s).to(device=nrm.device, dtype=dt).reshape(3)
        al = torch.as_tensor(al).to(device=nrm.device, dtype=dt).reshape(3)
        cands.append((nrm.to(dt), _Spec(s, al) if bool((s > 0).any()) else None))
    act = capture.mask[0] if active is None else active
    out_n = cands[0][0].clone()
    floor = 1e-6 * float(capture.images.detach().abs().amax().clamp_min(1e-30))
    iters_max, cost_sum = 0, 0.0
    for r0, r1 in _row_blocks(capture):
        a = act[r0:r1].reshape(-1)
        if not bool(a.any()):
            continue
        ch = _chunk(capture, r0, r1, dt)
        thetas = [(_theta_of(nrm[:, r0:r1].reshape(3, -1)), sp) for nrm, sp in cands]
        theta, cost, it = _solve_chunk(ch, w, a, thetas, iters, floor, propagate)
        n, _ = _normals_of(theta)
        out_n[:, r0:r1] = torch.where(a.unsqueeze(0), n, out_n[:, r0:r1].reshape(3, -1)).reshape(3, r1 - r0, w)
        iters_max = max(iters_max, it)
        cost_sum += float(cost.sum())
    return out_n, {"iterations": iters_max, "robust_cost": cost_sum / max(1, int(act.sum()))}


def _work_dtype(capture) -> torch.dtype:
    """float64 for float64 photos, else float32 (per-pixel sums over a few dozen observations)."""
    return torch.float64 if capture.images.dtype == torch.float64 else torch.float32
