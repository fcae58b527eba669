"""The coating's shot plan: the shots ranked by the specular energy the first subsample fit predicts in them
(:class:`~torchmetal.select.plan.ShotPlan`, whose module says which choice holds which shots)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from torchmetal.fit.lobes import lobe_factor
from torchmetal.fit.refine import chunk_terms
from torchmetal.select.plan import ShotPlan

if TYPE_CHECKING:
    from torch import Tensor

    from torchmetal.fit.problem import Observations
    from torchmetal.fit.refine import SpecFit


def shot_plan(obs: Observations, fit: SpecFit) -> ShotPlan:
    """The plan of a capture whose subsample observations ``obs`` the specular ``fit`` was fitted to."""
    energy = specular_energy(obs, fit)
    order = sorted(range(int(energy.numel())), key=lambda k: (-float(energy[k]), k))
    return ShotPlan(tuple(order))


def specular_energy(obs: Observations, fit: SpecFit) -> Tensor:
    """(N,) float64 Σ w·(s·b)² per shot: how much of each shot the specular term predicts."""
    energy = torch.zeros(obs.num_shots, dtype=torch.float64, device=obs.device)
    for j, _, (_, _, u, L, w, inten), s3, a3 in chunk_terms(obs, fit.s, fit.alpha, obs.labels):
        b = s3 * inten * u * lobe_factor(L, a3, obs.geo_chunk(j), obs.lobe)
        energy += (w * b * b).sum((1, 2)).double()
    return energy


