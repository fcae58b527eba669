"""torchmetal plan: plan.json per docs/design.md §2.5, K shots best first, the figure, one-line errors."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from torchmetal.cli import main
from torchmetal.errors import InputError
from torchmetal.plan.core import PlanOptions, Scene, camera_frame, expected_error, fisher_sums, plan_shots, shot_terms
from torchmetal.plan.run import plan_directory
from torchmetal.synth.zoo import Scene as ZooScene
from torchmetal.synth.zoo import make_case


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    case = make_case(ZooScene("plan", size=40, shots=4, held=1, layout="hemisphere", s=0.5, alpha=60.0, seed=43902),
                     tmp_path_factory.mktemp("plan"))
    return case.capture_dir


def _scene(lights=None) -> Scene:
    """A flat 24² sample, global Phong, past flash shots at ``lights`` (camera = light)."""
    lights = torch.zeros(0, 4, dtype=torch.float64) if lights is None else lights
    return Scene(texture=torch.full((3, 24, 24), 0.3, dtype=torch.float64), s=torch.full((1, 3), 0.5, dtype=torch.float64),
                 alpha=torch.full((1, 3), 60.0, dtype=torch.float64), labels=None, normals=None, size=(0.1, 0.1),
                 lobe="phong", lights=lights, cameras=lights.clone(), intensities=torch.ones(lights.shape[0], 3, dtype=torch.float64))


def test_plan_json_exact_and_figure(capture_dir, tmp_path):
    out = tmp_path / "p"
    assert main(["plan", str(capture_dir), "-n", "2", "-o", str(out)]) == 0
    doc = json.loads((out / "plan.json").read_text())
    assert list(doc) == ["shots"] and len(doc["shots"]) == 2
    for shot in doc["shots"]:
        assert list(shot) == ["light", "camera"]
        assert len(shot["light"]) == 4 and shot["light"][3] == 1 and len(shot["camera"]) == 4 and shot["camera"][3] == 1
        assert shot["camera"][2] > 0 and shot["light"][2] > 0
    png = (out / "plan.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_best_first_and_distinct():
    plan = plan_shots(_scene(), PlanOptions(shots=3, azimuths=8))
    assert plan.lights.shape == (3, 4)
    # greedy: each shot is scored given the ones before it, so the scores cannot rise
    assert bool((plan.scores[1:] <= plan.scores[:-1] + 1e-12).all()), plan.scores
    assert len({tuple(c) for c in plan.cameras.tolist()}) == 3


def test_a_seen_highlight_is_not_asked_for_again():
    """Past shots straight above the sample cover its centre: with coverage weighed (0.5; the default 0.05 only breaks
    near-ties of E, which here prefers the overhead view's diffuse light) the first planned shot looks elsewhere."""
    above = torch.tensor([[0.0, 0.0, 0.5, 1.0], [0.0, 0.0, 0.35, 1.0], [0.0, 0.0, 0.7, 1.0]], dtype=torch.float64)
    # tilts of a few degrees: the hotspot (mirror direction within 6.7°) of a steeper shot misses the 0.1 sample
    plan = plan_shots(_scene(above), PlanOptions(shots=1, distance=(1.0,), tilts=(0.0, 2.0, 4.0, 6.0, 10.0), azimuths=8,
                                                 cover_weight=0.5))
    cam = plan.cameras[0, :3]
    assert float(cam[:2].norm()) > 1e-6  # not straight above again
    assert float(plan.cover_gain[0]) > 0


def test_information_grows_and_error_drops():
    sc = _scene(torch.tensor([[0.05, 0.0, 0.5, 1.0]], dtype=torch.float64))
    rows, cols = slice(0, 24, 2), slice(0, 24, 2)
    t = shot_terms(sc, rows, cols, sc.lights, sc.cameras, sc.intensities)
    S = fisher_sums(t)
    assert S.shape == (6, 3, 144) and bool((S[0] > 0).all())
    e1 = expected_error(S, S, None, 1)
    e2 = expected_error(2 * S, S, None, 1)
    assert float(e2) < float(e1)


def test_camera_frame_is_a_rotation_looking_at_the_target():
    cam = torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64)
    R = camera_frame(cam, torch.zeros(3, dtype=torch.float64))[0]
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(R[2], -cam[0] / cam[0].norm())
    assert float(torch.det(R)) > 0


