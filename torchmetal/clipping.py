"""How a clipped channel is read: on its own ("channel": the other two channels of the observation stay
valid) or as the whole pixel's ("pixel": the observation is dropped in all three channels).

A linear sensor that clips one channel measures the other two as they are; a phone's processing (white
balance, colour matrix, highlight roll-off after the sensor clipped) leaves them wrong too. On the shared
card (cards_blue) a gold highlight clipped in red and green but not blue made the fit's gold specular white
(s 0.26 / 0.26 / 0.24; 0.22 / 0.21 / 0.15 with "pixel") and drew orange and purple rims along the foil's
embossed edges; on the zoo's synthetic captures, clipped per channel by their generator, the other
channels are exact and "pixel" discards them (two_materials 54.52 → 54.05 dB). So ``clipping="auto"``
decides it per capture on shots left out of the fit, like the normals (:mod:`torchmetal.normals.choice`):
on a pixel grid, for each group of shots, a Phong fit on the other shots read each way predicts the group;
both are scored on the group's observations with no channel clipped (valid under either reading), paired
per observation (:func:`~torchmetal.fit.decision.paired_choice`, its error lower by ``MIN_GAIN``); "channel",
the reading that keeps more data, is the reference. A capture without a partly clipped observation keeps
"channel" untested.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.fit.api import fit_phong
from torchmetal.fit.decision import MIN_GAIN_ABS, Decision, paired_choice
from torchmetal.fit.holdout import valid_mean_square, valid_pixels
from torchmetal.fit.shot_plan import shot_groups
from torchmetal.normals.choice import strided_capture

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

CLIPPING_MODES = ("auto", "channel", "pixel")
CANDIDATES = ("channel", "pixel")
PIXELS = 128 * 128  # the decision's pixel grid: clipping sits in highlights, a few of its pixels each
FOLDS = 3  # shot groups left out in turn
MIN_SHOTS = 3  # a fit on two shots beside a left-out one
# dropping data must pay for itself: below 0.5 % the zoo's flakes_orange (clipped per channel, honestly) took
# pixel (−0.42 %, z 4.8) and lost 0.35 dB against its truth; sphere_sharp72 gains 1.3 dB at −0.97 %, the card −3.2 %
MIN_GAIN = 0.005
FIT = {"lobe": "phong", "specular": "global", "noise_weights": False}  # the test fits: the paper's model


def pixel_clipped(capture: Capture) -> Capture:
    """``capture`` with each observation that has a clipped channel marked clipped in all three."""
    sat = capture.saturated
    if sat is None:
        return capture
    return replace(capture, saturated=sat.any(1, keepdim=True).expand_as(sat).contiguous())


def partly_clipped(capture: Capture) -> int:
    """How many observations (shot, pixel) have some but not all channels clipped."""
    sat = capture.saturated
    if sat is None:
        return 0
    return int((sat.any(1) & ~sat.all(1)).sum())


def _errors(fit, hold: Capture) -> Tensor:
    """(M,) float64: squared errors of ``fit``'s render of ``hold`` on its valid observations (shot-major)."""
    with torch.no_grad():
        pred = fit.render(hold.lights, hold.intensities, hold.cameras)
    return (pred - hold.images).double().square()[valid_pixels(hold)]


def _untested(reason: str) -> tuple[str, Decision]:
    """"channel", the reference, kept without a test, and its record."""
    return "channel", Decision("clipping", CANDIDATES, "channel", reference="channel", reason=reason)


def choose_clipping(capture: Capture, *, fit_kwargs: dict | None = None, max_pixels: int = PIXELS,
                    folds: int = FOLDS, **rule: float) -> tuple[str, Decision]:
    """"channel" or "pixel", decided on left-out shots (module docstring). ``rule``:
    :func:`~torchmetal.fit.decision.paired_choice`'s ``z_min`` / ``min_gain``."""
    n = int(capture.images.shape[0])
    partial = partly_clipped(capture)
    if partial == 0:
        return _untested("no observation has some but not all channels clipped")
    if n < MIN_SHOTS:
        return _untested(f"a left-out test of the clipping needs >= {MIN_SHOTS} shots, found {n}")
    kw = {**(fit_kwargs or {}), **FIT}
    sub = strided_capture(capture, max_pixels)
    readings = {"channel": sub, "pixel": pixel_clipped(sub)}
    groups = shot_groups(n, folds)
    errors: dict[str, list[Tensor]] = {k: [] for k in CANDIDATES}
    for group in groups:
        train = [k for k in range(n) if k not in group]
        hold = readings["pixel"].subset(group)  # no channel clipped: valid under either reading
        for name, cap in readings.items():
            errors[name].append(_errors(fit_phong(cap.subset(train), **kw), hold))
    cat = {k: torch.cat(e) for k, e in errors.items()}
    floor = MIN_GAIN_ABS * valid_mean_square(readings["pixel"])  # not float rounding
    d = paired_choice("clipping", cat, "channel", **{"min_gain": MIN_GAIN, "floor": floor, **rule})
    d.holds = groups
    d.pixels = int(sub.images.shape[-2] * sub.images.shape[-1])
    d.reason += f" ({partial} partly clipped observations in the capture)"
    return d.chosen, d


def with_clipping(capture: Capture, mode: str, *, fit_kwargs: dict | None = None) -> tuple[Capture, dict]:
    """The capture as ``mode`` ("auto": :func:`choose_clipping`) reads it, and a report ({"mode", "chosen",
    "decision" for auto})."""
    if mode not in CLIPPING_MODES:
        raise InputError(f"clipping: expected one of {list(CLIPPING_MODES)}, found {mode!r}")
    report: dict = {"mode": mode}
    chosen = mode
    if mode == "auto":
        chosen, d = choose_clipping(capture, fit_kwargs=fit_kwargs)
        report["decision"] = d.to_dict()
    report["chosen"] = chosen
    return (pixel_clipped(capture) if chosen == "pixel" else capture), report
