"""Bake torchmetal's flakes into engine maps (formats without a flake model: glTF, USD preview).

Each flake texel (footprint ≥ 1/2 in torchmetal's deterministic flake field) becomes a tiny GGX
mirror: its normal is the flake normal, its roughness and reflectance come from a numeric fit of
the GGX lobe to one glint, c·exp(−|m − h|²/(2σ_g²)) (:func:`~torchmetal.formats.lobe_fit.fit_glint`),
scaled by the texel's footprint and glint colour. Two layer layouts:

- ``"base"``: coat and flakes share the base layer; a flake texel loses the coat lobe.
- ``"clearcoat"``: the base layer holds only the flakes (specular 0 elsewhere) under a smooth
  KHR_materials_clearcoat layer carrying the coat lobe; the glTF coat is grey with F0 = 0.04·weight,
  so a coat brighter than that is clipped.
- ``"flake_clearcoat"``: the base layer keeps the coat lobe everywhere and the flakes become the clear
  coat (weight = the glint's F0/0.04 on flake texels, 0 elsewhere; the coat normal map = the flake
  normals; grey): torchmetal adds its sparkles on top of the coat, and so does this layout. Needs a
  separate coat normal (glTF has one, UsdPreviewSurface does not).

``"auto"`` renders every candidate against torchmetal's renderer
(:func:`~torchmetal.formats.engine.check_lights`) and keeps the one with the lower relative error; all
errors go to ``extras["flake_bake"]``.
``texels_per_pixel`` k > 1 bakes a k× finer field with the same statistics (density/k², areas·k²);
k = 1 reproduces torchmetal's own flakes texel for pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import TYPE_CHECKING

import torch

from torchmetal.errors import ExportError
from torchmetal.flakes.model.field import flake_field
from torchmetal.formats.engine_brdf import (
    COAT_F0,
    Coat,
    EngineMaterial,
    check_lights,
    finish_base_color,
    reference_render,
    render_error,
)
from torchmetal.formats.lobe_fit import LobeFit, fit_glint
from torchmetal.geometry import normalize

if TYPE_CHECKING:
    from torchmetal.material import Material

MODES = ("auto", "base", "clearcoat", "flake_clearcoat")


def _up(x: torch.Tensor, k: int) -> torch.Tensor:
    return x if k == 1 else x.repeat_interleave(k, 1).repeat_interleave(k, 2)


def bake_flakes(em: EngineMaterial, material: Material, *, mode: str = "auto", texels_per_pixel: int = 1,
                views: torch.Tensor | None = None, coat_normals: bool = True) -> EngineMaterial:
    """``em`` with ``material.flakes`` baked in (see the module docstring); ``coat_normals`` False
    leaves "flake_clearcoat" out of "auto" (targets whose coat has no normal map of its own)."""
    if mode not in MODES:
        raise ExportError(f"flakes: expected one of {', '.join(MODES)}, found {mode!r}")
    k = int(texels_per_pixel)
    if k < 1 or k > 8:
        raise ExportError(f"texels_per_pixel: expected an integer in [1, 8], found {texels_per_pixel!r}")
    model = material.flakes
    if k > 1:
        model = replace(model, density=model.density / (k * k), area_log_mean=model.area_log_mean + 2.0 * math.log(k))
    normals = normalize(_up(material.flat_normals().detach().float().cpu(), k), dim=0)
    field = flake_field(model, material.height * k, material.width * k, normals)
    glint = fit_glint((1.0, 1.0, 1.0), float(field.glint_sigma), views=views)
    flake = (field.weight[0] >= 0.5)
    colour = field.color * field.weight  # (3, H, W) footprint × glint reflectance
    f0_flake = colour * torch.tensor(glint.f0, dtype=torch.float32).view(3, 1, 1)
    f90_flake = torch.maximum(f0_flake.max(0, keepdim=True).values, colour.max(0, keepdim=True).values * glint.f90)
    clipped = float(((f90_flake > 1.0) & flake).float().sum() / flake.float().sum().clamp_min(1.0))
    scale = torch.where(f90_flake > 1.0, 1.0 / f90_flake.clamp_min(1e-30), torch.ones_like(f90_flake))
    f0_flake, f90_flake = f0_flake * scale, f90_flake * scale

    up = {name: _up(getattr(em, name), k) for name in ("base_color", "roughness", "f0", "f90")}
    bake = _Layouts(em=em, up=up, flake=flake, f0_flake=f0_flake, f90_flake=f90_flake,
                    normal=torch.where(flake, field.normal.float(), normals), normals=normals, glint=glint)
    auto = ("base", "clearcoat", "flake_clearcoat") if coat_normals else ("base", "clearcoat")
    candidates = auto if mode == "auto" else (mode,)
    light, inten, cam = check_lights(em.size)
    ref = reference_render(material, light, inten, cam) if len(candidates) > 1 else None
    errors = {}
    built = {}
    for which in candidates:
        built[which] = bake.layout(which)
        errors[which] = render_error(built[which], material, light, inten, cam, reference=ref)
    chosen = min(errors, key=errors.get)
    out = built[chosen]
    out.extras["flakes"] = material.flakes.to_dict()
    out.extras["flake_bake"] = {
        "mode": chosen, "render_error": errors, "texels_per_pixel": k,
        "flake_texels": float(flake.float().mean()), "flakes": int(field.count),
        "glint_fit": glint.to_dict(), "clipped_flake_texels": bake.clip.get(chosen, clipped),
    }
    return out


@dataclass
class _Layouts:
    """The baked field's parts, each layer layout built from them (:meth:`layout`) and the clipped flake
    texels' fraction of the layouts that clip their own (``clip``)."""

    em: EngineMaterial
    up: dict[str, torch.Tensor]  # em's maps at the baked resolution
    flake: torch.Tensor  # (1, H, W) bool: flake texels
    f0_flake: torch.Tensor
    f90_flake: torch.Tensor
    normal: torch.Tensor  # the flake normals on flake texels, the surface's elsewhere
    normals: torch.Tensor  # the surface's
    glint: LobeFit
    clip: dict[str, float] = dc_field(default_factory=dict)

    def layout(self, which: str) -> EngineMaterial:
        """The engine material of layout ``which`` ("base", "clearcoat" or "flake_clearcoat")."""
        em, up, flake, glint, normals = self.em, self.up, self.flake, self.glint, self.normals
        texture = up["base_color"]
        if which == "base":
            f0 = torch.where(flake, self.f0_flake, up["f0"])
            f90 = torch.where(flake, self.f90_flake, up["f90"])
            rough = torch.where(flake, torch.full_like(up["roughness"], glint.roughness), up["roughness"])
            coat = None
        elif which == "flake_clearcoat":
            f0, f90, rough = up["f0"], up["f90"], up["roughness"]
            weight = torch.where(flake, self.f0_flake.mean(0, keepdim=True) / COAT_F0, torch.zeros_like(up["roughness"]))
            coat = Coat(weight=weight.clamp(0.0, 1.0), roughness=torch.full_like(rough, glint.roughness),
                        normal=self.normal.clone())
            self.clip["flake_clearcoat"] = float(((weight > 1.0) & flake).float().sum() / flake.float().sum().clamp_min(1.0))
            return finish_base_color(EngineMaterial(base_color=texture.clone(), roughness=rough.clone(), f0=f0.clone(),
                                                    f90=f90.clone(), normal=normals.clone(), size=em.size, coat=coat,
                                                    extras=dict(em.extras)), texture)
        else:
            f0 = torch.where(flake, self.f0_flake, torch.zeros_like(up["f0"]))
            f90 = torch.where(flake, self.f90_flake, torch.zeros_like(up["f90"]))
            rough = torch.full_like(up["roughness"], glint.roughness)
            weight = (up["f0"].mean(0, keepdim=True) / COAT_F0).clamp(0.0, 1.0)
            coat = Coat(weight=weight, roughness=up["roughness"].clone(), normal=normals.clone())
        out = EngineMaterial(base_color=texture.clone(), roughness=rough, f0=f0, f90=f90, normal=self.normal.clone(),
                             size=em.size, coat=coat, extras=dict(em.extras))
        return finish_base_color(out, texture)
