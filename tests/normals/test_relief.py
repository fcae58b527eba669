"""normals="relief" (torchmetal.normals.relief): an embossing as a high-passed height field, fitted with the
global Phong terms (the choice on left-out shots: tests/select/test_choices.py)."""

from dataclasses import replace

import pytest
import torch

from torchmetal.geometry import shading_geometry
from torchmetal.normals import with_normals
from torchmetal.normals.relief import fit_relief, grid_shape, high_pass, relief_normals
from torchmetal.phong import phong_shading
from torchmetal.synth import synth_capture

SIZE = 64


def _angle_deg(a, b):
    return torch.rad2deg(torch.acos((a * b).sum(0).clamp(-1.0, 1.0)))


def _embossed(seed: int, noise: float = 0.003):
    """A capture of a sample embossed with a random relief (in the model's own form), and its normals."""
    base = synth_capture(size=SIZE, shots=8, seed=seed, noise=0.0).capture
    g = torch.Generator().manual_seed(seed)
    gh, gw = grid_shape(SIZE, SIZE)
    heights = 0.08 * base.size[0] / gw * torch.randn(gh, gw, generator=g, dtype=torch.float64)  # slopes ~0.1
    normals = relief_normals(heights, (SIZE, SIZE), base.size).float()
    tex = 0.15 + 0.5 * torch.rand(3, SIZE, SIZE, generator=g)
    geom = shading_geometry(normals, base.lights, base.intensities, base.cameras, base.size)
    clean = phong_shading(tex, torch.tensor([0.5, 0.5, 0.5]), torch.tensor([30.0, 30.0, 30.0]), geom)
    images = clean * (1.0 + noise * torch.randn(clean.shape, generator=g))
    return replace(base, images=images, normals=None), normals


@pytest.fixture(scope="module")
def embossed():
    return _embossed(5)


def test_high_pass_drops_a_tilt_and_keeps_a_bump():
    yy, xx = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    tilt = (0.3 * xx - 0.2 * yy).double()
    assert high_pass(tilt)[6:-6, 6:-6].abs().max() < 1e-5  # a plane is the lights' error, not the embossing
    bump = torch.exp(-((xx - 16) ** 2 + (yy - 16) ** 2) / 2.0).double()
    assert high_pass(bump)[16, 16] > 0.5  # a bump a few cells wide stays


def test_relief_normals_lean_away_from_a_bump():
    yy, xx = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    bump = torch.exp(-((xx - 8) ** 2 + (yy - 8) ** 2) / 4.0).double()
    n = relief_normals(bump, (64, 64), (1.0, 1.0))
    assert torch.allclose(n.norm(dim=0), torch.ones(64, 64, dtype=torch.float64))
    assert n[0, 32, 40] > 0.05 and n[0, 32, 24] < -0.05  # right of the top leans right (+x), left leans left
    assert n[1, 24, 32] > 0.05 and n[1, 40, 32] < -0.05  # above (smaller row) leans up (+y)
    assert torch.allclose(relief_normals(torch.zeros(8, 8, dtype=torch.float64), (20, 30), (1.0, 1.0))[2],
                          torch.ones(20, 30, dtype=torch.float64))


def test_fit_recovers_an_embossing(embossed):
    cap, truth = embossed
    fit = fit_relief(cap)
    flat = fit_relief(cap, relief=False)
    est = relief_normals(fit.heights, (SIZE, SIZE), cap.size).float()
    tilt = _angle_deg(truth, torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)).mean()
    err = _angle_deg(est, truth)[4:-4, 4:-4].mean()
    assert tilt > 3.0 and err < 0.5 * tilt, (float(tilt), float(err))
    assert fit.loss < 0.5 * flat.loss


def test_relief_mode_reports_its_fit(embossed):
    cap, _ = embossed
    out, rep = with_normals(cap, "relief")
    assert not out.flat and out.normals.shape == (3, SIZE, SIZE) and out.normals.dtype == cap.images.dtype
    assert rep["mode"] == "relief" and rep["grid"] == list(grid_shape(SIZE, SIZE)) and rep["tilt_mean_deg"] > 1.0
