"""The lobes of :mod:`torchmetal.lobes` in the batched fit's per-observation form.

The fit writes the specular basis of shot k, pixel p as b = i·u·exp(λ(α)) and needs
t = ∂λ/∂β (β = log α) for its Gauss–Newton terms (:mod:`torchmetal.fit.refine`). With the
per-observation ``L`` (N, 1, P) of :class:`~torchmetal.fit.problem.Observations`, and for GGX the
extra geometry ``geo`` (N, 3, P):

- ``phong``: L = log max(r·v, 0), λ = α·L, t = α·L (docs/design.md §2.2, unchanged);
- ``blinn``: L = log max(n·h, 0), λ = α·L, t = α·L — the same algebra on another cosine;
- ``ggx``: L = log F̂(v·h) (α-free Fresnel factor; ``LOG_OFF`` where n·v ≤ 0), geo = (1 − n·h,
  n·l, n·v) with placeholder 1 where n·l ≤ 0 or n·v ≤ 0 (u = 0 or L = LOG_OFF gate those), and
  λ = L + log core(k), t = ∂ log core/∂β from :func:`torchmetal.lobes.ggx_log_core`.

So everything the fit derives from b and t — variable projection, LM, IRLS, clusters, the
held-out checks — works for every lobe unchanged. A GGX lobe has heavy tails (never below
e⁻⁴⁰ where it is seen), so its chunks are never skipped; Blinn's are, as Phong's.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmetal.lobes import LOBES, check_lobe, fresnel_ratio, ggx_k, ggx_log_core

__all__ = ["LOBES", "FIT_LOBES", "observation_lobe_terms", "lobe_terms", "lobe_factor", "geo_channels"]

FIT_LOBES = LOBES
LOG_OFF = -1.0e4  # L where the lobe is off (r·v ≤ 0, n·v ≤ 0): exp(α·L) = 0 for every α ≥ 1


def geo_channels(lobe: str) -> int:
    """How many extra geometry rows per observation the lobe needs (0, or 3 for GGX)."""
    return 3 if check_lobe(lobe) == "ggx" else 0


def observation_lobe_terms(
    lobe: str, n_dot_l: Tensor, spec_q: Tensor, half_q: Tensor | None, n_dot_v: Tensor | None, v_dot_h: Tensor | None,
    log_cos: Tensor,
) -> tuple[Tensor, Tensor | None]:
    """Per-observation (L, geo) of ``lobe`` from the shading terms, any one shape S (e.g. (n, R, C)).

    Args:
        n_dot_l, spec_q (1 − r·v): as from :func:`~torchmetal.geometry.grid_shading_terms`;
        half_q (1 − n·h), n_dot_v, v_dot_h: from :func:`~torchmetal.lobes.grid_half_terms`
            (None for phong);
        log_cos: the L of Phong computed from ``spec_q`` (phong) or ``half_q`` (blinn) by
            :func:`~torchmetal.fit.grid_terms.observation_geometry`; unused for GGX.

    Returns:
        L (S) and, for GGX, geo (3, *S) = (1 − n·h, n·l, n·v) with safe placeholders; else None.
    """
    if check_lobe(lobe) != "ggx":
        return log_cos, None
    seen = n_dot_v > 0
    one = torch.ones_like(n_dot_v)
    L = torch.where(seen, torch.log(fresnel_ratio(v_dot_h)), torch.full_like(n_dot_v, LOG_OFF))
    geo = torch.stack([half_q, torch.where(n_dot_l > 0, n_dot_l, one), torch.where(seen, n_dot_v, one)])
    return L, geo


def lobe_terms(
    g: Tensor, u: Tensor, L: Tensor, inten: Tensor, alpha: Tensor, geo: Tensor | None = None, lobe: str = "phong",
) -> tuple[Tensor, Tensor, Tensor]:
    """a = i·g, b = i·u·exp(λ), t = ∂λ/∂β, all (n, 3, c).

    Args:
        g, u, L: (n, 1, c); inten: (n, 3, 1); alpha: (1, 3, 1) or (1, 3, c);
        geo: (n, 3, c) GGX geometry (1 − n·h, n·l, n·v), None for phong/blinn.
    """
    if lobe != "ggx":
        t = alpha * L
        return inten * g, (inten * u) * torch.exp(t), t
    log_core, t = ggx_log_core(geo[:, 0:1], geo[:, 1:2], geo[:, 2:3], ggx_k(alpha))
    return inten * g, (inten * u) * torch.exp(L + log_core), t


def lobe_factor(L: Tensor, alpha: Tensor, geo: Tensor | None = None, lobe: str = "phong") -> Tensor:
    """exp(λ) (n, 3, c): the lobe per unit i·u (``torch.exp(α·L)`` for phong, as before)."""
    if lobe != "ggx":
        return torch.exp(alpha * L)
    log_core, _ = ggx_log_core(geo[:, 0:1], geo[:, 1:2], geo[:, 2:3], ggx_k(alpha))
    return torch.exp(L + log_core)
