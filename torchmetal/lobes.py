"""Specular lobes beside the Phong one: Blinn-Phong and a GGX microfacet lobe (docs/design.md §2.2 extensions).

Each lobe takes the place of max(r·v, 0)^α in docs/design.md §2.2's model,

    I_k(p)_c = E_c · [ d_c(p)·max(n·l, 0) + [n·l > 0] · s_c · lobe_c ],

with one sharpness α per channel (global (3,) or per-pixel (3, H, W)) for every lobe:

- ``phong`` (the default, docs/design.md §2.2): max(r·v, 0)^α, r = 2(n·l)n − l.
- ``blinn``: max(n·h, 0)^α, h = (l + v)/|l + v|. Near the peak the angle between n and h is half
  the one between r and v, so a Blinn α is about 4× the Phong α of the same highlight.
- ``ggx``: the Cook–Torrance microfacet term with the GGX (Trowbridge–Reitz) distribution,
  Schlick's Fresnel and Smith's separable shadowing, normalised to 1 at normal incidence:

      lobe = D̂(n·h) · F̂(v·h) · G₁(n·l) · G₁(n·v)/(n·v) · [n·v > 0]
      k = m² = 2/(α + 2)                     (m: GGX roughness; α ≥ 0 ↔ m ∈ (0, 1])
      D̂ = (k / (k + (1 − k)(1 − (n·h)²)))²   = π·m²·D_GGX, 1 at n = h
      F̂ = F_Schlick(v·h)/F0 = 1 + (1/F0 − 1)(1 − v·h)⁵,  F0 = 0.04 (a dielectric coat, IOR 1.5)
      G₁(x) = 2x / (x + √(k + (1 − k)x²))

  so s·lobe = c·D·F·G/(4 n·v) (the microfacet radiance per unit irradiance, BRDF × n·l) with
  c = 4π·k·s/F0: s keeps Phong's meaning, the peak at normal incidence. k = 2/(α + 2) makes
  D̂ ≈ exp(−(α + 2)·θ²) near the peak, the width of a Blinn lobe of exponent 2(α + 2).

The half-vector terms come from the vectors, as ``1 − n·h = |n − h|²/2`` (``half_q``), so the
lobes keep their precision near the peak; no ``pow`` (the Fresnel power is four products), every
base is clamped before use and untaken branches of ``where`` see safe values (finite gradients
at grazing angles, at n·v ≤ 0 and for α from 0 to 1e8). Shapes: geometry terms (B, 1, H, W) (or
any shape that broadcasts), α and s (3,) or (3, H, W), results (B, 3, H, W).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.geometry import (
    ShadingGeometry,
    _grid_direction,  # the one separable direction builder
    dot,
    shading_geometry,
)
from torchmetal.phong import (
    PhongModel,
    _plane_cos_lobe,
    _plane_ok,
    _plane_radiance,
    _plane_terms,
    channel_map,
    phong_render,
    phong_shading,
    specular_lobe,
)

__all__ = [
    "LOBES", "F0", "check_lobe", "half_terms", "grid_half_terms", "ggx_k", "fresnel_ratio", "blinn_lobe", "ggx_lobe",
    "ggx_log_core", "lobe_value", "lobe_shading", "lobe_render", "LobeModel",
]

LOBES = ("phong", "blinn", "ggx")
F0 = 0.04  # Schlick's normal-incidence reflectance of a dielectric coat (IOR 1.5)
K_MIN = 1e-8  # k = m² floor (α ≤ 2e8): D̂ stays a ratio of normal floats


def check_lobe(lobe: str, options: tuple[str, ...] = LOBES) -> str:
    """``lobe`` if it is one of ``options``, else a one-line :class:`InputError`."""
    if lobe not in options:
        raise InputError(f"lobe: expected one of {list(options)}, found {lobe!r}")
    return lobe


def _half_q(nh_x: Tensor, nh_y: Tensor, nh_z: Tensor) -> Tensor:
    return 0.5 * (nh_x * nh_x + nh_y * nh_y + nh_z * nh_z)


def half_terms(geom: ShadingGeometry) -> tuple[Tensor, Tensor, Tensor]:
    """Half-vector terms of B shots: (1 − n·h, n·v, v·h), each (B, 1, H, W).

    1 − n·h = |n − h|²/2 (exact near the peak); h = (l + v)/|l + v| (zero when l = −v, then
    1 − n·h = 1/2 and the pixel is unlit or unseen anyway).
    """
    h = geom.half
    d = geom.n - h
    return 0.5 * (d * d).sum(1, keepdim=True), dot(geom.n, geom.v), dot(geom.v, h)


def grid_half_terms(
    light: Tensor, camera: Tensor, x: Tensor, y: Tensor, normals: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`half_terms` on a grid of plane points, the way
    :func:`~torchmetal.geometry.grid_shading_terms` builds the Phong terms (separable offsets).

    Args:
        light, camera: (B, 4) homogeneous light / camera.
        x: (C,) x of the columns; y: (R,) y of the rows (see :func:`~torchmetal.geometry.pixel_axes`).
        normals: (3, R, C) unit normals, or None for (0, 0, 1) everywhere.

    Returns:
        1 − n·h, n·v, v·h, each (B, R, C).
    """
    (lx, ly, lz), _ = _grid_direction(light, x, y)
    (vx, vy, vz), _ = _grid_direction(camera, x, y)
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    inv = 1.0 / torch.sqrt((hx * hx + hy * hy + hz * hz).clamp_min(1e-24))
    hx, hy, hz = hx * inv, hy * inv, hz * inv
    vh = vx * hx + vy * hy + vz * hz
    if normals is None:
        return _half_q(hx, hy, 1.0 - hz), vz, vh
    nx, ny, nz = normals.unsqueeze(1).unbind(0)  # (1, R, C) each
    return _half_q(nx - hx, ny - hy, nz - hz), nx * vx + ny * vy + nz * vz, vh


