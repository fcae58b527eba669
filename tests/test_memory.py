"""Handing freed heap pages back: only for large captures, a no-op where glibc is absent."""

import sys
from types import SimpleNamespace

import pytest
import torch

from torchmetal.memory import (
    CPU_CHUNK,
    DEVICE_CHUNK_BYTES,
    LARGE_BYTES,
    STREAM_BYTES,
    is_large,
    pixels_per_chunk,
    release_free_memory,
    streams_geometry,
)


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


def test_pixels_per_chunk_small_on_the_cpu_large_on_an_accelerator():
    cpu = SimpleNamespace(images=torch.empty(16, 3, 8, 8), num_shots=16)
    assert pixels_per_chunk(cpu) == CPU_CHUNK == 4096
    dev = SimpleNamespace(images=torch.empty(16, 3, 8, 8, device="meta"), num_shots=16)
    assert pixels_per_chunk(dev) == DEVICE_CHUNK_BYTES // (4 * 3 * 16) == 699050  # one (16, 3, chunk) float32: 128 MiB
    many = SimpleNamespace(images=torch.empty(10**5, 3, 1, 1, device="meta"), num_shots=10**5)
    assert pixels_per_chunk(many) == CPU_CHUNK  # never below the CPU's chunk
