from dataclasses import replace

import pytest

from torchmetal.errors import InputError
from torchmetal.lightcal import LightCalibration, choose_light, with_light
from torchmetal.synth import synth_capture


def _capture(falloff=0.0, layout="near", shots=8, seed=5):
    cap = synth_capture(size=40, shots=shots, layout=layout, texture="procedural", seed=seed, noise=0.01).capture
    return replace(cap, images=cap.images * LightCalibration(falloff=falloff).factor(cap))


def test_a_flash_with_falloff_is_calibrated():
    cap = _capture(falloff=-6.0)
    out, cal, rep = with_light(cap, "auto")
    assert rep["chosen"] == "falloff" and rep["decision"]["name"] == "light"
    assert abs(cal.falloff + 6.0) < 1.5
    assert out.images.shape == cap.images.shape and out is not cap


def test_isotropic_lights_keep_no_calibration():
    cap = _capture(falloff=0.0)
    out, cal, rep = with_light(cap, "auto")
    assert rep["chosen"] == "off" and cal.identity and out is cap
    assert rep["decision"]["z"]["falloff"] <= 4.0


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
