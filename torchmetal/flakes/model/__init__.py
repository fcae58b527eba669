"""The flake render model: the lowest layer of :mod:`torchmetal.flakes`, what the material and its renderer
need and nothing that fits.

- :mod:`~torchmetal.flakes.model.params`: :class:`FlakeModel`, the statistical model's parameters and their
  bounds (re-exported here);
- :mod:`~torchmetal.flakes.model.field`: its deterministic flake field and the sparkle shading;
- :mod:`~torchmetal.flakes.model.observed`: the sample's own flakes and the field a material renders;
- :mod:`~torchmetal.flakes.model.md`: the paper's Metallic Difference (:func:`torchmetal.metrics.md`);
- :mod:`~torchmetal.flakes.model.filters`: box means by running sums (MD, the detector and the screen use them).

It imports nothing of the estimation (:mod:`torchmetal.flakes.estimate`), the stage and its choices, the
renderer or the metrics.
"""

from torchmetal.flakes.model.params import MAP_FIELDS, MAX_AREA_OFFSET, MAX_COLOR, MAX_DENSITY, MIN_CELL, FlakeModel

__all__ = ["FlakeModel", "MIN_CELL", "MAX_DENSITY", "MAX_COLOR", "MAX_AREA_OFFSET", "MAP_FIELDS"]
