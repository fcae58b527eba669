"""Per-pixel normals from the photos (``fit --normals estimate``): photometric stereo with the
known lights, refined jointly with the Phong terms of docs/design.md §2.2.

Per pixel, with the normal written through the surface gradient θ = (θx, θy),
n = (−θx, −θy, 1)/√(1 + θx² + θy²) (so n·z > 0 by construction), for shot k and channel c:

    y_kc = E_kc · [ d_c·max(n·l_k, 0) + [n·l_k > 0]·s_c·max(r_k·v_k, 0)^α_c ]

l, v, E come from :mod:`torchmetal.geometry` (point and directional lights, any camera).

1. **Robust Lambertian init** (:mod:`~torchmetal.normals.lambert`). Per pixel, the channel sum of
   y/E is g·l_k (g = (Σ_c d_c)·n), solved by weighted least squares over the shots that are lit,
   unsaturated and not dark, then again without the shots the fit predicts in attached shadow or
   whose residual stands out (highlights, glints, cast shadows).
2. **Robust refinement** (:func:`~torchmetal.normals.refine.refine_normals`): a 2-parameter
   Levenberg–Marquardt per pixel on θ with the texture d eliminated in closed form (variable
   projection, Kaufman's Jacobian) and Cauchy weights (IRLS), so highlights the model does not
   explain, glints and shadows the Lambertian init mistook for shading are down-weighted, never
   fitted. max(n·l, 0) models attached shadows.
3. **Alternation** (:func:`estimate_normals`): round 0 refines, per pixel, the best of three
   starts — the Lambertian init under s = 0, it and the flat normal under the Phong terms fitted
   with flat normals; each further round fits the global Phong terms
   (:func:`~torchmetal.fit.fit_phong`, specular "global") with the current normals and refines the
   normals under them, then tries the 4 neighbours' normals (local minima near highlights).
4. **Joint refinement** of the normals with the global s, α
   (:func:`~torchmetal.normals.joint.joint_refine`): the alternation alone has a biased fixed
   point (normal errors broaden the lobe the Phong fit sees). When the Phong fits saw no highlight in
   some channel (s = 0), a weak, broad lobe is still tried from a small start
   (:func:`~torchmetal.normals.joint.try_weak_lobe`): Lambertian normals tilted towards the half
   vectors absorb such a lobe, and then no residual shows it; kept when it explains the shots better.
5. **Second chances** (:mod:`~torchmetal.normals.restart`): pixels whose robust cost stands out
   try a grid of starts, then neighbours' normals propagate across the image until settled, each
   move kept where it cuts the pixel's robust cost by 30 % (patches caught in a wrong minimum near
   highlights, which one propagation pass does not reach).
6. **The neighbourhood's normal where it explains a pixel as well** (:mod:`~torchmetal.normals.median`,
   a truncated loss: a glint explained by a tilted normal), then
   **flat where the photos cannot tell** (:mod:`~torchmetal.normals.flat`): a per-pixel
   likelihood-ratio test against (0, 0, 1).

The normals are fitted to the channel sum of each shot, z_k = Σ_c y_kc (shots with a clipped
channel are left out): with Ē_k the channel mean of E_k and κ_kc = E_kc/Ē_k (the light's colour),
z_k = Ē_k·[D·max(n·l_k, 0) + Σ_c κ_kc·s_c·lobe_kc], D = Σ_c κ_c·d_c — one residual per shot
instead of three (the geometry is shared by the channels; the texture is :func:`fit_phong`'s).
Every per-pixel term is independent, so the work runs in row chunks (memory only; robust scales
are per chunk). Pixels outside the mask, or with fewer than 3 usable shots, keep (0, 0, 1).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.errors import FitError, InputError
from torchmetal.fit.api import fit_phong
from torchmetal.geometry import direction_to, surface_points
from torchmetal.normals.core import work_dtype
from torchmetal.normals.flat import flat_where_unresolved
from torchmetal.normals.joint import joint_refine, try_weak_lobe
from torchmetal.normals.lambert import MIN_SHOTS, lambertian_normals
from torchmetal.normals.median import median_where_as_good
from torchmetal.normals.refine import refine_normals
from torchmetal.normals.restart import restart_and_settle

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture


@dataclass
class NormalsEstimate:
    """Outcome of :func:`estimate_normals`.

    Attributes:
        normals: (3, H, W) unit normals, n·z > 0; (0, 0, 1) outside the mask.
        s, alpha: (3,) the specular terms the normals were refined with (the joint stage's, else the last round's).
        report: JSON-able: per stage s, α, iterations and time; pixels unsolved or kept flat; "s", "alpha" as above.
    """

    normals: Tensor
    s: Tensor
    alpha: Tensor
    report: dict = field(default_factory=dict)


def _check_capture(capture: Capture) -> None:
    n = capture.num_shots
    if n < MIN_SHOTS:
        raise InputError(f"normals='estimate': expected at least {MIN_SHOTS} shots (photometric stereo), found {n}")
    h, w = capture.height, capture.width
    pts = surface_points(h, w, capture.size, rows=(h // 2, h // 2 + 1), dtype=torch.float64,
                         device=capture.images.device)[:, :, w // 2 : w // 2 + 1]
    l, _ = direction_to(pts, capture.lights.to(torch.float64))
    sv = torch.linalg.svdvals(l[:, :, 0, 0])
    if float(sv[-1]) < 1e-3 * float(sv[0]):
        raise InputError("normals='estimate': expected lights from at least 3 non-coplanar directions, found "
                         f"directions of rank < 3 (singular values {[round(float(x), 4) for x in sv]})")


def estimate_normals(capture: Capture, *, rounds: int = 1, iters: int = 12, joint: bool = True, weak_lobe: bool = True,
                     restart: bool = True, median_test: bool = True, flat_test: bool = True,
                     fit_kwargs: dict | None = None) -> NormalsEstimate:
    """Per-pixel normals from the photos and the known lights (see the module docstring).

    Args:
        capture: a :class:`~torchmetal.io.capture.Capture`; its own normals are ignored.
        rounds: Phong rounds after the Lambertian refinement (0: Lambertian only).
        iters: LM iterations per pixel and round.
        joint: finish with the joint refinement of the normals and s, α
            (:func:`~torchmetal.normals.joint.joint_refine`).
        weak_lobe: with ``joint``, when the Phong fits saw no highlight (s = 0), still try a weak, broad
            lobe jointly with the normals, kept when it explains the shots better
            (:func:`~torchmetal.normals.joint.try_weak_lobe`).
        restart: give high-cost pixels a grid of starts, then propagate neighbours' normals until
            settled (:func:`~torchmetal.normals.restart.restart_and_settle`: wrong minima near highlights).
        median_test: take the 5×5 neighbourhood's median normal where it explains a pixel as well
            (:func:`~torchmetal.normals.median.median_where_as_good`: glints, noisy dark pixels).
        flat_test: keep (0, 0, 1) where the estimate does not explain the shots significantly
            better (:func:`~torchmetal.normals.flat.flat_where_unresolved`).
        fit_kwargs: extra arguments of :func:`~torchmetal.fit.fit_phong` for the rounds' fits
            (e.g. ``tol``, ``max_iters``); specular is "global".

    Returns:
        :class:`NormalsEstimate`.

    Raises:
        InputError: fewer than 3 shots, or lights that cannot determine a normal.
        FitError: the estimate went non-finite.
    """
    _check_inputs(capture, rounds, iters)
    t0 = time.perf_counter()
    normals, solvable = lambertian_normals(capture, work_dtype(capture))
    kw = {k: v for k, v in (fit_kwargs or {}).items() if k not in ("specular", "robust")}
    normals, s, alpha, fit, first = _round_zero(capture, normals, solvable, iters, kw)
    history = [{**first, "time": time.perf_counter() - t0}]
    for k in range(1, rounds + 1):
        normals, s, alpha, fit, entry = _phong_round(capture, normals, solvable, iters, kw, k)
        history.append(entry)
    if joint:
        normals, s, alpha = _joint_stages(capture, normals, s, alpha, fit, solvable, iters, weak_lobe, history)
    if restart:
        t1 = time.perf_counter()
        normals, rep = restart_and_settle(capture, normals, s, alpha, iters=iters, active=solvable)
        history.append({"round": "restart", **rep, "time": time.perf_counter() - t1})
    n_median = 0
    if median_test:
        normals, n_median = median_where_as_good(capture, normals, s, alpha, active=solvable)
    n_flat = 0
    if flat_test:
        normals, n_flat = flat_where_unresolved(capture, normals, s, alpha, active=solvable)
    counts = {"took_median": n_median, "kept_flat": n_flat}
    return _finish(capture, normals, s, alpha, solvable, history, counts, t0)


def _check_inputs(capture: Capture, rounds: int, iters: int) -> None:
    """:func:`estimate_normals`'s arguments: InputError for bad counts, shots or lights; FitError for non-finite input."""
    if not (isinstance(rounds, int) and rounds >= 0):
        raise InputError(f"rounds: expected an int >= 0, found {rounds!r}")
    if not (isinstance(iters, int) and iters >= 1):
        raise InputError(f"iters: expected an int >= 1, found {iters!r}")
    _check_capture(capture)
    for name in ("images", "intensities", "lights", "cameras"):
        if not bool(torch.isfinite(getattr(capture, name)).all()):
            raise FitError(f"capture.{name}: expected finite values, found NaN/Inf")


