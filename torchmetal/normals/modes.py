"""The normals a fit uses (``fit --normals auto|given|flat|estimate|relief``): the capture's own, the flat
plane, the estimate from the photos, the embossing's relief, or (``auto``) the one shots left out of the
fit prefer."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import torch

from torchmetal.errors import InputError
from torchmetal.normals.choice import choose_normals, choose_relief
from torchmetal.normals.estimate import estimate_normals
from torchmetal.normals.relief import with_relief

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

NORMALS_MODES = ("auto", "given", "flat", "estimate", "relief")


def with_normals(capture: Capture, mode: str, **kw: Any) -> tuple[Capture, dict]:
    """The capture with the normals ``mode`` asks for, and a report entry.

    "auto": the capture's own when it has them, else "estimate" or "flat" as shots left out of the fit
    prefer (:func:`~torchmetal.normals.choice.choose_normals`; the report's "decision" says why), and
    where they keep flat, "relief" if they prefer it (:func:`~torchmetal.normals.choice.choose_relief`;
    the report's "relief_decision"); "given": the capture's own (its normals.npy, flat (0, 0, 1) without
    one); "flat": (0, 0, 1) everywhere; "estimate": :func:`~torchmetal.normals.estimate.estimate_normals`
    (``kw`` passed on); "relief": :func:`~torchmetal.normals.relief.with_relief`.

    Returns:
        (capture, report dict).
    """
    if mode not in NORMALS_MODES:
        raise InputError(f"normals: expected one of {list(NORMALS_MODES)}, found {mode!r}")
    if mode == "auto":
        t0 = time.perf_counter()
        chosen, decision = choose_normals(capture, fit_kwargs=kw.get("fit_kwargs"))
        record = {"decision": decision.to_dict(), "decision_time": time.perf_counter() - t0}
        if chosen == "flat":
            t0 = time.perf_counter()
            chosen, relief = choose_relief(capture)
            record |= {"relief_decision": relief.to_dict(), "relief_decision_time": time.perf_counter() - t0}
        cap, report = with_normals(capture, chosen, **kw)
        return cap, {**report, "mode": "auto", "chosen": chosen, **record}
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
