"""The per-pixel refinement behind :func:`~torchmetal.normals.estimate_normals`: θ (the surface
gradient, :mod:`~torchmetal.normals.core`) solved by a 2-parameter Levenberg–Marquardt per pixel
inside Cauchy IRLS rounds, the texture eliminated; converged pixels leave the working set. Per
pixel the best of several starts is kept, and neighbours' normals are tried (:data:`PROPAGATE`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.normals.core import (
    CAUCHY_C,
    SLOPE_MAX,
    Chunk,
    Spec,
    cauchy_weights,
    chunk_subset,
    model_state,
    normals_of,
    robust_cost,
    robust_scale,
    row_blocks,
    row_chunk,
    theta_of,
    work_dtype,
)

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

IRLS_ROUNDS = 3  # Cauchy weights recomputed this many times
STEP_TOL = 1e-4  # a pixel stops when its θ step is below this (relative; ~0.006°)


def _lm(ch: Chunk, theta: Tensor, spec: Spec | None, w: Tensor, iters: int) -> tuple[Tensor, int]:
    """Per-pixel LM on θ (2, P) with fixed weights w (N, 1, P); pixels that converged leave the
    working set. Returns θ and the iterations run."""
    theta = theta.clone()
    st = model_state(ch, theta, spec, w)
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
        st_t = model_state(ch, trial, spec, w)
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
            ch = chunk_subset(ch, keep)
    return theta, it


def _irls(ch: Chunk, theta: Tensor, spec: Spec | None, scale: Tensor, iters: int) -> tuple[Tensor, int]:
    """IRLS (Cauchy weights, ``IRLS_ROUNDS`` rounds) around a per-pixel LM on θ (2, P)."""
    total = 0
    per_round = max(1, math.ceil(iters / IRLS_ROUNDS))
    w = ch.ok.to(ch.y.dtype)
    for _ in range(IRLS_ROUNDS):
        st = model_state(ch, theta, spec, w, jac=False)
        w = cauchy_weights(ch, st.r, scale)
        theta, it = _lm(ch, theta, spec, w, per_round)
        total += it
    return theta, total


def best_of(sub: Chunk, theta: Tensor, cost: Tensor, cands: list, spec: Spec | None, scale: Tensor,
             gain: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Per pixel the least robust cost among θ (2, P) at ``cost`` (P,) and the candidates (each
    (2, P)), a candidate winning only below (1 − gain) × the cost to beat; returns θ, its cost and
    whether a candidate won (P,)."""
    won = torch.zeros_like(cost, dtype=torch.bool)
    for t in cands:
        c = robust_cost(sub, t, spec, scale)
        take = c < (1.0 - gain) * cost
        theta, cost, won = torch.where(take, t, theta), torch.where(take, c, cost), won | take
    return theta, cost, won


def refine_kept(sub: Chunk, theta: Tensor, cost: Tensor, spec: Spec | None, scale: Tensor,
                 iters: int) -> tuple[Tensor, Tensor, int]:
    """θ (2, P) refined by :func:`_irls` where that lowers the robust cost (P,); and the LM iterations run."""
    t, it = _irls(sub, theta, spec, scale, iters)
    c = robust_cost(sub, t, spec, scale)
    better = c < cost
    return torch.where(better, t, theta), torch.where(better, c, cost), it


def shifted(x: Tensor, width: int, dy: int, dx: int) -> Tensor:
    """A (2, R·W) map moved by (dy, dx) pixels within the chunk (edges repeat)."""
    m = x.reshape(x.shape[0], -1, width)
    r = m.shape[1]
    rows = (torch.arange(r, device=x.device) - dy).clamp(0, r - 1)
    cols = (torch.arange(width, device=x.device) - dx).clamp(0, width - 1)
    return m[:, rows][:, :, cols].reshape(x.shape)


PROPAGATE = tuple((d * sy, d * sx) for d in (1, 3, 9) for sy, sx in ((0, 1), (0, -1), (1, 0), (-1, 0)))
"""Shifts (rows, cols) of the neighbours whose normals a pixel tries: 1, 3 and 9 px in the four
directions, so a patch caught in a wrong minimum near a highlight takes its rim's normals."""


