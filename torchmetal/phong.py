"""The reflectance model of docs/design.md §2.2, as pure functions plus a thin ``nn.Module``.

I_k(p)_c = E_c · [ d_c(p)·max(n·l, 0) + [n·l > 0] · s_c · max(r·v, 0)^{α_c} ]

``s`` and ``α`` are per channel, either global ``(3,)`` (the paper's model, the default) or
per-pixel maps ``(3, H, W)`` (the spatially varying extension); both broadcast the same way.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from torchmetal.geometry import (
    ShadingGeometry,
    grid_shading_terms,
    is_flat,
    pixel_axes,
    shading_geometry,
    surface_points,
)


def log1p_exact(y: Tensor) -> Tensor:
    """log(1 + y) in the Kahan form, exact after ONNX export (``torch.log1p`` is not).

    log1p(y) = y·log(u)/(u − 1) with u = 1 + y, and y where u == 1. Double ``where`` keeps the
    gradient finite on the untaken branch. Requires y > −1.
    """
    u = 1.0 + y
    same = u == 1.0
    denom = torch.where(same, torch.ones_like(u), u - 1.0)
    return torch.where(same, y, y * torch.log(u) / denom)


def channel_map(x: Tensor) -> Tensor:
    """Broadcast per-channel terms ``(3,)`` or maps ``(3, H, W)`` against ``(B, 3, H, W)``."""
    return x.reshape(1, 3, 1, 1) if x.dim() == 1 else x.unsqueeze(0)


def exp_normal(x: Tensor) -> Tensor:
    """exp(x) with x clamped to 1 + log(smallest normal number) of its dtype: the result is never
    subnormal. A far-off lobe exp(α·log cos) lands there (α in the thousands) and subnormal
    arithmetic is ~10× slower on x86; the clamp changes values below 3.2e-38 (float32) only."""
    return torch.exp(x.clamp_min(_exp_floor(x.dtype)))


def _exp_floor(dtype: torch.dtype) -> float:
    """The smallest argument :func:`exp_normal` passes to exp: 1 + log(smallest normal number of ``dtype``)."""
    return 1.0 + math.log(torch.finfo(dtype).tiny)


def specular_lobe(spec_q: Tensor, alpha: Tensor) -> Tensor:
    """max(r·v, 0)^α written as exp(α·log1p(−q)) with q = 1 − r·v = |r − v|²/2.

    Finite values and gradients for q ∈ [0, 2] (r·v ≤ 0 gives exactly 0) and α up to 1e4;
    relative precision near the peak ~1e-7 instead of ~α·6e-8 for ``pow(r·v, α)``.

    Args:
        spec_q: (B, 1, H, W) in [0, 2].
        alpha: (3,) or (3, H, W), α ≥ 0.

    Returns:
        (B, 3, H, W) lobe in [0, 1].
    """
    inside = spec_q < 1.0
    return lobe_from_log(lobe_log(spec_q, inside), inside, alpha)


def lobe_log(spec_q: Tensor, inside: Tensor) -> Tensor:
    """log1p(−q) where ``inside`` (there q < 1), log1p(−0.5) elsewhere: a finite stand-in the caller masks, so
    that neither value nor gradient is ever inf or NaN; exact near the peak (:func:`log1p_exact`). The lobe's
    exponent per unit of α (:func:`specular_lobe`), formed once where only α changes."""
    return log1p_exact(-torch.where(inside, spec_q, torch.full_like(spec_q, 0.5)))


def lobe_from_log(log: Tensor, inside: Tensor, alpha: Tensor) -> Tensor:
    """(B, 3, H, W) exp(α·``log``) where ``inside``, 0 elsewhere (``log``, ``inside``: (B, 1, H, W), :func:`lobe_log`)."""
    lobe = exp_normal(channel_map(alpha) * log)
    return torch.where(inside, lobe, torch.zeros_like(lobe))


def phong_shading(texture: Tensor, s: Tensor, alpha: Tensor, geom: ShadingGeometry) -> Tensor:
    """Phong radiance for precomputed geometry.

    An irradiance that overflowed (inf, e.g. float16 above 65504) stays inf where the surface
    reflects light and gives 0 where the shading term is exactly 0 (unlit, back-facing): never
    the NaN of inf·0, in values or gradients. Finite irradiance is untouched.

    Args:
        texture: (3, H, W) diffuse texture d(p), or (B, 3, H, W).
        s: (3,) or (3, H, W) specular strength; alpha: (3,) or (3, H, W) exponent.
        geom: shading geometry of B shots.

    Returns:
        (B, 3, H, W) linear radiance.
    """
    return _phong_terms(texture, s, alpha, geom.n_dot_l, geom.spec_q, geom.irradiance)


def _phong_terms(texture: Tensor, s: Tensor, alpha: Tensor, n_dot_l: Tensor, spec_q: Tensor, e: Tensor) -> Tensor:
    """:func:`phong_shading` from its three scalar terms: n·l and q (B, 1, H, W), the irradiance E (B, 3, H, W)."""
    lit = n_dot_l > 0
    diffuse = texture * n_dot_l.clamp_min(0.0)
    spec = channel_map(s) * specular_lobe(spec_q, alpha)
    spec = torch.where(lit, spec, torch.zeros_like(spec))
    shade = diffuse + spec
    dark = (shade == 0) & torch.isinf(e)  # inf·0: no light leaves the surface
    return torch.where(dark, torch.ones_like(e), e) * shade


def _plane_phong(texture: Tensor, s: Tensor, alpha: Tensor, normals: Tensor, light: Tensor, intensity: Tensor,
                 camera: Tensor, size: tuple[float, float]) -> Tensor:
    """:func:`phong_render` on the plane's pixel grid from the separable scalar terms
    (:func:`~torchmetal.geometry.grid_shading_terms`): no (B, 3, H, W) light or view vectors, about a third of
    the geometry's time and memory. The same formulas; for values, not gradients (its in-place steps)."""
    nl, q, e, _ = _plane_terms(normals, light, intensity, camera, size)
    if not bool(torch.isfinite(e).all()):  # an overflowed irradiance: the inf·0 rule of _phong_terms
        return _phong_terms(texture, s, alpha, nl, q, e)
    return _plane_radiance(texture, s, *_plane_cos_lobe(q, nl, alpha, e.dtype), nl, e)