def test_bad_input(tmp_path, capsys):
    with pytest.raises(InputError, match="at least 1 shot"):
        plan_shots(_scene(), PlanOptions(shots=0))
    with pytest.raises(InputError, match="capture .* or a material"):
        plan_directory(tmp_path, tmp_path / "out")
    assert main(["plan", str(tmp_path), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchmetal plan: error:")


def test_material_with_and_without_its_capture(capture_dir, tmp_path):
    from torchmetal.fit import fit_phong
    from torchmetal.fit.uncertainty import fit_uncertainty
    from torchmetal.io.capture import load_capture
    from torchmetal.material import save_material

    cap = load_capture(capture_dir)
    fit = fit_phong(cap, specular="global", lobe="phong")
    save_material(fit.to_material({"uncertainty": fit_uncertainty(fit, cap)}), tmp_path / "m")
    plan, seconds = plan_directory(tmp_path / "m", tmp_path / "o1", options=PlanOptions(shots=2), capture=capture_dir)
    assert plan.lights.shape == (2, 4) and seconds > 0
    blind, _ = plan_directory(tmp_path / "m", tmp_path / "o2", options=PlanOptions(shots=1))
    assert any("no past" in n for n in blind.notes)
    with pytest.raises(InputError, match="capture already"):
        plan_directory(capture_dir, tmp_path / "o3", capture=capture_dir)


def test_no_highlight_seen_plans_for_coverage():
    """A fit without a highlight (s = 0, α at its floor 1): coverage is that of a typical gloss, not of α = 1 (whose
    lobe is 'hot' everywhere), and the first planned shot puts a hotspot where none has been."""
    sc = _scene(torch.tensor([[0.3, 0.0, 0.2, 1.0], [-0.3, 0.0, 0.2, 1.0]], dtype=torch.float64))
    sc.s, sc.alpha = torch.zeros(1, 3, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64)
    plan = plan_shots(sc, PlanOptions(shots=1, azimuths=8))
    assert float(plan.coverage.double().mean()) < 0.5
    assert float(plan.cover_gain[0]) > 0


def test_score_shots_is_the_plans_own_first_score():
    """Scoring given positions uses the plan's criterion: the planned first shot gets the plan's score, and no
    reachable position scores above it."""
    from torchmetal.plan.core import reachable, score_shots

    sc = _scene(torch.tensor([[0.02, 0.0, 0.5, 1.0], [-0.01, 0.02, 0.4, 1.0]], dtype=torch.float64))
    o = PlanOptions(shots=2, azimuths=8)
    plan = plan_shots(sc, o)
    got = score_shots(sc, plan.lights, plan.cameras, plan.intensities, o)
    assert float(got["score"][0]) == pytest.approx(float(plan.scores[0]), rel=1e-6)
    lights, cams, inten, _ = reachable(sc, o)
    every = score_shots(sc, lights, cams, inten, o)["score"]
    assert float(every.max()) == pytest.approx(float(plan.scores[0]), rel=1e-6)
    assert float(got["score"][1]) <= float(plan.scores[0]) + 1e-12


def test_coverage_of_a_broad_lobe_is_where_the_mirror_passed():
    """A broad fitted lobe (α 7) reaches half its peak over the whole sample from one overhead flash; the coverage
    map counts only where the mirror direction passed (a lobe at least α 100): a disc under the flash, not all."""
    from torchmetal.plan.core import HOT_ALPHA

    above = torch.tensor([[0.0, 0.0, 0.3, 1.0]], dtype=torch.float64)
    broad = replace(_scene(above), alpha=torch.full((1, 3), 7.0, dtype=torch.float64))
    cover = plan_shots(broad, PlanOptions(shots=1, azimuths=4)).coverage
    assert 0.05 < float(cover.double().mean()) < 0.5
    assert bool(cover[12, 12]) and not bool(cover[0, 0])  # the centre under the flash, not the corner
    # a sharper fitted lobe than HOT_ALPHA keeps its own, smaller, hotspot
    sharp = replace(_scene(above), alpha=torch.full((1, 3), 4 * HOT_ALPHA, dtype=torch.float64))
    assert float(plan_shots(sharp, PlanOptions(shots=1, azimuths=4)).coverage.double().mean()) < float(cover.double().mean())


def test_figure_labels_do_not_overlap():
    from torchmetal.plan.run import _free_offsets

    placed: list = []
    offs = _free_offsets([(100.0, 100.0), (101.0, 100.0), (100.0, 101.0)], placed)
    assert len(set(offs)) == 3
    for i in range(3):
        for j in range(i):
            a, b = placed[i], placed[j]
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3])


def test_only_the_sample_counts():
    """Pixels off the mask carry no information and no highlight: the coverage, its gain and E ignore them."""
    above = torch.tensor([[0.0, 0.0, 0.3, 1.0]], dtype=torch.float64)
    mask = torch.zeros(24, 24, dtype=torch.bool)
    mask[:, :12] = True
    sc = replace(_scene(above), mask=mask)
    plan = plan_shots(sc, PlanOptions(shots=2, azimuths=4))
    assert plan.inside is not None and not bool((plan.coverage & ~plan.inside).any())
    assert not bool((plan.planned_cover & ~plan.inside).any())
    assert plan.seen() == pytest.approx(float(plan.coverage[plan.inside].double().mean()))
    # what lies off the sample changes nothing
    other = replace(sc, texture=torch.where(mask, sc.texture, torch.full_like(sc.texture, 0.9)))
    again = plan_shots(other, PlanOptions(shots=2, azimuths=4))
    assert torch.equal(again.cameras, plan.cameras) and torch.allclose(again.scores, plan.scores)
