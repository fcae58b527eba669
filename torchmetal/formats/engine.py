"""The material as engines see it: metallic-roughness maps of a GGX dielectric (+ an optional coat).

:func:`engine_material` turns a :class:`~torchmetal.material.Material` into an
:class:`EngineMaterial` — per-texel base colour, GGX roughness, F0/F90, normal map and an optional
clear coat — once; the glTF, MaterialX and USD writers only encode it. :func:`engine_render`
evaluates exactly the BRDF those formats specify (glTF 2.0 + KHR_materials_specular +
KHR_materials_clearcoat), so every export can be compared with torchmetal's own renderer. The maps'
types, that BRDF and the comparison live in :mod:`torchmetal.formats.engine_brdf` (the flake bake
builds on them too) and are importable from here as well.

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

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.errors import ExportError
from torchmetal.formats.bake import bake_flakes
from torchmetal.formats.engine_brdf import (
    COAT_F0,
    Coat,
    EngineMaterial,
    check_lights,
    engine_render,
    finish_base_color,
    reference_render,
    render_error,
)
from torchmetal.formats.lobe_fit import LobeFit, fit_lobe
from torchmetal.geometry import normalize

if TYPE_CHECKING:
    from torchmetal.material import Material


# the maps' types and their BRDF live in engine_brdf (the flake bake needs them too); callers find them here as well
__all__ = ["COAT_F0", "MAX_GROUPS", "Coat", "EngineMaterial", "check_lights", "engine_material", "engine_render",
           "finish_base_color", "reference_render", "render_error", "specular_fits"]

MAX_GROUPS = 64  # distinct exponent triples fitted one by one; more are binned in log α


def _lobe_kind(material) -> str:
    return str(getattr(material, "lobe", None) or "phong")


def specular_fits(material: Material, views: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, list[dict]]:
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


def engine_material(material: Material, *, views: Tensor | None = None, flakes: str = "auto",
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


