from dataclasses import replace

import pytest
import torch

from tests.lightcal.helpers import flash_capture, misplaced_capture, photographed
from torchmetal.errors import InputError
from torchmetal.lightcal import LightCalibration, choose_light, with_light
from torchmetal.lightcal.choice import NO_LOBE
from torchmetal.synth import synth_capture


def _capture(falloff=0.0, layout="near", shots=8, seed=5):
    cap = synth_capture(size=40, shots=shots, layout=layout, texture="procedural", seed=seed, noise=0.01).capture
    return replace(cap, images=cap.images * LightCalibration(falloff=falloff).factor(cap))


def test_a_flash_with_falloff_is_calibrated():
    cap = _capture(falloff=-6.0)
    out, cal, rep = with_light(cap, "falloff")
    assert rep["mode"] == "falloff" and "decision" not in rep
    assert abs(cal.falloff + 6.0) < 1.5
    assert out.images.shape == cap.images.shape and out is not cap


def test_isotropic_lights_keep_no_calibration():
    cap = _capture(falloff=0.0)
    out, cal, rep = with_light(cap, "auto")
    assert rep["chosen"] == "off" and cal.identity and out is cap and rep["decision"]["name"] == "light"
    assert rep["decision"]["candidates"] == ["off", "flash"] and rep["decision"]["z"]["flash"] <= 4.0


def test_a_flash_beside_the_lens_is_found():
    """Every photo taken with the light 6 mm below and 2 mm above where capture.json puts it."""
    cap, move, _ = flash_capture()
    out, cal, rep = with_light(cap, "auto")
    assert rep["chosen"] == "flash", rep["decision"]["reason"]
    assert set(rep["decision"]["scores"]) == {"phong", "ggx"}  # it must win with the fits of either lobe
    found = torch.tensor(cal.flash, dtype=torch.float64)
    assert float((found - move)[:2].norm()) < 0.2 * float(move[:2].norm())  # across: measured 0.8 mm of 6
    assert float((found - move).norm()) < 0.5 * float(move.norm())  # depth trades against the texture's level
    assert cal.offsets is None and cal.for_unseen() == cal  # the rig's move carries over to unseen shots
    assert torch.equal(out.lights, cal.lights(cap)) and torch.equal(out.images, cap.images)


def test_no_highlight_no_move():
    """A matte sample photographed with the flash moved: the test fits keep no specular lobe, so the capture's
    lights stay, though here the move is real (without the rule it was chosen): a diffuse-only fit's misfit
    moves the lights as readily as a misplaced flash does (yellow_box without shot 6: a 5.7 cm move that cost
    that shot 2.4 dB), and the capture's lights are the simpler option."""
    r = synth_capture(size=40, shots=8, layout="near", texture="procedural", seed=5, s=(0.0, 0.0, 0.0))
    move = torch.tensor((0.0, -0.006, 0.002), dtype=torch.float64)
    cap, _ = photographed(r, move.expand(8, 3), 0.01, torch.Generator().manual_seed(7))
    mode, d = choose_light(cap)
    assert mode == "off" and d.chosen == "off" and d.reason.startswith(f"phong fits: {NO_LOBE}"), d.reason
    assert f"ggx fits: {NO_LOBE}" in d.reason  # neither test lobe votes: the capture's lights stay


@pytest.mark.parametrize("lobed, chosen", [({"phong"}, "flash"), (set(), "off")])
def test_a_test_lobe_without_highlights_has_no_vote(monkeypatch, lobed, chosen):
    """The move wins when every test lobe that kept its lobe prefers it (cards_blue without shot 1, each
    channel's clipping dropping the observation: a GGX test fit lost its lobe on the grid and its veto had
    kept the capture's lights against the Phong fits' clear preference, z 21.9); none voting keeps them."""
    from torchmetal.lightcal import choice

    def fold_errors(train, hold, kw):
        base = torch.rand(200, dtype=torch.float64, generator=torch.Generator().manual_seed(len(train.names)))
        return {"off": base, "flash": 0.5 * base}, kw["lobe"] in lobed

    monkeypatch.setattr(choice, "_fold_errors", fold_errors)
    mode, d = choose_light(_capture())
    assert mode == d.chosen == chosen and set(d.scores) == {"phong", "ggx"}, d.reason
    assert (f"ggx fits: {NO_LOBE}" in d.reason) and ((f"phong fits: {NO_LOBE}" in d.reason) == ("phong" not in lobed))


def test_misplaced_lights_are_moved_when_asked():
    """Photos taken with each light 6 mm (~10 % of its distance) from where capture.json puts it."""
    cap, true, _ = misplaced_capture()
    out, cal, rep = with_light(cap, "positions")
    assert rep["mode"] == "positions" and "decision" not in rep
    found = torch.tensor(cal.offsets, dtype=torch.float64)
    err = (found - true).norm(dim=1).mean()
    assert float((found - true)[:, :2].norm(dim=1).mean()) < 0.3 * 0.006  # across: measured 0.0009
    assert float(err) < 0.5 * 0.006  # depth trades against the texture's level: measured 0.0025
    assert torch.equal(out.lights, cal.lights(cap)) and torch.equal(out.images, cap.images)


def test_skips_are_reported():
    mode, d = choose_light(_capture(layout="far"))
    assert mode == "off" and "directional" in d.reason
    mode, d = choose_light(_capture(shots=3))
    assert mode == "off" and d.chosen == "off"
    _, cal, rep = with_light(_capture(layout="far"), "falloff")
    assert cal.identity and rep["skipped"]


def test_unknown_mode_is_refused():
    with pytest.raises(InputError, match="light: expected one of"):
        with_light(_capture(), "lamp")
