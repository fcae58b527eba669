from dataclasses import replace

import pytest
import torch

from torchmetal.errors import InputError
from torchmetal.lightcal import LightCalibration, choose_light, with_light
from torchmetal.lightcal.positions import moved_lights
from torchmetal.lobes import lobe_render
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
    assert rep["decision"]["candidates"] == ["off", "positions"] and rep["decision"]["z"]["positions"] <= 4.0


def test_misplaced_lights_are_moved():
    """Photos taken with each light 5–8 mm (~10 % of its distance) from where capture.json puts it."""
    r = synth_capture(size=40, shots=8, layout="near", texture="procedural", seed=5, noise=0.01,
                      alpha=(60.0, 60.0, 60.0), s=(0.5, 0.5, 0.5))
    cap, t = r.capture, r.truth
    g = torch.Generator().manual_seed(2)
    true = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=torch.float64), dim=1) * 0.006
    photo = lobe_render(t["texture"], t["s"], t["alpha"], t["normals"], moved_lights(cap.lights, true),
                        cap.intensities, cap.cameras, cap.size)
    noisy = photo * (1 + 0.01 * torch.randn(photo.shape, generator=g))
    out, cal, rep = with_light(replace(cap, images=noisy), "auto")
    assert rep["chosen"] == "positions" and rep["decision"]["z"]["positions"] > 4.0
    found = torch.tensor(cal.offsets, dtype=torch.float64)
    assert float((found - true).norm(dim=1).mean()) < 0.3 * 0.006


def test_skips_are_reported():
    mode, d = choose_light(_capture(layout="far"))
    assert mode == "off" and "directional" in d.reason
    mode, d = choose_light(_capture(shots=3))
    assert mode == "off" and d.chosen == "off"
    _, cal, rep = with_light(_capture(layout="far"), "falloff")
    assert cal.identity and rep["skipped"]


def test_unknown_mode_is_refused():
    with pytest.raises(InputError, match="light: expected one of"):
        with_light(_capture(), "flash")