def _round_zero(capture: Capture, lambertian: Tensor, solvable: Tensor, iters: int,
                kw: dict) -> tuple[Tensor, Tensor, Tensor, FitResult, dict]:
    """Round 0: the Lambertian start under s = 0, and (when the Phong fit with flat normals saw a
    highlight) it and the flat normals under that fit's terms; per pixel the one that explains the
    shots best, refined. Returns normals, s, α, the flat fit and the round's report entry."""
    dt = lambertian.dtype
    flat = torch.zeros_like(lambertian)
    flat[2] = 1.0
    zero = torch.zeros(3, dtype=dt, device=lambertian.device)
    fit = fit_phong(replace(capture, normals=flat.to(capture.images.dtype)), specular="global", **kw)
    s, alpha = fit.s.to(dt), fit.alpha.to(dt)
    cands = [(lambertian, zero, torch.ones_like(zero))]
    if bool((s > 0).any()):
        cands += [(flat, s, alpha), (lambertian, s, alpha)]
    normals, rep = refine_normals(capture, cands, iters=iters, active=solvable, propagate=False)
    entry = {"round": 0, "candidates": ["lambertian"] + (["flat+phong", "lambertian+phong"] if len(cands) > 1 else []),
             "flat_fit": {"s": s.tolist(), "alpha": alpha.tolist()}, **rep}
    return normals, s, alpha, fit, entry


