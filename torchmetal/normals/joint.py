"""Joint refinement of the per-pixel normals and the global specular terms (the last stage of
:func:`~torchmetal.normals.estimate.estimate_normals`).

Alternating "normals under fixed s, α" with "s, α under fixed normals" has a biased fixed point:
the Phong fit takes the normals as exact, so their errors broaden the lobe it sees (lower α and
s), and normals refined under a broader lobe keep their errors. Here both move together:
unknowns θ_p (the surface gradient of every pixel, 2 each) and two global log-scales
g = (u, w) with s = s₀·e^u and α = α₀·e^w (all channels together); the texture is eliminated per
pixel as in :mod:`~torchmetal.normals.core` (variable projection). Each Gauss–Newton step solves
the per-pixel 2×2 blocks and the 2×2 global block through the Schur complement

    (H_gg − Σ_p H_gpH_pp⁻¹H_pg)·δg = b_g − Σ_p H_gpH_pp⁻¹b_p,   δθ_p = H_pp⁻¹(b_p − H_pg·δg)

(Levenberg damping on both, one accept/reject on the total cost), with the Cauchy weights of the
start fixed. Chunks are held in memory between passes (the observations of the active pixels).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.normals.core import (
    CAUCHY_C,
    SLOPE_MAX,
    Spec,
    active_blocks,
    cauchy_weights,
    model_state,
    normals_of,
    robust_cost,
    robust_scale,
    theta_of,
    work_dtype,
)
from torchmetal.normals.refine import refine_normals

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture


def _inv2(a11: Tensor, a12: Tensor, a22: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    det = a11 * a22 - a12 * a12
    ok = det > 0
    det = torch.where(ok, det, torch.ones_like(det))
    z = torch.zeros_like(a11)
    return torch.where(ok, a22 / det, z), torch.where(ok, -a12 / det, z), torch.where(ok, a11 / det, z)


def joint_refine(capture: Capture, normals: Tensor, s: Tensor, alpha: Tensor, *, iters: int = 8,
                 active: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, dict]:
    """Refine normals (3, H, W) and the global s, α (3,) together (see the module docstring).

    Returns:
        normals (3, H, W), s (3,), α (3,) and a report (iterations, accepted steps, the scales).
    """
    dt = work_dtype(capture)
    s0, a0 = s.to(dt).reshape(3), alpha.to(dt).reshape(3)
    if not bool((s0 > 0).any()):
        return normals, s, alpha, {"skipped": "no specular (s = 0)"}
    act = capture.mask[0] if active is None else active
    floor = 1e-6 * float(capture.images.detach().abs().amax().clamp_min(1e-30))
    spec0 = Spec(s0, a0)
    parts = _start_parts(capture, normals, spec0, act, floor, dt)
    g = torch.zeros(2, dtype=torch.float64, device=s0.device)
    spec_of = lambda g: Spec(s0 * math.exp(float(g[0])), a0 * math.exp(float(g[1])))  # noqa: E731
    lam, accepted, it = 1e-3, 0, 0
    cost = sum(float(model_state(p[3], p[4], spec0, p[5], jac=False).cost.double().sum()) for p in parts)
    for it in range(1, iters + 1):  # noqa: B007 (the count is reported after the loop)
        S, b, blocks = _schur_system(parts, spec_of(g), lam)
        dg = torch.linalg.solve(S, b) if bool(torch.isfinite(S).all()) and float(torch.det(S)) > 0 else torch.zeros_like(b)
        trial_g = g + dg.clamp(-0.5, 0.5)
        trial_th, new_cost = _trial_step(parts, blocks, trial_g - g, spec_of(trial_g))
        if math.isfinite(new_cost) and new_cost < cost:
            for p, t in zip(parts, trial_th):
                p[4] = t
            g, cost, lam, accepted = trial_g, new_cost, max(lam / 3.0, 1e-7), accepted + 1
            if float(dg.abs().max()) < 1e-5:
                break
        else:
            lam *= 5.0
            if lam > 1e6:
                break
    out = normals.to(dt).clone()
    for r0, r1, keep, _, th, _ in parts:
        n, _ = normals_of(th)
        blk = out[:, r0:r1].reshape(3, -1)
        blk[:, keep] = n
        out[:, r0:r1] = blk.reshape(3, r1 - r0, capture.width)
    spec = spec_of(g)
    return out, spec.s, spec.alpha, {"iterations": it, "accepted": accepted, "log_scales": g.tolist()}


def _start_parts(capture: Capture, normals: Tensor, spec0: Spec, act: Tensor, floor: float,
                 dt: torch.dtype) -> list[list]:
    """Per row block with active pixels: [r0, r1, keep, chunk of the active pixels, θ, Cauchy weights
    at the start (fixed from then on)]."""
    parts = []
    for r0, r1, keep, sub in active_blocks(capture, act, dt):
        th = theta_of(normals[:, r0:r1].reshape(3, -1).to(dt))[:, keep]
        st = model_state(sub, th, spec0, sub.ok.to(dt), jac=False)
        scale = CAUCHY_C * robust_scale(st.r, sub.ok, floor)
        parts.append([r0, r1, keep, sub, th, cauchy_weights(sub, st.r, scale)])
    return parts


def _schur_system(parts: list[list], spec: Spec, lam: float) -> tuple[Tensor, Tensor, list]:
    """The damped Gauss–Newton system of the global log-scales after eliminating every pixel's θ
    (the Schur complement S (2, 2) and its right side b (2,), float64), and per part the
    H_pp⁻¹·H_pg (2, 2, P) and H_pp⁻¹·b_p (2, P) that give the pixels' steps."""
    S = torch.zeros(2, 2, dtype=torch.float64, device=spec.s.device)
    b = torch.zeros(2, dtype=torch.float64, device=spec.s.device)
    blocks = []
    for _, _, _, sub, th, wt in parts:
        st = model_state(sub, th, spec, wt, glob=True)
        j, gj = st.jac, st.gjac
        wj = [wt * x for x in j]
        a11, a12, a22 = (wj[0] * j[0]).sum(0)[0], (wj[0] * j[1]).sum(0)[0], (wj[1] * j[1]).sum(0)[0]
        bp = torch.stack([(wj[0] * st.r).sum(0)[0], (wj[1] * st.r).sum(0)[0]])  # (2, P)
        B = torch.stack([torch.stack([(wj[i] * gj[k]).sum(0)[0] for k in (0, 1)]) for i in (0, 1)])  # (2, 2, P)
        tiny = 1e-9 * (a11 + a22) + 1e-30
        i11, i12, i22 = _inv2(a11 * (1 + lam) + tiny, a12, a22 * (1 + lam) + tiny)
        # H_pp⁻¹·B (2, 2, P) and H_pp⁻¹·b_p (2, P)
        ib = torch.stack([i11 * B[0] + i12 * B[1], i12 * B[0] + i22 * B[1]])
        ibp = torch.stack([i11 * bp[0] + i12 * bp[1], i12 * bp[0] + i22 * bp[1]])
        wg = [wt * x for x in gj]
        for k in (0, 1):
            b[k] += float((wg[k] * st.r).double().sum()) - float((B[:, k] * ibp).double().sum())
            for m in (0, 1):
                S[k, m] += float((wg[k] * gj[m]).double().sum()) - float((B[:, k] * ib[:, m]).double().sum())
        blocks.append((ib, ibp))
    S = S + lam * torch.diag(S.diagonal()) + 1e-12 * S.diagonal().sum() * torch.eye(2, dtype=S.dtype, device=S.device)
    return S, b, blocks


