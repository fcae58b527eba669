"""``lobe="auto"``: pick the specular lobe (phong, blinn, ggx) on shots left out of the fit.

On the selection subsample (the same strided pixel grid as the cluster choice), the capture's shot plan
(:mod:`torchmetal.select.plan`; without one, a global Phong fit on all shots) ranks the shots by
predicted specular energy; the ``holds`` most telling ones
(every shot, up to 12) are left out, in up to ``FOLDS`` groups dealt round-robin down that ranking (one shot
per group for up to 6 of them). For each candidate lobe: a coarse α grid on all shots, then per group the
variable-projection LM (:func:`~torchmetal.fit.refine.fit_specular`) on the other shots from that start,
and the squared errors of rendering the group's valid observations. (A grid per fold and one shot per fold
cost 14 s on the zoo's 66-shot sphere, 2 s this way; the LM ends at the fold's own optimum either way.)

Phong — docs/design.md §2.2's model — is kept unless another lobe's errors are lower beyond noise
(:func:`~torchmetal.select.rule.paired_choice`: paired z over the same observations). So a Phong-like
sample keeps the paper's lobe.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor

from torchmetal.fit.clusters import evidence, heldout_errors
from torchmetal.fit.problem import Observations, build_observations
from torchmetal.fit.refine import SpecFit, fit_specular, grid_beta, texture_map
from torchmetal.fit.shot_plan import shot_plan
from torchmetal.lobes import LOBES
from torchmetal.select.plan import ShotPlan
from torchmetal.select.rule import MIN_GAIN, heldout_psnr, paired_choice

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

__all__ = ["LobeSelection", "choose_lobe", "LOBE_GRID", "HOLDS", "FOLDS"]

LOBE_GRID = tuple(float(2**i) for i in range(14))  # α = 1 … 8192, ×2 steps: every lobe starts near its optimum
HOLDS = 12  # shots left out (the ones with most predicted specular energy): every shot of most captures
FOLDS = 6  # … in at most this many groups (one fit per group and lobe)


@dataclass
class LobeSelection:
    """Outcome of the held-out comparison: the chosen lobe and the evidence."""

    lobe: str
    holds: list[int] = field(default_factory=list)
    mse: dict = field(default_factory=dict)  # lobe → mean held-out MSE over ``holds``
    z: dict = field(default_factory=dict)  # lobe → paired z of its gain over phong (> 0: lower errors)
    alpha: dict = field(default_factory=dict)  # lobe → fitted α (3,) on the first fold (mean over clusters)
    clusters: int = 1  # specular elements each lobe was fitted with (the kept clusters)
    reason: str = ""
    decision: dict | None = None  # the Decision record (as a dict), when the lobes were compared

    def to_dict(self) -> dict:
        return {"lobe": self.lobe, "holds": list(self.holds), "mse": dict(self.mse), "psnr_heldout": heldout_psnr(self.mse),
                "z": dict(self.z), "alpha": dict(self.alpha), "clusters": self.clusters,
                "reason": self.reason}


def fit_lobe(obs: Observations, *, tol: float, max_iters: int, grid: tuple[float, ...] = LOBE_GRID, k: int = 1) -> SpecFit:
    """Specular fit of ``obs``'s lobe (K elements: ``obs.labels`` when K > 1): best α of ``grid``, then the LM."""
    return fit_specular(obs, grid_beta(obs, k, grid=grid), tol=tol, max_iters=max_iters)


def choose_lobe(
    capture: Capture, *, stride: int, tol: float, max_iters: int, dtype: torch.dtype, chunk: int,
    candidates: tuple[str, ...] = LOBES, holds: int = HOLDS, folds: int = FOLDS, min_gain: float = MIN_GAIN,
    z_min: float | None = None, labeler: Callable[[Tensor, Tensor], Tensor] | None = None, plan: ShotPlan | None = None,
) -> LobeSelection:
    """Fit each candidate lobe on all shots but a group (in turn, ``holds`` shots in ``folds`` groups) on a
    pixel grid of ``stride``; keep the lowest held-out MSE, Phong unless beaten beyond noise (module docstring).
    With ``labeler`` (:class:`~torchmetal.fit.cluster_features.Labeler`, the kept specular clusters) every lobe is
    fitted per cluster: the lobes compete on the specular structure the fit will use (one global lobe
    averaged over two Phong materials looks like GGX's tail). With ``plan`` (:mod:`torchmetal.select.plan`, the
    capture's), its first ``holds`` shots are left out; without, the ranking of the base lobe's own fit."""
    n = int(capture.images.shape[0])
    if n < 3:
        return LobeSelection("phong", reason=f"a held-out test needs >= 3 shots, found {n}: phong (docs/design.md §2.2)")
    k = 1 if labeler is None else labeler.k
    every = build_observations(capture, stride=stride, dtype=dtype, chunk=chunk, labeler=labeler)
    base = fit_lobe(every, tol=tol, max_iters=max_iters, k=k)
    if not bool(evidence(base).any()):
        return LobeSelection("phong", reason="no highlight evidence: the lobe shape is not observable; phong (docs/design.md §2.2)")
    if plan is None:
        plan = shot_plan(every, base)
    del every
    held, groups = plan.holds(holds), plan.groups(holds, folds)
    sel = LobeSelection("phong", holds=held, clusters=k)
    errors: dict[str, Tensor] = {}
    for lobe in candidates:
        if lobe == "phong":
            start = torch.log(base.alpha)
        else:
            start = grid_beta(build_observations(capture, stride=stride, dtype=dtype, chunk=chunk, lobe=lobe,
                                                 labeler=labeler), k, grid=LOBE_GRID)
        parts = []
        for i, group in enumerate(groups):
            obs = build_observations(capture, stride=stride, shots=[j for j in range(n) if j not in group], dtype=dtype,
                                     chunk=chunk, lobe=lobe, labeler=labeler)
            fit = fit_specular(obs, start, tol=tol, max_iters=max_iters)
            ho = build_observations(capture, stride=stride, shots=group, dtype=dtype, chunk=chunk, lobe=lobe)
            parts.append(heldout_errors(ho, texture_map(obs, fit.s, fit.eb), fit.s, fit.alpha, obs.labels))
            if i == 0:
                sel.alpha[lobe] = [float(a) for a in fit.alpha.mean(0)]
        errors[lobe] = torch.cat(parts)
    d = paired_choice("lobe", errors, "phong" if "phong" in errors else next(iter(errors)), z_min=z_min,
                      min_gain=min_gain)
    sel.lobe, sel.mse, sel.z = d.chosen, d.mse, d.z
    sel.reason = f"shots {held}: {d.reason}"
    d.holds, d.pixels = held, int(ho.num_pixels)
    sel.decision = d.to_dict()
    return sel
