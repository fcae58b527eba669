"""A synthetic capture whose photos were taken with each point light away from where capture.json puts it."""

from dataclasses import replace

import torch

from torchmetal.lightcal.positions import moved_lights
from torchmetal.lobes import lobe_render
from torchmetal.synth import synth_capture


def misplaced_capture(size=40, shots=8, seed=5, shift=0.006, noise=0.01):
    """(capture, true offsets (N, 3) float64, the synthetic truth dict): a glossy "near" scene (lights ~0.06 from a 0.1 wide surface),
    each light ``shift`` away in a seeded direction, relative Gaussian noise ``noise``."""
    r = synth_capture(size=size, shots=shots, layout="near", texture="procedural", seed=seed,
                      alpha=(60.0, 60.0, 60.0), s=(0.5, 0.5, 0.5))
    cap, t = r.capture, r.truth
    g = torch.Generator().manual_seed(seed + 1)
    true = torch.nn.functional.normalize(torch.randn(shots, 3, generator=g, dtype=torch.float64), dim=1) * shift
    photo = lobe_render(t["texture"], t["s"], t["alpha"], t["normals"], moved_lights(cap.lights, true),
                        cap.intensities, cap.cameras, cap.size)
    photo = photo * (1 + noise * torch.randn(photo.shape, generator=g))
    return replace(cap, images=photo.clamp_min(0.0)), true, t


def flash_capture(size=40, shots=8, seed=5, move=(0.0, -0.006, 0.002), noise=0.01):
    """(capture, the move (3,) float64, the truth dict): the same scene, every light moved alike (a flash
    beside the lens where the capture put it on the lens)."""
    r = synth_capture(size=size, shots=shots, layout="near", texture="procedural", seed=seed,
                      alpha=(60.0, 60.0, 60.0), s=(0.5, 0.5, 0.5))
    cap, t = r.capture, r.truth
    m = torch.tensor(move, dtype=torch.float64)
    photo = lobe_render(t["texture"], t["s"], t["alpha"], t["normals"], moved_lights(cap.lights, m.expand(shots, 3)),
                        cap.intensities, cap.cameras, cap.size)
    photo = photo * (1 + noise * torch.randn(photo.shape, generator=torch.Generator().manual_seed(seed + 2)))
    return replace(cap, images=photo.clamp_min(0.0)), m, t
