"""Tiny synthetic flake captures with known truth (Phong + hash flake field + noise + 8-bit)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.field import FlakeField, flake_field, sparkle_render
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
    from torchmetal.flakes.model.field import _normal_pair, _tangent_frame, cell_size, hash_uniform

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


@dataclass
class ResidualScene:
    """Photos = Phong + known Gaussian glints + brightness-dependent noise (see :func:`residual_scene`)."""

    photos: torch.Tensor  # (N, 3, H, W)
    phong: torch.Tensor  # (N, 3, H, W) the Phong estimate handed to the detector
    irradiance: torch.Tensor  # (N, 3, 1, 1)
    sigma: torch.Tensor  # (N, 1, H, W) true per-pixel noise σ of each photo channel
    shot: torch.Tensor  # (F,) int64 shot of each true glint
    row: torch.Tensor  # (F,) glint centre, pixel-centre coordinates (row + 0.5 at a pixel centre)
    col: torch.Tensor  # (F,)
    peak: torch.Tensor  # (F,) peak of the channel-mean glint in photo units
    bright: torch.Tensor  # (F,) bool, glint lies on the bright half of the texture


def residual_scene(
    h: int = 128,
    w: int = 128,
    *,
    shots: int = 2,
    noise: float = 0.004,
    snr: tuple[float, float] = (10.0, 16.0),
    spacing: int = 16,
    bright: float = 0.5,
    dark: float = 0.02,
    edge_margin: int = 40,
    seed: int = 0,
) -> ResidualScene:
    """A detector test scene with known glints on a bright (left) and a dark (right) texture half.

    The photo noise is shot-noise-like, σ ∝ √(Phong), so the bright half is ~√(bright/dark)
    times noisier; each glint's channel-mean peak is ``snr``× the *local* σ of that mean, so a
    single global threshold cannot find the dark-half glints without flooding the bright half
    with false alarms. Glints sit on a jittered ``spacing`` grid, at least 12 px from the image
    border and ``edge_margin`` px from the texture edge (the detector's noise map is smoothed
    over ~1.5 tiles, so next to a sharp noise step the dark side's σ reads high), as isotropic
    Gaussians (σ 0.6–1.2 px, random colour).
    The Phong estimate carries a smooth additive error (0.5 % of the bright level, ~250 px
    wavelength), as a real fit would.
    """
    gen = torch.Generator().manual_seed(seed)
    half = w // 2
    tex = torch.full((3, h, w), dark)
    tex[:, :, :half] = bright
    tex = tex * torch.tensor([1.0, 0.9, 0.8]).view(3, 1, 1)
    e = 1.0 + 0.5 * torch.rand(shots, 1, 1, 1, generator=gen)
    phong = e * tex.unsqueeze(0).expand(shots, -1, -1, -1)
    sigma = noise * torch.sqrt(phong.mean(1, keepdim=True) / bright)  # per channel
    sigma_mean = sigma / math.sqrt(3.0)  # σ of the channel mean
    shot, rows, cols, on_bright = [], [], [], []
    for k in range(shots):
        for r0 in range(12, h - 12, spacing):
            for c0 in range(12, w - 12, spacing):
                if abs(c0 + 1 - half) < edge_margin:
                    continue
                shot.append(k), rows.append(r0), cols.append(c0), on_bright.append(c0 < half)
    n = len(shot)
    shot_t = torch.tensor(shot, dtype=torch.int64)
    row = torch.tensor(rows, dtype=torch.float32) + 2.0 * torch.rand(n, generator=gen) + 0.5
    col = torch.tensor(cols, dtype=torch.float32) + 2.0 * torch.rand(n, generator=gen) + 0.5
    width = 0.6 + 0.6 * torch.rand(n, generator=gen)
    z = snr[0] + (snr[1] - snr[0]) * torch.rand(n, generator=gen)
    colour = 0.6 + 0.8 * torch.rand(n, 3, generator=gen)
    colour = colour / colour.mean(1, keepdim=True)
    peak = z * sigma_mean[shot_t, 0, row.long(), col.long()]
    # each glint drawn on its 11×11 neighbourhood (the Gaussian is < 1e-8 of its peak beyond)
    d = torch.arange(-5, 6)
    ii = (row.long().view(-1, 1, 1) + d.view(1, -1, 1)).expand(-1, 11, 11)
    jj = (col.long().view(-1, 1, 1) + d.view(1, 1, -1)).expand(-1, 11, 11)
    blob = torch.exp(-((ii + 0.5 - row.view(-1, 1, 1)) ** 2 + (jj + 0.5 - col.view(-1, 1, 1)) ** 2) / (2 * width.view(-1, 1, 1) ** 2))
    glints = torch.zeros(shots, h, w, 3)
    kk = shot_t.view(-1, 1, 1).expand_as(ii)
    glints.index_put_((kk, ii, jj), (peak.view(-1, 1, 1) * blob).unsqueeze(-1) * colour.view(-1, 1, 1, 3), accumulate=True)
    glints = glints.permute(0, 3, 1, 2)
    yy = torch.arange(h, dtype=torch.float32).view(-1, 1) + 0.5
    xx = torch.arange(w, dtype=torch.float32).view(1, -1) + 0.5
    yy01, xx01 = yy / h, xx / w
    error = 0.005 * bright * e * torch.sin(2 * math.pi * (0.7 * xx01 + 0.4 * yy01))
    photos = phong + glints + sigma * torch.randn(phong.shape, generator=gen)
    return ResidualScene(
        photos, (phong + error).contiguous(), e.expand(-1, 3, -1, -1).contiguous(), sigma,
        shot_t, row, col, peak, torch.tensor(on_bright, dtype=torch.bool),
    )


def capture_of(scene: Scene):
    """The :class:`~torchmetal.io.capture.Capture` of a :func:`make_scene` scene (its photos,
    normals, lights, cameras and size; saturated where the photo clipped)."""
    from torchmetal.io.capture import Capture

    return Capture(
        images=scene.photos, normals=scene.normals, lights=scene.lights, intensities=scene.intensities,
        cameras=scene.cameras, size=scene.size, saturated=(scene.photos >= 1.0),
    )