def _phong_round(capture: Capture, normals: Tensor, solvable: Tensor, iters: int, kw: dict,
                 k: int) -> tuple[Tensor, Tensor, Tensor, FitResult, dict]:
    """Round k ≥ 1: the global Phong terms fitted with the current normals, the normals refined under
    them (neighbours' normals tried). Returns normals, s, α, the fit and the round's report entry."""
    t1 = time.perf_counter()
    dt = normals.dtype
    fit = fit_phong(replace(capture, normals=normals.to(capture.images.dtype)), specular="global", **kw)
    s, alpha = fit.s.to(dt), fit.alpha.to(dt)
    normals, rep = refine_normals(capture, [(normals, s, alpha)], iters=iters, active=solvable)
    entry = {"round": k, "s": s.tolist(), "alpha": alpha.tolist(), "phong_rmse": float(fit.rmse), **rep,
             "time": time.perf_counter() - t1}
    return normals, s, alpha, fit, entry


def _joint_stages(capture: Capture, normals: Tensor, s: Tensor, alpha: Tensor, fit: FitResult, solvable: Tensor,
                  iters: int, weak_lobe: bool, history: list) -> tuple[Tensor, Tensor, Tensor]:
    """The weak-lobe try (with ``weak_lobe``, when the rounds saw no highlight in some channel: s = 0), then, with a
    lobe, the joint refinement of the normals and s, α and one more refinement under its terms.
    Appends the stages' report entries to ``history``; returns normals, s, α."""
    if not bool((s > 0).all()) and weak_lobe:  # a channel without highlight: a weak, broad lobe may hide
        t1 = time.perf_counter()
        inside = capture.mask[0]
        zero = torch.zeros(3, dtype=normals.dtype, device=normals.device)
        tex = fit.texture.to(normals.dtype)[:, inside].mean(1) if bool(inside.any()) else torch.zeros_like(zero)
        weak_normals, weak_s, weak_alpha, rep = try_weak_lobe(capture, normals, tex, iters=iters, active=solvable)
        if rep["kept"] or not bool((s > 0).any()):  # not kept: the rounds' own (partial) lobe stays
            normals, s, alpha = weak_normals, weak_s, weak_alpha
        history.append({"round": "weak_lobe", **rep, "time": time.perf_counter() - t1})
    if bool((s > 0).any()):
        t1 = time.perf_counter()
        normals, s, alpha, rep = joint_refine(capture, normals, s, alpha, active=solvable)
        history.append({"round": "joint", "s": s.tolist(), "alpha": alpha.tolist(), **rep,
                        "time": time.perf_counter() - t1})
        t1 = time.perf_counter()  # the joint terms: refine and propagate once more
        normals, rep = refine_normals(capture, [(normals, s, alpha)], iters=iters, active=solvable)
        history.append({"round": "polish", **rep, "time": time.perf_counter() - t1})
    return normals, s, alpha


