"""Per-pixel normals from the photos (``fit --normals estimate``): photometric stereo with the
known lights, refined jointly with the Phong terms of DESIGN 2.2.

Per pixel, with the normal written through the surface gradient θ = (θx, θy),
n = (−θx, −θy, 1)/√(1 + θx² + θy²) (so n·z > 0 by construction), for shot k and channel c:

    y_kc = E_kc · [ d_c·max(n·l_k, 0) + [n·l_k > 0]·s_c·max(r_k·v_k, 0)^α_c ]

l, v, E come from :mod:`torchmetal.geometry` (point and directional lights, any camera).

1. **Robust Lambertian init.** Per pixel, the channel sum of y/E is g·l_k (g = (Σ_c d_c)·n),
   solved by weighted least squares over the shots that are lit, unsaturated and not dark, then
   again without the shots the fit predicts in attached shadow (n·l below ``SHADOW``) or whose
   residual exceeds ``INIT_K``·σ (highlights, glints, cast shadows); σ is the chunk's robust scale.
2. **Robust refinement** (:func:`refine_normals`): a 2-parameter Levenberg–Marquardt per pixel on
   θ with the texture d eliminated in closed form (variable projection, Kaufman's Jacobian) and
   Cauchy weights (IRLS), so highlights the model does not explain, glints and shadows the
   Lambertian init mistook for shading are down-weighted, never fitted. max(n·l, 0) models
   attached shadows.
3. **Alternation** (:func:`estimate_normals`): round 0 refines, per pixel, the best of three
   starts — the Lambertian init under s = 0, it and the flat normal under the Phong terms fitted
   with flat normals; each further round fits the global Phong terms
   (:func:`~torchmetal.fit.fit_phong`, specular "global") with the current normals and refines the
   normals under them, then tries the 4 neighbours' normals (local minima near highlights).
4. **Joint refinement** of the normals with the global s, α
   (:func:`~torchmetal.fit.normals_joint.joint_refine`): the alternation alone has a biased fixed
   point (normal errors broaden the lobe the Phong fit sees).
5. **Flat where the photos cannot tell** (:mod:`~torchmetal.fit.normals_flat`): a per-pixel
   likelihood-ratio test against (0, 0, 1).

The normals are fitted to the channel sum of each shot, z_k = Σ_c y_kc (shots with a clipped
channel are left out): with Ē_k the channel mean of E_k and κ_kc = E_kc/Ē_k (the light's colour),
z_k = Ē_k·[D·max(n·l_k, 0) + Σ_c κ_kc·s_c·lobe_kc], D = Σ_c κ_c·d_c — one residual per shot
instead of three (the geometry is shared by the channels; the texture is :func:`fit_phong`'s).
Every per-pixel term is independent, so the work runs in row chunks (memory only; robust scales
are per chunk). Pixels outside the mask, or with fewer than 3 usable shots, keep (0, 0, 1).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from torchmetal.errors import FitError, InputError
from torchmetal.geometry import direction_to, surface_points
from torchmetal.phong import log1p_exact

NORMALS_MODES = ("given", "flat", "estimate")
DARK = 0.02  # init: shots darker than this fraction of the pixel's brightest are left out
SHADOW = 0.05  # init: shots with predicted n·l below this are attached shadow
INIT_K = 3.0  # init: |residual| > INIT_K·σ leaves a shot out (highlights, glints, cast shadows)
INIT_ROUNDS = 4
CAUCHY_C = 5.0  # refinement: Cauchy scale in units of σ
SLOPE_MAX = 57.0  # |θ| cap: normals at most ~89° from z
MIN_SHOTS = 3
IRLS_ROUNDS = 3  # refinement: Cauchy weights recomputed this many times
STEP_TOL = 1e-4  # refinement: a pixel stops when its θ step is below this (relative; ~0.006°)
CHUNK_OBS = 1 << 18  # observations (shots × channels × pixels) per chunk
MAD = 1.4826


@dataclass
class NormalsEstimate:
    """Outcome of :func:`estimate_normals`.

    Attributes:
        normals: (3, H, W) unit normals, n·z > 0; (0, 0, 1) outside the mask.
        s, alpha: (3,) the Phong terms of the last round.
        report: JSON-able: per-round s, α and cost, pixels that kept (0, 0, 1), time.
    """

    normals: Tensor
    s: Tensor
    alpha: Tensor
    report: dict = field(default_factory=dict)


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


# ------------------------------------------------------------------------------- 1. Lambertian init


def _solve3(l: Tensor, z: Tensor, w: Tensor) -> Tensor:
    """Per-pixel weighted least squares z_k = g·l_k: l (N, 3, P), z, w (N, P) → g (3, P)."""
    wl = l * w.unsqueeze(1)
    a = torch.einsum("nip,njp->pij", wl, l).double()
    b = torch.einsum("nip,np->pi", wl, z).double()
    tr = a.diagonal(dim1=1, dim2=2).sum(-1)
    ridge = torch.where(tr > 0, 1e-9 * tr, torch.ones_like(tr))  # no observation: g = 0
    a = a + ridge.view(-1, 1, 1) * torch.eye(3, dtype=a.dtype, device=a.device)
    return torch.linalg.solve(a, b).T.to(z.dtype)


def _lambert_init(ch: _Chunk) -> tuple[Tensor, Tensor]:
    """Robust Lambertian photometric stereo: θ (2, P) and the pixels with ≥ MIN_SHOTS usable shots (P,)."""
    ok = ch.ok[:, 0]
    z = torch.where(ok, ch.y[:, 0] / torch.where(ok, ch.e[:, 0], torch.ones_like(ch.y[:, 0])), torch.zeros_like(ch.y[:, 0]))
    zmax = z.amax(0)
    w = ok & (z > DARK * zmax)
    for _ in range(INIT_ROUNDS):
        g = _solve3(ch.l, z, w.to(z.dtype))
        rho = g.norm(dim=0).clamp_min(1e-30)
        zh = (g.unsqueeze(0) * ch.l).sum(1)
        res = (z - zh) / rho
        sig = _robust_scale(res, w, 1e-6)
        keep = ok & (zh > SHADOW * rho) & (res.abs() <= INIT_K * sig)
        w = torch.where((keep.sum(0) >= MIN_SHOTS).unsqueeze(0), keep, w)
    g = _solve3(ch.l, z, w.to(z.dtype))
    return _theta_of(g), (w.sum(0) >= MIN_SHOTS) & ch.pix


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


def _shifted(x: Tensor, width: int, dy: int, dx: int) -> Tensor:
    """A (2, R·W) map moved by (dy, dx) pixels within the chunk (edges repeat)."""
    m = x.reshape(x.shape[0], -1, width)
    r = m.shape[1]
    rows = (torch.arange(r, device=x.device) - dy).clamp(0, r - 1)
    cols = (torch.arange(width, device=x.device) - dx).clamp(0, width - 1)
    return m[:, rows][:, :, cols].reshape(x.shape)


PROPAGATE = ((0, 1), (0, -1), (1, 0), (-1, 0))  # neighbours whose normals a pixel tries


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
        moved = torch.zeros_like(cost, dtype=torch.bool)
        for dy, dx in PROPAGATE:
            trial = _shifted(full, width, dy, dx)[:, keep]
            c = _robust_cost(sub, trial, spec, scale)
            take = c < cost
            theta, cost, moved = torch.where(take, trial, theta), torch.where(take, c, cost), moved | take
        idx = moved.nonzero().squeeze(1)
        if idx.numel():
            part = _subset(sub, idx)
            t, it = _irls(part, theta[:, idx], spec, scale, iters)
            total += it
            c = _robust_cost(part, t, spec, scale)
            better = c < cost[idx]
            theta[:, idx] = torch.where(better, t, theta[:, idx])
            cost[idx] = torch.where(better, c, cost[idx])
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
        propagate: then try the 4 neighbours' normals too (under the first candidate's terms).

    Returns:
        normals (3, H, W) and a report (LM iterations, mean robust cost per pixel).
    """
    dt = _work_dtype(capture)
    h, w = capture.height, capture.width
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


