"""The capture plan (issue 43): which photo next, from the fit's information and the highlight's coverage.

:func:`~torchmetal.plan.core.plan_shots` (the criterion: :mod:`torchmetal.plan.core`),
:func:`~torchmetal.plan.run.plan_directory` (CAPTURE_OR_MATERIAL → DIR/plan.json and DIR/plan.png),
the ``torchmetal plan`` verb (:mod:`torchmetal.plan.cli`).
"""
