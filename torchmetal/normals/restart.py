"""Second chances for pixels the per-pixel refinement left in a wrong minimum: a step of
:func:`~torchmetal.normals.estimate.estimate_normals` after the joint refinement.

Near highlights (and on dark, noisy texture) a pixel's robust cost has several minima; its start
(the Lambertian init, a neighbour's normal) can fall into a wrong one, and whole patches then
agree with each other, so neither one propagation pass inside a row chunk nor the median test
can tell, though the true normal costs a fraction of the estimate's (docs/design.md §4). Two moves, each kept only where it cuts the pixel's robust cost
(Cauchy, with the scale of its row chunk fixed at the start) by at least ``MOVE_GAIN``: a wrong
minimum costs several times the right one, while small gains are what a model that does not fit
(a second material's sharper lobe) buys with more tilt; taking those spreads the tilt:

1. **restart**: pixels whose robust cost exceeds ``RESTART_K`` × their chunk's median try a polar
   grid of normals (tilts ``GRID_TILTS_DEG`` × ``GRID_AZIMUTHS`` azimuths, and flat); the best
   start is refined (Cauchy IRLS around the per-pixel LM);
2. **propagation until settled**: each pixel tries its neighbours' normals at the
   :data:`~torchmetal.normals.refine.PROPAGATE` shifts across the whole image (not only
   inside its chunk); the pixels that take one are refined; the next pass looks only at the
   pixels next to one that moved, until none moves or after ``SETTLE_PASSES`` passes.

On a smooth, well-lit surface no pixel's cost stands out and a neighbour's normal never costs
much less than the pixel's own minimum, so little changes there. The one propagation pass inside
row chunks that ends the joint stage runs before, with any gain taken.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.normals.core import (
    CAUCHY_C,
    Spec,
    active_blocks,
    chunk_subset,
    model_state,
    normals_of,
    pass_setup,
    robust_cost,
    robust_scale,
    theta_of,
)
from torchmetal.normals.refine import PROPAGATE, best_of, refine_kept, shifted

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

RESTART_K = 3.0  # a pixel costing more than this × its chunk's median robust cost gets the grid of starts
GRID_TILTS_DEG = (5.0, 10.0, 15.0, 20.0, 30.0, 45.0)
GRID_AZIMUTHS = 8
SETTLE_PASSES = 6
MOVE_GAIN = 0.3  # a restart or a neighbour's normal must cut the pixel's robust cost by this fraction


def _grid(dt: torch.dtype, device) -> Tensor:
    """The restart's starts as surface gradients θ (2, G): flat, then tilts × azimuths."""
    pts = [(0.0, 0.0)]
    for t in GRID_TILTS_DEG:
        g = math.tan(math.radians(t))
        pts += [(g * math.cos(2 * math.pi * a / GRID_AZIMUTHS), g * math.sin(2 * math.pi * a / GRID_AZIMUTHS))
                for a in range(GRID_AZIMUTHS)]
    return torch.tensor(pts, dtype=dt, device=device).T


def restart_and_settle(capture: Capture, normals: Tensor, s: Tensor, alpha: Tensor, *, iters: int = 12,
                       active: Tensor | None = None) -> tuple[Tensor, dict]:
    """Normals (3, H, W) after the restart of high-cost pixels and propagation until settled (see
    the module docstring); ``active`` (H, W) the pixels that may change (default: the mask).

    Returns:
        normals (3, H, W) and a report: pixels restarted, restarts kept, propagation passes, moves.
    """
    dt, spec, act, floor = pass_setup(capture, s, alpha, active)
    h, w = capture.height, capture.width
    theta = theta_of(normals.to(dt).reshape(3, -1))  # (2, H·W)
    cost = torch.zeros(h * w, dtype=dt, device=theta.device)
    scales, tried, kept = _restart(capture, theta, cost, spec, act, floor, iters)
    passes, moves = _settle(capture, theta, cost, scales, spec, act, iters)
    act_flat = act.reshape(-1)
    n, _ = normals_of(theta)
    out = torch.where(act_flat.unsqueeze(0), n, normals.to(dt).reshape(3, -1)).reshape(3, h, w)
    return out, {"restarted": tried, "restart_kept": kept, "passes": passes, "moves": moves}


