"""Model selection: every choice beyond the paper's model is made on shots the fit did not see.

- :mod:`~torchmetal.select.rule`: the paired rule on held-out errors and the :class:`~torchmetal.select.rule.Decision`
  record every choice leaves;
- :mod:`~torchmetal.select.plan`: which shots the choices leave out (one plan per capture);
- :mod:`~torchmetal.select.harness`: a choice declared (:class:`~torchmetal.select.harness.Choice`: its candidates,
  the simplest first, how a candidate is fitted, its error measure, its screen) and the one harness that runs it
  (grid, folds, candidate fits, pairing, futility stop, the record);
- :mod:`~torchmetal.select.choices`: the choices made before the Phong fit (registration, clipping, normals, relief, light),
  each declared there and registered in :data:`~torchmetal.select.choices.PREFIT`.

This ``__init__`` imports nothing: the rule and the plan sit below the fit (the fit's own choices use them),
the harness and the choices above it.
"""
