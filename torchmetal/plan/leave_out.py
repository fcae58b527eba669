"""How sure are the estimated normals and the flake statistics: refits with one shot left out (jackknife over shots).

The curvature intervals of :mod:`torchmetal.fit.uncertainty` cover s, α and the texture. Estimated normals
come out of a per-pixel search with restarts, median and flat tests, and the flake statistics out of a
detection and a likelihood that is not a least squares: neither has a curvature to read. Both are refitted
here on the capture with each shot left out in turn (N refits), and the spread of the N answers gives the
interval (the jackknife: variance (N−1)/N·Σ(θ_i − θ̄)², N−1 degrees of freedom).

**Normals** (:func:`normals_intervals`): per pixel, the angle between each refit's normal and their mean
direction; ``std_deg`` = √((N−1)/N·Σ angle²) (the jackknife's total over the two tangent directions) and
the 90 % radius ``radius_deg`` = std·√F₀.₉(2, N−1) — the angle the truth lies within with probability 0.9
for a round error in the tangent plane (Hotelling's two-dimensional interval with N−1 degrees of freedom;
F(2, m) has the closed quantile m/2·((1−q)^(−2/m) − 1), ln 10 = 2.30 as m → ∞).
Where the material's own normal is exactly (0, 0, 1) — the flat test's snap (:mod:`torchmetal.normals.flat`) — the
refits mostly snap too and agree exactly, a radius of 0 though the test only says the tilt is too small for these
shots to tell (2026-12-07: 15 % of the pixels of random scenes, true tilt 2–2.6°, 26 % covered). There the radius
is at least ``flat_floor_deg``: the steepest estimate the test would have set flat on the full capture's shots
(:func:`~torchmetal.normals.flat.unrejected_tilt_deg`, its own threshold, at most its 5° cut).

**Flake statistics** (:func:`flake_intervals`): density, the area's log-normal mean and std, the aspect
mean, the colour mean (per channel), the tilt and the glint widths. Positive scales (density, the widths,
the area's log std) on a log scale, so the interval stays positive; the rest linear. Interval: the full
capture's estimate ± t₀.₉₅(N−1)·jackknife std, cut at the statistic's range (aspect in [0, 1], colour ≥ 0).
A refit whose flake stage found no model is left out (and counted); with fewer than 3 left the statistic gets
no interval.

Both are N times the cost of the estimate; measured coverage: docs/measurements.md (2026-12-06).
:func:`normals_jackknife` and :func:`flake_jackknife` take refits already made (``torchmetal intervals``,
:mod:`torchmetal.plan.intervals`, refits the material's whole fit once per left-out shot for both).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchmetal.errors import InputError

LEVEL = 0.9
LOG_STATS = ("density", "area_log_std", "tilt_sigma", "glint_sigma")
LINEAR_STATS = ("area_log_mean", "aspect_mean")
BOUNDS = {"aspect_mean": (0.0, 1.0), "color": (0.0, math.inf)}  # the linear statistics' ranges: intervals are cut there


def f2_quantile(q: float, dof: int) -> float:
    """The q-quantile of Fisher's F(2, dof)."""
    m = float(max(1, dof))
    return m / 2 * ((1 - q) ** (-2 / m) - 1)


def _left_out(capture, i: int):
    return capture.subset([j for j in range(capture.num_shots) if j != i])


def normals_intervals(capture, *, level: float = LEVEL, full: Tensor | None = None,
                      estimate: Callable | None = None) -> dict:
    """The jackknife of the estimated normals of ``capture``: {"std_deg", "radius_deg" (H, W) float64,
    "normals" (3, H, W) the full capture's estimate, "refits" (N, 3, H, W), "level", "median_radius_deg",
    "p90_radius_deg" (inside the mask)}. ``estimate``: capture → (3, H, W) normals (default
    :func:`torchmetal.normals.estimate.estimate_normals`' with its defaults, and then the flat test's floor where
    the full estimate is flat); ``full``: the full capture's, when already made (with the default ``estimate``:
    no floor, the terms its flat test ran with being unknown)."""
    n = capture.num_shots
    if n < 4:
        raise InputError(f"normals_intervals: expected at least 4 shots (3 left in each refit), found {n}")
    floor = None
    if estimate is None:
        from torchmetal.normals.estimate import estimate_normals
        from torchmetal.normals.flat import unrejected_tilt_deg

        def estimate(c):
            return estimate_normals(c).normals

        if full is None:
            est = estimate_normals(capture)
            full = est.normals
            floor = unrejected_tilt_deg(capture, full, est.s, est.alpha).cpu()
    full = estimate(capture) if full is None else full
    reps = torch.stack([estimate(_left_out(capture, i)).double() for i in range(n)])
    inside = capture.mask.bool().reshape(capture.height, capture.width)
    return normals_jackknife(full, reps, inside, level=level, flat_floor_deg=floor)


