"""The specular colour: per channel (the paper's s, one per channel) or white (one s for the three
channels: a dielectric coat reflects every colour alike), chosen on a held-out shot.

Given α, the projected cost of each channel is A − 2sB + s²C (:mod:`torchmetal.fit.refine`), so one s
for the three channels is optimal at ΣB / ΣC. :func:`fit_white` alternates that closed form with the LM
on β at s fixed (:func:`~torchmetal.fit.refine.fit_specular`'s ``s_fixed``): each step lowers the cost.
:func:`choose_colour` fits both on every shot but the selection's held-out one and keeps per-channel s
unless white predicts that shot better beyond noise (:func:`~torchmetal.select.rule.paired_choice`).
Measured on the shared real captures (one global lobe, three held-out shots): the embossed gold paper's
per-channel fit made its specular bluish (s 0.10 / 0.14 / 0.20, its gold in the diffuse), and white
predicts its left-out shots better (MSE 0.01658 vs 0.01666, z 6.9; s tinted like the diffuse: 0.01987);
the card keeps per-channel s (white 0.01759 vs 0.01718, z −13.7).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.fit.clusters import fit_without_hold, heldout_errors, mean_square
from torchmetal.fit.problem import Observations, Weighting
from torchmetal.fit.refine import SpecFit, evaluate_specular, fit_specular, spec_sums, texture_map
from torchmetal.select.rule import MIN_GAIN_ABS, Decision, paired_choice

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

WHITE_ROUNDS = 3  # closed-form s ↔ LM on β alternations


def white_s(stats: Tensor) -> Tensor:
    """(K, 3) float64: one s ≥ 0 per element row, ΣB / ΣC over the channels, from the stats (6, K, 3)."""
    B, C = stats[0], stats[1]
    s = B.sum(1, keepdim=True) / C.sum(1, keepdim=True).clamp_min(1e-300)
    return s.clamp_min(0.0).expand_as(B).contiguous()


def fit_white(obs: Observations, fit: SpecFit, *, tol: float, max_iters: int, on_iter=None) -> SpecFit:
    """The fit with one s for the three channels of each element, from ``fit``'s α (module docstring)."""
    alpha = fit.alpha.to(torch.float64)
    iterations, status = 0, fit.status
    for _ in range(WHITE_ROUNDS):
        s = white_s(spec_sums(obs, alpha)[0])
        step = fit_specular(obs, torch.log(alpha), tol=tol, max_iters=max_iters, s_fixed=s, on_iter=on_iter)
        alpha, iterations, status = step.alpha, iterations + step.iterations, step.status
    out = evaluate_specular(obs, white_s(spec_sums(obs, alpha)[0]), alpha)
    return replace(out, iterations=iterations, status=status)


def choose_colour(capture: Capture, glob: SpecFit, *, stride: int, hold: int, tol: float, max_iters: int,
                  dtype: torch.dtype, chunk: int, weighting: Weighting | None) -> Decision:
    """"free" (per-channel s) or "white", fitted on every shot but ``hold`` from the global fit ``glob``
    and scored on ``hold`` (module docstring)."""
    obs, ho, free = fit_without_hold(capture, glob, stride=stride, hold=hold, tol=tol, max_iters=max_iters, dtype=dtype,
                                     chunk=chunk, weighting=weighting)
    white = fit_white(obs, free, tol=tol, max_iters=max_iters)
    errors = {k: heldout_errors(ho, texture_map(obs, f.s, f.eb), f.s, f.alpha) for k, f in (("free", free), ("white", white))}
    d = paired_choice("specular colour", errors, "free", floor=MIN_GAIN_ABS * mean_square(ho))
    d.holds, d.pixels = [hold], ho.num_pixels
    return d
