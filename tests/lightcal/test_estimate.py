from dataclasses import replace
from types import SimpleNamespace

import torch

from torchmetal.lightcal import LightCalibration
from torchmetal.lightcal.estimate import log_ratio_step
from torchmetal.synth import synth_capture


def _truth_fit(result):
    """A stand-in fit whose render is the capture's noise-free photos before the light nuisance."""
    clean = result.capture.images.clone()
    return SimpleNamespace(render=lambda lights, intensities, cameras: clean)


def test_log_ratio_step_recovers_a_known_falloff_and_gains():
    r = synth_capture(size=32, shots=6, layout="near", texture="procedural", seed=3)
    true = LightCalibration(falloff=-5.0, gains=(0.8, 1.25, 1.0, 1.1, 0.9, 1 / (0.8 * 1.25 * 1.1 * 0.9)))
    cap = replace(r.capture, images=r.capture.images * true.factor(r.capture))
    p, b = log_ratio_step(cap, _truth_fit(r), gains=True)
    assert abs(p + 5.0) < 1e-3
    torch.testing.assert_close(b.exp(), torch.tensor(true.gains, dtype=torch.float64), atol=1e-4, rtol=0)
    p1, b1 = log_ratio_step(cap, _truth_fit(r), gains=False)
    assert abs(p1 + 5.0) < 0.5 and torch.equal(b1, torch.zeros(6, dtype=torch.float64))


def test_no_nuisance_gives_no_correction():
    r = synth_capture(size=32, shots=6, layout="near", texture="procedural", seed=3)
    p, b = log_ratio_step(r.capture, _truth_fit(r), gains=True)
    assert abs(p) < 1e-6 and float(b.abs().max()) < 1e-6
