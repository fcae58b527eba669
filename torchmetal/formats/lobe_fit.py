"""Numeric fit of an engine's GGX specular lobe to a torchmetal lobe (Phong, Blinn, GGX, glints).

Engines (glTF, OpenPBR, UsdPreviewSurface) shade a dielectric specular layer with the GGX
microfacet lobe; torchmetal's coat is the Phong lobe of docs/design.md §2.2. There is no exact mapping, so
the exporters fit one: over a set of (light, view) direction pairs around the mirror direction of
the views a capture sees, find the GGX roughness ``r`` (α_GGX = r²), the per-channel reflectance at
normal incidence ``F0_c`` and the grazing reflectance ``F90`` minimising

    Σ_samples Σ_c (π·F_c(v·h)·D(n·h)·V(n·l, n·v)·(n·l) − target_c(l, v))²,

with the glTF/KHR_materials_specular forms: D the GGX (Trowbridge–Reitz) distribution, V the
height-correlated Smith visibility, F_c = F0_c + (F90 − F0_c)(1 − v·h)^5 (Schlick). The factor π is
the light convention of every exporter here: an engine light of irradiance π·E reproduces a
torchmetal render under irradiance E (equivalently the base colour is the texture d itself,
an albedo). The sample directions are uniform in solid angle over a cone around each mirror
direction, wide enough for the lobe to fall to 1e-3 of its peak, so the error is an energy error.

``target`` is any function ``(l (N, 3), v (N, 3)) -> (N, C)`` of unit directions in the local frame
(normal (0, 0, 1)); :func:`lobe_target` (the material's lobe — Phong, Blinn or GGX — through
:func:`torchmetal.lobes.lobe_value`) and :func:`glint_target` (one flake's glint, through
:func:`torchmetal.flakes.model.field.sparkle_shading`) build the ones torchmetal's materials need. The fit is a coarse scan of
log r, a bounded 1-D refinement, and a closed-form least-squares amplitude at every r.
The reported error is the relative L2 error ‖fit − target‖/‖target‖ per channel.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import ExportError
from torchmetal.flakes.model.field import FlakeField, sparkle_shading
from torchmetal.formats.brent import minimize_bounded
from torchmetal.geometry import ShadingGeometry
from torchmetal.io.capture import Capture, load_capture
from torchmetal.lobes import LOBES, lobe_value

Target = Callable[[Tensor, Tensor], Tensor]

MIN_ROUGHNESS = 0.01
MAX_ROUGHNESS = 1.0
DEFAULT_VIEW_ANGLES = (0.0, 15.0, 30.0, 45.0, 60.0)  # degrees from the normal


@dataclass
class LobeFit:
    """A GGX lobe fitted to a target lobe.

    Attributes:
        roughness: engine roughness r (α_GGX = r²).
        f0: (C,) reflectance at normal incidence per channel (Schlick F0, ≤ f90).
        f90: grazing reflectance (glTF ``specularFactor``), in [0, 1].
        error: (C,) relative L2 lobe error per channel, ‖ggx − target‖ / ‖target‖ (0 when the
            target is 0).
        textbook_roughness: the closed-form mapping of the target's exponent when it has one
            (:func:`textbook_roughness`: Phong α → Blinn 4α → α_GGX = √(2/(n+2)) → r = √α_GGX), else None.
        textbook_error: (C,) the lobe error of that mapping with its best amplitude, or None.
        samples: number of (light, view) pairs the fit used.
    """

    roughness: float
    f0: tuple[float, ...]
    f90: float
    error: tuple[float, ...]
    textbook_roughness: float | None = None
    textbook_error: tuple[float, ...] | None = None
    samples: int = 0

    @property
    def max_error(self) -> float:
        return max(self.error)

    def to_dict(self) -> dict:
        return {"roughness": self.roughness, "f0": list(self.f0), "f90": self.f90, "error": list(self.error),
                "textbook_roughness": self.textbook_roughness,
                "textbook_error": None if self.textbook_error is None else list(self.textbook_error),
                "samples": self.samples}


# ------------------------------------------------------------------------------------ the GGX side
def _xp(x):
    return torch if isinstance(x, Tensor) else np


def ggx_terms(l, v, n, roughness):
    """π·D·V·(n·l) and the Schlick weight (1 − v·h)^5 for unit directions along the last axis.

    Works on torch tensors (the engine renderer) and on numpy arrays (the fit: many small
    evaluations, where numpy has no thread overhead).

    Args:
        l, v, n: (..., 3) unit light, view and normal directions (broadcast).
        roughness: engine roughness r (α = r²), broadcast against (...,).

    Returns:
        ``lobe`` (...,) = π·D·V·max(n·l, 0), zero where n·l ≤ 0 or n·v ≤ 0; ``schlick`` (...,).
    """
    xp = _xp(l)
    h = l + v
    h = h / xp.sqrt(xp.clip((h * h).sum(-1, keepdims=True) if xp is np else (h * h).sum(-1, keepdim=True), 1e-24, None))
    nl = (n * l).sum(-1)
    nv = (n * v).sum(-1)
    nh = xp.clip((n * h).sum(-1), -1.0, 1.0)
    vh = xp.clip((v * h).sum(-1), 0.0, 1.0)
    r = torch.as_tensor(roughness, dtype=l.dtype, device=l.device) if xp is torch else np.asarray(roughness, dtype=np.float64)
    a2 = (r * r) ** 2
    lit = (nl > 0) & (nv > 0)
    nl_c, nv_c = xp.clip(nl, 1e-9, None), xp.clip(nv, 1e-9, None)
    den = nh * nh * (a2 - 1.0) + 1.0
    d = a2 / (math.pi * den * den)
    vis = 0.5 / (nl_c * xp.sqrt(nv_c * nv_c * (1.0 - a2) + a2) + nv_c * xp.sqrt(nl_c * nl_c * (1.0 - a2) + a2))
    lobe = xp.where(lit, math.pi * d * vis * nl_c, 0.0 * nl)
    return lobe, (1.0 - vh) ** 5


def ggx_specular(l: Tensor, v: Tensor, n: Tensor, roughness, f0: Tensor, f90) -> Tensor:
    """π·F·D·V·(n·l): the glTF dielectric specular radiance per unit irradiance.

    Args:
        l, v, n: (..., 3) unit directions; roughness, f90: broadcast against (...,);
        f0: (..., C) or (C,) reflectance at normal incidence.

    Returns:
        (..., C) specular radiance (times E for an engine light of irradiance π·E).
    """
    lobe, s = ggx_terms(l, v, n, roughness)
    f90 = torch.as_tensor(f90, dtype=l.dtype, device=l.device)
    fres = f0 + (f90 - f0) * s.unsqueeze(-1) if f90.dim() == 0 else f0 + (f90.unsqueeze(-1) - f0) * s.unsqueeze(-1)
    return fres * lobe.unsqueeze(-1)


# ------------------------------------------------------------------------------- source lobes
def sample_geometry(l: Tensor, v: Tensor) -> ShadingGeometry:
    """Shading geometry of N (light, view) pairs on a surface with normal +z, unit irradiance:
    every term shaped (N, 1|3, 1, 1) like B shots of a 1×1 image."""
    n = torch.zeros_like(l)
    n[:, 2] = 1.0
    ll, vv, nn = (x.reshape(-1, 3, 1, 1) for x in (l, v, n))
    n_dot_l = ll[:, 2:3]
    r = 2.0 * n_dot_l * nn - ll
    spec_q = 0.5 * ((r - vv) ** 2).sum(1, keepdim=True)
    return ShadingGeometry(n=nn, l=ll, v=vv, n_dot_l=n_dot_l, spec_q=spec_q, irradiance=torch.ones_like(ll))


def lobe_target(kind: str, s: Tensor, alpha: Tensor) -> Target:
    """s_c·lobe_c(l, v) for n·l > 0, the material's specular term of docs/design.md §2.2 (``kind`` "phong")
    or of its lobe extensions ("blinn", "ggx"), evaluated by :func:`torchmetal.lobes.lobe_value`."""
    if kind not in LOBES:
        raise ExportError(f"lobe: expected one of {', '.join(LOBES)}, found {kind!r}")
    s = torch.as_tensor(s, dtype=torch.float64).reshape(-1)
    alpha = torch.as_tensor(alpha, dtype=torch.float64).reshape(-1)

    def f(l: Tensor, v: Tensor) -> Tensor:
        geom = sample_geometry(l, v)
        lobe = lobe_value(kind, geom, alpha.to(l)) * s.to(l).view(1, -1, 1, 1)
        return torch.where(geom.n_dot_l > 0, lobe, torch.zeros_like(lobe)).reshape(l.shape[0], -1)

    return f


def phong_target(s: Tensor, alpha: Tensor) -> Target:
    """s_c·max(r·v, 0)^α_c for n·l > 0 (docs/design.md §2.2)."""
    return lobe_target("phong", s, alpha)


def glint_target(color, sigma: float) -> Target:
    """One glint of :func:`torchmetal.flakes.model.field.sparkle_shading` in its flake's frame (flake normal
    +z, full footprint, glint colour ``color``): c_c·exp(−|m − h|²/(2σ²)) for n·l > 0."""
    color = torch.as_tensor(color, dtype=torch.float64).reshape(3, 1, 1)

    def f(l: Tensor, v: Tensor) -> Tensor:
        geom = sample_geometry(l, v)
        normal = torch.zeros(3, 1, 1, dtype=l.dtype)
        normal[2] = 1.0
        field = FlakeField(torch.ones(1, 1, 1, dtype=l.dtype), normal, color.to(l), float(sigma), 1)
        return sparkle_shading(field, geom).reshape(l.shape[0], 3)

    return f


def textbook_roughness(alpha: float, kind: str = "phong") -> float:
    """The closed-form mapping to the engine roughness √α_GGX, α_GGX = √(2/(n + 2)) with the Blinn
    exponent n = 4α for Phong (the peaks' angles differ by 2×), n = α for Blinn, and for torchmetal's
    GGX lobe exactly its k = m² = 2/(α + 2)."""
    n = 4.0 * float(alpha) if kind == "phong" else float(alpha)
    return math.sqrt(math.sqrt(2.0 / (n + 2.0)))


# ---------------------------------------------------------------------------------- directions
def phong_cone(alpha: float, floor: float = 1e-3) -> float:
    """Angle (rad) from the mirror direction where max(r·v, 0)^α falls to ``floor``."""
    return math.acos(floor ** (1.0 / max(float(alpha), 1e-6)))


def capture_views(cameras: Tensor, min_z: float = 0.05) -> Tensor:
    """View directions (V, 3) a capture saw at the sample centre, from its homogeneous cameras
    (N, 4) (docs/design.md §2.1: w = 1 a position, w = 0 a direction): pass them as ``views=`` to the
    writers so the lobe is fitted over the capture's own view angles. Views closer to the
    horizon than ``min_z`` are dropped; an empty result raises :class:`ExportError`."""
    c = torch.as_tensor(cameras, dtype=torch.float64).reshape(-1, 4)
    d = c[:, :3]  # the centre is the origin: a position and a direction give the same vector
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    d = d[d[:, 2] > min_z]
    if d.shape[0] == 0:
        raise ExportError(f"cameras: expected at least one camera above the surface (z > {min_z}), found none")
    return torch.unique(torch.round(d * 1e6) / 1e6, dim=0)


def resolve_views(views: Tensor | None = None, capture: Capture | str | os.PathLike | None = None) -> Tensor | None:
    """``views`` as given, else the views of ``capture`` (a Capture or a capture directory), else None
    (the default views)."""
    if views is not None or capture is None:
        return views
    if isinstance(capture, (str, os.PathLike)):
        capture = load_capture(capture)
    return capture_views(capture.cameras)


def lobe_directions(cone: float, views: Tensor | None = None, per_view: int = 512,
                    dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """(light, view) pairs around the mirror direction of each view, uniform in solid angle.

    Args:
        cone: half-angle (rad) of the cone of lights around each mirror direction (≤ π/2·0.98).
        views: (V, 3) unit view directions in the local frame (z = normal, z > 0); default
            :data:`DEFAULT_VIEW_ANGLES` polar angles in the x–z plane.
        per_view: lights per view (a Fibonacci spiral on the cone's cap).

    Returns:
        l (N, 3), v (N, 3) unit directions with l above the horizon, N ≤ V·per_view.
    """
    if views is None:
        th = torch.tensor(DEFAULT_VIEW_ANGLES, dtype=dtype) * (math.pi / 180.0)
        views = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)
    views = torch.as_tensor(views, dtype=dtype).reshape(-1, 3)
    views = views / views.norm(dim=-1, keepdim=True)
    if not bool((views[:, 2] > 0).all()):
        raise ExportError(f"views: expected directions above the surface (z > 0), found z = {views[:, 2].tolist()}")
    cone = min(float(cone), 0.49 * math.pi)
    k = torch.arange(per_view, dtype=dtype) + 0.5
    cos_d = 1.0 - (1.0 - math.cos(cone)) * k / per_view
    sin_d = torch.sqrt((1.0 - cos_d * cos_d).clamp_min(0.0))
    phi = k * (math.pi * (3.0 - math.sqrt(5.0)))
    local = torch.stack([sin_d * torch.cos(phi), sin_d * torch.sin(phi), cos_d], -1)  # around +z
    ls, vs = [], []
    for v in views:
        m = torch.stack([-v[0], -v[1], v[2]])  # mirror direction of v
        t1 = torch.linalg.cross(m, torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
        if float(t1.norm()) < 1e-6:
            t1 = torch.linalg.cross(m, torch.tensor([1.0, 0.0, 0.0], dtype=dtype))
        t1 = t1 / t1.norm()
        t2 = torch.linalg.cross(m, t1)
        l = local[:, :1] * t1 + local[:, 1:2] * t2 + local[:, 2:] * m
        keep = l[:, 2] > 0.02
        ls.append(l[keep])
        vs.append(v.expand(int(keep.sum()), 3))
    return torch.cat(ls), torch.cat(vs)


# ------------------------------------------------------------------------------------- the fit
def _amplitudes(lobe: np.ndarray, schlick: np.ndarray, target: np.ndarray, f90_max: float = 1.0):
    """Least-squares F0 (C,) and F90 for fixed D·V: target_c ≈ lobe·(F0_c(1 − S) + F90·S),
    with 0 ≤ F0_c ≤ F90 ≤ f90_max (normal equations of the C + 1 unknowns, then clipped)."""
    a = lobe * (1.0 - schlick)
    b = lobe * schlick
    c = target.shape[1]
    aa, ab, bb = float(a @ a), float(a @ b), float(b @ b)
    m = np.zeros((c + 1, c + 1))
    m[np.arange(c), np.arange(c)] = aa
    m[:c, c] = m[c, :c] = ab
    m[c, c] = c * bb
    rhs = np.concatenate([a @ target, [float((b @ target).sum())]])
    sol = np.linalg.lstsq(m, rhs, rcond=None)[0]
    f0 = np.clip(sol[:c], 0.0, f90_max)
    f90 = float(np.clip(sol[c], f0.max(), f90_max))
    # F0 again for the clipped F90, each channel clipped to [0, F90]
    f0 = np.clip((a @ (target - b[:, None] * f90)) / max(aa, 1e-300), 0.0, f90)
    return f0, f90


def _errors(pred: np.ndarray, target: np.ndarray) -> tuple[float, ...]:
    num = ((pred - target) ** 2).sum(0)
    den = (target**2).sum(0)
    return tuple(float(np.sqrt(n / d)) if d > 0 else 0.0 for n, d in zip(num, den))


def fit_ggx(target: Target, *, cone: float, views: Tensor | None = None, per_view: int = 512,
            textbook: float | None = None, f90_max: float = 1.0) -> LobeFit:
    """Fit the GGX lobe (roughness, F0 per channel, F90) to ``target`` (see the module docstring).

    Args:
        target: ``(l (N, 3), v (N, 3)) -> (N, C)`` float64, local frame (normal +z).
        cone: half-angle (rad) of the lights around each mirror direction.
        views: (V, 3) view directions (default :data:`DEFAULT_VIEW_ANGLES`).
        textbook: a closed-form roughness to evaluate (with its best amplitude) for the report.
        f90_max: upper bound of F90 (and so of every F0).

    Returns:
        :class:`LobeFit`.
    """
    l_t, v_t = lobe_directions(cone, views, per_view)
    y_t = target(l_t, v_t).to(torch.float64)
    if y_t.dim() != 2 or y_t.shape[0] != l_t.shape[0]:
        raise ExportError(f"lobe target: expected values of shape ({l_t.shape[0]}, C), found {tuple(y_t.shape)}")
    if not bool(torch.isfinite(y_t).all()):
        raise ExportError("lobe target: expected finite values, found NaN/Inf")
    l, v, y = l_t.numpy(), v_t.numpy(), y_t.numpy()
    n = np.zeros_like(l)
    n[:, 2] = 1.0
    c = y.shape[1]
    if float(np.abs(y).max()) == 0.0:  # no specular at all
        return LobeFit(MAX_ROUGHNESS, (0.0,) * c, 0.0, (0.0,) * c, samples=int(l.shape[0]))

    def solve(log_r: float):
        lobe, sch = ggx_terms(l, v, n, math.exp(log_r))
        f0, f90 = _amplitudes(lobe, sch, y, f90_max)
        pred = (f0 + (f90 - f0) * sch[:, None]) * lobe[:, None]
        return float(((pred - y) ** 2).sum()), f0, f90, pred

    lo, hi = math.log(MIN_ROUGHNESS), math.log(MAX_ROUGHNESS)
    grid = np.linspace(lo, hi, 25)
    costs = [solve(g)[0] for g in grid]
    i = int(np.argmin(costs))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    best_x, best_fun = minimize_bounded(lambda t: solve(t)[0], a, b, xatol=1e-5)
    log_r = float(best_x) if best_fun <= costs[i] else float(grid[i])
    _, f0, f90, pred = solve(log_r)
    tb_r = tb_err = None
    if textbook is not None:
        tb_r = float(textbook)
        tb_err = _errors(solve(math.log(tb_r))[3], y)
    return LobeFit(math.exp(log_r), tuple(float(x) for x in f0), float(f90), _errors(pred, y), tb_r, tb_err,
                   int(l.shape[0]))


def fit_lobe(s: Tensor, alpha: Tensor, kind: str = "phong", *, views: Tensor | None = None,
             per_view: int = 512) -> LobeFit:
    """Fit the GGX lobe to a material lobe with per-channel s, α (3,) — one shared roughness.

    The cone covers the widest channel's lobe down to 1e-3 of its peak (×1.5 for the tails; GGX's
    heavier tails ×3), expressed as the Phong exponent of the same width (Blinn α/4, GGX (α + 2)/2).
    The textbook mapping is evaluated at the s-weighted geometric mean exponent.
    """
    s = torch.as_tensor(s, dtype=torch.float64).reshape(-1)
    alpha = torch.as_tensor(alpha, dtype=torch.float64).reshape(-1)
    if not (bool(torch.isfinite(s).all()) and bool(torch.isfinite(alpha).all())):
        raise ExportError(f"lobe: expected finite s and alpha, found s={s.tolist()}, alpha={alpha.tolist()}")
    weight = s.clamp_min(0) + 1e-12
    strong = weight > 1e-9 * float(weight.max())
    a_min = float(alpha[strong].min())
    width = {"phong": a_min, "blinn": a_min / 4.0, "ggx": (a_min + 2.0) / 2.0}.get(kind, a_min)
    cone = (3.0 if kind == "ggx" else 1.5) * phong_cone(width)
    mean_alpha = float(torch.exp((weight * torch.log(alpha.clamp_min(1e-6))).sum() / weight.sum()))
    return fit_ggx(lobe_target(kind, s, alpha), cone=cone, views=views, per_view=per_view,
                   textbook=textbook_roughness(mean_alpha, kind))


def fit_glint(color_mean, glint_sigma: float, *, views: Tensor | None = None, per_view: int = 512) -> LobeFit:
    """Fit a GGX lobe (F90 free up to 1) to one flake's glint in its own frame."""
    cone = min(3.0 * glint_sigma * math.sqrt(2.0 * math.log(1e3)), 1.4)  # light moves 2× the half vector
    return fit_ggx(glint_target(torch.tensor(color_mean, dtype=torch.float64), glint_sigma), cone=cone,
                   views=views, per_view=per_view)