def _finish(capture: Capture, normals: Tensor, s: Tensor, alpha: Tensor, solvable: Tensor, history: list,
            counts: dict, t0: float) -> NormalsEstimate:
    """The estimate, unit length in the photos' dtype, and its report (``counts``: pixels the last
    steps changed); FitError when the normals went non-finite."""
    if not bool(torch.isfinite(normals).all()):
        raise FitError("estimate_normals: expected finite normals, found NaN/Inf")
    normals = normals / normals.norm(dim=0, keepdim=True)
    inside = capture.mask[0]
    tilt = torch.rad2deg(torch.acos(normals[2][inside].clamp(-1, 1)))
    report = {
        "mode": "estimate", "rounds": history, "time": time.perf_counter() - t0,
        "pixels": int(inside.sum()), "unsolved_pixels": int((inside & ~solvable).sum()), **counts,
        "s": s.tolist(), "alpha": alpha.tolist(),  # the terms of the last steps, the flat test's (plan.intervals.flat_floor)
        "tilt_deg": {"mean": float(tilt.mean()) if tilt.numel() else 0.0,
                     "max": float(tilt.max()) if tilt.numel() else 0.0},
    }
    out_dt = capture.images.dtype
    return NormalsEstimate(normals.to(out_dt), s.to(out_dt), alpha.to(out_dt), report)


def angular_error(a: Tensor, b: Tensor, mask: Tensor | None = None) -> Tensor:
    """Angle in degrees between unit normal maps a, b (3, H, W) → (M,) over ``mask`` (H, W) pixels."""
    c = (a.double() * b.double()).sum(0) / (a.double().norm(dim=0) * b.double().norm(dim=0)).clamp_min(1e-30)
    ang = torch.rad2deg(torch.acos(c.clamp(-1.0, 1.0)))
    return ang.reshape(-1) if mask is None else ang[mask]


__all__ = ["NormalsEstimate", "estimate_normals", "angular_error"]
