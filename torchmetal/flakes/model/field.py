"""Deterministic, hash-based flake field and its glint shading.

The texture plane is cut into square cells of ``C`` pixels. A 32-bit integer hash of
(cell row, cell column, seed, draw index) decides whether a cell holds a flake and draws that
flake's centre, ellipse, colour and normal tilt from the :class:`FlakeModel`. Integer hashing
in int64 (masked to 32 bits) is bit-identical on every device and runtime — no RNG ops.

With a density map (:attr:`FlakeModel.density_map`, glitter on part of the sample) a cell's
presence threshold is the local density, read at the map block of the cell's centre, and its colour
mean the block's (``color_map``) and its area log-mean ``area_log_mean`` plus the block's offset
(``area_map``); the hash bits are the same, so a uniform map of ones (and no area map) draws today's
field bit for bit, and the cell is sized for the densest block (:func:`field_cell`).

The field depends on the material only, not on the light, so it is built once (and baked into
the ONNX renderer). Footprints are anti-aliased ellipses whose weights sum to the drawn area (px²), so detected
flux/peak areas measure the model's area directly.

The light enters through the glint term

    sparkle = E · [n·l > 0] · w(p) · c(p) · exp(−|m(p) − h|² / (2 σ_g²)),

with w the flake footprint, c its colour, m its normal and h the half vector: moving the light
moves h smoothly, so glints fade in and out instead of flickering.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.flakes.model.params import MIN_CELL, FlakeModel
from torchmetal.geometry import ShadingGeometry, normalize, shading_geometry

_MASK32 = 0xFFFFFFFF
_TARGET_OCCUPANCY = 0.25  # fraction of cells holding a flake when the density allows it
_AREA_Q90 = 1.2816  # standard normal 90th percentile: with an area map the cell holds the largest block's 90 % flake


def hash32(x: Tensor) -> Tensor:
    """lowbias32 integer hash of the low 32 bits of an integer tensor, as int64 in [0, 2³²).

    Any integer dtype gives the same bits for the same values (int32/int16/uint8 inputs are
    widened to int64 first: 32-bit products would wrap before the mask); floats are rejected.
    """
    if x.is_floating_point() or x.is_complex() or x.dtype == torch.bool:
        raise InputError(f"hash32: expected an integer tensor, found dtype {x.dtype}")
    x = x.to(torch.int64) & _MASK32
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _MASK32
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & _MASK32
    x = x ^ (x >> 16)
    return x


def hash_uniform(ci: Tensor, cj: Tensor, seed: int, draw: int, dtype: torch.dtype) -> Tensor:
    """Uniform (0, 1) value for each cell and draw index, from chained hashes.

    Only the low 32 bits of ``seed`` and ``draw`` matter (so any Python int works and never
    overflows int64); float32 values are the float64 ones rounded to nearest.
    """
    seed, draw = int(seed) & _MASK32, int(draw) & _MASK32
    ci, cj = ci.to(torch.int64), cj.to(torch.int64)
    h = hash32(ci * 0x9E3779B1 + seed * 0x85EBCA77 + draw * 0xC2B2AE3D)
    h = hash32(h ^ (cj * 0x27D4EB2F))
    return ((h >> 8).to(dtype) + 0.5) * (1.0 / 16777216.0)


def _normal_pair(u1: Tensor, u2: Tensor) -> tuple[Tensor, Tensor]:
    """Box–Muller: two independent standard normals from two uniforms in (0, 1)."""
    r = torch.sqrt(-2.0 * torch.log(u1))
    return r * torch.cos(2.0 * math.pi * u2), r * torch.sin(2.0 * math.pi * u2)


def cell_size(density: float) -> int:
    """Cell edge in pixels so that about a quarter of the cells hold a flake."""
    if density <= 0:
        return MIN_CELL
    return max(MIN_CELL, math.ceil(math.sqrt(_TARGET_OCCUPANCY / density)))


def field_cell(model: FlakeModel) -> int:
    """Cell edge of ``model``'s field: sized for its densest block (the global density without a map;
    a uniform map of ones gives the same cell, so the same field bit for bit); with an area map, also
    at least the major axis of the largest block's 90th-percentile flake, as far as the densest
    block's presence probability stays ≤ 1."""
    if model.density_map is None:
        return cell_size(model.density)
    peak = model.density * float(model.density_map.max())
    c = cell_size(peak)
    if model.area_map is not None and peak > 0:  # room for the largest block's flakes (a flake never leaves its cell)
        big = math.exp(model.area_log_mean + float(model.area_map.max()) + _AREA_Q90 * model.area_log_std)
        need = math.ceil(2.0 * math.sqrt(big / (math.pi * min(max(model.aspect_mean, 0.2), 1.0))))
        c = max(c, min(need, math.floor(math.sqrt(1.0 / peak))))  # never past one flake per cell at the peak
    return c