def _solve_chunk(ch: Chunk, width: int, active: Tensor, candidates: list, iters: int, floor: float,
                 propagate: bool) -> tuple[Tensor, Tensor, int]:
    """Per ``active`` pixel: every candidate start (θ (2, P), spec) refined under its terms, the
    one of least robust cost kept; then (``propagate``) each neighbour's θ is tried under the first candidate's
    terms and the pixels that took one are refined again. Returns θ (2, P), the robust cost (P,)
    and the LM iterations run."""
    keep = active.nonzero().squeeze(1)
    sub = chunk_subset(ch, keep)
    starts = [(th[:, keep], sp) for th, sp in candidates]
    ls = [model_state(sub, th, sp, sub.ok.to(sub.y.dtype), jac=False) for th, sp in starts]
    best = torch.stack([st.cost for st in ls]).argmin(0)  # the scale: residuals of the best start
    r0 = torch.stack([st.r for st in ls]).gather(0, best.view(1, 1, 1, -1).expand(1, *ls[0].r.shape))[0]
    scale = CAUCHY_C * robust_scale(r0, sub.ok, floor)
    del ls, r0
    total, refined = 0, []
    for th, sp in starts:  # each start refined under its terms; per pixel the best kept
        t, it = _irls(sub, th, sp, scale, iters)
        total += it
        refined.append((t, robust_cost(sub, t, sp, scale)))
    costs = torch.stack([c for _, c in refined])
    best = costs.argmin(0)
    theta = torch.stack([t for t, _ in refined]).gather(0, best.view(1, 1, -1).expand(1, 2, -1))[0]
    cost = costs.gather(0, best.view(1, -1))[0]
    spec = starts[0][1]
    del refined, costs
    if propagate:
        full = candidates[0][0].clone()
        full[:, keep] = theta
        theta, cost, moved = best_of(sub, theta, cost, [shifted(full, width, dy, dx)[:, keep] for dy, dx in PROPAGATE],
                                      spec, scale)
        idx = moved.nonzero().squeeze(1)
        if idx.numel():
            theta[:, idx], cost[idx], it = refine_kept(chunk_subset(sub, idx), theta[:, idx], cost[idx], spec, scale, iters)
            total += it
    out_t = candidates[0][0].clone()
    out_t[:, keep] = theta
    c_full = torch.zeros(out_t.shape[1], dtype=cost.dtype, device=cost.device)
    c_full[keep] = cost
    return out_t, c_full, total


def refine_normals(
    capture: Capture, candidates: list[tuple[Tensor, Tensor, Tensor]], *, iters: int = 12, active: Tensor | None = None, propagate: bool = True,
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
    dt = work_dtype(capture)
    w = capture.width
    cands = []
    for nrm, s, al in candidates:
        s = torch.as_tensor(s).to(device=nrm.device, dtype=dt).reshape(3)
        al = torch.as_tensor(al).to(device=nrm.device, dtype=dt).reshape(3)
        cands.append((nrm.to(dt), Spec(s, al) if bool((s > 0).any()) else None))
    act = capture.mask[0] if active is None else active
    out_n = cands[0][0].clone()
    floor = 1e-6 * float(capture.images.detach().abs().amax().clamp_min(1e-30))
    iters_max, cost_sum = 0, 0.0
    for r0, r1 in row_blocks(capture):
        a = act[r0:r1].reshape(-1)
        if not bool(a.any()):
            continue
        ch = row_chunk(capture, r0, r1, dt)
        thetas = [(theta_of(nrm[:, r0:r1].reshape(3, -1)), sp) for nrm, sp in cands]
        theta, cost, it = _solve_chunk(ch, w, a, thetas, iters, floor, propagate)
        n, _ = normals_of(theta)
        out_n[:, r0:r1] = torch.where(a.unsqueeze(0), n, out_n[:, r0:r1].reshape(3, -1)).reshape(3, r1 - r0, w)
        iters_max = max(iters_max, it)
        cost_sum += float(cost.sum())
    return out_n, {"iterations": iters_max, "robust_cost": cost_sum / max(1, int(act.sum()))}
