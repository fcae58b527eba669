import math
from dataclasses import replace

import pytest
import torch

from torchmetal.errors import InputError
from torchmetal.lightcal import LightCalibration
from torchmetal.lightcal.model import log_axis_cosine
from torchmetal.synth import synth_capture


def _capture(layout="near", shots=4):
    return synth_capture(size=24, shots=shots, layout=layout, texture="procedural", seed=1).capture


def test_falloff_is_cos_power_of_the_angle_from_the_axis():
    cap = _capture()
    # one light straight over the surface centre at height 1: θ at a pixel is atan(r / 1)
    cap = replace(cap, lights=torch.tensor([[0.0, 0.0, 1.0, 1.0]] * cap.num_shots))
    f = LightCalibration(falloff=-3.0).factor(cap)
    h, w = cap.images.shape[-2:]
    x = ((torch.arange(w) + 0.5) / w - 0.5) * cap.size[0]
    y = (0.5 - (torch.arange(h) + 0.5) / h) * cap.size[1]
    r2 = y[:, None] ** 2 + x[None, :] ** 2
    expect = (1.0 / torch.sqrt(1.0 + r2)) ** -3.0
    assert f.shape == (cap.num_shots, 1, h, w)
    torch.testing.assert_close(f[0, 0], expect.float(), rtol=1e-5, atol=0)
    assert float(f.min()) >= 1.0  # p < 0: brighter away from the axis


def test_directional_lights_and_no_calibration_leave_the_photos_alone():
    far = _capture("far")
    assert torch.equal(LightCalibration(falloff=7.0).factor(far), torch.ones_like(far.images[:, :1]))
    assert torch.equal(log_axis_cosine(far), torch.zeros_like(far.images[:, :1], dtype=torch.float64))
    cap = _capture()
    assert LightCalibration().apply(cap) is cap


def test_gains_scale_each_shot_and_apply_divides():
    cap = _capture()
    cal = LightCalibration(falloff=2.0, gains=(0.5, 1.0, 2.0, 1.0))
    f = cal.factor(cap)
    f0 = cal.for_unseen().factor(cap)
    torch.testing.assert_close(f / f0, torch.tensor([0.5, 1.0, 2.0, 1.0])[:, None, None, None].expand_as(f))
    torch.testing.assert_close(cal.apply(cap).images * f, cap.images)
    assert math.isfinite(float(f.sum()))


def test_gains_must_match_the_shots():
    with pytest.raises(InputError, match="gains for 4 shots, found 2"):
        LightCalibration(gains=(1.0, 1.0)).factor(_capture())


def test_report_round_trip():
    cal = LightCalibration(falloff=-4.5, gains=(0.9, 1.1))
    assert LightCalibration.from_dict(cal.to_dict()) == cal
    assert LightCalibration.from_dict(None).identity
