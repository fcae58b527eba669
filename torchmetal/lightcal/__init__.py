"""Light calibration: nuisance parameters of the capture's lights, fitted beside the material
where asked for, or (``light="auto"``) where shots left out of the fit prefer them (docs/design.md §2.2, §4).

A phone's flash is not the isotropic point light of capture.json: it sits a centimetre or more from
where the capture put it, its beam falls off (or the phone's vignetting correction brightens the edges)
with the angle from its axis, and its power can drift from shot to shot. Four nuisances model that:

- **flash**: one offset (x, y, z) of every point light (the flash beside the lens, where the capture put
  it elsewhere: the same move in every shot, and in shots the fit did not see);
- **positions**: an offset per shot's point light, fitted to its photo;
- **falloff**: each point light's intensity × cos(θ)^p, θ the angle between the direction from the light
  to a surface point and the light's axis (from the light to the surface centre: the phone is aimed at
  the sample); one exponent p for the capture;
- **gains**: one multiplier per shot (geometric mean 1: the texture carries the overall level).

The offsets are fitted with the material held fixed and alternated with the material's fit (the lights
move: the fit sees other geometry). The falloff and the gains scale a shot's irradiance per pixel, and
the model is linear in irradiance, so a calibrated capture is the photos divided by the factor and its
lights moved (:meth:`LightCalibration.apply`). The material describes the sample, not the lights: it
carries no calibration, and a render compared with one of the capture's photos uses
:meth:`LightCalibration.lights` and is multiplied by :meth:`LightCalibration.factor` (a shot the fit did
not see gets the flash's move and the falloff, :meth:`LightCalibration.for_unseen`).

- :mod:`~torchmetal.lightcal.model`: :class:`LightCalibration` (lights, factor, apply, the report's dict);
- :mod:`~torchmetal.lightcal.positions`: the offsets, by Levenberg–Marquardt per shot or shared;
- :mod:`~torchmetal.lightcal.estimate`: the exponent and gains from a fit's log-ratio residuals, and the
  offsets alternated with the fit;
- :mod:`~torchmetal.lightcal.modes`: the calibration a fit uses, by mode (:func:`with_light`); ``light="auto"``
  (the capture's lights or the flash's move) is decided on left-out shots by :mod:`torchmetal.select.choices`.
"""

from torchmetal.lightcal.model import LightCalibration
from torchmetal.lightcal.modes import LIGHT_MODES, with_light

__all__ = ["LIGHT_MODES", "LightCalibration", "with_light"]
