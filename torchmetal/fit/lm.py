"""Batched Levenberg–Marquardt for many small independent problems (1 or 2 parameters each).

Every problem ``m`` of a batch of M has its own parameters x_m, cost, damping λ_m and acceptance;
nothing couples the elements except that one evaluation (``oracle``) computes them all at once.
The cost model around x is the Gauss–Newton quadratic

    cost(x + δ) ≈ cost(x) + 2·gᵀδ + δᵀHδ,   g = Jᵀ W r (½ gradient),  H = Jᵀ W J,

and the damped step solves (H + λ·D)·δ = −g with D the Marquardt diagonal max(diag H, running
max, floor) (Moré 1978), in closed form (1×1 or Jacobi-scaled 2×2 cofactors — never
``torch.linalg.solve``/``lstsq``, which raise on one bad element of a large batch). The step is
projected onto box bounds and the gain ratio uses the projected step. λ follows Nielsen's rule,
clamped to [1e-10, 1e10]; an element accepts a step only when its new cost is finite and not
larger than its current cost, so an accepted step never raises the cost.

Facts behind these choices: ``shared/notes/tooling.md`` §1.2, §1.4 and §1.5.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import torch
from torch import Tensor

LAMBDA_MIN = 1e-10
LAMBDA_MAX = 1e10
LAMBDA_INIT = 1e-3
NU_MAX = 2.0**30
D_FLOOR = 1e-30  # absolute floor of the Marquardt diagonal (relative floors come from the caller)


@dataclass
class LMEval:
    """One evaluation of M problems.

    Attributes:
        cost: (M,) cost at x (a sum of weighted squares).
        grad: (M, P) g = JᵀWr with r = data − model and J = ∂r/∂x (half the cost gradient).
        hess: (M, P, P) Gauss–Newton matrix JᵀWJ.
        aux: anything the caller keeps per evaluation (merged element-wise on acceptance).
        floor: (M,) cost resolution: changes below it are evaluation noise (optional).
    """

    cost: Tensor
    grad: Tensor
    hess: Tensor
    aux: Any = None
    floor: Tensor | None = None


@dataclass
class LMResult:
    x: Tensor  # (M, P)
    eval: LMEval
    iterations: int
    converged: Tensor  # (M,) bool
    status: str  # "converged" | "max_iters"
    costs: list[Tensor] = field(default_factory=list)  # accepted cost per iteration (M,)


# ------------------------------------------------------------------------- small closed forms


def marquardt_diag(diag: Tensor, running: Tensor, floor: Tensor | float = D_FLOOR) -> Tensor:
    """Marquardt scaling D = max(diag(H), running max, floor), element-wise; same shape as diag."""
    d = torch.maximum(diag, running)
    return torch.clamp_min(d, floor) if not isinstance(floor, Tensor) else torch.maximum(d, floor)


def solve_1x1(h: Tensor, g: Tensor) -> Tensor:
    """δ = −g / h for h > 0 (else 0); any shape."""
    ok = h > 0
    return torch.where(ok, -g / torch.where(ok, h, torch.ones_like(h)), torch.zeros_like(g))


def solve_2x2(h11: Tensor, h12: Tensor, h22: Tensor, g1: Tensor, g2: Tensor) -> tuple[Tensor, Tensor]:
    """δ = −H⁻¹ g for symmetric positive definite 2×2 H, in closed form.

    Jacobi scaling (unit diagonal) first, so the determinant cannot overflow; elements whose
    scaled determinant is not positive get δ = 0. All arguments share one shape (any).
    """
    one = torch.ones_like(h11)
    ok = (h11 > 0) & (h22 > 0)
    s1 = torch.where(ok, torch.rsqrt(torch.where(ok, h11, one)), one)
    s2 = torch.where(ok, torch.rsqrt(torch.where(ok, h22, one)), one)
    r = h12 * s1 * s2  # scaled off-diagonal, |r| < 1 for SPD
    det = 1.0 - r * r
    ok = ok & (det > 0)
    inv = torch.where(ok, 1.0 / torch.where(ok, det, one), torch.zeros_like(det))
    b1, b2 = g1 * s1, g2 * s2
    x1 = -(b1 - r * b2) * inv
    x2 = -(b2 - r * b1) * inv
    return x1 * s1, x2 * s2


def damped_step(grad: Tensor, hess: Tensor, lam: Tensor, dscale: Tensor) -> Tensor:
    """Solve (H + λ·diag(D))·δ = −g for each element; grad (M, P), hess (M, P, P), P ∈ {1, 2}."""
    p = grad.shape[-1]
    if p == 1:
        return solve_1x1(hess[:, 0, 0] + lam * dscale[:, 0], grad[:, 0]).unsqueeze(-1)
    if p == 2:
        h11 = hess[:, 0, 0] + lam * dscale[:, 0]
        h22 = hess[:, 1, 1] + lam * dscale[:, 1]
        x1, x2 = solve_2x2(h11, hess[:, 0, 1], h22, grad[:, 0], grad[:, 1])
        return torch.stack([x1, x2], -1)
    raise ValueError(f"damped_step: expected 1 or 2 parameters per element, found {p}")


def predicted_reduction(grad: Tensor, hess: Tensor, step: Tensor) -> Tensor:
    """cost(x) − model(x + δ) = −(2gᵀδ + δᵀHδ), (M,)."""
    hd = (hess * step.unsqueeze(-2)).sum(-1)
    return -(2.0 * (grad * step).sum(-1) + (step * hd).sum(-1))


def accept_step(cost_new: Tensor, cost_old: Tensor) -> Tensor:
    """Per-element acceptance: finite and not larger than the current cost."""
    return torch.isfinite(cost_new) & (cost_new <= cost_old)


def gain_ratio(actual: Tensor, predicted: Tensor) -> Tensor:
    """ρ = actual / predicted reduction (0 where the prediction is not positive)."""
    ok = predicted > 0
    return torch.where(ok, actual / torch.where(ok, predicted, torch.ones_like(predicted)), torch.zeros_like(actual))


def update_damping(lam: Tensor, nu: Tensor, accepted: Tensor, rho: Tensor) -> tuple[Tensor, Tensor]:
    """Nielsen's rule: accepted → λ·max(1/3, 1 − (2ρ − 1)³), ν = 2; rejected → λ·ν, ν·2.

    λ is clamped to [1e-10, 1e10] and ν to [2, 2³⁰], so neither can overflow.
    """
    shrink = torch.clamp_min(1.0 - (2.0 * rho.clamp(0.0, 1.0) - 1.0) ** 3, 1.0 / 3.0)
    lam_new = torch.where(accepted, lam * shrink, lam * nu)
    nu_new = torch.where(accepted, torch.full_like(nu, 2.0), torch.clamp_max(nu * 2.0, NU_MAX))
    return lam_new.clamp(LAMBDA_MIN, LAMBDA_MAX), nu_new


def select_eval(accepted: Tensor, new: LMEval, old: LMEval, merge: Callable[[Any, Any, Tensor], Any] | None) -> LMEval:
    """Element-wise choice between two evaluations (``merge`` combines the aux parts)."""
    a1 = accepted
    a2 = accepted[:, None]
    a3 = accepted[:, None, None]
    floor = None
    if new.floor is not None and old.floor is not None:
        floor = torch.where(a1, new.floor, old.floor)
    aux = merge(new.aux, old.aux, accepted) if merge is not None else new.aux
    return LMEval(torch.where(a1, new.cost, old.cost), torch.where(a2, new.grad, old.grad),
                  torch.where(a3, new.hess, old.hess), aux, floor)


# ------------------------------------------------------------------------------- the driver


def levenberg_marquardt(
    oracle: Callable[[Tensor], LMEval],
    x0: Tensor,
    *,
    lower: Tensor | float | None = None,
    upper: Tensor | float | None = None,
    tol: float = 1e-6,
    xtol: float = 1e-10,
    max_iters: int = 100,
    merge: Callable[[Any, Any, Tensor], Any] | None = None,
    first: LMEval | None = None,
    on_iter: Callable[[int, Tensor, LMEval, Tensor], None] | None = None,
    diag_floor: Tensor | float = D_FLOOR,
) -> LMResult:
    """Minimise M independent small least-squares problems with batched LM.

    Args:
        oracle: x (M, P) → :class:`LMEval` at x (all elements in one call).
        x0: (M, P) start, P ∈ {1, 2}.
        lower, upper: box bounds (broadcast to x); steps are projected onto them.
        tol: an element converges when an accepted step lowers its cost by at most
            tol·cost + floor, or when no step can (predicted reduction ≤ tol·cost + floor).
        xtol: ... or when the undamped Gauss–Newton step is below xtol·(1 + |x|).
        max_iters: cap on oracle calls after the first.
        merge: (aux_new, aux_old, accepted (M,)) → aux, for per-element state kept in aux.
        first: the evaluation at x0 when the caller already has it.
        on_iter: called after each iteration with (iteration, x, eval, converged).
        diag_floor: floor of the Marquardt diagonal (M, P) or scalar.

    Returns:
        :class:`LMResult`; ``costs`` lists the (accepted) cost after each iteration.
    """
    x = x0.clone()
    lo = None if lower is None else torch.as_tensor(lower, dtype=x.dtype, device=x.device).expand_as(x)
    hi = None if upper is None else torch.as_tensor(upper, dtype=x.dtype, device=x.device).expand_as(x)
    ev = first if first is not None else oracle(x)
    m = x.shape[0]
    lam = torch.full((m,), LAMBDA_INIT, dtype=x.dtype, device=x.device)
    nu = torch.full((m,), 2.0, dtype=x.dtype, device=x.device)
    dmax = torch.zeros_like(x)
    done = ~torch.isfinite(ev.cost)
    costs = [ev.cost.clone()]
    status = "max_iters"
    it = 0
    for it in range(1, max_iters + 1):
        x_new, dmax, pred, thresh, small = _trial_step(ev, x, lam, dmax, lo, hi, tol=tol, xtol=xtol, diag_floor=diag_floor)
        done = done | small
        if bool(done.all()):
            it -= 1
            status = "converged"
            break
        x_try = torch.where(done[:, None], x, x_new)
        x, ev, lam, nu, done = _take_step(oracle(x_try), ev, x, x_try, pred, thresh, lam, nu, done, merge)
        costs.append(ev.cost.clone())
        if on_iter is not None:
            on_iter(it, x, ev, done)
        if bool(done.all()):
            status = "converged"
            break
    return LMResult(x=x, eval=ev, iterations=it, converged=done, status=status, costs=costs)


def _trial_step(ev: LMEval, x: Tensor, lam: Tensor, dmax: Tensor, lo: Tensor | None, hi: Tensor | None, *, tol: float,
                xtol: float, diag_floor: Tensor | float) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The damped step from x, projected onto the bounds. Returns (x_new, the Marquardt diagonal (the next
    ``dmax``), predicted reduction, threshold tol·cost + floor, converged: no step can lower the cost)."""
    floor = ev.floor if ev.floor is not None else torch.zeros_like(ev.cost)
    diag = torch.diagonal(ev.hess, dim1=-2, dim2=-1)
    dscale = marquardt_diag(diag, dmax, diag_floor)
    step = damped_step(ev.grad, ev.hess, lam, dscale)
    x_new = x + step
    if lo is not None:
        x_new = torch.maximum(x_new, lo)
    if hi is not None:
        x_new = torch.minimum(x_new, hi)
    step = x_new - x
    pred = predicted_reduction(ev.grad, ev.hess, step)
    thresh = tol * ev.cost.abs() + floor
    newton = damped_step(ev.grad, ev.hess, torch.zeros_like(lam), dscale)  # undamped GN step
    small = (pred <= thresh) | (newton.abs() <= xtol * (1.0 + x.abs())).all(-1) | ~torch.isfinite(pred)
    return x_new, dscale, pred, thresh, small


def _take_step(new: LMEval, ev: LMEval, x: Tensor, x_try: Tensor, pred: Tensor, thresh: Tensor, lam: Tensor,
               nu: Tensor, done: Tensor, merge: Callable[[Any, Any, Tensor], Any] | None,
               ) -> tuple[Tensor, LMEval, Tensor, Tensor, Tensor]:
    """Accept the trial ``new`` (at x_try) where it lowers the cost, update the damping. Returns (x, eval,
    λ, ν, done)."""
    accepted = accept_step(new.cost, ev.cost) & ~done
    actual = ev.cost - new.cost
    rho = gain_ratio(actual, pred)
    x = torch.where(accepted[:, None], x_try, x)
    ev = select_eval(accepted, new, ev, merge)
    lam, nu = update_damping(lam, nu, accepted, rho)
    stalled = ~accepted & (lam >= LAMBDA_MAX)
    done = done | (accepted & (actual <= thresh)) | stalled
    return x, ev, lam, nu, done
