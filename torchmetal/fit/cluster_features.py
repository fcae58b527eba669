"""How the pixels of a clustered specular are grouped: per-pixel features and their k-means labeler.

Features, standardised:
- colour of T_min = min_k I_k/(E·n·l)_k (the paper's 4.1.6 texture bound, which highlights
  barely touch): log luminance and two chromaticities, at full resolution;
- specular: log(s_p/s) and β_p − β of a per-pixel Gauss–Newton step away from the global fit
  (pooled over 3×3 neighbours), on the selection subsample, sampled bilinearly elsewhere.
A :class:`Labeler` (nearest centroid of :func:`kmeans`) labels any pixel from its T_min and position, so labels drawn
on a subsample carry to the full resolution. Which feature set and K are kept is :mod:`torchmetal.fit.clusters`'.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.fit.lm import solve_2x2
from torchmetal.fit.problem import Observations
from torchmetal.fit.refine import SpecFit, spec_sums


def colour_features(t: Tensor, eps: float) -> Tensor:
    """(3, c) texture → (c, 3) features: log luminance and two chromaticities."""
    t = t.clamp_min(0.0)
    lum = t.mean(0)
    chroma = t[:2] / (3.0 * lum + eps)
    return torch.stack([torch.log(lum + eps), chroma[0], chroma[1]], -1)


@dataclass
class SpecFeatureMap:
    """Per-pixel specular features on a coarse grid, sampled bilinearly at any pixel.

    ``maps`` (2, h, w): log(s_p/s) and β_p − β of a per-pixel Gauss–Newton step from the global
    fit (pooled over 3×3 neighbours, 0 where a pixel shows no highlight); grid pixel (r, c) is
    full-resolution pixel (off + r·stride, off + c·stride).
    """

    maps: Tensor
    stride: int
    off: int

    def sample(self, ij: Tensor) -> Tensor:
        """(2, c) full-resolution (row, col) → (c, 2) features."""
        h, w = self.maps.shape[-2:]
        y = (ij[0] - self.off) / self.stride
        x = (ij[1] - self.off) / self.stride
        gx = 2.0 * x / max(w - 1, 1) - 1.0
        gy = 2.0 * y / max(h - 1, 1) - 1.0
        grid = torch.stack([gx, gy], -1).view(1, 1, -1, 2).to(self.maps.dtype)
        out = F.grid_sample(self.maps.unsqueeze(0), grid, mode="bilinear", padding_mode="border", align_corners=True)
        return out[0, :, 0].T


def spec_feature_map(obs: Observations, fit: SpecFit, stride: int) -> SpecFeatureMap:
    """Per-pixel specular features of ``obs`` (an h×w grid of the given stride) at the global fit."""
    st, _, _ = spec_sums(obs, fit.alpha[:1], per_pixel=True)  # (6, 3, P)
    h, w = obs.height, obs.width
    st = F.avg_pool2d(st.reshape(18, 1, h, w).double(), 3, stride=1, padding=1, count_include_pad=False).reshape(6, 3, h * w)
    B, C, Bc, Cc, Yc, _ = st.unbind(0)
    s = fit.s[0].view(3, 1).double().clamp_min(1e-12)
    # per-pixel Gauss–Newton step on (s, β) from the global terms: H [δs, δβ] = Jᵀr
    ds, db = solve_2x2(C, s * Bc, s * s * Cc, -(B - s * C), -(s * (Yc - s * Bc)))
    energy = s * s * C
    ref = energy[energy > 0].median() if bool((energy > 0).any()) else energy.new_ones(())
    wgt = (energy / ref.clamp_min(1e-300)).clamp(0.0, 1.0)  # evidence weight per pixel and channel
    wsum = wgt.sum(0).clamp_min(1e-12)
    f_s = (wgt * torch.log((s + ds).clamp_min(0.05 * s) / s).clamp(-2.0, 2.0)).sum(0) / wsum
    f_b = (wgt * db.clamp(-2.0, 2.0)).sum(0) / wsum
    keep = wgt.amax(0) > 1e-3
    maps = torch.stack([torch.where(keep, f_s, torch.zeros_like(f_s)), torch.where(keep, f_b, torch.zeros_like(f_b))])
    off = stride // 2 if stride > 1 else 0
    return SpecFeatureMap(maps.reshape(2, h, w).to(obs.dtype), stride, off)


FEATURE_SETS = {"colour": (0, 1, 2), "specular": (3, 4), "both": (0, 1, 2, 3, 4)}


@dataclass
class Labeler:
    """Nearest-centroid labels; callable on (T_min (3, c), pixel coordinates (2, c)) → (c,) int64.

    Features: colour of T_min (3) and the specular feature map sampled at the pixel (2),
    standardised with ``mean``/``std``; only ``dims`` take part.
    """

    centroids: Tensor  # (K, len(dims))
    mean: Tensor  # (5,)
    std: Tensor  # (5,)
    dims: tuple[int, ...]
    eps: float
    spec: SpecFeatureMap | None = None
    name: str = "colour"

    @property
    def k(self) -> int:
        return int(self.centroids.shape[0])

    def features(self, tmin: Tensor, ij: Tensor) -> Tensor:
        f = colour_features(tmin, self.eps)
        sp = self.spec.sample(ij) if self.spec is not None else torch.zeros(f.shape[0], 2, dtype=f.dtype, device=f.device)
        return torch.cat([f, sp.to(f.dtype)], -1)

    def __call__(self, tmin: Tensor, ij: Tensor) -> Tensor:
        f = (self.features(tmin, ij).to(self.centroids.dtype) - self.mean) / self.std
        return torch.cdist(f[:, list(self.dims)], self.centroids).argmin(-1)


def kmeans(x: Tensor, k: int, *, iters: int = 30, seed: int = 0) -> tuple[Tensor, Tensor]:
    """Lloyd's k-means with k-means++ seeding. x (P, F) → centroids (K, F), labels (P,)."""
    gen = torch.Generator(device=x.device).manual_seed(seed)
    p = x.shape[0]
    cent = x[torch.randint(p, (1,), generator=gen, device=x.device)]
    for _ in range(1, k):
        d2 = torch.cdist(x, cent).amin(-1) ** 2
        if float(d2.sum()) <= 0:
            break
        pick = torch.multinomial(d2 / d2.sum(), 1, generator=gen)
        cent = torch.cat([cent, x[pick]])
    labels = torch.cdist(x, cent).argmin(-1)
    for _ in range(iters):
        kk = cent.shape[0]
        cnt = torch.bincount(labels, minlength=kk).to(x.dtype)
        sums = torch.zeros(kk, x.shape[1], dtype=x.dtype, device=x.device).index_add_(0, labels, x)
        cent = torch.where(cnt[:, None] > 0, sums / cnt.clamp_min(1)[:, None], cent)
        new = torch.cdist(x, cent).argmin(-1)
        if bool((new == labels).all()):
            break
        labels = new
    return cent, labels


