"""Where the development captures live: one setting for the bench, the tests and the notebooks.

The real captures used for development (``cards_blue``, ``yellow_box``, ``uw_gray_sphere``) carry no
licence, so they are never in the repository or the package. They are looked up in the directory named
by the environment variable ``TORCHMETAL_SHARED_DATA``, by default ``../shared/data`` beside the
repository root (a checkout next to the team's shared folder). Whoever needs one asks
:func:`shared_capture`, which says None when it is absent, so tests skip cleanly.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV = "TORCHMETAL_SHARED_DATA"


def shared_data_dir() -> Path:
    """The shared-data directory: ``$TORCHMETAL_SHARED_DATA``, else ``<repository>/../shared/data``."""
    env = os.environ.get(ENV)
    if env:
        return Path(env)
    return (Path(__file__).resolve().parents[2] / ".." / "shared" / "data").resolve()


def shared_capture(name: str) -> Path | None:
    """The capture directory ``name`` of the shared data, or None when it is not there."""
    d = shared_data_dir() / name
    return d if (d / "capture.json").is_file() else None
