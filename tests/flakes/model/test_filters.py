"""The flake stage's local filters: shifted maxima equal torch's max pooling exactly."""

import pytest
import torch
import torch.nn.functional as F

from torchmetal.flakes.model.filters import axis_max, binary_morph, max_filter


@pytest.mark.parametrize("shape", [(37, 29), (3, 17, 40), (2, 3, 9, 5)])
@pytest.mark.parametrize("radius", [0, 1, 2, 7])
def test_max_filter_is_the_max_pool(shape, radius):
    x = torch.randn(shape, generator=torch.Generator().manual_seed(3))
    k = 2 * radius + 1
    want = F.max_pool2d(x.reshape(-1, 1, *shape[-2:]), k, stride=1, padding=radius).reshape(shape)
    assert torch.equal(max_filter(x, radius), want)


def test_axis_max_runs_along_one_axis_with_minus_inf_beyond_the_border():
    x = torch.tensor([[0.0, 5.0, 1.0, -2.0], [-3.0, -4.0, -1.0, 2.0]])
    assert torch.equal(axis_max(x, 1, -1), torch.tensor([[5.0, 5.0, 5.0, 1.0], [-3.0, -1.0, 2.0, 2.0]]))
    assert torch.equal(axis_max(x, 1, -2), torch.tensor([[0.0, 5.0, 1.0, 2.0], [0.0, 5.0, 1.0, 2.0]]))


def test_max_filter_of_a_mask_is_its_dilation():
    m = torch.zeros(7, 7)
    m[3, 3] = 1.0
    got = max_filter(m, 1) > 0
    assert int(got.sum()) == 9 and bool(got[2:5, 2:5].all())


@pytest.mark.parametrize("density", [0.02, 0.3, 0.7, 0.95])
@pytest.mark.parametrize("close,open_", [(3, 1), (1, 3), (3, 3), (5, 3), (1, 1)])
def test_binary_morph_is_kornia_closing_then_opening(density, close, open_):
    import kornia.morphology as km

    m = torch.rand(3, 1, 41, 33, generator=torch.Generator().manual_seed(5)) < density
    want = m.float()
    if close > 1:
        want = km.closing(want, torch.ones(close, close))
    if open_ > 1:
        want = km.opening(want, torch.ones(open_, open_))
    got = binary_morph(m, close, open_)
    assert got.dtype == torch.bool and torch.equal(got, want > 0.5)


def test_binary_morph_closes_a_one_pixel_gap_and_keeps_the_border():
    m = torch.zeros(5, 9, dtype=torch.bool)
    m[:, 0:4] = True
    m[:, 5:9] = True  # column 4 is a 1-px gap
    got = binary_morph(m, 3, 1)
    assert bool(got.all())  # the gap closed; the image border did not erode the mask
