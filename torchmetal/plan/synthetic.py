"""Take the planned photos of a synthetic scene: render them from its truth, as a phone would take them.

``take_shots(capture, case, lights, cameras, intensities, rng) -> Capture``: ``capture`` with K more shots of
the zoo ``case`` (:func:`torchmetal.synth.zoo.make_case`) rendered from the truth at the given positions
(lights, cameras (K, 4), intensities (K, 3)) with the scene's noise, clipping and encoding — the same as its
own shots. For the capture plan's proof (``torchmetal.bench.plan``) and its walkthrough (notebooks/08_plan).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchmetal.io.capture import Capture


def take_shots(capture: Capture, case, lights: Tensor, cameras: Tensor, intensities: Tensor,
               rng: np.random.Generator, names: list[str] | None = None) -> Capture:
    """``capture`` with one shot per row of ``lights``/``cameras`` (K, 4) and ``intensities`` (K, 3) appended."""
    from torchmetal.synth.zoo_render import _encode, decode, render_clean

    imgs, sats = [], []
    for lt, cm, it in zip(lights.double().numpy(), cameras.double().numpy(), intensities.double().numpy()):
        lin, sat = decode(_encode(render_clean(case.truth, lt, it, cm), case.scene, rng), case.scene.encoding)
        imgs.append(torch.as_tensor(lin.astype(np.float32)))
        sats.append(torch.as_tensor(sat))
    dt = capture.images.dtype
    cat = lambda t, x: torch.cat([t, x.to(t.dtype)])  # noqa: E731
    k = int(lights.shape[0])
    return Capture(images=cat(capture.images, torch.stack(imgs)), normals=capture.normals, mask=capture.mask,
                   lights=cat(capture.lights, lights), intensities=cat(capture.intensities, intensities),
                   cameras=cat(capture.cameras, cameras), size=capture.size,
                   saturated=torch.cat([capture.saturated, torch.stack(sats).to(capture.saturated.dtype)]),
                   names=[*capture.names, *(names or [f"taken{i + 1}" for i in range(k)])],
                   color_space=capture.color_space).to(dtype=dt)
