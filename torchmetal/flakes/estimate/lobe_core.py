"""Where the coating's own highlight is: the core of its fitted lobe.

A lobe of the wrong shape (a GGX or a measured highlight fitted by Phong, a sharp lobe on curved normals)
leaves compact positive peaks at the centre of every highlight, where the truth is more peaked than the
fit, and a shallow negative ring around them: in the residual they look like glints, and their mirror is
no blob at all. The screen and the null test therefore leave out the pixel-shots where the fitted lobe is
at least :data:`CORE_LEVEL` of its peak — the core of the coating's own highlight. Glints elsewhere (a
flake's normal is tilted away from the surface's) are still counted; only glints inside the highlight's
core are lost to the test, which a sample with flakes has in every other shot.

The core is kept small: on the zoo's sphere_sharp72 leaving out the pixel-shots within 3 % of the peak
already turns the screen's excess of positive outliers (26 vs 8 above SNR 20) into a deficit, while a
core at a quarter of the peak also took the glints of flakes_b at 160² (a ring of lights whose
highlights all fall near the centre, where its flakes glint) and failed it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.geometry import shading_geometry
from torchmetal.lobes import lobe_value

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.flakes.estimate.results import Particles
    from torchmetal.io.capture import Capture


CORE_LEVEL = 0.9  # fraction of the lobe's peak above which a pixel-shot is in the highlight's core
LOG_CORE = math.log(CORE_LEVEL)


def lobe_core_at(fit: FitResult, capture: Capture, shot: Tensor, row: Tensor, col: Tensor) -> Tensor:
    """Whether each pixel-shot (shot, row, col) (P,) lies in the core of the fit's highlight: (P,) bool.

    The lobe (:func:`~torchmetal.lobes.lobe_value`, the fit's own lobe and α, per pixel where the fit has
    maps) is evaluated at the P points only; channels count by their widest lobe. A fit without a
    specular (s = 0 everywhere) has no core."""
    p = shot.numel()
    s, alpha = fit.specular_maps()
    if p == 0 or not bool((s != 0).any()):
        return torch.zeros(p, dtype=torch.bool, device=shot.device)
    h, w = fit.texture.shape[-2:]
    dt = torch.float32
    row, col = row.clamp(0, h - 1), col.clamp(0, w - 1)
    x = ((col.to(dt) + 0.5) / w - 0.5) * fit.size[0]
    y = (0.5 - (row.to(dt) + 0.5) / h) * fit.size[1]
    points = torch.stack([x, y, torch.zeros_like(x)]).view(3, p, 1)
    normals = fit.normals.to(dt)
    normals = normals[:, row, col].view(3, p, 1) if normals.dim() == 3 and normals.shape[-2:] == (h, w) \
        else normals.reshape(3, 1, 1).expand(3, p, 1)
    alpha = alpha.to(dt)
    alpha = alpha[:, row, col].view(3, p, 1) if alpha.dim() == 3 else alpha
    out = torch.zeros(p, dtype=torch.bool, device=shot.device)
    for k in torch.unique(shot).tolist():  # one geometry per shot, over its own points only
        sel = torch.nonzero(shot == k, as_tuple=True)[0]
        geom = shading_geometry(normals[:, sel], capture.lights[k : k + 1].to(dt),
                                capture.intensities[k : k + 1].to(dt), capture.cameras[k : k + 1].to(dt),
                                points=points[:, sel])
        a = alpha[:, sel] if alpha.dim() == 3 else alpha
        lobe = lobe_value(fit.lobe, geom, a)  # (1, 3, P_k, 1)
        lit = geom.n_dot_l[0, 0, :, 0] > 0
        out[sel] = lit & (lobe[0].amax(0)[:, 0] >= CORE_LEVEL)
    return out


def drop_core(fit: FitResult, capture: Capture, particles: Particles) -> Particles:
    """``particles`` without those whose centre lies in the core of the fit's highlight in their shot."""
    core = lobe_core_at(fit, capture, particles.shot, particles.cy.floor().long(), particles.cx.floor().long())
    return particles.select(torch.nonzero(~core, as_tuple=True)[0]), int(core.sum())
