"""Metallic flakes, by layer.

- :mod:`torchmetal.flakes.model` (low): the render model: the statistical model, its deterministic field,
  the observed flakes and MD. The material, the renderer and the metrics import it.
- :mod:`torchmetal.flakes.estimate` (middle): detection and statistics, from a capture and its Phong renders.
- here (high, above the renderer): the stage (:mod:`~torchmetal.flakes.stage`: detect → associate → fit) and
  the choices made on left-out shots (:mod:`~torchmetal.flakes.choice`: observed flakes, flakes or none;
  :mod:`~torchmetal.flakes.density_choice`: a density map), which render candidates to compare them; and
  :mod:`~torchmetal.flakes.run`, the stage as the pipeline runs it (refits away from the glints, the choices).

A layer imports only the ones below it. The names exported here are the render model's.
"""

from torchmetal.flakes.model.field import FlakeField, flake_field, sparkle_render, sparkle_shading
from torchmetal.flakes.model.params import FlakeModel

__all__ = ["FlakeModel", "FlakeField", "flake_field", "sparkle_shading", "sparkle_render"]
