"""Score the sample's own flakes (:mod:`torchmetal.flakes.model.observed`) on held-out shots of a zoo flake scene.

For a fitted material on a :class:`~torchmetal.synth.zoo.ZooCase`, three renders of the held-out
shots are compared with their clean truth: ``none`` (no sparkles), ``statistical`` (the hash field
alone: the material without its observed flakes) and ``observed`` (the material as fitted). Numbers:
PSNR (linear, peak 1), MD (:func:`torchmetal.metrics.md`), and for the glints themselves — each
image minus its own flake-free render, with the same fixed noise (σ = ``NOISE``) added to truth and
prediction so that ``sparkle_count``'s robust σ is that of a photo — the sparkle count ratio
pred/truth over all held-out shots and the share of the truth's glints (blobs above k·σ) with a
predicted glint centroid within 2 px.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.bench.zoo import _psnr, render_material

if TYPE_CHECKING:  # annotations only: a real import would load torch (this module imports numpy only)
    from torchmetal.material import Material

NOISE = 0.005  # σ of the fixed noise the glint residuals are counted in
MATCH_PX = 2.0


def _blobs(res: np.ndarray, k: float = 5.0) -> np.ndarray:
    """(B, 2) centroids (row, col) of the 8-connected blobs of one (3, H, W) residual above k·σ (as sparkle_count)."""
    import cv2

    x = res.max(0)
    sigma = 1.4826 * np.median(np.abs(res - np.median(res)))
    bright = (x - np.median(res) > k * sigma).astype(np.uint8)
    n, _, _, cent = cv2.connectedComponentsWithStats(bright, connectivity=8)
    return cent[1:, ::-1]


def glint_scores(truth: np.ndarray, truth_base: np.ndarray, pred: np.ndarray, pred_base: np.ndarray,
                 seed: int = 0) -> dict:
    """Sparkle count ratio and share of truth glints matched within MATCH_PX, over (S, 3, H, W) shots."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.metrics import sparkle_count

    rng = np.random.default_rng(seed)
    nt = npred = matched = 0
    for k in range(len(truth)):
        noise = rng.normal(0.0, NOISE, truth[k].shape)
        rt, rp = truth[k] - truth_base[k] + noise, pred[k] - pred_base[k] + noise
        nt += sparkle_count(rt)
        npred += sparkle_count(rp)
        ct, cp = _blobs(rt), _blobs(rp)
        if len(ct) and len(cp):
            d = np.sqrt(((ct[:, None] - cp[None]) ** 2).sum(-1)).min(1)
            matched += int((d <= MATCH_PX).sum())
    return {"truth_sparkles": nt, "pred_sparkles": npred, "count_ratio": npred / max(nt, 1),
            "within_2px": matched / max(nt, 1)}


def score_observed(case, material: Material) -> dict:
    """{"none", "statistical", "observed"} → {"psnr", "md", and for the flake renders the glint scores}."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.metrics import md
    from torchmetal.synth.zoo_render import render_clean

    args = (case.held_lights, case.held_intensities, case.held_cameras)
    none = render_material(material, *args, flakes=False)
    base = np.stack([render_clean(case.truth, lt, e, c, flakes=False) for lt, e, c in zip(*args)]).astype(np.float32)
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
