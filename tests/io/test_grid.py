"""Pixel grids of a capture (torchmetal.io.grid)."""

from dataclasses import replace

import pytest
import torch

from torchmetal.geometry import surface_points
from torchmetal.io.grid import strided_capture
from torchmetal.synth import synth_capture


@pytest.fixture(scope="module")
def bumpy():
    return synth_capture(size=64, shots=8, seed=3, noise=0.003, bumpy=True).capture


@pytest.mark.parametrize("h,w,max_pixels", [(64, 64, 300), (101, 70, 500), (50, 97, 100)])
def test_strided_capture_keeps_each_pixel_where_it_was(bumpy, h, w, max_pixels):
    cap = replace(bumpy, images=torch.rand(3, 3, h, w), normals=None, mask=None, saturated=None,
                  lights=bumpy.lights[:3], intensities=bumpy.intensities[:3], cameras=bumpy.cameras[:3], names=[])
    sub = strided_capture(cap, max_pixels)
    hs, ws = sub.images.shape[-2:]
    assert hs * ws <= max_pixels and hs >= 2 and ws >= 2
    # the kept pixels: the centres of the sub-capture's grid are pixel centres of the capture, and the images agree
    full = surface_points(h, w, cap.size, dtype=torch.float64)
    part = surface_points(hs, ws, sub.size, dtype=torch.float64)
    rows = [int(torch.argmin((full[1, :, 0] - y).abs())) for y in part[1, :, 0]]
    cols = [int(torch.argmin((full[0, 0, :] - x).abs())) for x in part[0, 0, :]]
    assert torch.allclose(full[:, rows][:, :, cols], part, atol=1e-9)
    assert torch.equal(sub.images, cap.images[:, :, rows][..., cols])
