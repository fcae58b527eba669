"""Shared helpers of the stress suite."""

from __future__ import annotations

import dataclasses

from torchmetal.io.capture import Capture


def with_(cap: Capture, **kw) -> Capture:
    """A validated copy of ``cap`` (fresh image tensor) with the fields in ``kw`` replaced."""
    return dataclasses.replace(cap, **{"images": cap.images.clone(), **kw})
