"""Handing freed heap pages back: only for large captures, a no-op where glibc is absent."""

import sys
from types import SimpleNamespace

import torch

from torchmetal.memory import LARGE_BYTES, is_large, release_free_memory


def test_large_is_float32_images_above_the_threshold():
    side = 256
    shots = LARGE_BYTES // (3 * side * side * 4)  # exactly at the threshold: not large
    at = SimpleNamespace(images=torch.empty(shots, 3, side, side, dtype=torch.float16))
    over = SimpleNamespace(images=torch.empty(shots + 1, 3, side, side, dtype=torch.float16))
    assert not is_large(at) and is_large(over)  # counted as float32 whatever the stored dtype


def test_release_returns_pages_on_glibc_and_is_harmless_elsewhere():
    x = [torch.ones(1 << 18) for _ in range(8)]  # 1 MiB each, below glibc's raised mmap threshold
    del x
    assert release_free_memory() is sys.platform.startswith("linux")
    assert release_free_memory() is sys.platform.startswith("linux")  # idempotent
