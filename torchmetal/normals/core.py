"""What the steps of :func:`~torchmetal.normals.estimate_normals` share: the observations of a row
chunk, the normals written through the surface gradient θ, the model with its Jacobian in θ, and the
robust weights, scales and costs.

Per pixel, with n = (−θx, −θy, 1)/√(1 + θx² + θy²) (n·z > 0 by construction) and the channel
sum z_k = Σ_c y_kc of each shot (shots with a clipped channel left out):

    z_k = Ē_k·[D·max(n·l_k, 0) + [n·l_k > 0]·Σ_c κ_kc·s_c·max(r_k·v_k, 0)^α_c]

Ē_k the channel mean of the irradiance, κ_kc = E_kc/Ē_k the light's colour, D = Σ_c κ_c·d_c.
The texture D is eliminated in closed form (variable projection; Kaufman's Jacobian). Every term is
per pixel, so the work runs in row chunks (memory only; the robust scale is the chunk's).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.geometry import direction_to, surface_points
from torchmetal.phong import lobe_log

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

CAUCHY_C = 5.0  # Cauchy scale in units of σ
SLOPE_MAX = 57.0  # |θ| cap: normals at most ~89° from z
CHUNK_OBS = 1 << 18  # observations (shots × pixels) per chunk
MAD = 1.4826


# ------------------------------------------------------------------------------- per-chunk data


@dataclass
class Chunk:
    """Channel-summed observations of a block of rows, flattened to P pixels (working dtype)."""

    y: Tensor  # (N, 1, P) z = Σ_c y_c
    e: Tensor  # (N, 1, P) Ē, the channel mean of the irradiance
    kappa: Tensor  # (N, 3, 1) E_c / Ē, the light's colour
    l: Tensor  # (N, 3, P) unit to light
    v: Tensor  # (N, 3, P) unit to camera
    ok: Tensor  # (N, 1, P) bool: in the mask, no channel clipped, E > 0
    pix: Tensor  # (P,) bool: in the mask


def row_chunk(capture: Capture, r0: int, r1: int, dt: torch.dtype) -> Chunk:
    """The observations of rows r0 to r1 (exclusive) in the work dtype ``dt``."""
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
    return Chunk(y, e, kappa.view(n, 3, 1), l.reshape(n, 3, -1), v.reshape(n, 3, -1), ok, pix)


def row_blocks(capture: Capture) -> list[tuple[int, int]]:
    """Row ranges (r0, r1) of about ``CHUNK_OBS`` observations each."""
    rows = max(1, CHUNK_OBS // (capture.num_shots * capture.width))
    return [(r0, min(capture.height, r0 + rows)) for r0 in range(0, capture.height, rows)]


def active_blocks(capture: Capture, act: Tensor, dt: torch.dtype) -> Iterator[tuple[int, int, Tensor, Chunk]]:
    """Per row block with active pixels: (r0, r1, keep (k,) indices into the block, the block's chunk of them)."""
    for r0, r1 in row_blocks(capture):
        keep = act[r0:r1].reshape(-1).nonzero().squeeze(1)
        if keep.numel():
            yield r0, r1, keep, chunk_subset(row_chunk(capture, r0, r1, dt), keep)


def robust_scale(x: Tensor, keep: Tensor, floor: float) -> Tensor:
    """σ = 1.4826·median|x| over the ``keep`` entries (a 0-d tensor, at least ``floor``)."""
    vals = x[keep].abs()
    sig = MAD * vals.median() if vals.numel() else x.new_tensor(0.0)
    return sig.clamp_min(floor)


# ------------------------------------------------------------------------------- normals ↔ θ


def normals_of(theta: Tensor) -> tuple[Tensor, Tensor]:
    """θ (2, P) → unit n (3, P) and k = √(1 + |θ|²) (P,)."""
    k = torch.sqrt(1.0 + theta[0] * theta[0] + theta[1] * theta[1])
    return torch.stack([-theta[0], -theta[1], torch.ones_like(k)]) / k, k


def theta_of(g: Tensor) -> Tensor:
    """Any vectors g (3, P) with g_z > 0 preferred → θ (2, P); g_z is floored so |θ| ≤ SLOPE_MAX."""
    gz = torch.maximum(g[2], torch.hypot(g[0], g[1]) / SLOPE_MAX).clamp_min(1e-30)
    return torch.stack([-g[0] / gz, -g[1] / gz]).clamp(-SLOPE_MAX, SLOPE_MAX)


# ------------------------------------------------------------------------------- the model


@dataclass
class State:
    """The model at θ on a chunk's pixels (:func:`model_state`)."""

    r: Tensor  # (N, 1, P) residual z − model
    d: Tensor  # (1, P) texture D
    cost: Tensor  # (P,) weighted squared residual Σ w·r²
    jac: tuple[Tensor, Tensor]  # ∂model/∂θ projected off the texture, (N, 1, P) each
    gjac: tuple[Tensor, Tensor] | None = None  # ∂model/∂(log s, log α), when asked for

    def merge(self, other: "State", take: Tensor) -> "State":
        """Per pixel: ``other`` where ``take`` (P,), else self."""
        pick = lambda a, b: torch.where(take, b, a)  # noqa: E731
        return State(pick(self.r, other.r), pick(self.d, other.d), pick(self.cost, other.cost),
                     (pick(self.jac[0], other.jac[0]), pick(self.jac[1], other.jac[1])))

    def select(self, keep: Tensor) -> "State":
        return State(self.r[..., keep], self.d[..., keep], self.cost[keep], (self.jac[0][..., keep], self.jac[1][..., keep]))


@dataclass
class Spec:
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


def pass_setup(capture: Capture, s: Tensor, alpha: Tensor,
               active: Tensor | None) -> tuple[torch.dtype, Spec | None, Tensor, float]:
    """The common start of a per-pixel pass over the normals: the work dtype, the specular terms
    (None when s = 0 everywhere), the pixels that may change (H, W) (default the mask) and the
    cost floor (1e-6 of the brightest value)."""
    dt = work_dtype(capture)
    s, alpha = s.to(dt).reshape(3), alpha.to(dt).reshape(3)
    spec = Spec(s, alpha) if bool((s > 0).any()) else None
    act = capture.mask[0] if active is None else active
    floor = 1e-6 * float(capture.images.detach().abs().amax().clamp_min(1e-30))
    return dt, spec, act, floor


def model_state(ch: Chunk, theta: Tensor, spec: Spec | None, w: Tensor, jac: bool = True,
                glob: bool = False) -> State:
    """Residuals, the closed-form texture (weighted least squares with the weights w (N, 1, P)),
    the weighted cost and (``jac``) the Jacobian of the model in θ at θ (2, P); ``spec`` None:
    Lambertian. With ``glob`` (and spec), also the Jacobian in the log-scales of s and α
    (``State.gjac``, projected off the texture like the θ one)."""
    n, k = normals_of(theta)
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
        lg = lobe_log(q, inside)
        sh, dsh = spec.lobe(ch.kappa, lg, inside)
        target = ch.y - ch.e * sh
    d = ((wea * target).sum(0) * iden).clamp_min(0.0)
    r = target - ea * d
    cost = (w * r * r).sum(0)[0]
    if not jac:
        return State(r, d, cost, (r, r))
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
    st = State(r, d, cost, (jacs[0], jacs[1]))
    if glob and spec is not None:
        gj = []
        for dm in (ch.e * sh, ch.e * dsh * lg):  # ∂/∂ log s, ∂/∂ log α
            gj.append(dm - ea * ((wea * dm).sum(0) * proj).unsqueeze(0))
        st.gjac = (gj[0], gj[1])
    return st


def cauchy_weights(ch: Chunk, r: Tensor, scale: Tensor) -> Tensor:
    """IRLS weights 1/(1 + (r/scale)²) of the residuals r (N, 1, P); 0 where an observation is not ``ok``."""
    u = r / scale
    return torch.where(ch.ok, 1.0 / (1.0 + u * u), torch.zeros_like(u))


def chunk_subset(ch: Chunk, keep: Tensor) -> Chunk:
    """The chunk's pixels ``keep`` (indices (k,))."""
    return Chunk(ch.y[..., keep], ch.e[..., keep], ch.kappa, ch.l[..., keep], ch.v[..., keep], ch.ok[..., keep],
                 ch.pix[keep])


def robust_cost(ch: Chunk, theta: Tensor, spec: Spec | None, scale: Tensor) -> Tensor:
    """Σ_k log(1 + (r_k/scale)²) per pixel (P,) at θ, the texture solved by least squares with
    Cauchy weights of the plain least-squares residual (what selects between candidate normals)."""
    st = model_state(ch, theta, spec, ch.ok.to(ch.y.dtype), jac=False)
    st = model_state(ch, theta, spec, cauchy_weights(ch, st.r, scale), jac=False)
    u = st.r / scale
    return torch.where(ch.ok, torch.log1p(u * u), torch.zeros_like(u)).sum(0)[0]


def work_dtype(capture: Capture) -> torch.dtype:
    """float64 for float64 photos, else float32 (per-pixel sums over a few dozen observations)."""
    return torch.float64 if capture.images.dtype == torch.float64 else torch.float32