def normals_jackknife(full: Tensor, reps: Tensor, inside: Tensor, *, level: float = LEVEL,
                      flat_floor_deg: Tensor | None = None) -> dict:
    """:func:`normals_intervals` on refits already made: ``full`` (3, H, W) the full capture's normals, ``reps``
    (N, 3, H, W) one per shot left out, ``inside`` (H, W) bool the pixels the summaries count, ``flat_floor_deg``
    (H, W) the least radius where ``full`` is exactly (0, 0, 1) (module docstring; None: none)."""
    n = reps.shape[0]
    reps = reps.double()
    mean = torch.nn.functional.normalize(reps.mean(0), dim=0)
    ang = _angle(reps, mean.unsqueeze(0), 1)  # (N, H, W) radians
    std = ((n - 1) / n * (ang**2).sum(0)).sqrt()
    radius = torch.rad2deg(std * math.sqrt(f2_quantile(level, n - 1)))
    if flat_floor_deg is not None:
        if tuple(flat_floor_deg.shape) != tuple(radius.shape):
            raise InputError(f"normals_jackknife: expected flat_floor_deg of shape {tuple(radius.shape)}, "
                             f"found {tuple(flat_floor_deg.shape)}")
        f = full.double()
        snapped = (f[0] == 0) & (f[1] == 0) & (f[2] == 1)  # the flat test's (0, 0, 1), exactly
        radius = torch.where(snapped, torch.maximum(radius, flat_floor_deg.double().to(radius.device)), radius)
    r = radius[inside]
    return {"normals": full.double(), "refits": reps, "std_deg": torch.rad2deg(std), "radius_deg": radius,
            "level": level, "median_radius_deg": float(r.median()) if r.numel() else math.nan,
            "p90_radius_deg": float(r.quantile(0.9)) if r.numel() else math.nan}


def _angle(a: Tensor, b: Tensor, dim: int) -> Tensor:
    """Radians between the vectors of ``a`` and ``b`` along ``dim`` (atan2 of the cross and dot products: exact
    for small angles, where acos of a float dot product is not)."""
    a, b = a.double(), b.double()
    cross = torch.linalg.vector_norm(torch.cross(a, b.expand_as(a), dim=dim), dim=dim)
    return torch.atan2(cross, (a * b).sum(dim))


def angle_deg(a: Tensor, b: Tensor) -> Tensor:
    """(H, W) degrees between normal maps (3, H, W)."""
    return torch.rad2deg(_angle(a, b, 0))


def flake_stats(model) -> dict:
    """The scalar statistics of a :class:`~torchmetal.flakes.model.FlakeModel` the intervals are given for."""
    out = {k: float(getattr(model, k)) for k in (*LOG_STATS, *LINEAR_STATS)}
    for c, v in zip("rgb", model.color_mean):
        out[f"color_{c}"] = float(v)
    return out


def default_flake_fit(capture):
    """A capture → its FlakeModel (or None): ``fit_phong`` (default options), its renders, the flake stage."""
    from torchmetal.fit import fit_phong
    from torchmetal.flakes.stage import flake_stage

    fit = fit_phong(capture)
    with torch.no_grad():
        phong = fit.render(capture.lights, capture.intensities, capture.cameras)
    return flake_stage(capture, phong.to(capture.images.dtype)).model


def flake_intervals(capture, *, level: float = LEVEL, full=None, fit: Callable | None = None) -> dict:
    """The jackknife of the flake statistics of ``capture``: {name: {"value", "low", "high", "std", "scale"
    ("log"|"linear"), "refits"}} plus "failed_refits" and "level". ``fit``: capture → FlakeModel or None
    (default :func:`default_flake_fit`); ``full``: the full capture's model, when already made."""
    fit = fit or default_flake_fit
    n = capture.num_shots
    full = fit(capture) if full is None else full
    if full is None:
        raise InputError("flake_intervals: the full capture's flake stage found no flake model")
    return flake_jackknife(full, [fit(_left_out(capture, i)) for i in range(n)], level=level)


def flake_jackknife(full, reps: list, *, level: float = LEVEL) -> dict:
    """:func:`flake_intervals` on refits already made: ``full`` the full capture's FlakeModel, ``reps`` one
    FlakeModel (or None: no model found) per shot left out."""
    from torchmetal.fit.uncertainty import _student_t

    n = len(reps)
    ok = [flake_stats(m) for m in reps if m is not None]
    out: dict = {"level": level, "failed_refits": n - len(ok)}
    t = _student_t(0.5 + level / 2, len(ok) - 1) if len(ok) >= 3 else math.nan
    for name, value in flake_stats(full).items():
        log = name in LOG_STATS
        f = (lambda v: math.log(max(v, 1e-300))) if log else (lambda v: v)  # noqa: E731
        vals = torch.tensor([f(s[name]) for s in ok], dtype=torch.float64)
        m = len(ok)
        std = float(((m - 1) / m * ((vals - vals.mean()) ** 2).sum()).sqrt()) if m >= 3 else math.nan
        if log:  # value·e^(∓t·std): exactly the value where the refits agree (exp(log v) is not always v)
            lo, hi = value * math.exp(-t * std), value * math.exp(t * std)
        else:  # and within the statistic's range (a symmetric interval can leave it: aspect < 0, a negative colour)
            low_bound, high_bound = BOUNDS.get(name[:5] if name.startswith("color") else name, (-math.inf, math.inf))
            lo, hi = max(value - t * std, low_bound), min(value + t * std, high_bound)
        out[name] = {"value": value, "low": lo, "high": hi, "std": std, "scale": "log" if log else "linear",
                     "refits": [s[name] for s in ok]}
    return out