def ggx_k(alpha: Tensor) -> Tensor:
    """k = m² = 2/(α + 2) in [1e-8, 1] (α < 0 is treated as 0); any shape."""
    return (2.0 / (alpha.clamp_min(0.0) + 2.0)).clamp_min(K_MIN)


def fresnel_ratio(v_dot_h: Tensor, f0: float = F0) -> Tensor:
    """Schlick's F(v·h)/F0 = 1 + (1/F0 − 1)·(1 − v·h)⁵, with 1 − v·h clamped to [0, 1]; any shape."""
    x = (1.0 - v_dot_h).clamp(0.0, 1.0)
    x2 = x * x
    return 1.0 + (1.0 / f0 - 1.0) * (x2 * x2 * x)


def blinn_lobe(half_q: Tensor, alpha: Tensor) -> Tensor:
    """max(n·h, 0)^α from half_q = 1 − n·h (B, 1, H, W) in [0, 2]; α (3,) or (3, H, W) → (B, 3, H, W).

    The same function of its argument as :func:`torchmetal.phong.specular_lobe` (of 1 − r·v).
    """
    return specular_lobe(half_q, alpha)


def _smith_sqrt(x: Tensor, k: Tensor) -> Tensor:
    """√(k + (1 − k)·x²) ≥ √k > 0."""
    return torch.sqrt(k + (1.0 - k) * (x * x))


def ggx_lobe(half_q: Tensor, n_dot_l: Tensor, n_dot_v: Tensor, v_dot_h: Tensor, alpha: Tensor) -> Tensor:
    """The GGX lobe D̂·F̂·G₁(n·l)·G₁(n·v)/(n·v) of the module docstring, 0 where n·v ≤ 0.

    Args:
        half_q: 1 − n·h in [0, 2]; n_dot_l, n_dot_v, v_dot_h: cosines, each (B, 1, H, W).
        alpha: (3,) or (3, H, W) sharpness, k = 2/(α + 2).

    Returns:
        (B, 3, H, W), 1 at n = l = v, in [0, 1/F0·(4/√k)] elsewhere (grazing Fresnel × G/n·v).
    """
    k = channel_map(ggx_k(alpha))
    hq = half_q.clamp(0.0, 1.0)  # n·h < 0 cannot occur with n·l, n·v > 0; 1 − (n·h)² ≤ 1
    w = hq * (2.0 - hq)  # 1 − (n·h)², exact near the peak
    d = k / (k + (1.0 - k) * w)
    nl = n_dot_l.clamp(0.0, 1.0)
    seen = n_dot_v > 0
    nv = torch.where(seen, n_dot_v.clamp_max(1.0), torch.ones_like(n_dot_v))
    g = (2.0 * nl / (nl + _smith_sqrt(nl, k))) * (2.0 / (nv + _smith_sqrt(nv, k)))  # G₁(n·l)·G₁(n·v)/(n·v)
    lobe = (d * d) * fresnel_ratio(v_dot_h) * g
    return torch.where(seen, lobe, torch.zeros_like(lobe))


