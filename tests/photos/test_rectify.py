"""The rectification's block reductions (area mean, any-clipped, all-seen) against numpy's definitions."""

import numpy as np
import pytest

from torchmetal.photos.rectify import _block_mean


@pytest.mark.parametrize("ss", [1, 2, 3, 5, 8])
def test_block_mean_is_the_block_average(ss):
    rng = np.random.default_rng(ss)
    a = rng.random((7 * ss, 9 * ss, 3), dtype=np.float32)
    got = _block_mean(a, ss)
    assert got.shape == (7, 9, 3)
    np.testing.assert_allclose(got, a.reshape(7, ss, 9, ss, 3).mean((1, 3)), rtol=0, atol=1e-6)


@pytest.mark.parametrize("ss", [2, 3, 8])
def test_block_any_and_all(ss):
    rng = np.random.default_rng(10 + ss)
    # clipped reads are bilinear mixes of 0/1 with OpenCV's 1/32 weights: the smallest non-zero is 1/1024
    clip = np.where(rng.random((6 * ss, 5 * ss, 3)) < 0.02, np.float32(1 / 1024), np.float32(0))
    assert np.array_equal(_block_mean(clip, ss) > 0, clip.reshape(6, ss, 5, ss, 3).max((1, 3)) > 0)
    seen = rng.random((6 * ss, 5 * ss)) > 0.01
    got = _block_mean(seen.astype(np.float32), ss) == 1.0
    assert np.array_equal(got, seen.reshape(6, ss, 5, ss).all((1, 3))) and not got.all()
