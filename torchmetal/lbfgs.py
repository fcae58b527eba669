"""L-BFGS with a strong-Wolfe line search for small problems, without ``torch.optim``.

``torch.optim.Optimizer.__init__`` imports ``torch._dynamo`` on its first call: 1.9 s of a fresh
process on this 2-core machine, more than the whole flake statistics fit it served
(:mod:`torchmetal.flakes.estimate.stats`, 4 parameters). :func:`minimize` is the iteration of
``torch.optim.LBFGS.step`` (``lr=1``, ``line_search_fn="strong_wolfe"``) on a flat parameter
vector, with torch's own line search (``torch.optim.lbfgs._strong_wolfe``, a plain function): the
same iterates, tested against ``torch.optim.LBFGS``.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor
from torch.optim.lbfgs import _strong_wolfe


def minimize(value_grad: Callable[[Tensor], tuple[float, Tensor]], x0: Tensor, *, max_iter: int = 20,
             max_eval: int | None = None, tolerance_grad: float = 1e-7, tolerance_change: float = 1e-9,
             history_size: int = 100) -> tuple[Tensor, int]:
    """Minimise f from ``x0`` (P,); ``value_grad(x)`` → (f(x), ∇f(x) (P,)). Returns (x, iterations).

    Stops as ``torch.optim.LBFGS.step`` does: after ``max_iter`` iterations or ``max_eval``
    evaluations (default 1.25·max_iter), when max|∇f| ≤ ``tolerance_grad``, or when the step or the
    change of f falls below ``tolerance_change``. A step to a non-finite f or ∇f (an exponent overflowing far
    from the data) ends the iteration at the last finite iterate.
    """
    max_eval = max_iter * 5 // 4 if max_eval is None else max_eval
    x = x0.detach().clone()
    loss, grad = value_grad(x)
    evals = 1
    if float(grad.abs().max()) <= tolerance_grad:
        return x, 0
    dirs: list[Tensor] = []
    steps: list[Tensor] = []
    ro: list[Tensor] = []
    h_diag: Tensor | float = 1.0
    d = grad.neg()
    t: Tensor | float = 0.0
    prev_grad = grad.clone()
    n_iter = 0
    while n_iter < max_iter:
        n_iter += 1
        if n_iter > 1:  # the L-BFGS two-loop recursion on the stored pairs
            y = grad - prev_grad
            s = d * t
            ys = y.dot(s)
            if ys > 1e-10:
                if len(dirs) == history_size:  # limited memory: drop the oldest pair
                    del dirs[0], steps[0], ro[0]
                dirs.append(y)
                steps.append(s)
                ro.append(1.0 / ys)
                h_diag = ys / y.dot(y)
            q = grad.neg()
            al = [None] * len(dirs)
            for i in range(len(dirs) - 1, -1, -1):
                al[i] = steps[i].dot(q) * ro[i]
                q.add_(dirs[i], alpha=-al[i])
            d = r = torch.mul(q, h_diag)
            for i in range(len(dirs)):
                be_i = dirs[i].dot(r) * ro[i]
                r.add_(steps[i], alpha=al[i] - be_i)
        prev_grad.copy_(grad)
        prev_loss = loss
        t = min(1.0, 1.0 / float(grad.abs().sum())) if n_iter == 1 else 1.0
        gtd = grad.dot(d)
        if gtd > -tolerance_change:
            break
        try:
            found = _strong_wolfe(lambda xx, tt, dd: value_grad(xx + tt * dd), x, t, d, loss, grad, gtd,
                                  max_ls=max_eval - evals)
        except IndexError:  # torch's line search on NaN values finds no bracket (its list runs empty)
            break
        if not (math.isfinite(float(found[0])) and bool(torch.isfinite(found[1]).all())
                and bool(torch.isfinite(found[2] * d).all())):
            break  # the line search left the finite region: keep x
        loss, grad, t, ls_evals = found
        x = x + t * d
        evals += ls_evals
        if n_iter == max_iter or evals >= max_eval or float(grad.abs().max()) <= tolerance_grad:
            break
        if float((d * t).abs().max()) <= tolerance_change or abs(loss - prev_loss) < tolerance_change:
            break
    return x, n_iter