def ggx_log_core(half_q: Tensor, n_dot_l: Tensor, n_dot_v: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """log of the α-dependent part of the GGX lobe, D̂·G₁(n·l)·G₁(n·v)/(n·v), and its β derivative.

    For the fit (β = log α, k = 2/(α + 2), so ∂k/∂β = −k(1 − k)):

        ∂/∂β log D̂ = −(1 − k)·2w/(k + (1 − k)w),   w = 1 − (n·h)²
        ∂/∂β log G₁(x) = (1 − k)·k(1 − x²)/(2S(x + S)),   S = √(k + (1 − k)x²)

    Args:
        half_q: 1 − n·h; n_dot_l, n_dot_v: cosines, all > 0 where the lobe is used (callers
            pass safe placeholder values elsewhere and gate the result); any shapes that
            broadcast, e.g. (n, 1, c).
        k: k = ggx_k(α), broadcasting, e.g. (1, 3, 1) or (1, 3, c).

    Returns:
        (log core, ∂ log core/∂β), broadcast shape.
    """
    hq = half_q.clamp(0.0, 1.0)
    w = hq * (2.0 - hq)
    k1 = 1.0 - k
    d = k / torch.addcmul(k, k1, w)  # D̂^½ = k/(k + (1 − k)w)
    nl = n_dot_l.clamp(1e-12, 1.0)
    nv = n_dot_v.clamp(1e-12, 1.0)
    nl2, nv2 = nl * nl, nv * nv
    sl, sv = torch.addcmul(k, k1, nl2).sqrt(), torch.addcmul(k, k1, nv2).sqrt()
    gl, gv = 1.0 / (nl + sl), 1.0 / (nv + sv)  # G₁(x) = 2x/(x + S)
    log_core = torch.log((d * d) * (gl * gv) * (4.0 * nl))
    # ∂/∂β: (1 − k)·[k·((1 − nl²)/(2 S_l (nl + S_l)) + (1 − nv²)/(2 S_v (nv + S_v))) − 2w·D̂^½/k]
    dg = ((1.0 - nl2) * gl / sl + (1.0 - nv2) * gv / sv) * (0.5 * k) - (2.0 * w) * d / k
    return log_core, k1 * dg


def lobe_value(lobe: str, geom: ShadingGeometry, alpha: Tensor) -> Tensor:
    """The lobe (B, 3, H, W) of B shots for α (3,) or (3, H, W), without the [n·l > 0] gate."""
    check_lobe(lobe)
    if lobe == "phong":
        return specular_lobe(geom.spec_q, alpha)
    half_q, n_dot_v, v_dot_h = half_terms(geom)
    if lobe == "blinn":
        return blinn_lobe(half_q, alpha)
    return ggx_lobe(half_q, geom.n_dot_l, n_dot_v, v_dot_h, alpha)


def lobe_shading(texture: Tensor, s: Tensor, alpha: Tensor, geom: ShadingGeometry, lobe: str = "phong") -> Tensor:
    """Radiance (B, 3, H, W) of the model above; ``lobe="phong"`` is exactly
    :func:`torchmetal.phong.phong_shading` (same ops, same inf·0 handling).

    Args:
        texture: (3, H, W) or (B, 3, H, W); s, alpha: (3,) or (3, H, W); geom: B shots.
    """
    if check_lobe(lobe) == "phong":
        return phong_shading(texture, s, alpha, geom)
    lit = geom.n_dot_l > 0
    diffuse = texture * geom.n_dot_l.clamp_min(0.0)
    spec = channel_map(s) * lobe_value(lobe, geom, alpha)
    spec = torch.where(lit, spec, torch.zeros_like(spec))
    shade = diffuse + spec
    e = geom.irradiance
    dark = (shade == 0) & torch.isinf(e)
    return torch.where(dark, torch.ones_like(e), e) * shade


def lobe_render(
    texture: Tensor, s: Tensor, alpha: Tensor, normals: Tensor, light: Tensor, intensity: Tensor, camera: Tensor,
    size: tuple[float, float], lobe: str = "phong",
) -> Tensor:
    """:func:`torchmetal.phong.phong_render` with a choice of lobe; (B, 3, H, W)."""
    if check_lobe(lobe) == "phong":
        return phong_render(texture, s, alpha, normals, light, intensity, camera, size)
    if _plane_ok(texture, s, alpha, normals, light, intensity, camera):
        out = _plane_lobe(texture, s, alpha, normals, light, intensity, camera, size, lobe)
        if out is not None:
            return out
    geom = shading_geometry(normals, light, intensity, camera, size)
    return lobe_shading(texture, s, alpha, geom, lobe)


def _plane_lobe(texture: Tensor, s: Tensor, alpha: Tensor, normals: Tensor, light: Tensor, intensity: Tensor,
                camera: Tensor, size: tuple[float, float], lobe: str) -> Tensor | None:
    """:func:`lobe_render` for Blinn or GGX from the plane's separable scalar terms (as
    :func:`torchmetal.phong._plane_phong` does for Phong): the formulas of :func:`blinn_lobe` /
    :func:`ggx_lobe`, the (B, 3, H, W) products in place. For values, not gradients; None where an
    irradiance overflowed (the vector path's inf·0 rule applies)."""
    nl, _, e, (x, y, flat) = _plane_terms(normals, light, intensity, camera, size)
    if not bool(torch.isfinite(e).all()):
        return None
    half_q, nv, vh = (t.unsqueeze(1) for t in grid_half_terms(light, camera, x, y, flat))
    if lobe == "blinn":  # specular_lobe of 1 − n·h, the gate n·l > 0
        return _plane_radiance(texture, s, *_plane_cos_lobe(half_q, nl, alpha, e.dtype), nl, e)
    # ggx_lobe: D̂²·F̂·G₁(n·l)·G₁(n·v)/(n·v), 0 where n·v ≤ 0 or n·l ≤ 0
    gate = ((nl > 0) & (nv > 0)).to(e.dtype) * fresnel_ratio(vh)
    k = channel_map(ggx_k(alpha))
    hq = half_q.clamp(0.0, 1.0)
    wq = hq * (2.0 - hq)
    nlc = nl.clamp(0.0, 1.0)
    nvc = torch.where(nv > 0, nv.clamp_max(1.0), torch.ones_like(nv))
    spec = (wq * (1.0 - k)).add_(k).reciprocal_().mul_(k).square_()  # D̂
    sl = (nlc * nlc * (1.0 - k)).add_(k).sqrt_().add_(nlc)  # nl + S(nl)
    spec.div_(sl).mul_(2.0 * nlc)
    sv = (nvc * nvc * (1.0 - k)).add_(k).sqrt_().add_(nvc)  # nv + S(nv)
    spec.div_(sv).mul_(2.0)
    return _plane_radiance(texture, s, spec, gate, nl, e)


class LobeModel(PhongModel):
    """:class:`~torchmetal.phong.PhongModel` (texture, s, log α trainable) with any lobe of :data:`LOBES`."""

    def __init__(self, texture: Tensor, s: Tensor, alpha: Tensor, normals: Tensor | None = None,
                 size: tuple[float, float] = (1.0, 1.0), lobe: str = "phong") -> None:
        super().__init__(texture, s, alpha, normals, size)
        self.lobe = check_lobe(lobe)

    def forward(self, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
        geom = shading_geometry(self.normals, light, intensity, camera, points=self.points)
        return lobe_shading(self.texture, self.s, self.alpha, geom, self.lobe)

    def extra_repr(self) -> str:
        return f"lobe={self.lobe}"

