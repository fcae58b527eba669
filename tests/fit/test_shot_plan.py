"""The shot plan (torchmetal.fit.shot_plan): which shots every held-out choice leaves out, made once per capture."""

import torch

from torchmetal.fit import fit_phong
from torchmetal.select.plan import ShotPlan, flake_holds, shot_groups
from torchmetal.synth import synth_capture


def test_plan_holds_and_groups_follow_its_order():
    plan = ShotPlan((4, 1, 0, 3, 2))
    assert plan.hold == 4 and plan.holds(3) == [4, 1, 0] and plan.holds(0) == [4] and plan.holds(99) == [4, 1, 0, 3, 2]
    assert plan.groups(5, 2) == [[4, 0, 2], [1, 3]] and plan.groups(2, 6) == [[4], [1]]
    assert plan.with_flakes([3, 0]).to_dict() == {"order": [4, 1, 0, 3, 2], "flakes": [3, 0]}


def test_shot_groups_leave_three_shots_to_fit():
    assert shot_groups(7, 3) == [[0, 3, 6], [1, 4], [2, 5]]
    assert all(5 - len(g) >= 3 for g in shot_groups(5, 3))


def test_flake_holds_are_the_shots_with_most_associated_detections():
    shot = torch.tensor([0, 2, 2, 1, 2, 1, 3])
    fid = torch.tensor([0, 1, 2, -1, 3, 4, -1])  # shot 3's one detection has no flake
    assert flake_holds(shot, fid, 4, 2) == [2, 0] and flake_holds(shot, fid, 4, 9) == [2, 0, 1]


def test_a_fit_plans_by_specular_energy_and_a_given_plan_decides_the_held_out_shot():
    cap = synth_capture(size=48, shots=6, seed=2, noise=0.003).capture
    fit = fit_phong(cap, weights="auto")
    plan = fit.shot_plan
    assert sorted(plan.order) == list(range(6)) and fit.report()["shot_plan"]["order"] == list(plan.order)
    holds = {d["name"]: d["holds"] for d in fit.decisions}
    assert holds["weights"] == [plan.hold] and holds["specular evidence"] == [plan.hold]
    # another plan: every one-shot choice holds its first shot, and the refit reports it
    other = ShotPlan(tuple(reversed(plan.order)))
    refit = fit_phong(cap, weights="auto", plan=other)
    assert refit.shot_plan is other
    assert all(d["holds"] == [other.hold] for d in refit.decisions if d["name"] in ("weights", "specular evidence"))
