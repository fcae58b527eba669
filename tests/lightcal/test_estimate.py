from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchmetal.lightcal import LightCalibration
from torchmetal.lightcal.estimate import log_ratio_step
from torchmetal.synth import synth_capture


@dataclass
class _TruthFit:
    """A stand-in fit whose render is the capture's noise-free photos before the light nuisance, all diffuse."""

    clean: Tensor
    s: Tensor
    cluster_s: Tensor | None = None
    gloss_s: Tensor | None = None

    highlight: Tensor | None = None  # (N, 1, H, W) share of the render that is specular

    def render(self, lights, intensities, cameras):
        diffuse_only = not bool(self.s.any()) and self.highlight is not None
        return self.clean * (1 - self.highlight) if diffuse_only else self.clean


def _truth_fit(result):
    return _TruthFit(result.capture.images.clone(), torch.zeros(3))


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


def test_highlights_do_not_bend_the_falloff():
    """Where a lobe misfits, the residual is the lobe's: only diffuse-dominated observations count."""
    r = synth_capture(size=32, shots=6, layout="near", texture="procedural", seed=3)
    cap = r.capture
    f = LightCalibration(falloff=-5.0).factor(cap)
    spec = (f > f.median()).to(cap.images.dtype)  # the "highlight": half the observations, where the falloff shows
    photo = cap.images * torch.where(spec > 0, f, torch.ones_like(f))
    fit = _TruthFit(cap.images.clone(), torch.ones(3), highlight=0.5 * spec)
    p, _ = log_ratio_step(replace(cap, images=photo), fit, gains=False)
    assert abs(p) < 1e-6
    p_all, _ = log_ratio_step(replace(cap, images=photo), _truth_fit(r), gains=False)
    assert p_all < -1.0  # counted, they would have
