"""Per-shot, per-pixel shading geometry on the sample plane (docs/design.md §2.1, 2.2).

The surface is the plane z = 0 centred at the origin; pixel (row i, col j) of an H×W image is
x = ((j + 0.5)/W − 0.5)·width, y = (0.5 − (i + 0.5)/H)·height. Lights and cameras are
homogeneous 4-vectors: w = 1 a position, w = 0 a direction towards the light / camera.

Everything here is written in plain, ONNX-exportable ops (manual normalisation, ``where``,
``clamp``) so the renderer can share it verbatim.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

_EPS = 1e-12


def surface_points(
    height: int,
    width: int,
    size: tuple[float, float],
    *,
    rows: tuple[int, int] | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """World positions of pixel centres on the plane z = 0.

    Args:
        height, width: image size H, W.
        size: (width, height) of the surface in scene units.
        rows: optional row range ``(r0, r1)`` to build only rows r0..r1-1 (chunked work).

    Returns:
        (3, R, W) tensor, R = r1 − r0 (H by default).
    """
    r0, r1 = rows if rows is not None else (0, height)
    x, y = pixel_axes(height, width, size, rows=slice(r0, r1), dtype=dtype, device=device)
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    return torch.stack([xx, yy, torch.zeros_like(xx)])


def pixel_axes(
    height: int,
    width: int,
    size: tuple[float, float],
    *,
    rows: slice = slice(None),
    cols: slice = slice(None),
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Plane coordinates of pixel centres, separably: x of the columns, y of the rows.

    Args:
        height, width: image size H, W.
        size: (width, height) of the surface in scene units.
        rows, cols: slices of the rows / columns to keep (e.g. a stride or a row block).

    Returns:
        x (C,) and y (R,) for the C kept columns and R kept rows.
    """
    i = torch.arange(height, dtype=dtype, device=device)[rows]
    j = torch.arange(width, dtype=dtype, device=device)[cols]
    return ((j + 0.5) / width - 0.5) * size[0], (0.5 - (i + 0.5) / height) * size[1]


def normalize(x: Tensor, dim: int = -3) -> Tensor:
    """Unit vectors along ``dim``; zero vectors stay zero (no NaN)."""
    n2 = (x * x).sum(dim, keepdim=True)
    return x / torch.sqrt(n2.clamp_min(_EPS * _EPS))


def is_flat(normals: Tensor) -> bool:
    """True when every normal of ``normals`` (3, ...) is exactly (0, 0, 1): the flat sample's cheaper paths."""
    return bool((normals[0] == 0).all() and (normals[1] == 0).all() and (normals[2] == 1).all())


def dot(a: Tensor, b: Tensor, dim: int = -3) -> Tensor:
    """Dot product along the channel axis, keeping it: (..., 3, H, W) → (..., 1, H, W)."""
    return (a * b).sum(dim, keepdim=True)


