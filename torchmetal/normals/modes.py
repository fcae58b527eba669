"""The normals a fit uses (``fit --normals auto|given|flat|estimate|relief``): the capture's own, the flat
plane, the estimate from the photos or the embossing's relief. ``auto`` is chosen on shots left out of the
fit by :mod:`torchmetal.select.choices` (the normals and relief choices), which then calls :func:`with_normals`."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import torch

from torchmetal.errors import InputError
from torchmetal.normals.estimate import estimate_normals
from torchmetal.normals.relief import with_relief

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

NORMALS_MODES = ("auto", "given", "flat", "estimate", "relief")


def with_normals(capture: Capture, mode: str, **kw: Any) -> tuple[Capture, dict]:
    """The capture with the normals ``mode`` asks for, and a report entry.

    "given": the capture's own (its normals.npy, flat (0, 0, 1) without one); "flat": (0, 0, 1) everywhere;
    "estimate": :func:`~torchmetal.normals.estimate.estimate_normals` (``kw`` passed on); "relief":
    :func:`~torchmetal.normals.relief.with_relief`. "auto" is the selection's (module docstring).

    Returns:
        (capture, report dict).
    """
    if mode not in NORMALS_MODES or mode == "auto":
        raise InputError(f"normals: expected one of {[m for m in NORMALS_MODES if m != 'auto']} here (auto is chosen "
                         f"by torchmetal.select.choices, as fit_material does), found {mode!r}")
    if mode == "given":
        return capture, {"mode": "given", "flat": capture.flat}
    if mode == "flat":
        if capture.flat:
            return capture, {"mode": "flat"}
        n = torch.zeros_like(capture.normals)
        n[2] = 1.0
        return replace(capture, normals=n), {"mode": "flat", "ignored": "the capture's normals"}
    if mode == "relief":
        return with_relief(capture)
    est = estimate_normals(capture, **kw)
    return replace(capture, normals=est.normals), est.report


__all__ = ["NORMALS_MODES", "with_normals"]
