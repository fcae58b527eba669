"""The statistical flake model (the paper's 𝓜: Size, Shape, Color — plus tilt and glint).

Units: lengths and areas in texture pixels; angles in radians; colours are linear-RGB glint
reflectances (peak flake radiance divided by irradiance), comparable to the texture d(p).
"""

from __future__ import annotations

import math
from copy import deepcopy
from dataclasses import dataclass, field, fields

import torch

from torchmetal.errors import MaterialError

MIN_CELL = 3  # px: the hash field holds at most one flake per MIN_CELL² cell …
MAX_DENSITY = 1.0 / (MIN_CELL * MIN_CELL)  # … so this is the densest field it can draw (flakes/px)
MAX_COLOR = 1.0e4  # glint reflectance bound: a mirror flake's peak is ~1/(π·glint σ²) ≈ 350 at σ = 0.03 rad


MAP_FIELDS = ("density_map", "color_map", "area_map")  # array fields: not in to_dict, files in the material directory
MAX_AREA_OFFSET = 5.0  # |log-area offset| of a block: e^5 ≈ 150× the global median area at most


def _as_map(x, name: str, dims: int) -> torch.Tensor:
    """A numpy array or tensor with ``dims`` dimensions → float32 CPU tensor (one-line error otherwise)."""
    try:
        t = torch.as_tensor(x).detach().to("cpu", torch.float32)
    except (TypeError, ValueError, RuntimeError) as e:
        raise MaterialError(f"FlakeModel.{name}: expected a numeric array, found {type(x).__name__} ({e})") from None
    if t.dim() != dims:
        raise MaterialError(f"FlakeModel.{name}: expected {dims} dimensions, found shape {tuple(t.shape)}")
    return t.contiguous()


def _check_covariance(cov: tuple[tuple[float, ...], ...]) -> None:
    """A colour covariance the renderer can factor: finite, symmetric, PSD, spread ≤ MAX_COLOR."""
    flat = [c for r in cov for c in r]
    if not all(math.isfinite(c) for c in flat):
        raise MaterialError(f"FlakeModel.color_cov: expected finite values, found {cov!r}")
    scale = max(abs(c) for c in flat)
    if scale > MAX_COLOR**2:
        raise MaterialError(f"FlakeModel.color_cov: expected entries <= {MAX_COLOR**2:g} (colour spread <= "
                            f"{MAX_COLOR:g}), found {scale:.3g}")
    tol = 1e-9 * max(scale, 1e-30)
    if any(abs(cov[i][j] - cov[j][i]) > tol for i in range(3) for j in range(3)):
        raise MaterialError(f"FlakeModel.color_cov: expected a symmetric matrix, found {cov!r}")
    # leading principal minors of cov + tol·I ≥ 0 (Sylvester, with the tolerance the renderer adds)
    a = [[cov[i][j] + (tol if i == j else 0.0) for j in range(3)] for i in range(3)]
    m1 = a[0][0]
    m2 = a[0][0] * a[1][1] - a[0][1] * a[1][0]
    m3 = (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
          + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))
    if m1 < 0 or m2 < -tol * scale or m3 < -tol * scale * scale:
        raise MaterialError(f"FlakeModel.color_cov: expected a positive semi-definite matrix, found {cov!r}")


