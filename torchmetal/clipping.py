"""How a clipped channel is read: on its own ("channel": the other two channels of the observation stay
valid) or as the whole pixel's ("pixel": the observation is dropped in all three channels).

A linear sensor that clips one channel measures the other two as they are; a phone's processing (white
balance, colour matrix, highlight roll-off after the sensor clipped) leaves them wrong too. On the shared
card (cards_blue) a gold highlight clipped in red and green but not blue made the fit's gold specular white
(s 0.26 / 0.26 / 0.24; 0.22 / 0.21 / 0.15 with "pixel") and drew orange and purple rims along the foil's
embossed edges; on the zoo's synthetic captures, clipped per channel by their generator, the other
channels are exact and "pixel" discards them (two_materials 54.52 → 54.05 dB). So ``clipping="auto"``
decides it per capture on shots left out of the fit (:data:`torchmetal.select.choices.CLIPPING`): a fit
of each reading predicts held-out shots, scored on their observations with no channel clipped (valid under
either reading); "channel", the reading that keeps more data, is the reference. A capture without a partly
clipped observation keeps "channel" untested.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

from torchmetal.errors import InputError

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

CLIPPING_MODES = ("auto", "channel", "pixel")


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


def with_clipping(capture: Capture, mode: str) -> tuple[Capture, dict]:
    """The capture as ``mode`` ("channel" or "pixel"; "auto" is the selection's) reads it, and a report."""
    if mode not in CLIPPING_MODES or mode == "auto":
        raise InputError(f"clipping: expected one of {[m for m in CLIPPING_MODES if m != 'auto']} here (auto is chosen "
                         f"by torchmetal.select.choices, as fit_material does), found {mode!r}")
    return (pixel_clipped(capture) if mode == "pixel" else capture), {"mode": mode, "chosen": mode}
