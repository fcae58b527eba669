"""The light calibration by mode (torchmetal.lightcal.modes); light="auto" is tested in tests/select/test_choices.py."""

from dataclasses import replace

import pytest
import torch

from tests.lightcal.helpers import misplaced_capture
from torchmetal.errors import InputError
from torchmetal.lightcal import LightCalibration, with_light
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


def test_unknown_mode_is_refused():
    for bad in ("lamp", "auto"):  # auto is the selection's
        with pytest.raises(InputError, match="light: expected one of"):
            with_light(_capture(), bad)
