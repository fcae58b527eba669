"""Score the sample's own flakes (:mod:`torchmetal.flakes.model.observed`) on held-out shots of a zoo flake scene.

For a fitted material on a :class:`~torchmetal.synth.zoo.ZooCase`, three renders of the held-out
shots are compared with their clean truth: ``none`` (no sparkles), ``statistical`` (the hash field
alone: the material without its observed flakes) and ``observed`` (the material as fitted). Numbers:
PSNR (linear, peak 1), MD (:func:`torchmetal.metrics.md`), and for the glints themselves
:func:`torchmetal.bench.scoring.glint_scores`.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

from torchmetal.bench.scoring import glint_scores
from torchmetal.bench.zoo import _psnr, render_material

if TYPE_CHECKING:  # annotations only: a real import would load torch (this module imports numpy only)
    from torchmetal.material import Material


def score_observed(case, material: Material) -> dict:
    """{"none", "statistical", "observed"} → {"psnr", "md", and for the flake renders the glint scores}."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.metrics import md
    from torchmetal.synth.zoo_render import held_out_renders

    args = (case.held_lights, case.held_intensities, case.held_cameras)
    none = render_material(material, *args, flakes=False)
    base = held_out_renders(case, flakes=False)
    out = {"observed_count": 0 if material.observed_flakes is None else len(material.observed_flakes),
           "density_map": material.observed_flakes is not None and material.observed_flakes.density is not None}
    renders = {"none": none}
    if material.flakes is not None:
        renders["statistical"] = render_material(replace(material, observed_flakes=None), *args)
        if material.observed_flakes is not None:
            renders["observed"] = render_material(material, *args)
    for name, pred in renders.items():
        row = {"psnr": _psnr(pred, case.clean), "md": float(md(torch.from_numpy(pred), torch.from_numpy(case.clean)))}
        if name != "none" and case.truth.flakes is not None:
            row.update(glint_scores(case.clean, base, pred, none))
        out[name] = row
    return out
