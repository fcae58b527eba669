"""Small materials of every kind the engine writers handle (flat/bumpy normals, global/clustered
specular, with/without flakes), built deterministically."""

from __future__ import annotations

import itertools

import torch

from torchmetal.flakes.model import FlakeModel
from torchmetal.material import Material

H, W = 20, 24
SIZE = (0.12, 0.1)
KINDS = [f"{n}-{s}-{f}" for n, s, f in itertools.product(("flat", "bumpy"), ("global", "clustered"), ("noflakes", "flakes"))]


def make_material(kind: str, h: int = H, w: int = W) -> Material:
    normals, spec, flakes = kind.split("-")
    g = torch.Generator().manual_seed(7)
    tex = 0.1 + 0.5 * torch.rand(3, h, w, generator=g)
    n = None
    if normals == "bumpy":
        yy, xx = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
        n = torch.stack([0.2 * torch.sin(3 * xx), 0.15 * torch.cos(2 * yy), torch.ones_like(xx)])
        n = n / n.norm(dim=0, keepdim=True)
    kw = {}
    if spec == "clustered":
        labels = (torch.arange(w).view(1, w).expand(h, w) >= w // 2).long()
        kw = dict(spec_labels=labels, cluster_s=torch.tensor([[0.08, 0.1, 0.12], [0.3, 0.25, 0.2]]),
                  cluster_alpha=torch.tensor([[15.0, 15.0, 15.0], [120.0, 100.0, 80.0]]))
    fm = None
    if flakes == "flakes":
        fm = FlakeModel(0.02, area_log_mean=1.5, color_mean=(0.9, 0.8, 0.6), tilt_sigma=0.12, glint_sigma=0.05, seed=3)
    return Material(tex, torch.tensor([0.1, 0.15, 0.2]), torch.tensor([40.0, 50.0, 60.0]), SIZE, normals=n, flakes=fm, **kw)
