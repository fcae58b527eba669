"""Give freed heap memory back to the operating system between the fit's stages.

glibc serves allocations below its (dynamic, up to 32 MiB) mmap threshold from the heap and keeps
what is freed there for reuse: after a stage's temporaries are gone, the process still holds
their pages, and the next stage's peak sits on top of them. ``malloc_trim(0)`` returns every free
page; the pages the next stage allocates are then faulted in again, which on a small capture costs
more than the memory is worth (docs/measurements.md). So it runs only for a large capture
(:func:`is_large`), twice: after loading and after the full-resolution LM. Elsewhere (macOS,
Windows, musl) this is a no-op.

It also sizes the fit's pixel chunks (:func:`pixels_per_chunk`): small on the CPU, where the (N, 3, chunk)
temporaries stay in cache, large on an accelerator, where every chunk costs dozens of kernel launches.
"""

from __future__ import annotations

import ctypes
import functools
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: torchmetal.io.capture imports this module
    from torchmetal.io.capture import Capture

#: a capture whose float32 images exceed this is "large": freed heap pages go back to the OS between stages.
LARGE_BYTES = 64 << 20
#: a capture whose float32 images exceed this streams its full-resolution fit's geometry
#: (:mod:`torchmetal.fit.grid_terms`): stored, it weighs 1.25× the images (1024² × 10 shots: 157 MiB)
STREAM_BYTES = 128 << 20
#: pixels per processing chunk of a fit on the CPU: its (N, 3, chunk) temporaries stay in cache
CPU_CHUNK = 4096
#: on an accelerator, the bytes of one float32 (N, 3, chunk) temporary of a fit's chunk: 4096-pixel chunks
#: made a 4096² × 16 fit ~2 million kernel launches (12.8 s on an H200, launch-bound)
DEVICE_CHUNK_BYTES = 128 << 20


def is_large(capture: Capture) -> bool:
    """Whether the capture's float32 images exceed :data:`LARGE_BYTES`."""
    return capture.images.numel() * 4 > LARGE_BYTES


def streams_geometry(capture: Capture) -> bool:
    """Whether the capture's float32 images exceed :data:`STREAM_BYTES`."""
    return capture.images.numel() * 4 > STREAM_BYTES


def pixels_per_chunk(capture: Capture) -> int:
    """The fit's default pixels per chunk: :data:`CPU_CHUNK` on the CPU, else as many as keep one float32
    (N, 3, chunk) temporary within :data:`DEVICE_CHUNK_BYTES` (16 shots: 699 050 pixels). Results do not
    depend on it."""
    if capture.images.device.type == "cpu":
        return CPU_CHUNK
    return max(CPU_CHUNK, DEVICE_CHUNK_BYTES // (4 * 3 * max(1, capture.num_shots)))


@functools.lru_cache(maxsize=1)
def _trim():
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


def release_free_memory() -> bool:
    """Return the heap's free pages to the OS (glibc); False where that is not available."""
    fn = _trim()
    if fn is None:
        return False
    fn(0)
    return True
