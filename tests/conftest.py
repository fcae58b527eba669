"""The suite on two worker processes (pytest-xdist; the README's command: ``-n 2 --dist loadfile``).

Each file's tests run on one worker, so its module fixtures are built once (``loadfile``; ``loadgroup`` would let
a directory share its session fixtures too, but with pytest 9.2 it silently stops grouping: pytest-xdist issue
1386). A worker runs torch on one intra-op thread: two workers on two cores, each with two threads, would fight
over them, and most tests' tensors are small, where one thread is as fast. The files that take minutes and sit
late in collection order start first (:data:`FIRST`).
"""

from __future__ import annotations

import os
from pathlib import Path

#: files of several minutes each that come last in collection order (the two-worker run of 2026-12-07, its
#: --durations: test_pipeline.py ~5 min, test_notebooks.py ~4.5 min, beside the zoo's and the quick bench's ~4 min,
#: which come first anyway): started first, so that no worker is left alone with one at the end
FIRST = ("tests/test_pipeline.py", "tests/test_notebooks.py")


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    root = Path(__file__).parent.parent
    items.sort(key=lambda item: Path(item.path).relative_to(root).as_posix() not in FIRST)  # stable: in-file order kept
