"""MaterialX ``flake2d`` (1.39.5 stdlib): a numpy port of its pattern, and the mapping from
torchmetal's :class:`~torchmetal.flakes.model.FlakeModel` to its inputs.

``flake2d(size, roughness, coverage, texcoord)`` cuts the texture plane into cells of ``size``
(texcoord units); a cell holds a flake with probability p(coverage) (MaterialX's fitted rational
curve); a flake is a randomly rotated cube of half-side 1.5/√3 cells cut by the plane, and the
highest-priority flake wins where flakes overlap. Its normal is a GGX sample, tan θ = r²·√(ξ/(1−ξ)).
:func:`flake2d_pattern` reproduces this bit for bit (Jenkins lookup3 hashes in uint32, as in
``mx_noise.glsl``/``mx_flake.glsl``), so the statistics below are those of the shader itself.

Mapping (:func:`flake2d_inputs`), texel units, 1 texcoord unit = the texture width W:

- ``coverage``: flake2d's covered fraction follows the Boolean model 1 − exp(−p·A), A the mean
  plane-section area of one isolated flake per column of cells (measured once on the port,
  :func:`isolated_flake_stats`); torchmetal's is density·E[area] (its flakes never overlap).
  ``coverage`` is the input whose probability p gives that fraction.
- ``size``: flake2d then shows p·Q flakes per cell², Q the mean number of flakes per column whose
  section is not empty; size = √(p·Q/density)/W makes the flake count per texel the model's density
  (and so the mean flake area the model's E[area]).
- ``roughness``: torchmetal's flake slopes are isotropic Gaussians, tan θ = σ·|N(0, I₂)|; GGX's
  are p(s) = 1/(π a²(1 + s²/a²)²). Glints come from flakes whose slope equals the half vector's, so
  a (= roughness²) is fitted to the slope density (relative error) over the slopes where 99 % of
  torchmetal's flakes lie; the closed-form start is the median match a = σ·√(2 ln 2).

Not mapped: flake shape (flake2d's sections of rotated cubes vs torchmetal's ellipses), the area
spread, per-flake colour (flake2d gives a normal only; the glint colour is the mean colour) and the
glint width (set by the base specular roughness, fitted to one glint).

:func:`glint_statistics` compares the two models (covered fraction, flakes per texel, mean
area, fraction of flakes glinting for a half vector at several tilts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.errors import ExportError
from torchmetal.formats.brent import minimize_bounded

if TYPE_CHECKING:
    from torchmetal.flakes.model import FlakeModel


_U32 = np.uint32
_DIAM = 1.5 / math.sqrt(3.0)  # flake_diameter of mx_flake.glsl (cube half-side, cell units)


# ------------------------------------------------------------------------------ mx_noise hashes
def _rot(x: np.ndarray, k: int) -> np.ndarray:
    return (x << _U32(k)) | (x >> _U32(32 - k))


def _mix(a, b, c):
    a = a - c; a ^= _rot(c, 4); c = c + b  # noqa: E702
    b = b - a; b ^= _rot(a, 6); a = a + c  # noqa: E702
    c = c - b; c ^= _rot(b, 8); b = b + a  # noqa: E702
    a = a - c; a ^= _rot(c, 16); c = c + b  # noqa: E702
    b = b - a; b ^= _rot(a, 19); a = a + c  # noqa: E702
    c = c - b; c ^= _rot(b, 4); b = b + a  # noqa: E702
    return a, b, c


def _final(a, b, c):
    c = c ^ b; c = c - _rot(b, 14)  # noqa: E702
    a = a ^ c; a = a - _rot(c, 11)  # noqa: E702
    b = b ^ a; b = b - _rot(a, 25)  # noqa: E702
    c = c ^ b; c = c - _rot(b, 16)  # noqa: E702
    a = a ^ c; a = a - _rot(c, 4)  # noqa: E702
    b = b ^ a; b = b - _rot(a, 14)  # noqa: E702
    c = c ^ b; c = c - _rot(b, 24)  # noqa: E702
    return c


def _to01(bits: np.ndarray) -> np.ndarray:
    return bits.astype(np.float64) / float(0xFFFFFFFF)


def _seed(n: int) -> np.uint32:
    return _U32((0xDEADBEEF + (n << 2) + 13) & 0xFFFFFFFF)


def cell_noise_float3(ix, iy, iz) -> np.ndarray:
    """mx_cell_noise_float(vec3) of integer cells."""
    s = _seed(3)
    with np.errstate(over="ignore"):
        return _to01(_final(s + ix.astype(_U32), s + iy.astype(_U32), s + iz.astype(_U32)))


def cell_noise_float4(ix, iy, iz, iw) -> np.ndarray:
    """mx_cell_noise_float(vec4) of integer cells."""
    s = _seed(4)
    with np.errstate(over="ignore"):
        a, b, c = _mix(s + ix.astype(_U32), s + iy.astype(_U32), s + iz.astype(_U32))
        return _to01(_final(a + _U32(iw), b, c))


def cell_noise_vec3_3(ix, iy, iz) -> np.ndarray:
    """mx_cell_noise_vec3(vec3): (..., 3)."""
    s = _seed(4)
    with np.errstate(over="ignore"):
        a, b, c = _mix(s + ix.astype(_U32), s + iy.astype(_U32), s + iz.astype(_U32))
        return np.stack([_to01(_final(a + _U32(k), b, c)) for k in range(3)], -1)


def cell_noise_vec3_4(ix, iy, iz, iw) -> np.ndarray:
    """mx_cell_noise_vec3(vec4): (..., 3)."""
    s = _seed(5)
    with np.errstate(over="ignore"):
        a, b, c = _mix(s + ix.astype(_U32), s + iy.astype(_U32), s + iz.astype(_U32))
        a = a + _U32(iw)
        return np.stack([_to01(_final(a, b + _U32(k), c)) for k in range(3)], -1)


def density_to_probability(x):
    """mx_flake_density_to_probability: coverage input → per-cell flake probability."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    a, b, c, d, e, f = -26.19771808, 26.39663835, 85.53857017, -102.35069432, -101.42634862, 118.45082288
    return (a * x * x + b * x) / (c * x ** 3 + d * x * x + e * x + f)


