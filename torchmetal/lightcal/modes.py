"""The light calibration a fit uses (``fit --light auto|off|flash|positions|falloff|gains``): the capture's
lights, the flash's one move of every light, per-shot positions, the falloff or per-shot gains. ``auto``
(the capture's lights or the flash's move) is chosen on shots left out of the fit by
:mod:`torchmetal.select.choices` (the light choice), which then calls :func:`with_light`.

Not candidates of ``auto`` (docs/design.md §4): per-shot positions — a left-out shot's own position is an
unknown the fitted shots do not tell; the falloff — it absorbs misplaced lights; gains — a left-out shot has no
gain to predict it with.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from torchmetal.errors import InputError
from torchmetal.fit.api import fit_phong
from torchmetal.io.grid import strided_capture
from torchmetal.lightcal.estimate import calibrate, calibrate_positions
from torchmetal.lightcal.model import LightCalibration
from torchmetal.lightcal.positions import PIXELS

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

LIGHT_MODES = ("auto", "off", "flash", "positions", "falloff", "gains")
FIT = {"lobe": "phong"}  # the estimate's fits where the caller gives no model (the selection gives the final fit's)
ROUNDS = 3  # steps of the chosen calibration's estimate on all shots (a synthetic −6: −4.4 after one step)


def _skip_reason(capture: Capture) -> str | None:
    """Why no calibration can be fitted; None when it can."""
    if not bool((capture.lights[:, 3] > 0).any()):
        return "directional lights only: no falloff or position to calibrate"
    return None


def with_light(capture: Capture, mode: str, *, fit_kwargs: dict | None = None,
               max_pixels: int = PIXELS) -> tuple[Capture, LightCalibration, dict]:
    """The capture calibrated as ``mode`` asks (:data:`LIGHT_MODES` but "auto", the selection's), the
    calibration, and the report entry (the calibration's dict, the mode). The calibration is estimated on the
    capture's pixel grid (:func:`~torchmetal.io.grid.strided_capture`) with ``fit_kwargs``' fits."""
    if mode not in LIGHT_MODES or mode == "auto":
        raise InputError(f"light: expected one of {[m for m in LIGHT_MODES if m != 'auto']} here (auto is chosen by "
                         f"torchmetal.select.choices, as fit_material does), found {mode!r}")
    t0 = time.perf_counter()
    report: dict = {"mode": mode}
    chosen = mode
    if mode != "off" and (skip := _skip_reason(capture)) is not None:
        chosen = "off"
        report["skipped"] = skip
    cal = LightCalibration()
    if chosen in ("positions", "flash"):
        cal, _ = calibrate_positions(strided_capture(capture, max_pixels), fit_kwargs={**FIT, **(fit_kwargs or {})},
                                     shared=chosen == "flash")
    elif chosen != "off":
        kw = {**(fit_kwargs or {}), "lobe": "phong"}  # the falloff's measured estimate (docs/design.md §4)
        sub = strided_capture(capture, max_pixels)
        fit = fit_phong(sub, **kw)
        for step in range(ROUNDS):  # the texture absorbs part of the falloff in one step: refine
            cal, fit = calibrate(sub, fit, gains=chosen == "gains", fit_kwargs=kw, base=cal, refit=step < ROUNDS - 1)
    report.update(cal.to_dict(), time=time.perf_counter() - t0)
    return cal.apply(capture), cal, report
