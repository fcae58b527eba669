from dataclasses import replace

import pytest
import torch

from tests.lightcal.helpers import glossy_scene, photographed
from torchmetal.fit.api import fit_phong
from torchmetal.lightcal import LightCalibration, with_light
from torchmetal.lightcal.estimate import calibrate_positions
from torchmetal.lightcal.positions import MAX_MOVE, fit_offsets, material_offsets, move_capture, moved_lights
from torchmetal.material import Material
from torchmetal.synth import synth_capture

TRUE = torch.tensor([[0.6, -0.4, 0.3], [-0.5, 0.2, -0.4], [0.3, 0.5, 0.2], [-0.2, -0.5, 0.5], [0.4, 0.3, -0.3],
                     [-0.6, 0.1, 0.2]], dtype=torch.float64) * 0.01  # the "near" lights sit ~0.06 from a 0.1 wide surface


def _scene(size=48, shots=6, seed=4, noise=0.0):
    """A glossy synthetic capture photographed with each point light at TRUE[k] from where capture.json says."""
    r = glossy_scene(size, shots, seed)
    cap, render = photographed(r, TRUE[:shots], noise, torch.Generator().manual_seed(seed))
    return r, cap, render


def test_moved_lights_moves_point_lights_only():
    lights = torch.tensor([[1.0, 2.0, 3.0, 1.0], [0.0, 0.0, 1.0, 0.0]])
    out = moved_lights(lights, torch.tensor([[0.5, 0.5, 0.5], [9.0, 9.0, 9.0]], dtype=torch.float64))
    assert torch.equal(out, torch.tensor([[1.5, 2.5, 3.5, 1.0], [0.0, 0.0, 1.0, 0.0]]))
    assert out.dtype == lights.dtype and moved_lights(lights, None) is lights


def test_fit_offsets_finds_the_lights_with_the_true_material():
    r, cap, render = _scene()
    off = fit_offsets(cap, render)
    assert float((off - TRUE).norm(dim=1).max()) < 1e-4  # the capture's lights sit ~0.005 away
    dist = cap.lights[:, :3].double().norm(dim=1)
    assert bool(((off.norm(dim=1) <= MAX_MOVE * dist + 1e-9)).all())
    again = fit_offsets(cap, render)
    assert torch.equal(off, again)  # reproducible


def test_fit_offsets_stops_once_converged(monkeypatch):
    """FTOL ends a search when an accepted step gains less than 1e-6 of its error: the same offsets to within 1 % of
    the move; shared (the pipeline's flash test), far fewer renders than the 15 iterations' 7 each (per shot, a shot
    whose steps keep being rejected still runs them all)."""
    import torchmetal.lightcal.positions as positions

    r, cap, render = _scene(noise=0.01)
    calls = []
    counted = lambda lights: calls.append(1) or render(lights)  # noqa: E731
    for shared in (False, True):
        calls.clear()
        off = fit_offsets(cap, counted, shared=shared)
        stopped = len(calls)
        monkeypatch.setattr(positions, "FTOL", 0.0)
        calls.clear()
        full = fit_offsets(cap, counted, shared=shared)
        monkeypatch.setattr(positions, "FTOL", 1e-6)
        assert float((off - full).norm(dim=1).max()) < 0.01 * float(full.norm(dim=1).max())
        assert stopped < (0.6 if shared else 1.01) * len(calls), (stopped, len(calls))


def test_fit_offsets_leaves_directional_lights_and_empty_masks_alone():
    r = synth_capture(size=24, shots=4, layout="far", texture="procedural", seed=1)
    cap = r.capture
    off = fit_offsets(cap, lambda lights: cap.images)
    assert torch.equal(off, torch.zeros(4, 3, dtype=torch.float64))
    near = synth_capture(size=24, shots=4, layout="near", texture="procedural", seed=1).capture
    blown = replace(near, saturated=torch.ones_like(near.images, dtype=torch.bool))  # no valid observation
    assert torch.equal(fit_offsets(blown, lambda lights: near.images), torch.zeros(4, 3, dtype=torch.float64))


