"""Flake estimation: the middle layer of :mod:`torchmetal.flakes`, from a capture and its Phong renders to
the flake model's statistics. It uses the render model (:mod:`torchmetal.flakes.model`) and never the
renderer; the stage and the choices made on left-out shots sit above it.

- is it worth looking? :mod:`~torchmetal.flakes.estimate.prescreen` (a pixel screen),
  :mod:`~torchmetal.flakes.estimate.null_test` (detections against their mirror),
  :mod:`~torchmetal.flakes.estimate.rim` and :mod:`~torchmetal.flakes.estimate.lobe_core` (where not to look);
- detection: :mod:`~torchmetal.flakes.estimate.detect`, :mod:`~torchmetal.flakes.estimate.regions`,
  :mod:`~torchmetal.flakes.estimate.results` (the particle table), :mod:`~torchmetal.flakes.estimate.overlay`
  (pictures of it), :mod:`~torchmetal.flakes.estimate.texture` (the texture without the glints);
- statistics: :mod:`~torchmetal.flakes.estimate.shot_geometry`, :mod:`~torchmetal.flakes.estimate.association`,
  :mod:`~torchmetal.flakes.estimate.glint_model`, :mod:`~torchmetal.flakes.estimate.visibility`,
  :mod:`~torchmetal.flakes.estimate.likelihood`, :mod:`~torchmetal.flakes.estimate.shape_colour`,
  :mod:`~torchmetal.flakes.estimate.stats`;
- where and which: :mod:`~torchmetal.flakes.estimate.density_map` (a density map),
  :mod:`~torchmetal.flakes.estimate.observed_flakes` and :mod:`~torchmetal.flakes.estimate.placement`
  (the sample's own flakes).
"""
