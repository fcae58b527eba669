"""Uniform density or a density map (:mod:`torchmetal.flakes.estimate.density_map`)? Decided on left-out shots.

Like the other flake choices (:mod:`torchmetal.flakes.choice`): for each of the ``HELD`` shots with the
most associated detections, the map is estimated from the *other* shots' detections only, and the
left-out photo is compared with the material rendered with the uniform model and with the map, on

- MD (:func:`torchmetal.metrics.md`, the paper's sparkle metric, 16-px blocks), and
- the per-block sparkle density: the sparkles (local maxima of the channel-mean high-pass above
  5× the larger robust noise σ of render and photo, as MD counts them) in each map block of the
  render and of the photo, scored as the mean |log((pred + 1)/(obs + 1))| over the blocks.

The candidates are the uniform model and a map per detectability model ("map:glint", "map:area":
:func:`~torchmetal.flakes.estimate.density_map.detectability`). A map wins when its mean MD and its mean
block error are both no higher than the uniform model's and one is lower (a default must never be
worse than the simpler option, and a tie keeps the simpler one: zoo flakes_b, whose observed flakes
leave the map nothing to change, scores identically), the lowest MD among those; it is then estimated from every shot. The coating, the flake statistics and the observed flakes (when kept, measured without the
left-out shot) are shared by both candidates.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.flakes.choice import (
    HELD,
    MD_WINDOW,
    held_shots,
    mean_score,
    observed_without,
    render_held,
    shot_valid,
)
from torchmetal.flakes.estimate.density_map import DETECT_MODES, estimate_map, with_map
from torchmetal.flakes.model.field import map_blocks
from torchmetal.flakes.model.filters import box_mean, max_filter
from torchmetal.metrics import md
from torchmetal.select.rule import Decision

if TYPE_CHECKING:
    from torchmetal.flakes.estimate.results import FlakeStageResult, Particles
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.io.capture import Capture
    from torchmetal.material import Material

SPARKLE_K = 5.0  # sparkle threshold in robust σ of the high-pass (MD's)


def sparkle_counts(pred: Tensor, photo: Tensor, grid: tuple[int, int], valid: Tensor | None = None,
                   *, k: float = SPARKLE_K) -> tuple[Tensor, Tensor]:
    """Sparkles per map block of a render and a photo, (gh, gw) float64 each.

    Args:
        pred, photo: (3, H, W) linear images; grid: (gh, gw) map blocks;
        valid: optional (H, W) bool: pixels where sparkles count (unsaturated, in the mask).
    """
    x = torch.stack([pred, photo]).float().mean(1, keepdim=True)  # (2, 1, H, W)
    hp = x - box_mean(x, 2)
    sig = 1.4826 * hp[..., ::2, ::2].flatten(1).abs().median(1).values
    thr = k * float(sig.max().clamp_min(1e-6))
    peaks = (hp >= max_filter(hp, 1)) & (hp > thr)
    if valid is not None:
        peaks &= valid.view(1, 1, *valid.shape)
    h, w = x.shape[-2:]
    bi, bj = map_blocks(grid[0], grid[1], torch.arange(h).view(-1, 1), torch.arange(w).view(1, -1), h, w)
    block = (bi * grid[1] + bj).reshape(-1).to(x.device)
    out = [torch.bincount(block[peaks[i, 0].reshape(-1)], minlength=grid[0] * grid[1]).double().view(grid).cpu()
           for i in range(2)]
    return out[0], out[1]


def block_error(pred: Tensor, obs: Tensor) -> float:
    """Mean |log((pred + 1)/(obs + 1))| over the blocks."""
    return float(torch.log((pred + 1.0) / (obs + 1.0)).abs().mean())


def score_shot(material: Material, capture: Capture, k: int, grid: tuple[int, int], pred: Tensor | None = None) -> dict:
    """MD, block sparkle error and the per-block sparkle counts of shot ``k``'s render (``pred`` (3, H, W)
    when the caller has it) against its photo."""
    pred = render_held(material, capture, [k])[0] if pred is None else pred
    photo = capture.images[k].float()
    p, o = sparkle_counts(pred, photo, grid, shot_valid(capture, k))
    return {"md": float(md(pred, photo, window=MD_WINDOW)), "block_error": block_error(p, o),
            "predicted": p.tolist(), "observed": o.tolist()}


def choose_density_map(capture: Capture, material: Material, flake_result: FlakeStageResult | None, *,
                       held: int = HELD, shots: list[int] | None = None,
                       renders: dict | None = None) -> tuple[FlakeModel | None, dict]:
    """``material.flakes`` with a density map when left-out shots prefer it, else unchanged.

    The candidates are the uniform model and a map per detectability mode
    (:data:`~torchmetal.flakes.estimate.density_map.DETECT_MODES`: "map:glint", "map:area").

    Args:
        capture: the fitted capture; material: the material with its kept flake model (and observed
            flakes, or None); flake_result: the flake stage's result (particles, flake_id).
        held: how many shots to leave out; shots: which (the capture's shot plan,
            :mod:`torchmetal.select.plan`; None: the ``held`` with most associated detections).
        renders: ``material``'s renders of left-out shots the caller already has (shot → (3, H, W), e.g.
            :func:`~torchmetal.flakes.choice.choose_observed`'s), for the uniform candidate.

    Returns:
        (FlakeModel or None, report {"candidates", "held", "per_shot" {candidate: [score_shot dicts]},
        "scores" {candidate: {"md", "block_error"}}, "winner", "kept", "reason", "folds",
        "map_estimate"}): which won and why, and the kept map's estimate (grid, counts,
        expectations, colour test).
    """
    model = material.flakes
    cands = ["uniform"] + [f"map:{m}" for m in DETECT_MODES]
    rep = {"candidates": cands, "held": [], "per_shot": {c: [] for c in cands}, "winner": "uniform", "kept": False}
    fid = None if flake_result is None else flake_result.flake_id
    reason = _not_applicable(capture, model, fid)
    if reason is not None:
        rep["reason"] = reason
        return model, rep
    parts = flake_result.particles
    _score_folds(rep, capture, material, parts, fid,
                 held_shots(parts, fid, capture.num_shots, held) if shots is None else shots, renders or {})
    if not rep["held"]:
        rep["reason"] = "no left-out shot gave a non-uniform map (too few flakes, one block, or Poisson-like counts)"
        return model, rep
    rep["scores"] = {c: {"md": mean_score(rep["per_shot"][c], "md"), "block_error": mean_score(rep["per_shot"][c], "block_error")}
                     for c in cands}
    winner, reason = _best_candidate(rep, cands)
    final = estimate_map(capture, model, parts, fid, mode=winner.split(":")[1]) if winner != "uniform" else None
    if winner != "uniform" and (final is None or final.uniform):
        winner, reason = "uniform", reason + "; the map from every shot is uniform"
    rep.update({"kept": winner != "uniform", "winner": winner, "reason": reason})
    rep["decision"] = Decision("density map", tuple(cands), winner, reference="uniform", holds=list(rep["held"]),
                               pixels=int(capture.mask.sum()), reason=reason,
                               scores={c: dict(v) for c, v in rep["scores"].items()}).to_dict()
    if winner == "uniform":
        return model, rep
    rep["map_estimate"] = final.report
    return with_map(model, final), rep


def _not_applicable(capture: Capture, model: FlakeModel | None, fid: Tensor | None) -> str | None:
    """Why no density map can be chosen on this capture (None when one can)."""
    if model is None:
        return "no flake model"
    if min(capture.images.shape[-2:]) < MD_WINDOW:
        return f"images under {MD_WINDOW} px a side: too small for MD's blocks"
    if fid is None or not bool((fid >= 0).any()):
        return "no associated detections"
    if capture.num_shots < 3:
        return f"{capture.num_shots} shots: none to leave out of the map's estimate"
    return None


def _score_folds(rep: dict, capture: Capture, material: Material, parts: Particles, fid: Tensor,
                 shots: list[int], renders: dict) -> None:
    """Score every candidate on each left-out shot of ``shots`` (its maps estimated from the other shots) into ``rep``."""
    model = material.flakes
    rep["folds"] = []
    folds = []
    for k in shots:
        others = [i for i in range(capture.num_shots) if i != k]
        maps = {f"map:{m}": estimate_map(capture, model, parts, fid, others, mode=m) for m in DETECT_MODES}
        if any(dm is None or dm.uniform for dm in maps.values()):
            rep["folds"].append({"shot": k, "skipped": "too few flakes, one block, or Poisson-like block counts"})
            continue
        folds.append((k, maps))
        rep["held"].append(k)
        rep["folds"].append({"shot": k, **{name: dm.report["density_map"] for name, dm in maps.items()}})
    # the uniform model needs no fold's estimate: without observed flakes, one render of every left-out shot
    # (those the caller has are not rendered again)
    uniform = {}
    if folds and material.observed_flakes is None:
        todo = [k for k in rep["held"] if k not in renders]
        uniform = {**{k: renders[k] for k in rep["held"] if k in renders},
                   **(dict(zip(todo, render_held(material, capture, todo))) if todo else {})}
    for k, maps in folds:
        base = material
        if material.observed_flakes is not None:
            base = replace(material, observed_flakes=observed_without(capture, parts, fid, model, k))
        grid = maps["map:glint"].grid
        rep["per_shot"]["uniform"].append(score_shot(base, capture, k, grid, uniform.get(k)))
        for name, dm in maps.items():
            rep["per_shot"][name].append(score_shot(replace(base, flakes=with_map(model, dm)), capture, k, grid))


def _best_candidate(rep: dict, cands: list[str]) -> tuple[str, str]:
    """The winning candidate on the left-out scores and why."""
    uni = rep["scores"]["uniform"]
    def beats(v: dict) -> bool:  # no worse on both scores, better on one (a tie keeps the simpler model)
        return (v["md"] <= uni["md"] and v["block_error"] <= uni["block_error"]
                and (v["md"] < uni["md"] or v["block_error"] < uni["block_error"]))

    ok = [c for c in cands[1:] if beats(rep["scores"][c])]
    winner = min(ok, key=lambda c: (rep["scores"][c]["md"], rep["scores"][c]["block_error"])) if ok else "uniform"
    summary = "; ".join(f"{c} MD {v['md']:.2f}, block sparkle error {v['block_error']:.3f}" for c, v in rep["scores"].items())
    reason = (f"left-out shots {rep['held']}: {summary} (a map wins when neither score is above the uniform "
              "model's and one is below; the lowest MD among those)")
    return winner, reason


def region_report(scores: dict) -> dict:
    """Summed predicted and observed sparkles over the left-out shots per block, from a choice report's
    per-shot entries (a list of :func:`score_shot` dicts)."""
    if not scores:
        return {}
    p = sum(torch.tensor(s["predicted"]) for s in scores)
    o = sum(torch.tensor(s["observed"]) for s in scores)
    return {"predicted": p.tolist(), "observed": o.tolist(), "block_error": block_error(p, o),
            "total": [float(p.sum()), float(o.sum())], "log_ratio": math.log((float(p.sum()) + 1) / (float(o.sum()) + 1))}
