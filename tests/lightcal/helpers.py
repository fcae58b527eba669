"""Synthetic captures whose photos were taken with the point lights away from where capture.json puts them."""

from dataclasses import replace

import torch

from torchmetal.lightcal.positions import moved_lights
from torchmetal.lobes import lobe_render
from torchmetal.synth import synth_capture


def glossy_scene(size=40, shots=8, seed=5):
    """A glossy "near" synthetic scene (lights ~0.06 from a 0.1 wide surface, α 60, s 0.5)."""
    return synth_capture(size=size, shots=shots, layout="near", texture="procedural", seed=seed,
                         alpha=(60.0, 60.0, 60.0), s=(0.5, 0.5, 0.5))


def photographed(r, offsets, noise=0.0, generator=None):
    """(capture, render): ``r``'s capture with photos taken with each point light moved by ``offsets``
    (N, 3), times 1 + ``noise`` × a standard normal draw of ``generator``; ``render(lights)`` renders the truth."""
    cap, t = r.capture, r.truth

    def render(lights):
        return lobe_render(t["texture"], t["s"], t["alpha"], t["normals"], lights, cap.intensities, cap.cameras, cap.size)

    photo = render(moved_lights(cap.lights, offsets))
    if noise:
        photo = photo * (1 + noise * torch.randn(photo.shape, generator=generator))
    return replace(cap, images=photo.clamp_min(0.0)), render


def misplaced_capture(size=40, shots=8, seed=5, shift=0.006, noise=0.01):
    """(capture, true offsets (N, 3) float64, the synthetic truth dict): :func:`glossy_scene`, each light
    ``shift`` away in a seeded direction, relative Gaussian noise ``noise``."""
    r = glossy_scene(size, shots, seed)
    g = torch.Generator().manual_seed(seed + 1)
    true = torch.nn.functional.normalize(torch.randn(shots, 3, generator=g, dtype=torch.float64), dim=1) * shift
    cap, _ = photographed(r, true, noise, g)
    return cap, true, r.truth


def flash_capture(size=40, shots=8, seed=5, move=(0.0, -0.006, 0.002), noise=0.01):
    """(capture, the move (3,) float64, the truth dict): :func:`glossy_scene`, every light moved alike (a
    flash beside the lens where the capture put it on the lens)."""
    r = glossy_scene(size, shots, seed)
    m = torch.tensor(move, dtype=torch.float64)
    cap, _ = photographed(r, m.expand(shots, 3), noise, torch.Generator().manual_seed(seed + 2))
    return cap, m, r.truth