def grid_coords(obs_h: int, obs_w: int, stride: int, device: torch.device) -> Tensor:
    """(2, h·w) full-resolution (row, col) of the pixels of a strided grid."""
    off = stride // 2 if stride > 1 else 0
    r = off + torch.arange(obs_h, device=device) * stride
    c = off + torch.arange(obs_w, device=device) * stride
    rr, cc = torch.meshgrid(r, c, indexing="ij")
    return torch.stack([rr.reshape(-1), cc.reshape(-1)])


def make_labeler(tmin: Tensor, ij: Tensor, usable: Tensor, k: int, *, spec: SpecFeatureMap | None,
                 features: str = "colour", seed: int = 0) -> Labeler:
    """Fit a K-cluster :class:`Labeler` on the pixels ``usable`` (P,) of T_min (3, P) at ``ij`` (2, P)."""
    sel = usable if bool(usable.any()) else torch.ones_like(usable)
    t, pos = tmin[:, sel], ij[:, sel]
    eps = 0.05 * float(t.clamp_min(0).mean(0).median()) + 1e-12
    lab = Labeler(torch.zeros(k, 1), torch.zeros(5), torch.ones(5), FEATURE_SETS[features], eps, spec, features)
    f = lab.features(t, pos.to(t.dtype)).double()
    mean = f.mean(0) if f.shape[0] > 1 else torch.zeros(5, dtype=f.dtype, device=f.device)
    std = f.std(0).clamp_min(1e-6) if f.shape[0] > 1 else torch.ones(5, dtype=f.dtype, device=f.device)
    z = ((f - mean) / std)[:, list(lab.dims)]
    if z.shape[0] > 20000:  # k-means on a fixed-size sample; labels come from the centroids
        z = z[:: z.shape[0] // 20000 + 1]
    cent, _ = kmeans(z, k, seed=seed)
    lab.centroids, lab.mean, lab.std = cent, mean, std
    return lab