def _plane_terms(normals: Tensor, light: Tensor, intensity: Tensor, camera: Tensor, size: tuple[float, float]
                 ) -> tuple[Tensor, Tensor, Tensor, tuple]:
    """The plane path's shared terms: n·l and q = |r − v|²/2 (B, 1, H, W), the irradiance E (B, 3, H, W), and the
    grid (x (W,), y (H,), the normals or None where flat) for more separable terms (:mod:`torchmetal.lobes`)."""
    h, w = normals.shape[-2:]
    x, y = pixel_axes(h, w, size, dtype=normals.dtype, device=normals.device)
    flat = None if is_flat(normals) else normals
    nl, q, d2 = (t.unsqueeze(1) for t in grid_shading_terms(light, camera, x, y, flat))
    return nl, q, intensity[:, :, None, None] / d2, (x, y, flat)


def _plane_cos_lobe(q: Tensor, nl: Tensor, alpha: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """:func:`specular_lobe` of q = 1 − cos (B, 1, H, W) in fewer passes over (B, 3, H, W): the lobe (exp_normal in
    place) and its gate [n·l > 0]·[q < 1] (B, 1, H, W), applied by :func:`_plane_radiance`."""
    gate = ((nl > 0) & (q < 1.0)).to(dtype)
    log_cos = torch.log1p(-torch.where(q < 1.0, q, torch.full_like(q, 0.5)))
    return (channel_map(alpha) * log_cos).clamp_min_(_exp_floor(dtype)).exp_(), gate


def _plane_radiance(texture: Tensor, s: Tensor, lobe: Tensor, gate: Tensor, nl: Tensor, e: Tensor) -> Tensor:
    """E·(d·max(n·l, 0) + gate·s·lobe), in place in ``lobe`` (B, 3, H, W)."""
    lobe.mul_(channel_map(s)).mul_(gate)
    return lobe.addcmul_(texture, nl.clamp_min(0.0)).mul_(e)


def _plane_ok(*tensors: Tensor) -> bool:
    """Whether :func:`_plane_phong` may stand in for the vector geometry: float32/float64, nothing needing a gradient."""
    return all(t.dtype in (torch.float32, torch.float64) and not (t.requires_grad and torch.is_grad_enabled())
               for t in tensors)


def phong_render(
    texture: Tensor,
    s: Tensor,
    alpha: Tensor,
    normals: Tensor,
    light: Tensor,
    intensity: Tensor,
    camera: Tensor,
    size: tuple[float, float],
) -> Tensor:
    """Render B shots of a Phong material.

    Args:
        texture: (3, H, W); s, alpha: (3,) or (3, H, W); normals: (3, H, W) unit.
        light: (B, 4); intensity: (B, 3); camera: (B, 4); size: (width, height).

    Returns:
        (B, 3, H, W) linear radiance. Values without a gradient come from the plane's separable terms
        (:func:`_plane_phong`, faster; the same within float rounding).
    """
    if _plane_ok(texture, s, alpha, normals, light, intensity, camera):
        return _plane_phong(texture, s, alpha, normals, light, intensity, camera, size)
    geom = shading_geometry(normals, light, intensity, camera, size)
    return phong_shading(texture, s, alpha, geom)


class PhongModel(nn.Module):
    """Trainable Phong material: texture, s and β = log α as parameters.

    ``forward(light (B,4), intensity (B,3), camera (B,4)) -> (B,3,H,W)``. Keep training it in your
    own loop (Adam etc.); gradients flow through :func:`phong_shading`.
    """

    def __init__(
        self,
        texture: Tensor,
        s: Tensor,
        alpha: Tensor,
        normals: Tensor | None = None,
        size: tuple[float, float] = (1.0, 1.0),
    ) -> None:
        super().__init__()
        _, h, w = texture.shape
        if normals is None:
            normals = torch.zeros_like(texture)
            normals[2] = 1.0
        self.size = (float(size[0]), float(size[1]))
        self.texture = nn.Parameter(texture.detach().clone())
        self.s = nn.Parameter(s.detach().clone())
        self.log_alpha = nn.Parameter(torch.log(alpha.detach().clamp_min(1e-6)))
        self.register_buffer("normals", normals.detach().clone())
        self.register_buffer("points", surface_points(h, w, self.size, dtype=texture.dtype, device=texture.device))

    @property
    def alpha(self) -> Tensor:
        return torch.exp(self.log_alpha)

    def forward(self, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
        geom = shading_geometry(self.normals, light, intensity, camera, points=self.points)
        return phong_shading(self.texture, self.s, self.alpha, geom)