@dataclass
class FlakeModel:
    """Distribution of metallic flakes over the sample.

    Attributes:
        density: expected flakes per pixel, including flakes that never glint (≤ MAX_DENSITY).
        area_log_mean, area_log_std: area ~ LogNormal(mean, std), area in px².
        aspect_mean, aspect_std: minor/major axis ratio ~ Normal, clipped to [0.2, 1].
        color_mean: (3,) mean linear-RGB glint reflectance; color_cov: 3×3 covariance.
        tilt_sigma: std of the flake-normal slope per tangent axis (radians, small-angle).
        glint_sigma: angular width of one glint (radians): how far the half vector may leave the
            flake normal before the glint fades.
        shape_lines: the paper's limit lines (b1, k1, b2, k2): b + k·√area bounds the semi-major
            axis from below and above; descriptive, fitted from detections.
        seed: seed of the deterministic hash field.
        density_map: optional (gh, gw) float32 map of the density relative to ``density`` over a
            gh×gw grid of blocks covering the texture (glitter on part of the sample;
            :mod:`torchmetal.flakes.estimate.density_map`); None = uniform. ``density``·max ≤ MAX_DENSITY.
        color_map: optional (gh, gw, 3) float32 colour mean per block of ``density_map`` (replaces
            ``color_mean`` there; the covariance stays global); None = ``color_mean`` everywhere.
        area_map: optional (gh, gw) float32 log-area offset per block of ``density_map``: the block's
            areas are LogNormal(``area_log_mean`` + offset, ``area_log_std``) (relative, like the
            density map, so rescaling ``area_log_mean`` rescales every block); None = 0 everywhere.
    """

    density: float
    area_log_mean: float = math.log(6.0)
    area_log_std: float = 0.4
    aspect_mean: float = 0.7
    aspect_std: float = 0.15
    color_mean: tuple[float, float, float] = (0.8, 0.8, 0.8)
    color_cov: tuple[tuple[float, ...], ...] = ((0.01, 0.0, 0.0), (0.0, 0.01, 0.0), (0.0, 0.0, 0.01))
    tilt_sigma: float = 0.15
    glint_sigma: float = 0.03
    shape_lines: tuple[float, float, float, float] | None = None
    seed: int = 0
    extra: dict = field(default_factory=dict)
    density_map: torch.Tensor | None = field(default=None, compare=False, repr=False)
    color_map: torch.Tensor | None = field(default=None, compare=False, repr=False)
    area_map: torch.Tensor | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        checks = {
            "density": (self.density, 0.0, MAX_DENSITY),
            "area_log_std": (self.area_log_std, 0.0, 5.0),
            "aspect_mean": (self.aspect_mean, 0.0, 1.0),
            "aspect_std": (self.aspect_std, 0.0, 1.0),
            "tilt_sigma": (self.tilt_sigma, 0.0, 1.5),
            "glint_sigma": (self.glint_sigma, 1e-4, 1.5),
        }
        for name, (value, lo, hi) in checks.items():
            if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
                raise MaterialError(f"FlakeModel.{name}: expected a number in [{lo}, {hi}], found {value!r}")
        if len(self.color_mean) != 3 or not all(math.isfinite(c) and c >= 0 for c in self.color_mean):
            raise MaterialError(f"FlakeModel.color_mean: expected 3 finite values >= 0, found {self.color_mean!r}")
        if not all(c <= MAX_COLOR for c in self.color_mean):
            raise MaterialError(f"FlakeModel.color_mean: expected glint reflectances <= {MAX_COLOR:g}, "
                                f"found {self.color_mean!r}")
        if len(self.color_cov) != 3 or any(len(r) != 3 for r in self.color_cov):
            raise MaterialError(f"FlakeModel.color_cov: expected a 3x3 matrix, found {self.color_cov!r}")
        self.color_mean = tuple(float(c) for c in self.color_mean)  # type: ignore[assignment]
        self.color_cov = tuple(tuple(float(c) for c in r) for r in self.color_cov)
        _check_covariance(self.color_cov)
        self._check_maps()

    def _check_maps(self) -> None:
        """density_map (gh, gw) finite ≥ 0 within the field's capacity; color_map (gh, gw, 3) and
        area_map (gh, gw) on its grid."""
        if self.density_map is None:
            for name in ("color_map", "area_map"):
                if getattr(self, name) is not None:
                    raise MaterialError(f"FlakeModel.{name}: expected a density_map to give its grid, found none")
            return
        self.density_map = _as_map(self.density_map, "density_map", 2)
        dm = self.density_map
        if dm.numel() == 0 or not bool(torch.isfinite(dm).all()) or bool((dm < 0).any()):
            raise MaterialError(f"FlakeModel.density_map: expected a non-empty finite (gh, gw) map >= 0, found shape "
                                f"{tuple(dm.shape)}, min {float(dm.min()) if dm.numel() else float('nan'):g}")
        peak = self.density * float(dm.max())
        if peak > MAX_DENSITY * (1.0 + 1e-5):
            raise MaterialError(f"FlakeModel.density_map: expected density x max(map) <= {MAX_DENSITY:.6g} (the field's "
                                f"capacity), found {peak:.6g}")
        if self.area_map is not None:
            self.area_map = _as_map(self.area_map, "area_map", 2)
            am = self.area_map
            if tuple(am.shape) != tuple(dm.shape):
                raise MaterialError(f"FlakeModel.area_map: expected shape {tuple(dm.shape)} (the density map's grid), "
                                    f"found {tuple(am.shape)}")
            if not bool(torch.isfinite(am).all()) or float(am.abs().max()) > MAX_AREA_OFFSET:
                raise MaterialError(f"FlakeModel.area_map: expected finite log-area offsets in [-{MAX_AREA_OFFSET:g}, "
                                    f"{MAX_AREA_OFFSET:g}], found min {float(am.min()):g}, max {float(am.max()):g}")
        if self.color_map is None:
            return
        self.color_map = _as_map(self.color_map, "color_map", 3)
        cm = self.color_map
        if tuple(cm.shape) != (*dm.shape, 3):
            raise MaterialError(f"FlakeModel.color_map: expected shape {(*dm.shape, 3)}, found {tuple(cm.shape)}")
        if not bool(torch.isfinite(cm).all()) or bool((cm < 0).any()) or bool((cm > MAX_COLOR).any()):
            raise MaterialError(f"FlakeModel.color_map: expected finite values in [0, {MAX_COLOR:g}], found min "
                                f"{float(cm.min()):g}, max {float(cm.max()):g}")

    @property
    def median_area(self) -> float:
        return math.exp(self.area_log_mean)

    def to_dict(self) -> dict:
        """The JSON-able statistics (the maps are arrays: the material directory stores them as files)."""
        d = {f.name: deepcopy(getattr(self, f.name)) for f in fields(self) if f.name not in MAP_FIELDS}
        d["color_mean"] = list(self.color_mean)
        d["color_cov"] = [list(r) for r in self.color_cov]
        d["shape_lines"] = list(self.shape_lines) if self.shape_lines is not None else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "FlakeModel":
        try:
            d = dict(d)
            if d.get("shape_lines") is not None:
                d["shape_lines"] = tuple(d["shape_lines"])
            d["color_mean"] = tuple(d["color_mean"])
            d["color_cov"] = tuple(tuple(r) for r in d["color_cov"])
            return cls(**d)
        except (TypeError, KeyError) as e:
            raise MaterialError(f"flakes: expected a FlakeModel dictionary, found {sorted(d)} ({e})") from None