# ------------------------------------------------------------------------------- 3. the estimate


def _check_capture(capture) -> None:
    n = capture.num_shots
    if n < MIN_SHOTS:
        raise InputError(f"normals='estimate': expected at least {MIN_SHOTS} shots (photometric stereo), found {n}")
    h, w = capture.height, capture.width
    pts = surface_points(h, w, capture.size, rows=(h // 2, h // 2 + 1), dtype=torch.float64,
                         device=capture.images.device)[:, :, w // 2 : w // 2 + 1]
    l, _ = direction_to(pts, capture.lights.to(torch.float64))
    sv = torch.linalg.svdvals(l[:, :, 0, 0])
    if float(sv[-1]) < 1e-3 * float(sv[0]):
        raise InputError("normals='estimate': expected lights from at least 3 non-coplanar directions, found "
                         f"directions of rank < 3 (singular values {[round(float(x), 4) for x in sv]})")


def estimate_normals(capture, *, rounds: int = 1, iters: int = 12, joint: bool = True, flat_test: bool = True,
                     fit_kwargs: dict | None = None) -> NormalsEstimate:
    """Per-pixel normals from the photos and the known lights (see the module docstring).

    Args:
        capture: a :class:`~torchmetal.io.capture.Capture`; its own normals are ignored.
        rounds: Phong rounds after the Lambertian refinement (0: Lambertian only).
        iters: LM iterations per pixel and round.
        joint: finish with the joint refinement of the normals and s, α
            (:func:`~torchmetal.fit.normals_joint.joint_refine`).
        flat_test: keep (0, 0, 1) where the estimate does not explain the shots significantly
            better (:func:`~torchmetal.fit.normals_flat.flat_where_unresolved`).
        fit_kwargs: extra arguments of :func:`~torchmetal.fit.fit_phong` for the rounds' fits
            (e.g. ``tol``, ``max_iters``); specular is "global".

    Returns:
        :class:`NormalsEstimate`.

    Raises:
        InputError: fewer than 3 shots, or lights that cannot determine a normal.
        FitError: the estimate went non-finite.
    """
    from torchmetal.fit.api import fit_phong

    if not (isinstance(rounds, int) and rounds >= 0):
        raise InputError(f"rounds: expected an int >= 0, found {rounds!r}")
    if not (isinstance(iters, int) and iters >= 1):
        raise InputError(f"iters: expected an int >= 1, found {iters!r}")
    _check_capture(capture)
    for name in ("images", "intensities", "lights", "cameras"):
        if not bool(torch.isfinite(getattr(capture, name)).all()):
            raise FitError(f"capture.{name}: expected finite values, found NaN/Inf")
    t0 = time.perf_counter()
    h, w = capture.height, capture.width
    dt = _work_dtype(capture)
    normals = torch.zeros(3, h, w, dtype=dt, device=capture.images.device)
    normals[2] = 1.0
    solvable = torch.zeros(h, w, dtype=torch.bool, device=normals.device)
    for r0, r1 in _row_blocks(capture):
        theta, good = _lambert_init(_chunk(capture, r0, r1, dt))
        n, _ = _normals_of(theta)
        normals[:, r0:r1] = torch.where(good.unsqueeze(0), n, normals[:, r0:r1].reshape(3, -1)).reshape(3, r1 - r0, w)
        solvable[r0:r1] = good.reshape(r1 - r0, w)
    kw = {k: v for k, v in (fit_kwargs or {}).items() if k not in ("specular", "robust")}
    flat = torch.zeros_like(normals)
    flat[2] = 1.0
    zero = torch.zeros(3, dtype=dt, device=normals.device)
    # round 0: the Lambertian start under s = 0, and it and the flat normals under the Phong terms
    # fitted with flat normals; per pixel the one that explains the shots best
    fit = fit_phong(replace(capture, normals=flat.to(capture.images.dtype)), specular="global", **kw)
    s, alpha = fit.s.to(dt), fit.alpha.to(dt)
    cands = [(normals, zero, torch.ones_like(zero))]
    if bool((s > 0).any()):
        cands += [(flat, s, alpha), (normals, s, alpha)]
    normals, rep = refine_normals(capture, cands, iters=iters, active=solvable, propagate=False)
    history = [{"round": 0, "candidates": ["lambertian"] + (["flat+phong", "lambertian+phong"] if len(cands) > 1 else []),
                "flat_fit": {"s": s.tolist(), "alpha": alpha.tolist()}, **rep}]
    history[0]["time"] = time.perf_counter() - t0
    for k in range(1, rounds + 1):
        t1 = time.perf_counter()
        fit = fit_phong(replace(capture, normals=normals.to(capture.images.dtype)), specular="global", **kw)
        s, alpha = fit.s.to(dt), fit.alpha.to(dt)
        normals, rep = refine_normals(capture, [(normals, s, alpha)], iters=iters, active=solvable)
        history.append({"round": k, "s": s.tolist(), "alpha": alpha.tolist(), "phong_rmse": float(fit.rmse), **rep,
                        "time": time.perf_counter() - t1})
    if joint and bool((s > 0).any()):
        from torchmetal.fit.normals_joint import joint_refine

        t1 = time.perf_counter()
        normals, s, alpha, rep = joint_refine(capture, normals, s, alpha, active=solvable)
        history.append({"round": "joint", "s": s.tolist(), "alpha": alpha.tolist(), **rep,
                        "time": time.perf_counter() - t1})
    n_flat = 0
    if flat_test:
        from torchmetal.fit.normals_flat import flat_where_unresolved

        normals, n_flat = flat_where_unresolved(capture, normals, s, alpha, active=solvable)
    if not bool(torch.isfinite(normals).all()):
        raise FitError("estimate_normals: expected finite normals, found NaN/Inf")
    normals = normals / normals.norm(dim=0, keepdim=True)
    inside = capture.mask[0]
    tilt = torch.rad2deg(torch.acos(normals[2][inside].clamp(-1, 1)))
    report = {
        "mode": "estimate", "rounds": history, "time": time.perf_counter() - t0,
        "pixels": int(inside.sum()), "unsolved_pixels": int((inside & ~solvable).sum()), "kept_flat": n_flat,
        "tilt_deg": {"mean": float(tilt.mean()) if tilt.numel() else 0.0,
                     "max": float(tilt.max()) if tilt.numel() else 0.0},
    }
    out_dt = capture.images.dtype
    return NormalsEstimate(normals.to(out_dt), s.to(out_dt), alpha.to(out_dt), report)


def with_normals(capture, mode: str, **kw):
    """The capture with the normals ``mode`` asks for, and a report entry.

    "given": the capture's own (its normals.npy, flat (0, 0, 1) without one); "flat": (0, 0, 1)
    everywhere; "estimate": :func:`estimate_normals` (``kw`` passed on).

    Returns:
        (capture, report dict).
    """
    if mode not in NORMALS_MODES:
        raise InputError(f"normals: expected one of {list(NORMALS_MODES)}, found {mode!r}")
    if mode == "given":
        return capture, {"mode": "given", "flat": capture.flat}
    if mode == "flat":
        if capture.flat:
            return capture, {"mode": "flat"}
        n = torch.zeros_like(capture.normals)
        n[2] = 1.0
        return replace(capture, normals=n), {"mode": "flat", "ignored": "the capture's normals"}
    est = estimate_normals(capture, **kw)
    return replace(capture, normals=est.normals), est.report


def angular_error(a: Tensor, b: Tensor, mask: Tensor | None = None) -> Tensor:
    """Angle in degrees between unit normal maps a, b (3, H, W) → (M,) over ``mask`` (H, W) pixels."""
    c = (a.double() * b.double()).sum(0) / (a.double().norm(dim=0) * b.double().norm(dim=0)).clamp_min(1e-30)
    ang = torch.rad2deg(torch.acos(c.clamp(-1.0, 1.0)))
    return ang.reshape(-1) if mask is None else ang[mask]


__all__ = ["NORMALS_MODES", "NormalsEstimate", "estimate_normals", "refine_normals", "with_normals", "angular_error"]
