"""The material as engines see it: metallic-roughness maps of a GGX dielectric (+ an optional coat).

:func:`engine_material` turns a :class:`~torchmetal.material.Material` into an
:class:`EngineMaterial` — per-texel base colour, GGX roughness, F0/F90, normal map and an optional
clear coat — once; the glTF, MaterialX and USD writers only encode it. :func:`engine_render`
evaluates exactly the BRDF those formats specify (glTF 2.0 + KHR_materials_specular +
KHR_materials_clearcoat), so every export can be compared with torchmetal's own renderer.

Conventions (all writers): an engine light of irradiance π·E equals a torchmetal light of
irradiance E (the base colour is the texture d as an albedo); the quad is the plane z = 0 with
u along +x, v along −y (image row 0 at the top, +y), tangent +x, bitangent +y, so a world normal
(x, y, z) is also its tangent-space normal.

Specular: the material's lobe (``material.lobe`` when present, else "phong") is fitted by
:mod:`torchmetal.formats.lobe_fit` for every distinct exponent triple (global, clustered or
per-pixel gloss maps; the fit is linear in s, so one fit per exponent serves every s). The diffuse
is divided by (1 − max_c F0_c) to undo the energy the glTF specular layer takes from it.
Flakes are baked by :mod:`torchmetal.formats.bake` (see there for the two layer layouts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchmetal.errors import ExportError
from torchmetal.formats.lobe_fit import LobeFit, ggx_terms, fit_lobe
from torchmetal.geometry import is_flat, normalize, shading_geometry

COAT_F0 = 0.04  # glTF/OpenPBR clear coat at IOR 1.5
MAX_GROUPS = 64  # distinct exponent triples fitted one by one; more are binned in log α


@dataclass
class Coat:
    """A clear coat over the base: weight (1, H, W) in [0, 1] (glTF ``clearcoatFactor``·texture,
    coat F0 = 0.04·weight), roughness (1, H, W), normal (3, H, W) unit."""

    weight: Tensor
    roughness: Tensor
    normal: Tensor


@dataclass
class EngineMaterial:
    """Engine maps at texture resolution (H, W); all float32 tensors.

    Attributes:
        base_color: (3, H, W) linear albedo in [0, 1].
        roughness: (1, H, W) GGX roughness (α = r²).
        f0: (3, H, W) specular reflectance at normal incidence; f90: (1, H, W) grazing (F0 ≤ F90 ≤ 1).
        normal: (3, H, W) unit normals of the base layer (world = tangent frame).
        coat: optional :class:`Coat`.
        size: (width, height) of the quad.
        extras: what the writers store beside the maps (lobe fits, flake statistics, clipping).
    """

    base_color: Tensor
    roughness: Tensor
    f0: Tensor
    f90: Tensor
    normal: Tensor
    size: tuple[float, float]
    coat: Coat | None = None
    extras: dict = field(default_factory=dict)

    @property
    def height(self) -> int:
        return int(self.base_color.shape[1])

    @property
    def width(self) -> int:
        return int(self.base_color.shape[2])

    @property
    def flat(self) -> bool:
        return is_flat(self.normal)


def _lobe_kind(material) -> str:
    return str(getattr(material, "lobe", None) or "phong")


def specular_fits(material, views: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, list[dict]]:
    """GGX maps of the material's specular lobe.

    Returns:
        roughness (1, H, W), f0 (3, H, W), f90 (1, H, W) and one report entry per fitted exponent
        triple (alpha, roughness, error, textbook mapping, pixel share).
    """
    s_map, a_map = material.specular_maps()
    h, w = material.height, material.width
    s_map = s_map.detach().double().cpu()
    a_map = a_map.detach().double().cpu()
    s_px = (s_map.reshape(3, 1).expand(3, h * w) if s_map.dim() == 1 else s_map.reshape(3, -1)).t()
    a_px = (a_map.reshape(3, 1).expand(3, h * w) if a_map.dim() == 1 else a_map.reshape(3, -1)).t()
    if not (bool(torch.isfinite(s_px).all()) and bool(torch.isfinite(a_px).all())):
        raise ExportError("specular: expected finite s and alpha, found NaN/Inf")
    key = a_px
    uniq, inverse = torch.unique(key, dim=0, return_inverse=True)
    if uniq.shape[0] > MAX_GROUPS:  # per-pixel gloss maps: bin the exponents (1/16 in log α)
        key = torch.exp(torch.round(torch.log(a_px.clamp_min(1e-6)) * 16.0) / 16.0)
        uniq, inverse = torch.unique(key, dim=0, return_inverse=True)
    kind = _lobe_kind(material)
    rough = torch.empty(h * w, dtype=torch.float64)
    f0 = torch.empty(h * w, 3, dtype=torch.float64)
    f90 = torch.empty(h * w, dtype=torch.float64)
    report = []
    for g in range(uniq.shape[0]):
        sel = inverse == g
        # one fit at the group's mean s (the channel weights of the shared roughness); s scales
        # the target, hence F0/F90, linearly, so each pixel gets F0 = s/s_mean·F0_mean
        s_sel = s_px[sel].clamp_min(0.0)
        s_mean = s_sel.mean(0)
        fit: LobeFit = fit_lobe(s_mean, uniq[g], kind, views=views)
        ratio = torch.where(s_mean > 0, s_sel / s_mean.clamp_min(1e-300), torch.zeros_like(s_sel))
        f0_sel = ratio * torch.tensor(fit.f0, dtype=torch.float64)
        f90_sel = torch.maximum(f0_sel.max(1).values, fit.f90 * ratio.max(1).values)
        rough[sel] = fit.roughness
        f0[sel] = f0_sel
        f90[sel] = f90_sel
        report.append({"lobe": kind, "alpha": uniq[g].tolist(), "pixels": float(sel.double().mean()),
                       "roughness": fit.roughness, "error": list(fit.error),
                       "textbook_roughness": fit.textbook_roughness,
                       "textbook_error": None if fit.textbook_error is None else list(fit.textbook_error),
                       "samples": fit.samples})
    clipped = float((f90 > 1.0).double().mean())
    scale = torch.where(f90 > 1.0, 1.0 / f90.clamp_min(1e-30), torch.ones_like(f90))
    f0, f90 = f0 * scale.unsqueeze(1), f90 * scale
    if clipped:
        report.append({"clipped_specular_pixels": clipped})
    f32 = torch.float32
    return (rough.reshape(1, h, w).to(f32), f0.t().reshape(3, h, w).to(f32), f90.reshape(1, h, w).to(f32), report)


def engine_material(material, *, views: Tensor | None = None, flakes: str = "auto",
                    texels_per_pixel: int = 1, coat_normals: bool = True) -> EngineMaterial:
    """The engine maps of ``material`` (see the module docstring).

    Args:
        material: a torchmetal Material.
        views: (V, 3) view directions for the lobe fit (default: polar 0–60°), e.g. the capture's own:
            :func:`torchmetal.formats.lobe_fit.capture_views` (capture.cameras).
        flakes: "auto" (the layout whose render matches torchmetal's best), "base", "clearcoat" or
            "flake_clearcoat" (see :mod:`torchmetal.formats.bake`); ignored without flakes.
        texels_per_pixel: flake bake density (1: torchmetal's own flakes, texel for pixel).
        coat_normals: whether the target has a separate coat normal map (glTF yes, USD preview no).
    """
    from torchmetal.formats.bake import bake_flakes

    tex = material.texture.detach().float().cpu()
    rough, f0, f90, fits = specular_fits(material, views)
    normal = material.flat_normals().detach().float().cpu()
    normal = normalize(normal, dim=0)
    em = EngineMaterial(base_color=tex, roughness=rough, f0=f0, f90=f90, normal=normal,
                        size=(float(material.size[0]), float(material.size[1])),
                        extras={"lobe": _lobe_kind(material), "lobe_fit": fits,
                                "light_convention": "engine irradiance = pi x torchmetal irradiance; base colour = texture d"})
    if material.flakes is not None:  # the bake finishes the base colour of its layout
        return bake_flakes(em, material, mode=flakes, texels_per_pixel=texels_per_pixel, views=views,
                           coat_normals=coat_normals)
    return finish_base_color(em, tex)


def finish_base_color(em: EngineMaterial, texture: Tensor) -> EngineMaterial:
    """Base colour = texture (3, H, W) divided by the energy the specular layers take, in [0, 1]."""
    d = texture
    keep = (1.0 - em.f0.max(0, keepdim=True).values).clamp_min(1e-3)
    if em.coat is not None:
        keep = keep * (1.0 - COAT_F0 * em.coat.weight)
    base = d / keep
    em.extras["base_color_clipped"] = float((base > 1.0).any(0).float().mean())
    em.base_color = base.clamp(0.0, 1.0)
    return em


def engine_render(em: EngineMaterial, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
    """Radiance (B, 3, H, W) of the engine BRDF under torchmetal lights (engine irradiance π·E).

    glTF 2.0 dielectric with KHR_materials_specular and KHR_materials_clearcoat:
    base = (1 − max_c F_c)·albedo·(n·l) + π·F·D·V·(n·l), F = F0 + (F90 − F0)(1 − v·h)^5;
    with a coat: (1 − w·F_c)·base + w·F_c·π·D_c·V_c·(n_c·l), F_c = 0.04 + 0.96(1 − v·h)^5.
    """
    geom = shading_geometry(em.normal, light.float(), intensity.float(), camera.float(), em.size)
    l = geom.l.permute(0, 2, 3, 1)  # (B, H, W, 3)
    v = geom.v.permute(0, 2, 3, 1)
    n = em.normal.permute(1, 2, 0).unsqueeze(0)
    lobe, sch = ggx_terms(l, v, n, em.roughness[0].unsqueeze(0))
    sch = sch.unsqueeze(1)  # (B, 1, H, W)
    fres = em.f0.unsqueeze(0) + (em.f90.unsqueeze(0) - em.f0.unsqueeze(0)) * sch
    nl = geom.n_dot_l.clamp_min(0.0)
    base = (1.0 - fres.max(1, keepdim=True).values) * em.base_color.unsqueeze(0) * nl + fres * lobe.unsqueeze(1)
    if em.coat is not None:
        nc = em.coat.normal.permute(1, 2, 0).unsqueeze(0)
        lobe_c, _ = ggx_terms(l, v, nc, em.coat.roughness[0].unsqueeze(0))
        fc = em.coat.weight.unsqueeze(0) * (COAT_F0 + (1.0 - COAT_F0) * sch)
        base = (1.0 - fc) * base + fc * lobe_c.unsqueeze(1)
    return geom.irradiance * base


def reference_render(material, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
    """torchmetal's render (B, 3, H, W) of ``material`` (the reference of :func:`render_error`)."""
    from torchmetal.renderer import MaterialRenderer

    with torch.inference_mode():
        return MaterialRenderer(material.to("cpu")).eval()(light, intensity, camera)


def render_error(em: EngineMaterial, material, light: Tensor, intensity: Tensor, camera: Tensor,
                 reference: Tensor | None = None) -> float:
    """Relative L2 error ‖engine − torchmetal‖/‖torchmetal‖ of the two renders over the shots
    (``reference``: torchmetal's render when already computed)."""
    ref = reference_render(material, light, intensity, camera) if reference is None else reference
    with torch.inference_mode():
        got = engine_render(em, light, intensity, camera)
    if got.shape != ref.shape:  # baked at a finer texel density: compare at the material's pixels
        got = torch.nn.functional.avg_pool2d(got, got.shape[-1] // ref.shape[-1])
    return float(torch.linalg.vector_norm(got - ref) / torch.linalg.vector_norm(ref).clamp_min(1e-30))


def check_lights(size: tuple[float, float], angles_deg=(20.0, 40.0, 60.0)) -> tuple[Tensor, Tensor, Tensor]:
    """Directional lights at the given polar angles with the camera at each mirror direction,
    plus the same lights seen from overhead: the shots that compare engine and torchmetal renders."""
    ls, cs = [], []
    for a in angles_deg:
        t = math.radians(a)
        ls.append([math.sin(t), 0.0, math.cos(t), 0.0])
        cs.append([-math.sin(t), 0.0, math.cos(t), 0.0])
    for a in angles_deg:
        t = math.radians(a)
        ls.append([0.0, math.sin(t), math.cos(t), 0.0])
        cs.append([0.0, 0.0, 1.0, 0.0])
    light = torch.tensor(ls, dtype=torch.float32)
    camera = torch.tensor(cs, dtype=torch.float32)
    return light, torch.ones(light.shape[0], 3), camera