def test_calibrated_positions_give_a_truer_material():
    r, cap, _ = _scene(noise=0.01)
    plain = fit_phong(cap, lobe="phong")
    cal, fit = calibrate_positions(cap, fit_kwargs={"lobe": "phong"})
    err = lambda f: float((f.texture - r.truth["texture"]).abs().mean())  # noqa: E731
    assert err(fit) < 0.8 * err(plain)  # measured 0.0080 vs 0.0117
    assert abs(float(fit.alpha.mean()) - 60.0) < abs(float(plain.alpha.mean()) - 60.0)
    found = torch.tensor(cal.offsets, dtype=torch.float64)
    assert float((found - TRUE).norm(dim=1).mean()) < 0.3 * float(TRUE.norm(dim=1).mean())


def test_material_offsets_on_a_strided_grid():
    r, cap, _ = _scene(size=64)
    t = r.truth
    m = Material(t["texture"], t["s"], t["alpha"], cap.size, normals=None)
    off = material_offsets(m, cap, max_pixels=32 * 32)
    assert float((off - TRUE).norm(dim=1).max()) < 1e-3
    ones = LightCalibration().factor(cap)  # (N, 1, 1, 1)
    assert torch.equal(material_offsets(m, cap, ones, max_pixels=32 * 32), off)
    f = LightCalibration(falloff=-2.0).factor(cap)  # (N, 1, H, W), not in the photos: the offsets move
    assert not torch.equal(material_offsets(m, cap, f, max_pixels=32 * 32), off)
    with pytest.raises(ValueError, match="expected photos of 64x64"):
        material_offsets(m, synth_capture(size=32, shots=2, layout="near", texture="procedural").capture)


def test_a_calibration_with_offsets_moves_the_lights_and_round_trips():
    r, cap, _ = _scene(size=16)
    cal = LightCalibration(offsets=tuple(tuple(o) for o in TRUE.tolist()))
    out = cal.apply(cap)
    torch.testing.assert_close(out.lights.double(), moved_lights(cap.lights, TRUE).double())
    assert torch.equal(out.images, cap.images)
    assert LightCalibration.from_dict(cal.to_dict()) == cal
    assert cal.for_unseen().identity and not cal.identity
    with pytest.raises(Exception, match="expected offsets for 2 shots, found 6"):
        cal.lights(cap.subset([0, 1]))
    both = LightCalibration(falloff=-3.0, offsets=cal.offsets)
    f = both.factor(cap)
    torch.testing.assert_close(f, LightCalibration(falloff=-3.0).factor(move_capture(cap, TRUE)))


def test_with_light_positions_reports_the_offsets():
    _, cap, _ = _scene(size=32)
    out, cal, rep = with_light(cap, "positions")
    assert rep["mode"] == "positions" and len(rep["offsets"]) == 6 and cal.offsets is not None
    assert not torch.equal(out.lights, cap.lights) and torch.equal(out.images, cap.images)


def test_a_shared_offset_moves_every_light_alike():
    move = torch.tensor([0.0, -0.006, 0.002], dtype=torch.float64)  # a flash beside the lens
    cap, render = photographed(glossy_scene(), move.expand(8, 3))

    off = fit_offsets(cap, render, shared=True)
    assert bool((off == off[:1]).all())  # one move, in every row
    assert float((off[0] - move).norm()) < 1e-4
    cal = LightCalibration(flash=tuple(off[0].tolist()))
    assert LightCalibration.from_dict(cal.to_dict()) == cal and cal.for_unseen() == cal and not cal.identity
    torch.testing.assert_close(cal.lights(cap).double(), moved_lights(cap.lights, off).double())
    per_shot, fit = calibrate_positions(cap, fit_kwargs={"lobe": "phong"}, shared=True)
    found = torch.tensor(per_shot.flash, dtype=torch.float64)  # the material refitted: depth trades against its level
    assert per_shot.offsets is None and float((found - move)[:2].norm()) < 0.2 * float(move[:2].norm())