def map_blocks(gh: int, gw: int, rows: Tensor, cols: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Block (row, col) of a gh×gw map covering an H×W texture for pixel ``rows``/``cols`` (int64)."""
    return (rows * gh // height).clamp(0, gh - 1), (cols * gw // width).clamp(0, gw - 1)


def _cell_maps(model: FlakeModel, c: int, gi: Tensor, gj: Tensor, height: int, width: int,
               dtype) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Per hash cell (the grid ``gi``, ``gj``): presence probability (dtype; computed in float64 as
    the scalar path's Python float is), colour mean (3, gi, gj) or None and area log-mean (gi, gj)
    (dtype; ``area_log_mean`` + the block's offset, in float64) or None, all read at the block of the
    cell's centre pixel."""
    dm = model.density_map.to(gi.device, torch.float64)
    rows = (gi * c + c // 2).clamp(max=height - 1)
    cols = (gj * c + c // 2).clamp(max=width - 1)
    bi, bj = map_blocks(dm.shape[0], dm.shape[1], rows, cols, height, width)
    presence = (model.density * dm[bi, bj] * c * c).clamp(max=1.0).to(dtype)
    mean = None
    if model.color_map is not None:
        mean = model.color_map.to(gi.device, dtype)[bi, bj].permute(2, 0, 1)
    log_mean = None
    if model.area_map is not None:
        log_mean = (model.area_log_mean + model.area_map.to(gi.device, torch.float64)[bi, bj]).to(dtype)
    return presence, mean, log_mean


@dataclass
class FlakeField:
    """Per-pixel flake maps (light-independent).

    weight: (1, H, W) footprint in [0, 1]; normal: (3, H, W) unit flake normal (world frame);
    color: (3, H, W) glint reflectance; glint_sigma: angular width (radians);
    count: number of flakes in the field.
    """

    weight: Tensor
    normal: Tensor
    color: Tensor
    glint_sigma: float
    count: int


def _tangent_frame(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit tangents (3, H, W), or (3, 1, 1) for a flat surface, orthogonal to the unit normals n."""
    if bool(((n[0] == 0) & (n[1] == 0) & (n[2] == 1)).all()):
        # flat: the general case below gives exactly x and y there; a third of a flake field's time at 1024²
        t1 = torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype, device=n.device).view(3, 1, 1)
        return t1, torch.tensor([0.0, 1.0, 0.0], dtype=n.dtype, device=n.device).view(3, 1, 1)
    ex = torch.zeros_like(n)
    ex[0] = 1.0
    t1 = normalize(ex - (ex * n).sum(0, keepdim=True) * n, dim=0)
    t2 = torch.cross(n, t1, dim=0)
    return t1, t2


def flake_field(model: FlakeModel, height: int, width: int, normals: Tensor | None = None) -> FlakeField:
    """Build the deterministic flake field of ``model`` on an H×W texture.

    Args:
        model: flake statistics (density per pixel, areas in px², tilt/glint in radians).
        height, width: texture size.
        normals: optional (3, H, W) surface normals the flake tilt is relative to
            (default (0, 0, 1)); its dtype/device are used, else float32 on CPU.

    Returns:
        :class:`FlakeField`.
    """
    dtype = normals.dtype if normals is not None else torch.float32
    device = normals.device if normals is not None else None
    if normals is None:
        normals = torch.zeros(3, height, width, dtype=dtype, device=device)
        normals[2] = 1.0
    c = field_cell(model)
    ii = torch.arange(height, device=device)
    jj = torch.arange(width, device=device)
    ci = (ii // c).view(-1, 1).expand(height, width)
    cj = (jj // c).view(1, -1).expand(height, width)

    # hash once per cell, then gather to the pixels (c² times fewer integer ops, same bits)
    gi = torch.arange(-(-height // c), device=device).view(-1, 1)
    gj = torch.arange(-(-width // c), device=device).view(1, -1)
    gi, gj = gi.expand(gi.shape[0], gj.shape[1]), gj.expand(gi.shape[0], gj.shape[1])

    def u(k: int) -> Tensor:
        return hash_uniform(gi, gj, model.seed, k, dtype)[ci, cj]

    presence, present, cell_mean, cell_log_area = _presence(model, c, gi, gj, ci, cj, u, height, width, dtype)
    weight = _footprint(model, c, ii, jj, ci, cj, u, cell_log_area, dtype) * present.to(dtype)

    sx, sy = _normal_pair(u(6), u(7))
    t1, t2 = _tangent_frame(normals)
    m = normalize(normals + model.tilt_sigma * (sx * t1 + sy * t2), dim=0)
    color = _colour(model, ci, cj, u, cell_mean, dtype, device)

    count = int((present & (ci * c < height) & (cj * c < width))[::c, ::c].sum()) if presence > 0 else 0
    return FlakeField(weight.unsqueeze(0), m, color, float(model.glint_sigma), count)


def _presence(model: FlakeModel, c: int, gi: Tensor, gj: Tensor, ci: Tensor, cj: Tensor, u, height: int, width: int,
              dtype: torch.dtype) -> tuple[float, Tensor, Tensor | None, Tensor | None]:
    """The (largest) probability that a cell holds a flake, the pixels' cells that do (H, W) bool, and with a
    density map the cells' colour means and area log-means (None without one)."""
    if model.density_map is None:
        presence = min(1.0, model.density * c * c)
        cell_mean = cell_log_area = None
        present = u(0) < presence
    else:  # the local density: same hash bits, a per-cell threshold
        cell_presence, cell_mean, cell_log_area = _cell_maps(model, c, gi, gj, height, width, dtype)
        presence = float(cell_presence.max())
        present = hash_uniform(gi, gj, model.seed, 0, dtype)[ci, cj] < cell_presence[ci, cj]
    return presence, present, cell_mean, cell_log_area


def _footprint(model: FlakeModel, c: int, ii: Tensor, jj: Tensor, ci: Tensor, cj: Tensor, u,
               cell_log_area: Tensor | None, dtype: torch.dtype) -> Tensor:
    """(H, W) anti-aliased ellipse weight of each pixel's cell's flake (whether or not the cell holds one)."""
    z_area, z_aspect = _normal_pair(u(3), u(4))
    if cell_log_area is None:
        area = torch.exp(model.area_log_mean + model.area_log_std * z_area)
    else:  # the block's area log-mean: same hash bits
        area = torch.exp(cell_log_area[ci, cj] + model.area_log_std * z_area)
    aspect = (model.aspect_mean + model.aspect_std * z_aspect).clamp(0.2, 1.0)
    a, b = _axes(area, aspect, 0.5 * c)  # a flake never leaves its cell
    margin = a.clamp(max=0.5 * c)
    cy = ci.to(dtype) * c + margin + u(1) * (c - 2 * margin)
    cx = cj.to(dtype) * c + margin + u(2) * (c - 2 * margin)
    theta = math.pi * u(5)
    dy = ii.to(dtype).view(-1, 1) + 0.5 - cy
    dx = jj.to(dtype).view(1, -1) + 0.5 - cx
    return _ellipse_weight(a, b, dy, dx, theta)


def _axes(area: Tensor, aspect: Tensor, max_axis: float) -> tuple[Tensor, Tensor]:
    """Semi-axes (a, b) in px of the anti-aliased ellipse of ``area`` px² and ``aspect`` (minor/major)."""
    a = torch.sqrt(area / (math.pi * aspect))  # semi-major axis (px)
    b = aspect * a
    # the 1-px anti-aliasing ramp adds π/(12·aspect) px² to the footprint; shrinking both
    # axes by k = √(1 − 1/(12 b²)) makes Σ weight = area (exact for b ≳ 0.4 px)
    k = torch.sqrt((1.0 - 1.0 / (12.0 * b * b)).clamp_min(0.25))
    a = a * k
    b = b * k
    a = a.clamp(max=max_axis)
    return a, torch.minimum(b, a)


def _ellipse_weight(a: Tensor, b: Tensor, dy: Tensor, dx: Tensor, theta: Tensor) -> Tensor:
    """Footprint weight in [0, 1] of a pixel centre (dy, dx) px from an ellipse's centre (rows down)."""
    # image rows grow downwards; angle measured from +x towards +y (up) like the surface frame
    along = dx * torch.cos(theta) - dy * torch.sin(theta)
    across = dx * torch.sin(theta) + dy * torch.cos(theta)
    rho = torch.sqrt((along / a) ** 2 + (across / b) ** 2)
    return ((1.0 - rho) * b + 0.5).clamp(0.0, 1.0)


#: draws of :func:`mean_peak_weight`: its mean's standard error stays under ~0.5 % of a weight in [0.3, 1]
PEAK_DRAWS = 4096


def mean_peak_weight(area_log_mean: float, area_log_std: float, aspect_mean: float, aspect_std: float,
                     *, draws: int = PEAK_DRAWS) -> float:
    """E[largest footprint weight of a flake's pixels] of the field's flakes with this shape distribution.

    A flake renders as E·w·c·g (:func:`sparkle_shading`), so its brightest pixel holds c times this
    weight: below 1 for a fine flake that no pixel centre sits deep inside. Deterministic (fixed
    draws): a flake's centre uniform in its pixel, its angle uniform, the 3×3 pixels around it.
    """
    gen = torch.Generator().manual_seed(0)
    z = torch.randn(2, draws, generator=gen, dtype=torch.float64)
    area = torch.exp(area_log_mean + area_log_std * z[0])
    aspect = (aspect_mean + aspect_std * z[1]).clamp(0.2, 1.0)
    a, b = _axes(area, aspect, math.inf)
    off = torch.rand(3, draws, generator=gen, dtype=torch.float64)
    theta = math.pi * off[2]
    step = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)
    dy = (step.view(3, 1, 1) + 0.5 - off[0]).expand(3, 3, draws)  # (3, 3, D): pixel rows −1, 0, 1
    dx = (step.view(1, 3, 1) + 0.5 - off[1]).expand(3, 3, draws)
    w = _ellipse_weight(a, b, dy, dx, theta)
    return float(w.flatten(0, 1).max(0).values.mean())


def _colour(model: FlakeModel, ci: Tensor, cj: Tensor, u, cell_mean: Tensor | None, dtype: torch.dtype,
            device) -> Tensor:
    """(3, H, W) colour of each pixel's cell's flake: the mean (the block's with a density map) plus the
    colour covariance's factor times normal draws, clamped at 0."""
    z1, z2 = _normal_pair(u(8), u(9))
    z3, _ = _normal_pair(u(10), u(11))
    chol = colour_factor(model.color_cov).to(dtype=dtype, device=device)
    mean = torch.tensor(model.color_mean, dtype=dtype, device=device).view(3, 1, 1)
    if cell_mean is not None:
        mean = cell_mean[:, ci, cj]
    z = torch.stack([z1, z2, z3])
    return (mean + torch.einsum("ij,jhw->ihw", chol, z)).clamp_min(0.0)


def colour_factor(cov: Sequence[Sequence[float]] | Tensor) -> Tensor:
    """L (3, 3) float64 with L·Lᵀ = cov: the symmetric square root of cov's PSD part.

    An eigen-decomposition with negative eigenvalues clipped to 0, so a covariance that is PSD
    only to rounding (FlakeModel checks it) never fails the way a Cholesky factorisation does.
    """
    c = torch.tensor(cov, dtype=torch.float64)
    vals, vecs = torch.linalg.eigh(0.5 * (c + c.T))
    return vecs * vals.clamp_min(0.0).sqrt().unsqueeze(0) @ vecs.T


def sparkle_shading(field: FlakeField, geom: ShadingGeometry) -> Tensor:
    """Glint radiance of the flake field for B shots, (B, 3, H, W)."""
    d = field.normal.unsqueeze(0) - geom.half
    g = torch.exp(-(d * d).sum(1, keepdim=True) / (2.0 * field.glint_sigma**2))
    g = torch.where(geom.n_dot_l > 0, g, torch.zeros_like(g))
    return geom.irradiance * (field.weight * field.color).unsqueeze(0) * g


def sparkle_render(
    field: FlakeField,
    normals: Tensor,
    light: Tensor,
    intensity: Tensor,
    camera: Tensor,
    size: tuple[float, float],
) -> Tensor:
    """Additive sparkle image of B shots, (B, 3, H, W)."""
    return sparkle_shading(field, shading_geometry(normals, light, intensity, camera, size))
