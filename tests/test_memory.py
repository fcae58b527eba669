"""Handing freed heap pages back: only for large captures, a no-op where glibc is absent."""

import sys
from types import SimpleNamespace

import pytest
import torch

from torchmetal.memory import LARGE_BYTES, STREAM_BYTES, is_large, release_free_memory, streams_geometry


@pytest.mark.parametrize("test,limit", [(is_large, LARGE_BYTES), (streams_geometry, STREAM_BYTES)])
def test_thresholds_are_on_float32_images(test, limit):
    side = 256
    shots = limit // (3 * side * side * 4)  # exactly at the threshold: not over
    at = SimpleNamespace(images=torch.empty(shots, 3, side, side, dtype=torch.float16))
    over = SimpleNamespace(images=torch.empty(shots + 1, 3, side, side, dtype=torch.float16))
    assert not test(at) and test(over)  # counted as float32 whatever the stored dtype


def test_release_returns_pages_on_glibc_and_is_harmless_elsewhere():
    x = [torch.ones(1 << 18) for _ in range(8)]  # 1 MiB each, below glibc's raised mmap threshold
    del x
    assert release_free_memory() is sys.platform.startswith("linux")
    assert release_free_memory() is sys.platform.startswith("linux")  # idempotent
