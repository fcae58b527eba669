"""Observed or statistical flakes, decided on left-out shots (torchmetal.flakes.choice).

End to end: tests/flakes/test_observed.py (zoo flakes_b: the left-out shots keep them) and
tests/test_pipeline.py (the dense hemisphere case: MD of a left-out photo with the default).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import pytest
import torch

import torchmetal.flakes.choice as choice
from torchmetal.flakes.choice import choose_observed, held_shots, keep_flakes, observed_without
from torchmetal.flakes.estimate.results import Particles
from torchmetal.flakes.model import FlakeModel


def _particles(shots: list[int], cy: list[float], cx: list[float]) -> Particles:
    n = len(shots)
    one = torch.ones(n)
    return Particles(shot=torch.tensor(shots), area=2 * one, cy=torch.tensor(cy), cx=torch.tensor(cx), major=4 * one,
                     minor=4 * one, angle=0 * one, rgb=torch.full((n, 3), 0.5), lab=torch.zeros(n, 3),
                     peak=torch.full((n, 3), 0.5), amp=0.5 * one, snr=20 * one, flux=one, sigma=0.02 * one)


def _capture(n: int = 4, h: int = 24, w: int = 24):
    normals = torch.zeros(3, h, w)
    normals[2] = 1.0
    lights = torch.tensor([[0.1 * k, 0.0, 1.0, 1.0] for k in range(n)])
    return SimpleNamespace(images=torch.zeros(n, 3, h, w), normals=normals, size=(1.0, 1.0), lights=lights,
                           intensities=torch.ones(n, 3), cameras=torch.tensor([[0.0, 0.0, 2.0, 1.0]] * n), num_shots=n,
                           mask=torch.ones(1, h, w, dtype=torch.bool), saturated=torch.zeros(n, 3, h, w, dtype=torch.bool))


def test_held_shots_are_those_with_most_associated_detections():
    p = _particles([0, 2, 2, 3, 3, 3, 1], [5.0] * 7, [5.0] * 7)
    fid = torch.tensor([0, 1, 2, 0, 1, 2, -1])  # shot 1's only detection is not associated
    assert held_shots(p, fid, 4, 2) == [3, 2]
    assert held_shots(p, fid, 4, 9) == [3, 2, 0]  # never a shot without associated detections


def test_observed_without_leaves_the_shot_out_of_detections_and_probes():
    cap = _capture()
    p = _particles([0, 1, 2, 3], [5.0, 5.0, 15.0, 15.0], [5.0, 5.0, 15.0, 15.0])
    fid = torch.tensor([0, 0, 1, 1])
    obs = observed_without(cap, p, fid, FlakeModel(density=0.01, glint_sigma=0.05), 2)
    assert obs is not None and len(obs) == 2  # flake 1 is still seen, in shot 3 (renumbered 2)
    assert torch.equal(obs.probe_lights, cap.lights[[0, 1, 3]])
    alone = observed_without(cap, p, torch.tensor([0, 0, 1, -1]), FlakeModel(density=0.01, glint_sigma=0.05), 2)
    assert len(alone) == 1  # flake 1 was seen in shot 2 only


def test_no_associated_detections_keep_the_field():
    cap = _capture()
    res = SimpleNamespace(particles=_particles([0], [5.0], [5.0]), flake_id=torch.tensor([-1]),
                          model=FlakeModel(density=0.01, glint_sigma=0.05))
    obs, rep = choose_observed(cap, None, res)
    assert obs is None and not rep["kept"] and not rep["held"] and "decision" not in rep  # no left-out test


def test_bad_mode_is_one_line_error():
    from torchmetal.errors import InputError
    from torchmetal.pipeline import fit_material

    with pytest.raises(InputError, match="observed_flakes: expected one of"):
        fit_material(_capture(), observed_flakes="sometimes")


@dataclass
class _Tagged:
    """A stand-in material: a tag for the fake scores, and its observed flakes."""

    tag: str
    observed_flakes: object = None


def _fake_scores(monkeypatch, table: dict):
    """choice._scores from a table {(material tag, shot): (psnr, md)}; materials are tagged namespaces."""
    monkeypatch.setattr(choice, "_scores", lambda material, capture, shots: [
        dict(zip(("psnr", "md"), table[(material.tag, k)])) for k in shots])


@pytest.mark.parametrize("flake_md, kept", [(10.0, True), (30.0, False), (20.0, True)])
def test_keep_flakes_when_left_out_md_is_no_higher(monkeypatch, flake_md, kept):
    """The decision is the mean MD over the left-out shots (PSNR does not enter): reused from the
    observed choice's report, the kept candidate's scores; the flake-free material scored on the same shots."""
    plain = SimpleNamespace(tag="plain")
    _fake_scores(monkeypatch, {("plain", 3): (30.0, 25.0), ("plain", 1): (30.0, 15.0)})
    material = SimpleNamespace(tag="flaky", observed_flakes=None)
    oc = {"held": [3, 1], "observed": [{"psnr": 0.0, "md": 99.0}] * 2,  # not the kept candidate: ignored
          "statistical": [{"psnr": 20.0, "md": flake_md}, {"psnr": 20.0, "md": flake_md}]}
    keep, rep = keep_flakes(_capture(), material, plain, None, oc)
    assert keep is kept and rep["kept"] is kept and rep["held"] == [3, 1]
    assert [r["md"] for r in rep["none"]] == [25.0, 15.0]
    d = rep["decision"]  # MD decides: the only score in the record
    assert d["chosen"] == ("flakes" if kept else "none") and set(d["scores"]["flakes"]) == set(d["scores"]["none"]) == {"md"}


def test_keep_flakes_scores_its_own_left_out_shots(monkeypatch):
    """Without the observed choice's report (observed flakes forced on): the shots with the most associated
    detections are left out, the observed flakes measured without each."""
    cap = _capture()
    p = _particles([0, 1, 2, 3, 3], [5.0, 5.0, 15.0, 15.0, 9.0], [5.0, 5.0, 15.0, 15.0, 9.0])
    res = SimpleNamespace(particles=p, flake_id=torch.tensor([0, 0, 1, 1, 2]),
                          model=FlakeModel(density=0.01, glint_sigma=0.05))
    seen = []

    def scores(material, capture, shots):
        obs = material.observed_flakes
        seen.extend((material.tag, k, None if obs is None else len(obs)) for k in shots)
        return [{"psnr": 30.0, "md": 5.0 if material.tag == "flaky" else 50.0} for _ in shots]

    monkeypatch.setattr(choice, "_scores", scores)
    keep, rep = keep_flakes(cap, _Tagged("flaky", object()), _Tagged("plain"), res, None)
    assert keep and rep["held"] == [3, 0]
    # shot 3 left out: flakes 0 (shots 0, 1) still seen, flake 1 in shot 2, flake 2 only in shot 3 → 2
    assert seen[:2] == [("flaky", 3, 2), ("flaky", 0, 3)] and seen[2:] == [("plain", 3, None), ("plain", 0, None)]


def test_keep_flakes_without_associated_detections_keeps():
    res = SimpleNamespace(particles=_particles([0], [5.0], [5.0]), flake_id=torch.tensor([-1]), model=None)
    keep, rep = keep_flakes(_capture(), SimpleNamespace(observed_flakes=None), None, res, None)
    assert keep and not rep["held"] and "decision" not in rep  # no shot to leave out: kept untested


def test_images_too_small_for_md_keep_the_flakes_and_the_field():
    """MD needs 16-px blocks: a smaller capture is not scored (no error on valid input), flakes kept."""
    cap = _capture(h=12, w=12)
    res = SimpleNamespace(particles=_particles([0, 1], [5.0, 5.0], [5.0, 5.0]), flake_id=torch.tensor([0, 0]),
                          model=FlakeModel(density=0.01, glint_sigma=0.05))
    keep, rep = keep_flakes(cap, _Tagged("flaky"), _Tagged("plain"), res, None)
    assert keep and not rep["held"] and "decision" not in rep
    obs, rep = choose_observed(cap, _Tagged("flaky"), res)
    assert obs is None and not rep["held"] and "decision" not in rep
