"""Observed or statistical flakes, decided on left-out shots (torchmetal.flakes.choice).

End to end: tests/flakes/test_observed.py (zoo flakes_b: the left-out shots keep them) and
tests/test_pipeline.py (the dense hemisphere case: MD of a left-out photo with the default).
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from torchmetal.flakes.choice import _held_shots, _observed_without, choose_observed
from torchmetal.flakes.results import Particles
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
    assert _held_shots(p, fid, 4, 2) == [3, 2]
    assert _held_shots(p, fid, 4, 9) == [3, 2, 0]  # never a shot without associated detections


def test_observed_without_leaves_the_shot_out_of_detections_and_probes():
    cap = _capture()
    p = _particles([0, 1, 2, 3], [5.0, 5.0, 15.0, 15.0], [5.0, 5.0, 15.0, 15.0])
    fid = torch.tensor([0, 0, 1, 1])
    obs = _observed_without(cap, p, fid, FlakeModel(density=0.01, glint_sigma=0.05), 2)
    assert obs is not None and len(obs) == 2  # flake 1 is still seen, in shot 3 (renumbered 2)
    assert torch.equal(obs.probe_lights, cap.lights[[0, 1, 3]])
    alone = _observed_without(cap, p, torch.tensor([0, 0, 1, -1]), FlakeModel(density=0.01, glint_sigma=0.05), 2)
    assert len(alone) == 1  # flake 1 was seen in shot 2 only


def test_no_associated_detections_keep_the_field():
    cap = _capture()
    res = SimpleNamespace(particles=_particles([0], [5.0], [5.0]), flake_id=torch.tensor([-1]),
                          model=FlakeModel(density=0.01, glint_sigma=0.05))
    obs, rep = choose_observed(cap, None, res)
    assert obs is None and not rep["kept"] and rep["reason"] == "no associated detections"


def test_bad_mode_is_one_line_error():
    from torchmetal.errors import InputError
    from torchmetal.pipeline import fit_material

    with pytest.raises(InputError, match="observed_flakes: expected one of"):
        fit_material(_capture(), observed_flakes="sometimes")