def _rotate(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    """mx_rotate_flake (Arvo's fast random rotation) of points p (..., 3) by uniforms r (..., 3)."""
    theta, phi, z = 2 * math.pi * r[..., 0], 2 * math.pi * r[..., 1], 2 * r[..., 2]
    rr = np.sqrt(z)
    vx, vy, vz = np.sin(phi) * rr, np.cos(phi) * rr, np.sqrt(2 - z)
    st, ct = np.sin(theta), np.cos(theta)
    sx, sy = vx * ct - vy * st, vx * st + vy * ct
    # GLSL mat3 is column-major: m * p = sum_j column_j * p_j
    c0 = np.stack([vx * sx - ct, vx * sy - st, vx * vz], -1)
    c1 = np.stack([vy * sx + st, vy * sy - ct, vy * vz], -1)
    c2 = np.stack([vz * sx, vz * sy, 1 - z], -1)
    return c0 * p[..., 0:1] + c1 * p[..., 1:2] + c2 * p[..., 2:3]


# ----------------------------------------------------------------------------------- pattern
_OFFS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])


def _cells(c: np.ndarray):
    return (c[..., i].astype(np.int32).view(np.uint32) for i in range(3))


def _inside(pp: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """Whether the rotated flake cube of each cell contains the offsets pp (..., 3) from its centre."""
    return (np.abs(_rotate(pp, cell_noise_vec3_3(*_cells(cell)))) <= _DIAM).all(-1)


def flake2d_pattern(points: np.ndarray, size: float, roughness: float, coverage: float) -> tuple[np.ndarray, np.ndarray]:
    """flake2d at texcoord points (N, 2), as mx_flake.glsl: the winning flake's cell key (N,)
    (−1: none) and the flake normal (N, 3) in the tangent frame (+z the surface normal)."""
    probability = float(density_to_probability(coverage))
    p = np.concatenate([np.asarray(points, dtype=np.float64) / size, np.zeros((len(points), 1))], 1)
    cell = np.floor(p).astype(np.int64)[:, None, :] + _OFFS[None]  # (N, 27, 3)
    pp = p[:, None, :] - cell - 0.5
    ok = ((pp * pp).sum(-1) < _DIAM * _DIAM * 3.0) & (cell_noise_float3(*_cells(cell)) <= probability)
    pi, ci = np.nonzero(ok)  # only present, near cells are rotated
    hit = _inside(pp[pi, ci], cell[pi, ci])
    pi, ci = pi[hit], ci[hit]
    prio = np.full(ok.shape, -1.0)
    cc = cell[pi, ci]
    prio[pi, ci] = cell_noise_float4(*_cells(cc), 3)
    j = prio.argmax(1)
    found = np.take_along_axis(prio, j[:, None], 1)[:, 0] > 0.0
    win = cell[np.arange(len(p)), j]
    key = np.where(found, (((win[:, 0] + 2**20) << 21) + (win[:, 1] + 2**20)) * 4 + (win[:, 2] + 1), -1)  # ≥ 0
    xi = cell_noise_vec3_4(*_cells(win), 2)
    a = roughness * roughness
    tan_t = a * np.sqrt(xi[:, 1]) / np.sqrt(1.0 - xi[:, 1])
    sin_t = tan_t / np.sqrt(1.0 + tan_t * tan_t)
    cos_t = np.sqrt(1.0 - sin_t * sin_t)
    phi = 2 * math.pi * xi[:, 0]
    n = np.stack([np.cos(phi) * sin_t, np.sin(phi) * sin_t, cos_t], -1)
    n[~found] = (0.0, 0.0, 1.0)
    return key, n


@lru_cache(maxsize=1)
def isolated_flake_stats(cells: int = 40, samples: int = 256) -> tuple[float, float]:
    """Per column of cells (the three z layers the plane can cut), the mean area (cell²) the flakes'
    plane sections cover and the mean number of flakes that show at all, each flake alone;
    Monte Carlo over ``cells``² columns with ``samples`` points per 3×3-cell window."""
    g = np.random.default_rng(0)
    ij = np.stack(np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij"), -1).reshape(-1, 2)
    area = np.zeros(len(ij))
    shows = np.zeros(len(ij))
    for k in (-1, 0, 1):
        cell = np.concatenate([ij, np.full((len(ij), 1), k)], 1)
        pts = g.uniform(-1.0, 2.0, size=(len(ij), samples, 2))  # cell-local window [-1, 2)²
        pp = np.concatenate([pts - 0.5, np.full(pts.shape[:2] + (1,), -0.5 - k)], -1)
        inside = _inside(pp, np.repeat(cell[:, None, :], samples, 1))
        a = inside.mean(1) * 9.0
        area += a
        shows += a > 0
    return float(area.mean()), float(shows.mean())


# ----------------------------------------------------------------------------------- mapping
def slope_density_ours(s: np.ndarray, sigma: float) -> np.ndarray:
    return np.exp(-s * s / (2 * sigma * sigma)) / (2 * math.pi * sigma * sigma)


def slope_density_ggx(s: np.ndarray, a: float) -> np.ndarray:
    return 1.0 / (math.pi * a * a * (1 + s * s / (a * a)) ** 2)


def fit_flake_roughness(tilt_sigma: float) -> tuple[float, float]:
    """GGX a for torchmetal's Gaussian slopes (see the module docstring); returns (roughness, relative
    RMS error of the slope density over the slopes that hold 99 % of the flakes)."""
    sigma = max(float(tilt_sigma), 1e-4)
    s = np.linspace(0.0, sigma * math.sqrt(-2 * math.log(0.01)), 200)
    w = s  # polar measure: slope density × s ds
    ref = slope_density_ours(s, sigma)

    def err(log_a: float) -> float:
        d = slope_density_ggx(s, math.exp(log_a)) - ref
        return float(np.sqrt((w * d * d).sum() / (w * ref * ref).sum()))

    a0 = sigma * math.sqrt(2 * math.log(2))
    x, _ = minimize_bounded(err, math.log(a0) - 2, math.log(a0) + 2)
    return math.sqrt(math.exp(x)), err(x)


@dataclass
class Flake2dInputs:
    size: float  # texcoord units (1 = texture width)
    roughness: float
    coverage: float
    probability: float
    covered_fraction: float  # target fraction (torchmetal)
    slope_error: float
    drawn: bool = False  # the target is the flake field's drawn coverage (flakes clamped to their cells)


MAX_COVERED = 0.95  # flake2d's Boolean model cannot cover more


def drawn_coverage(model: FlakeModel, side: int = 192) -> tuple[float, float]:
    """Covered fraction and flakes per texel of torchmetal's own flake field on a ``side``² patch (a
    uniform density: the map, if any, scales coverage per block elsewhere)."""
    from dataclasses import replace

    # on use: loads torch (this module imports numpy only)
    from torchmetal.flakes.model.field import flake_field

    f = flake_field(replace(model, density_map=None, color_map=None, area_map=None), side, side)
    return float((f.weight >= 0.5).float().mean()), f.count / float(side * side)


def flake2d_inputs(model: FlakeModel, width_px: int) -> Flake2dInputs:
    """flake2d ``size``/``roughness``/``coverage`` for a FlakeModel on a texture ``width_px`` wide.

    The target is the model's covered fraction, density × mean area (torchmetal's flakes never overlap);
    where that reaches :data:`MAX_COVERED` (a dense layer of flakes wider than the field's cells, which the
    field draws clamped to them: the real card at capacity), it is the coverage the field actually draws."""
    if model.density <= 0:
        raise ExportError(f"flakes: expected a density > 0 for flake2d, found {model.density!r}")
    mean_area = math.exp(model.area_log_mean + 0.5 * model.area_log_std ** 2)
    target, density, drawn = model.density * mean_area, model.density, False
    if target >= MAX_COVERED:
        (target, density), drawn = drawn_coverage(model), True
    if not 0.0 < target < MAX_COVERED:
        raise ExportError(f"flakes: expected a covered fraction in (0, 0.95) for flake2d, found {target:.3f}")
    area, shows = isolated_flake_stats()
    p = -math.log(1.0 - target) / area  # Boolean model: covered = 1 − exp(−p·area)
    if p > float(density_to_probability(1.0)):
        raise ExportError(f"flakes: expected a coverage flake2d can draw, found a covered fraction {target:.3f}")
    size_px = math.sqrt(p * shows / density)  # visible flakes per texel = the model's (drawn) density
    xs = np.linspace(0.0, 1.0, 20001)  # the coverage input whose probability is p (increasing curve)
    coverage = float(np.interp(p, density_to_probability(xs), xs))
    rough, err = fit_flake_roughness(model.tilt_sigma)
    return Flake2dInputs(size_px / width_px, rough, coverage, p, target, err, drawn)


def glint_statistics(model: FlakeModel, inputs: Flake2dInputs, width_px: int, tilts_deg=(0.0, 5.0, 10.0, 20.0),
                     cone_deg: float | None = None, height_px: int = 192) -> dict:
    """Both models on a ``height_px``² texel patch: covered fraction, flakes per texel, mean area
    (texel²), and per half-vector tilt the fraction of flakes whose normal lies within ``cone_deg``
    (default 2·glint σ) of it. torchmetal's side is its own flake field."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.flakes.model.field import flake_field

    f = flake_field(model, height_px, height_px)
    weight = f.weight[0].numpy()
    ours_cov = float((weight >= 0.5).mean())
    ours_count = f.count / float(height_px * height_px)
    centre = weight >= 0.5
    m_ours = f.normal.permute(1, 2, 0).numpy()[centre]

    t = (np.arange(height_px) + 0.5) / width_px
    yy, xx = np.meshgrid(t, t, indexing="ij")
    key, n = flake2d_pattern(np.stack([xx.ravel(), yy.ravel()], 1), inputs.size, inputs.roughness, inputs.coverage)
    mx_cov = float((key >= 0).mean())
    mx_count = len(np.unique(key[key >= 0])) / float(height_px * height_px)
    m_mx = n[key >= 0]
    cone = math.radians(cone_deg) if cone_deg is not None else 2.0 * model.glint_sigma
    out = {"covered_fraction": [ours_cov, mx_cov], "flakes_per_texel": [ours_count, mx_count],
           "mean_area_texels": [ours_cov / max(ours_count, 1e-30), mx_cov / max(mx_count, 1e-30)], "glinting": {}}
    for tilt in tilts_deg:
        h = np.array([math.sin(math.radians(tilt)), 0.0, math.cos(math.radians(tilt))])
        g = [float((np.arccos(np.clip(m @ h, -1, 1)) < cone).mean()) if len(m) else 0.0 for m in (m_ours, m_mx)]
        out["glinting"][f"{tilt:g}"] = g
    return out
