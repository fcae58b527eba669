"""Light calibration: nuisance parameters of the capture's lights, fitted beside the material
where asked for, or (``light="auto"``) where shots left out of the fit prefer them (docs/design.md §2.2, §4).

A phone's flash is not the isotropic point light of capture.json: it sits a centimetre or more from
where the capture put it, its beam falls off (or the phone's vignetting correction brightens the edges)
with the angle from its axis, and its power can drift from shot to shot. Three nuisances model that:

- **positions**: an offset (x, y, z) per shot's point light, fitted to its photo with the material held
  fixed and alternated with the material's fit (the lights move: the fit sees other geometry);
- **falloff**: each point light's intensity × cos(θ)^p, θ the angle between the direction from the light
  to a surface point and the light's axis (from the light to the surface centre: the phone is aimed at
  the sample); one exponent p for the capture;
- **gains**: one multiplier per shot (geometric mean 1: the texture carries the overall level).

The falloff and the gains scale a shot's irradiance per pixel, and the model is linear in irradiance, so
a calibrated capture is the photos divided by the factor and its lights moved by the offsets
(:meth:`LightCalibration.apply`). The material describes the sample, not the lights: it carries no
calibration, and a render compared with one of the capture's photos uses :meth:`LightCalibration.lights`
and is multiplied by :meth:`LightCalibration.factor` (a shot the fit did not see gets the falloff only,
:meth:`LightCalibration.for_unseen`).

- :mod:`~torchmetal.lightcal.model`: :class:`LightCalibration` (lights, factor, apply, the report's dict);
- :mod:`~torchmetal.lightcal.positions`: the offsets, by Levenberg–Marquardt per shot;
- :mod:`~torchmetal.lightcal.estimate`: the exponent and gains from a fit's log-ratio residuals, and the
  positions alternated with the fit;
- :mod:`~torchmetal.lightcal.choice`: ``light="auto"``: the capture's lights or the positions, decided on
  left-out shots (:func:`~torchmetal.fit.decision.paired_choice`); the falloff and gains only when asked for.
"""

from torchmetal.lightcal.choice import LIGHT_MODES, choose_light, with_light
from torchmetal.lightcal.model import LightCalibration

__all__ = ["LIGHT_MODES", "LightCalibration", "choose_light", "with_light"]
