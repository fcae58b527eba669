"""Tiny synthetic flake captures with known truth (Phong + hash flake field + noise + 8-bit)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchmetal.flakes.field import FlakeField, flake_field, sparkle_render
from torchmetal.flakes.model import FlakeModel
from torchmetal.geometry import normalize, shading_geometry
from torchmetal.phong import phong_render


def _texture(kind: str, h: int, w: int, gen: torch.Generator) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    if kind == "checker":
        base = ((torch.floor(xx * 8) + torch.floor(yy * 8)) % 2) * 0.15 + 0.15
        tex = torch.stack([base, base * 0.9, base * 0.7])
    elif kind == "stripes":
        base = 0.2 + 0.1 * torch.sin(2 * math.pi * 6 * xx + 3 * yy)
        tex = torch.stack([base * 0.6, base, base * 1.2])
    else:  # smooth noise
        lo = torch.rand(3, 1, 9, 9, generator=gen)
        tex = torch.nn.functional.interpolate(lo, size=(h, w), mode="bicubic", align_corners=True)[:, 0]
        tex = 0.1 + 0.25 * tex.clamp(0, 1)
    return tex.clamp(0.02, 0.6)


def _normals(bumpy: bool, h: int, w: int) -> torch.Tensor:
    n = torch.zeros(3, h, w)
    n[2] = 1.0
    if bumpy:
        yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
        n[0] = 0.08 * torch.sin(2 * math.pi * 2 * xx)
        n[1] = 0.08 * torch.cos(2 * math.pi * 1.5 * yy)
        n = normalize(n, dim=0)
    return n


def layout(kind: str = "pairs", shots: int = 8) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(lights (N,4), intensities (N,3), cameras (N,4)) for a 1×1 sample."""
    lights, cams = [], []
    if kind == "pairs":  # light pairs a few glint widths apart, fixed camera
        for i in range(shots):
            pair = i // 2
            az = 2 * math.pi * pair / max(1, shots // 2) + 0.3
            r = (0.3 if pair % 2 == 0 else 0.7) + 0.06 * (i % 2)
            lights.append([r * math.cos(az), r * math.sin(az), 2.0, 1.0])
            cams.append([0.0, 0.0, 2.5, 1.0])
    elif kind == "flash":  # light at the camera, camera moving (like cards_blue)
        for i in range(shots):
            az = 2 * math.pi * i / shots
            r = 0.03 + 0.05 * (i % 3)
            p = [r * math.cos(az), r * math.sin(az), 2.2, 1.0]
            lights.append(p)
            cams.append(p)
    else:
        raise ValueError(kind)
    lights_t = torch.tensor(lights)
    inten = torch.full((len(lights), 3), 4.0)
    return lights_t, inten, torch.tensor(cams)


def srgb_decode(x: torch.Tensor) -> torch.Tensor:
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


@dataclass
class Scene:
    photos: torch.Tensor  # (N,3,H,W)
    phong: torch.Tensor  # (N,3,H,W) true Phong render
    sparkle: torch.Tensor  # (N,3,H,W) true sparkle term
    irradiance: torch.Tensor  # (N,3,H,W)
    valid: torch.Tensor  # (N,1,H,W)
    normals: torch.Tensor
    lights: torch.Tensor
    intensities: torch.Tensor
    cameras: torch.Tensor
    size: tuple[float, float]
    texture: torch.Tensor
    s: torch.Tensor
    alpha: torch.Tensor
    model: FlakeModel | None
    field: FlakeField | None
    noise: float


def make_scene(
    h: int = 256,
    w: int = 256,
    model: FlakeModel | None = None,
    *,
    texture: str = "noise",
    bumpy: bool = False,
    kind: str = "pairs",
    shots: int = 8,
    noise: float = 0.004,
    quantize: bool = True,
    seed: int = 0,
) -> Scene:
    gen = torch.Generator().manual_seed(seed)
    tex = _texture(texture, h, w, gen)
    normals = _normals(bumpy, h, w)
    lights, inten, cams = layout(kind, shots)
    size = (1.0, 1.0)
    s = torch.tensor([0.15, 0.15, 0.15])
    alpha = torch.tensor([40.0, 40.0, 40.0])
    phong = phong_render(tex, s, alpha, normals, lights, inten, cams, size)
    geom = shading_geometry(normals, lights, inten, cams, size)
    field = None
    sparkle = torch.zeros_like(phong)
    if model is not None:
        field = flake_field(model, h, w, normals)
        sparkle = sparkle_render(field, normals, lights, inten, cams, size)
    img = phong + sparkle + noise * torch.randn(phong.shape, generator=gen)
    img = img.clamp(0, 1)
    valid = (img < 1.0).all(1, keepdim=True)
    if quantize:
        img = srgb_decode(torch.round(srgb_encode(img) * 255) / 255)
    irr = geom.irradiance.expand(-1, 3, h, w).contiguous()
    return Scene(img, phong, sparkle, irr, valid, normals, lights, inten, cams, size, tex, s, alpha, model, field, noise)


def true_flakes(model: FlakeModel, h: int, w: int, normals: torch.Tensor) -> dict:
    """Per-flake truth of :func:`flake_field` (same hash draws): centre, normal, colour, area."""
    from torchmetal.flakes.field import _normal_pair, _tangent_frame, cell_size, hash_uniform

    c = cell_size(model.density)
    presence = min(1.0, model.density * c * c)
    gi = torch.arange(0, -(-h // c))
    gj = torch.arange(0, -(-w // c))
    ci, cj = torch.meshgrid(gi, gj, indexing="ij")

    def u(k: int) -> torch.Tensor:
        return hash_uniform(ci, cj, model.seed, k, torch.float32)

    present = (u(0) < presence) & (ci * c < h) & (cj * c < w)
    z_area, _ = _normal_pair(u(3), u(4))
    area = torch.exp(model.area_log_mean + model.area_log_std * z_area)
    sx, sy = _normal_pair(u(6), u(7))
    z1, z2 = _normal_pair(u(8), u(9))
    z3, _ = _normal_pair(u(10), u(11))
    chol = torch.linalg.cholesky(torch.tensor(model.color_cov, dtype=torch.float64) + 1e-12 * torch.eye(3, dtype=torch.float64)).float()
    color = (torch.tensor(model.color_mean).view(3, 1, 1) + torch.einsum("ij,jhw->ihw", chol, torch.stack([z1, z2, z3]))).clamp_min(0)
    row = (ci * c + c // 2).clamp(max=h - 1)
    col = (cj * c + c // 2).clamp(max=w - 1)
    n = normals[:, row, col]
    t1, t2 = _tangent_frame(n)
    m = normalize(n + model.tilt_sigma * (sx * t1 + sy * t2), dim=0)
    p = present
    return {"row": row[p], "col": col[p], "normal": m[:, p].t(), "color": color[:, p].t(), "area": area[p], "count": int(p.sum())}