def direction_to(points: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Unit direction from surface points to homogeneous targets, and the squared distance.

    Args:
        points: (3, H, W) surface points.
        target: (B, 4) homogeneous lights or cameras (w = 1 position, w = 0 direction).

    Returns:
        unit direction (B, 3, H, W), squared distance (B, 1, H, W) (1 for directions).
    """
    xyz = target[:, :3, None, None]
    w = target[:, 3:4, None, None]
    d = xyz - w * points.unsqueeze(0)
    d2 = (d * d).sum(1, keepdim=True)
    unit = d / torch.sqrt(d2.clamp_min(_EPS * _EPS))
    dist2 = _light_dist2(d2, w)
    return unit, dist2


def reflect(n: Tensor, l: Tensor) -> Tensor:
    """Mirror direction r = 2(n·l)n − l, channel axis −3."""
    return 2.0 * dot(n, l) * n - l


@dataclass
class ShadingGeometry:
    """Per-shot shading terms, all (B, 1|3, H, W).

    ``spec_q`` = |r − v|²/2 = 1 − r·v, computed from the vectors so the lobe keeps its precision
    near the mirror direction (see :func:`torchmetal.phong.specular_lobe`).
    """

    n: Tensor  # (1|B, 3, H, W) unit normal
    l: Tensor  # (B, 3, H, W) unit, to light
    v: Tensor  # (B, 3, H, W) unit, to camera
    n_dot_l: Tensor  # (B, 1, H, W)
    spec_q: Tensor  # (B, 1, H, W) in [0, 2]
    irradiance: Tensor  # (B, 3, H, W)

    @property
    def r_dot_v(self) -> Tensor:
        return 1.0 - self.spec_q

    @property
    def half(self) -> Tensor:
        """Unit half vector (l + v)/|l + v|, (B, 3, H, W)."""
        return normalize(self.l + self.v)


def shading_geometry(
    normals: Tensor,
    light: Tensor,
    intensity: Tensor,
    camera: Tensor,
    size: tuple[float, float] | None = None,
    *,
    points: Tensor | None = None,
) -> ShadingGeometry:
    """Shading geometry of B shots.

    Args:
        normals: (3, H, W) unit normals (world frame).
        light: (B, 4) homogeneous light; intensity: (B, 3) radiant intensity (point) or
            irradiance (directional).
        camera: (B, 4) homogeneous camera.
        size: (width, height) of the surface; used to build the surface points.
        points: (3, H, W) precomputed surface points (e.g. a row chunk); overrides ``size``.

    Returns:
        :class:`ShadingGeometry` with irradiance E = intensity/dist² (point) or intensity.
    """
    if points is None:
        if size is None:
            raise TypeError("shading_geometry needs either size or points")
        points = surface_points(normals.shape[-2], normals.shape[-1], size, dtype=normals.dtype, device=normals.device)
    n = normals.unsqueeze(0)
    l, dist2 = direction_to(points, light)
    v, _ = direction_to(points, camera)
    r = reflect(n, l)
    rv = r - v
    spec_q = 0.5 * (rv * rv).sum(1, keepdim=True)
    irradiance = intensity[:, :, None, None] / dist2
    return ShadingGeometry(n=n, l=l, v=v, n_dot_l=dot(n, l), spec_q=spec_q, irradiance=irradiance)


def _grid_offsets(target: Tensor, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Offsets from the plane points (x_j, y_i, 0) to homogeneous targets (B, 4): dx (B, 1, C),
    dy (B, R, 1), dz (B, 1, 1), their squared length (B, R, C) and w (B, 1, 1)."""
    b = target.shape[0]
    w = target[:, 3].view(b, 1, 1)
    dx = target[:, 0].view(b, 1, 1) - w * x.view(1, 1, -1)
    dy = target[:, 1].view(b, 1, 1) - w * y.view(1, -1, 1)
    dz = target[:, 2].view(b, 1, 1)  # the plane is z = 0
    return dx, dy, dz, (dx * dx + dz * dz) + dy * dy, w


def grid_distance2(target: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """Squared distance (B, R, C) from the plane points (x_j, y_i, 0) to homogeneous targets
    (B, 4) (1 for directions), built separably (see :func:`pixel_axes` for x (C,), y (R,))."""
    *_, d2, w = _grid_offsets(target, x, y)
    return _light_dist2(d2, w)


def _light_dist2(d2: Tensor, w: Tensor) -> Tensor:
    """The squared distance d2 of a point target (w = 1), 1 for a direction (w = 0)."""
    return torch.where(w > 0.5, d2, 1.0)


def _grid_direction(target: Tensor, x: Tensor, y: Tensor) -> tuple[tuple[Tensor, Tensor, Tensor], Tensor]:
    """Unit direction components from the plane points (x_j, y_i, 0) to homogeneous targets (B, 4),
    each (B, R, C), and the squared distance (B, R, C) (1 for directions)."""
    dx, dy, dz, d2, w = _grid_offsets(target, x, y)
    inv = d2.clamp_min(_EPS * _EPS).rsqrt_()  # one reciprocal square root, three products
    return (dx * inv, dy * inv, dz * inv), _light_dist2(d2, w)


def grid_shading_terms(
    light: Tensor, camera: Tensor, x: Tensor, y: Tensor, normals: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """The scalar shading terms of :func:`shading_geometry` on a grid of plane points, cheaply.

    The plane points (x_j, y_i, 0) are separable, so the light and camera offsets are built per
    row and per column and only the scalar terms are formed per pixel (no (B, 3, R, C) vectors).
    Same formulas as :func:`shading_geometry` (q from |r − v|², not 1 − r·v).

    Args:
        light, camera: (B, 4) homogeneous light / camera.
        x: (C,) x of the columns; y: (R,) y of the rows (see :func:`pixel_axes`).
        normals: (3, R, C) unit normals, or None for the flat normal (0, 0, 1) everywhere.

    Returns:
        n·l (B, R, C), spec_q = |r − v|²/2 (B, R, C), squared light distance (B, R, C) (1 for a
        directional light).
    """
    (lx, ly, lz), dist2 = _grid_direction(light, x, y)
    (vx, vy, vz), _ = _grid_direction(camera, x, y)
    if normals is None:  # r = (−l_x, −l_y, l_z)
        nl = lz
        ex, ey, ez = lx + vx, ly + vy, lz - vz  # −(r − v) in x, y; r − v in z
    else:
        nx, ny, nz = normals.unsqueeze(1).unbind(0)  # (1, R, C) each
        nl = nx * lx + ny * ly + nz * lz
        k = 2.0 * nl
        ex, ey, ez = k * nx - lx - vx, k * ny - ly - vy, k * nz - lz - vz
    spec_q = (ex * ex).addcmul_(ey, ey).addcmul_(ez, ez).mul_(0.5)
    return nl, spec_q, dist2
