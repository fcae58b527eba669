"""Phong fit (the source paper's section 4.1, batched, plus a joint refinement).

``fit_phong(capture, scheme="refine", specular="auto", ...) -> FitResult``; ``leave_one_out``
renders each shot from a fit on the others. Modules: :mod:`~torchmetal.fit.lm` (batched LM
primitives), :mod:`~torchmetal.fit.problem` (precomputed observations, chunked),
:mod:`~torchmetal.fit.paper` (4.1), :mod:`~torchmetal.fit.refine` (variable projection),
:mod:`~torchmetal.fit.clusters` (spatially varying specular), :mod:`~torchmetal.fit.result`.
"""

from torchmetal.fit.api import fit_phong
from torchmetal.fit.holdout import leave_one_out
from torchmetal.fit.result import ClusteredPhongModel, FitResult

__all__ = ["fit_phong", "FitResult", "ClusteredPhongModel", "leave_one_out"]
