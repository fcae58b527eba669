"""Which shots the held-out choices leave out of their fits: one plan per capture.

Every choice made on left-out shots (docs/design.md §4) scores candidates on shots their fits did not
see. Which shots those are is decided once, not by each choice:

- the coating's choices (weights, highlight evidence, clusters, relabelling, gloss maps, specular colour,
  lobe) rank the shots by the specular energy the first subsample fit predicts in them
  (:func:`torchmetal.fit.shot_plan.shot_plan`): a shot without highlight cannot tell two lobes, or two
  specular structures, apart. The single-shot choices hold the first of that ranking; the gloss maps leave
  out each of its first three in turn; the lobe deals the first ``HOLDS`` of it round-robin into groups. A
  refit of the same capture (the flake stage's) is given the first fit's plan, so it holds the same shots;
- the choices made before the fit (:mod:`torchmetal.select.harness`: registration, clipping, normals, relief, light) deal
  every shot into groups (:func:`shot_groups`; the normals leave each shot out alone);
- the flake choices (observed flakes, keep flakes, density map) hold the shots with the most detections
  associated with a flake (:func:`flake_holds`): a shot without glints cannot tell flake models apart.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch


@dataclass(frozen=True)
class ShotPlan:
    """The shots held out by the coating's choices (``order``) and by the flake choices (``flakes``)."""

    order: tuple[int, ...]  # every shot, most predicted specular energy first (ties: the lower index)
    flakes: tuple[int, ...] = ()  # the flake choices' held-out shots (most associated detections first)

    @property
    def hold(self) -> int:
        """The single shot the one-shot choices leave out."""
        return self.order[0]

    def holds(self, count: int) -> list[int]:
        """The first ``count`` shots of ``order`` (at least one)."""
        return list(self.order[: max(1, min(count, len(self.order)))])

    def groups(self, count: int, folds: int) -> list[list[int]]:
        """:meth:`holds` dealt round-robin into ≤ ``folds`` groups (one fit each)."""
        held = self.holds(count)
        return [held[g::folds] for g in range(min(folds, len(held)))]

    def with_flakes(self, shots: list[int]) -> ShotPlan:
        return replace(self, flakes=tuple(int(k) for k in shots))

    def to_dict(self) -> dict:
        return {"order": list(self.order), "flakes": list(self.flakes)}


def shot_groups(n: int, folds: int) -> list[list[int]]:
    """The shots 0..n−1 dealt into ≤ ``folds`` groups to leave out in turn (shot k in group k mod folds),
    each cut where it would leave fewer than 3 shots to fit."""
    return [list(range(g, n, min(folds, n)))[: n - 3] for g in range(min(folds, n))]


def flake_holds(shot: torch.Tensor, flake_id: torch.Tensor, num_shots: int, count: int) -> list[int]:
    """Up to ``count`` shots with the most detections associated with a flake (``flake_id`` ≥ 0; ``shot`` (P,)
    the detections' shots; ties: the lower index); never a shot without one."""
    per = torch.bincount(shot[flake_id >= 0], minlength=num_shots)
    order = sorted(range(num_shots), key=lambda k: (-int(per[k]), k))
    return [k for k in order[:count] if int(per[k]) > 0]