def _trial_step(parts: list[list], blocks: list, dg: Tensor, spec: Spec) -> tuple[list[Tensor], float]:
    """Every pixel's θ after the global step ``dg`` (back-substituted through ``blocks``) and the
    total weighted cost there under ``spec``."""
    trial_th, new_cost = [], 0.0
    for (_, _, _, sub, th, wt), (ib, ibp) in zip(parts, blocks):
        dgt = dg.to(ib.dtype)
        dth = ibp - (ib[:, 0] * dgt[0] + ib[:, 1] * dgt[1])
        t = (th + torch.where(torch.isfinite(dth), dth, torch.zeros_like(dth))).clamp(-SLOPE_MAX, SLOPE_MAX)
        trial_th.append(t)
        new_cost += float(model_state(sub, t, spec, wt, jac=False).cost.double().sum())
    return trial_th, new_cost


WEAK_S = 0.1  # the weak lobe's start: s = WEAK_S × the texture's mean (per channel), α = WEAK_ALPHA
WEAK_ALPHA = 10.0
WEAK_ITERS = 30
WEAK_GAIN = 0.01  # kept when it lowers the total robust cost by more than this fraction


def try_weak_lobe(capture: Capture, normals: Tensor, texture_mean: Tensor, *, iters: int = 12,
                  active: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, dict]:
    """When :func:`~torchmetal.fit.fit_phong` saw no highlight (s = 0): a weak, broad lobe (s ≈ 10 %
    of the diffuse, α ≈ 10) hides in Lambertian normals tilted towards the half vectors, and then no
    residual shows it. From the Lambertian normals (3, H, W), refine under a small lobe
    (texture_mean (3,) × ``WEAK_S``, ``WEAK_ALPHA``), fit the normals and s, α jointly
    (:func:`joint_refine`), and keep the result when its total robust cost, at the Lambertian
    residual's scale, is lower by more than ``WEAK_GAIN``.

    Returns:
        normals (3, H, W), s (3,), α (3,) — the input and zeros when not kept — and a report.
    """
    dt = work_dtype(capture)
    s0 = (WEAK_S * texture_mean.to(dt).reshape(3)).clamp_min(0.0)
    zero = torch.zeros(3, dtype=dt, device=normals.device)
    if not bool((s0 > 0).any()):
        return normals, zero, torch.ones_like(zero), {"kept": False, "reason": "zero texture"}
    a0 = torch.full_like(s0, WEAK_ALPHA)
    start, _ = refine_normals(capture, [(normals, s0, a0)], iters=iters, active=active, propagate=False)
    out, s, alpha, rep = joint_refine(capture, start, s0, a0, iters=WEAK_ITERS, active=active)
    act = capture.mask[0] if active is None else active
    floor = 1e-6 * float(capture.images.detach().abs().amax().clamp_min(1e-30))
    spec = Spec(s.to(dt), alpha.to(dt))
    c_lam, c_lobe = 0.0, 0.0
    for r0, r1, keep, sub in active_blocks(capture, act, dt):
        th0 = theta_of(normals[:, r0:r1].reshape(3, -1).to(dt))[:, keep]
        th1 = theta_of(out[:, r0:r1].reshape(3, -1).to(dt))[:, keep]
        scale = CAUCHY_C * robust_scale(model_state(sub, th0, None, sub.ok.to(dt), jac=False).r, sub.ok, floor)
        c_lam += float(robust_cost(sub, th0, None, scale).double().sum())
        c_lobe += float(robust_cost(sub, th1, spec, scale).double().sum())
    kept = c_lobe < (1.0 - WEAK_GAIN) * c_lam
    rep = {"kept": kept, "cost_lambertian": c_lam, "cost_lobe": c_lobe, "s": s.tolist(), "alpha": alpha.tolist(), **rep}
    if not kept:
        return normals, zero, torch.ones_like(zero), rep
    return out, s, alpha, rep