def _restart(capture: Capture, theta: Tensor, cost: Tensor, spec: Spec | None, act: Tensor, floor: float,
             iters: int) -> tuple[list[Tensor], int, int]:
    """1. restart: in each row block, the pixels whose robust cost exceeds ``RESTART_K`` × the block's
    median try the grid of starts, kept where the refined best cuts their cost by ``MOVE_GAIN``.
    Writes θ (2, H·W) and the robust cost (H·W,) in place; returns the blocks' Cauchy scales, the
    pixels restarted and the restarts kept."""
    dt, w = theta.dtype, capture.width
    grid = _grid(dt, theta.device)
    scales, tried, kept = [], 0, 0
    for r0, _, keep, sub in active_blocks(capture, act, dt):
        idx = r0 * w + keep
        th = theta[:, idx]
        scale = CAUCHY_C * robust_scale(model_state(sub, th, spec, sub.ok.to(dt), jac=False).r, sub.ok, floor)
        scales.append(scale)
        c = robust_cost(sub, th, spec, scale)
        bad = (c > RESTART_K * c.median()).nonzero().squeeze(1)
        if bad.numel():
            part = chunk_subset(sub, bad)
            n_b = bad.numel()
            starts = [grid[:, g:g + 1].expand(2, n_b) for g in range(grid.shape[1])]
            t0, c0, _ = best_of(part, th[:, bad], torch.full_like(c[bad], math.inf), starts, spec, scale)
            t1, c1, _ = refine_kept(part, t0, c0, spec, scale, iters)
            better = c1 < (1.0 - MOVE_GAIN) * c[bad]
            th[:, bad] = torch.where(better, t1, th[:, bad])
            c[bad] = torch.where(better, c1, c[bad])
            tried, kept = tried + n_b, kept + int(better.sum())
        theta[:, idx], cost[idx] = th, c
    return scales, tried, kept


def _settle(capture: Capture, theta: Tensor, cost: Tensor, scales: list[Tensor], spec: Spec | None, act: Tensor,
            iters: int) -> tuple[int, int]:
    """2. propagation until settled: each pixel next to one whose normal is new tries its
    neighbours' normals (:data:`PROPAGATE` shifts, across the whole image), taken where they cut its
    cost by ``MOVE_GAIN`` and then refined; until none moves or ``SETTLE_PASSES``. Writes θ and the
    cost in place; returns the passes run and the moves made."""
    dt, w = theta.dtype, capture.width
    act_flat = act.reshape(-1)
    front = act_flat.clone()  # pixels whose normal is new to their neighbours
    passes, moves = 0, 0
    for passes in range(1, SETTLE_PASSES + 1):  # noqa: B007 (reported after the loop)
        new = (front & act_flat).view(1, -1)  # a neighbour's normal is a candidate where it is new
        src = [(shifted(theta, w, dy, dx), shifted(new, w, dy, dx)[0]) for dy, dx in PROPAGATE]
        moved = torch.zeros_like(front)
        for (r0, _, keep, sub), scale in zip(active_blocks(capture, act, dt), scales):
            idx = r0 * w + keep
            look = torch.stack([f[idx] for _, f in src]).any(0).nonzero().squeeze(1)
            if not look.numel():
                continue
            part, at = chunk_subset(sub, look), idx[look]
            cands = [torch.where(f[at].unsqueeze(0), t[:, at], theta[:, at]) for t, f in src]
            th, c, won = best_of(part, theta[:, at], cost[at], cands, spec, scale, MOVE_GAIN)
            hit = won.nonzero().squeeze(1)
            if hit.numel():
                th[:, hit], c[hit], _ = refine_kept(chunk_subset(part, hit), th[:, hit], c[hit], spec, scale, iters)
            theta[:, at], cost[at] = th, c
            moved[at] = won
        n_moved = int(moved.sum())
        moves += n_moved
        front = moved
        if n_moved == 0:
            break
    return passes, moves
