"""The fit report's measurements of the capture against the fitted material: each shot's registration
(:mod:`torchmetal.registration`) and the map of the pixels whose shots disagree with the model beyond the
noise (:mod:`torchmetal.report.disagreement`), written beside the material as ``disagreement.png``.

They read the result, they never change it: ``torchmetal fit`` calls :func:`add_fit_maps` after the fit and before
saving (the report layer sits above the pipeline, docs/design.md §4 keeps the fit's choices its own).
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
import torch.nn.functional as F

from torchmetal.io.capture import Capture
from torchmetal.lobes import lobe_render
from torchmetal.material import DISAGREEMENT_FILE
from torchmetal.registration import shot_shifts, unregistrable, valid_observations
from torchmetal.report.disagreement import disagreement_map, disagreement_png

__all__ = ["add_fit_maps", "fit_maps", "DISAGREEMENT_PNG"]

DISAGREEMENT_PNG = DISAGREEMENT_FILE  # its name in the material directory (save_material carries it: Material.disagreement_png)


def fit_renders(capture: Capture, result) -> torch.Tensor:
    """(N, 3, H, W) the fitted material's render of each shot as the fit saw it: the light calibration's
    lights and factor (``result.light``), without the sparkles: their random positions match no photo's glints
    (the map's median over the shots leaves a glint out either way), and they cost 4× the coat's render."""
    light = getattr(result, "light", None)
    lights = capture.lights if light is None else light.lights(capture)
    m = result.material
    s, alpha = m.specular_maps()
    dt = torch.float32
    with torch.no_grad():  # the coat as the fit renders it (lobes.lobe_render; the ONNX renderer's model, not its ops)
        pred = lobe_render(m.texture.to(dt), s.to(dt), alpha.to(dt), m.flat_normals().to(dt), lights.to(dt),
                           capture.intensities.to(dt), capture.cameras.to(dt), m.size, m.lobe)
        if light is not None:
            pred = pred * light.factor(capture)
    return pred.detach().float().cpu()


def fit_maps(capture: Capture, result) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The report entries ``registration`` and ``disagreement`` (``render`` in the latter: {"time": the seconds of
    the renders the map needs}), the (H', W') disagreement map and the first photo at the map's size."""
    valid = valid_observations(capture)
    why = unregistrable(capture)
    registration = shot_shifts(capture.images, valid) if why is None else {"measured": False, "reason": why}
    t0 = time.perf_counter()
    renders = fit_renders(capture, result)
    render_time = time.perf_counter() - t0
    marked, summary = disagreement_map(capture.images, renders, valid)
    f = summary["factor"]
    photo = capture.images[0].float().cpu()
    if f > 1:
        photo = F.avg_pool2d(photo[None, :, : marked.shape[0] * f, : marked.shape[1] * f], f)[0]
    summary["render"] = {"time": render_time}
    return {"registration": registration, "disagreement": summary}, marked, photo


def add_fit_maps(result, capture: Capture, png: str | Path) -> Path:
    """Add ``registration`` and ``disagreement`` to ``result.material.report`` and write the map to ``png``
    (to be copied into the material directory as :data:`DISAGREEMENT_PNG`); returns ``png``."""
    entries, marked, photo = fit_maps(capture, result)
    entries["disagreement"]["file"] = DISAGREEMENT_PNG
    result.material.report.update(entries)
    return disagreement_png(png, marked, photo)
