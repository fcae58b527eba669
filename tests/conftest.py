"""The suite on two worker processes (pytest-xdist; the README's command: ``-n 2 --dist loadfile``).

Each file's tests run on one worker, so its module fixtures are built once (``loadfile``; ``loadgroup`` would let
a directory share its session fixtures too, but with pytest 9.2 it silently stops grouping: pytest-xdist issue
1386). A worker runs torch on one intra-op thread: two workers on two cores, each with two threads, would fight
over them, and most tests' tensors are small, where one thread is as fast. Without workers (``pytest`` alone)
nothing changes.
"""

from __future__ import annotations

import os


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)
