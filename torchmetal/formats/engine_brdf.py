"""The engine material and the BRDF engines evaluate on it, apart from the conversion that makes it.

:class:`EngineMaterial` (with its optional :class:`Coat`) holds the metallic-roughness maps of a
GGX dielectric; :func:`finish_base_color` divides the base colour by the energy the specular
layers take; :func:`engine_render` evaluates the glTF 2.0 + KHR_materials_specular +
KHR_materials_clearcoat BRDF on those maps and :func:`render_error` compares it with torchmetal's
own renderer (:func:`reference_render`) under :func:`check_lights`. The conversion from a
:class:`~torchmetal.material.Material` is :func:`torchmetal.formats.engine.engine_material`, the
flake bake :mod:`torchmetal.formats.bake`; both build on this module, and the conventions (light
units, quad and tangent frame) are in :mod:`torchmetal.formats.engine`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.formats.lobe_fit import ggx_terms
from torchmetal.geometry import is_flat, shading_geometry
from torchmetal.renderer import MaterialRenderer

if TYPE_CHECKING:
    from torchmetal.material import Material


COAT_F0 = 0.04  # glTF/OpenPBR clear coat at IOR 1.5


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


def reference_render(material: Material, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
    """torchmetal's render (B, 3, H, W) of ``material`` (the reference of :func:`render_error`)."""
    with torch.inference_mode():
        return MaterialRenderer(material.to("cpu")).eval()(light, intensity, camera)


def render_error(em: EngineMaterial, material: Material, light: Tensor, intensity: Tensor, camera: Tensor,
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
