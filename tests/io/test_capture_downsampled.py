"""Capture.downsampled: a box-downsampled capture whose pixels stay where their blocks were."""

from dataclasses import replace

import pytest
import torch

from torchmetal.geometry import surface_points
from torchmetal.synth import synth_capture


def test_downsampled_keeps_pixels_on_the_sample():
    cap = synth_capture(size=(50, 37), shots=3, seed=1).capture
    sat = torch.zeros_like(cap.saturated)
    sat[1, 2, 1, 0] = True
    ds = replace(cap, saturated=sat).downsampled(4)
    assert ds.images.shape == (3, 3, 12, 9) and ds.saturated[1, 2, 0, 0] and int(ds.saturated.sum()) == 1
    # 2 rows dropped (one at each edge), 1 column (at the right): a pixel is its block's mean
    assert torch.allclose(ds.images[0, :, 0, 0], cap.images[0, :, 1:5, :4].mean((-2, -1)))
    assert ds.size == pytest.approx((cap.size[0] * 36 / 37, cap.size[1] * 48 / 50))
    full = surface_points(50, 37, cap.size, dtype=torch.float64)[:, 1:49, :36]
    blocks = torch.nn.functional.avg_pool2d(full.unsqueeze(0), 4)[0]
    part = surface_points(12, 9, ds.size, dtype=torch.float64)
    pitch_x = cap.size[0] / 37
    assert torch.allclose(part[1], blocks[1], atol=1e-9)  # rows: exactly the blocks' centres
    assert (part[0] - blocks[0]).abs().max() <= 0.5 * pitch_x + 1e-9  # an odd column dropped: within half a pixel
    assert ds.downsampled(1) is ds and cap.downsampled(1) is cap


def test_downsampled_mask_and_normals():
    cap = synth_capture(size=32, shots=2, seed=2, bumpy=True).capture
    mask = torch.ones_like(cap.mask)
    mask[0, 0, 0] = False
    ds = replace(cap, mask=mask).downsampled(4)
    assert not ds.mask[0, 0, 0] and bool(ds.mask.sum() == 63)  # a block is inside only when all of it is
    assert torch.allclose(ds.normals.norm(dim=0), torch.ones(8, 8), atol=1e-6) and not ds.flat
    assert synth_capture(size=32, shots=2, seed=2).capture.downsampled(4).flat
