"""Normals from the photos: per-pixel photometric stereo with the known lights, refined with the
Phong terms (``fit --normals``; docs/design.md §2.2, the choice in §4).

Modules: the estimate, the core its steps share, the steps in the order they run, and the modes:

* :mod:`~torchmetal.normals.estimate`: :func:`estimate_normals`, the whole estimate stage by stage;
* :mod:`~torchmetal.normals.core`: what the steps share (row chunks of observations, normals ↔ surface
  gradients, the model and its Jacobian, robust weights, scales and costs);
* :mod:`~torchmetal.normals.lambert`: the robust Lambertian start;
* :mod:`~torchmetal.normals.refine`: the per-pixel robust refinement (:func:`refine_normals`);
* :mod:`~torchmetal.normals.joint`: the normals jointly with the global s, α (:func:`joint_refine`,
  :func:`try_weak_lobe`);
* :mod:`~torchmetal.normals.restart`: second chances for pixels in a wrong minimum (:func:`restart_and_settle`);
* :mod:`~torchmetal.normals.median`: the neighbourhood's normal where it explains a pixel as well
  (:func:`median_where_as_good`);
* :mod:`~torchmetal.normals.flat`: flat where the photos cannot tell (:func:`flat_where_unresolved`), and the tilt
  it could not reject (:func:`unrejected_tilt_deg`);
* :mod:`~torchmetal.normals.relief`: an embossing's relief, a high-passed height field fitted with the
  global Phong terms (:func:`with_relief`);
* :mod:`~torchmetal.normals.modes`: the normals a fit uses, by mode (:func:`with_normals`); ``normals="auto"``
  is decided on left-out shots by :mod:`torchmetal.select.choices` (normals, relief).
"""

from torchmetal.normals.estimate import NormalsEstimate, angular_error, estimate_normals
from torchmetal.normals.flat import flat_where_unresolved, unrejected_tilt_deg
from torchmetal.normals.joint import joint_refine, try_weak_lobe
from torchmetal.normals.median import median_where_as_good
from torchmetal.normals.modes import NORMALS_MODES, with_normals
from torchmetal.normals.refine import refine_normals
from torchmetal.normals.relief import with_relief
from torchmetal.normals.restart import restart_and_settle

__all__ = [
    "NORMALS_MODES", "NormalsEstimate", "estimate_normals", "with_normals", "with_relief",
    "refine_normals", "joint_refine", "try_weak_lobe", "restart_and_settle", "median_where_as_good",
    "flat_where_unresolved", "unrejected_tilt_deg", "angular_error",
]
