"""Steps 1–4b of ``fit_phong``'s refine scheme (:mod:`torchmetal.fit.api`), on strided pixel subsamples:
the paper's scheme as init, the subsample fit with its weights, the highlight evidence, global vs
clustered specular and gloss maps — everything decided before the full-resolution solve, shared by
the in-memory fit and the tiled one (:mod:`torchmetal.scale.tiled`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.fit.cluster_features import Labeler
from torchmetal.fit.clusters import (
    Selection,
    choose_specular,
    evidence,
    fit_clustered,
    fit_without_hold,
    heldout_errors,
    heldout_evidence,
    mean_square,
)
from torchmetal.fit.colour import choose_colour
from torchmetal.fit.gloss import HOLDS as MAPS_HOLDS
from torchmetal.fit.gloss import choose_maps
from torchmetal.fit.lobe_choice import LOBE_GRID
from torchmetal.fit.paper import paper_scheme
from torchmetal.fit.problem import Observations, Reference, Weighting, build_observations, compute_dtype, grid_stride
from torchmetal.fit.refine import (
    SpecFit,
    evaluate_specular,
    fit_specular,
    grid_beta,
    noise_model,
    residual_scale,
    texture_map,
)
from torchmetal.fit.run import FitRun
from torchmetal.fit.shot_plan import shot_plan
from torchmetal.fit.start import Start
from torchmetal.select.plan import ShotPlan
from torchmetal.select.rule import MIN_GAIN_ABS, paired_choice

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

SIGMA_FLOOR = 1e-5  # residual scale floor, relative to the largest pixel value
INIT_TOL = 1e-3  # the paper's scheme as init: |ΔErr| ≤ 1e-3·Err …
INIT_ITERS = 10  # … or 10 iterations
OUTLIER_SKIP = 1e-5  # fewer outliers than this on the subsample: none are looked for at full resolution


def _sigma_floor(capture) -> float:
    """The residual scale below which residuals are rounding, not noise: :data:`SIGMA_FLOOR` of the largest value."""
    return SIGMA_FLOOR * float(capture.images.detach().abs().amax().clamp_min(1e-30))


@dataclass
class SubsampleDecisions:
    """What the refine scheme decides on strided subsamples (steps 1–4b), before the full-resolution solve."""

    spec: SpecFit | None  # the global or clustered fit on the subsample (None: no specular term)
    labeler: Labeler | None  # the kept clusters' pixel labeler (None: global or maps)
    s_fixed: Tensor | None  # (1, 3): NaN where s is fitted, 0 in channels without highlight evidence
    sel: Selection | None  # global vs clustered (None when not tried)
    use_maps: bool  # the full-resolution fit gets gloss maps
    maps_info: dict | None
    weighting: Weighting | None  # robust weights / outlier masks for the full-resolution observations
    white: bool = False  # one s for the three channels (:mod:`torchmetal.fit.colour`)
    plan: ShotPlan | None = None  # the shots the choices held out (None: no specular fit to plan by)
    per_channel: bool = False  # a refit of a GGX model that kept an α per channel: kept, not tested again (Start)


def subsample_decisions(capture: Capture, run: FitRun, *, specular: str, tol: float, max_iters: int, robust: str | None,
                        outliers: float | None, clusters: tuple[int, ...], chunk: int, sub_pixels: int,
                        select_pixels: int, seed: int, lobe: str = "phong", noise: bool | str = False,
                        colour: bool = True, relabel: bool = True, plan: ShotPlan | None = None,
                        start: Start | None = None) -> SubsampleDecisions:
    """Steps 1–4b of the refine scheme (module docstring) on strided pixel subsamples of ``capture``
    (any object with ``images`` (N, 3, H, W) readable by :func:`~torchmetal.fit.problem.build_observations`,
    such as the tiled fit's memory-mapped capture): the same values bit for bit for the same pixels.
    ``noise``: weigh each observation by its expected variance (:func:`~torchmetal.fit.refine.noise_model`,
    fitted to the subsample fit's residuals); "auto": where a held-out shot prefers it (:func:`_weights_decision`).
    ``relabel``: False skips the relabelling trial of kept clusters. ``plan``: the shots to hold out
    (:mod:`torchmetal.select.plan`; None: planned from this capture's first subsample fit). ``start``: a refit of
    a chosen model (:mod:`torchmetal.fit.start`; ignored unless ``lobe`` and ``specular`` are its): the subsample fit
    starts from its lobe, noise weights use its noise model, its highlight is not tested again on a held-out shot
    and its specular colour is kept."""
    imgs = capture.images
    dt = compute_dtype(imgs)
    n_shots, _, h, w = imgs.shape
    stride = grid_stride(h, w, sub_pixels)
    sel_stride = grid_stride(h, w, select_pixels)
    sub_tol = max(tol, 1e-4)
    if start is not None and (start.lobe != lobe or start.specular != specular or noise == "auto"):
        start = None  # not the model it was fitted with: chosen afresh
    if start is not None:  # the subsample fit need only find the structure: the full fit starts near its solution
        start, stride = start.to(imgs.device), sel_stride
    grids = _Grids(stride, sel_stride, dt, chunk, lobe)
    weighting = None
    if start is not None and robust is None and outliers is None and (not noise or start.variance is not None):
        sub, glob, weighting = _started_fit(capture, run, grids, start, noise=bool(noise), sub_tol=sub_tol,
                                            max_iters=max_iters)
        noise = False  # weighted already
    else:
        sub, glob = _initial_fit(capture, run, grids, specular=specular, tol=tol, sub_tol=sub_tol, max_iters=max_iters,
                                 start=start)
    if plan is None and glob is not None:
        plan = shot_plan(sub, glob)
    if noise == "auto":
        with run.stage("choice.weights"):
            sub, glob, weighting = _weights_decision(capture, run, grids, sub, glob, robust=robust, outliers=outliers,
                                                     sub_tol=sub_tol, max_iters=max_iters, plan=plan)
    elif outliers is not None or robust is not None or noise:
        sub, glob, weighting = _weighted_refit(capture, run, grids, sub, glob, robust=robust, outliers=outliers,
                                               noise=noise, sub_tol=sub_tol, max_iters=max_iters)
    with run.stage("choice.specular evidence"):
        glob, s_fixed = _highlight_evidence(capture, run, grids, glob, sub_tol=sub_tol, max_iters=max_iters,
                                            weighting=weighting, plan=plan, tested=start is None)
    # 4. global vs clustered
    sel: Selection | None = None
    if glob is not None and specular in ("auto", "clustered"):
        if n_shots < 3 and specular == "auto":
            run.skipped.append(f"specular clusters: a held-out test needs >= 3 shots, found {n_shots}")
        elif s_fixed is not None and specular == "auto":
            run.skipped.append("specular clusters: not tried (some channels show no highlight)")
        else:
            hold = plan.hold if n_shots >= 3 else None
            with run.stage("select"), run.stage("choice.specular clusters"):
                sel = choose_specular(capture, glob, candidates=clusters, stride=sel_stride, hold=hold,
                                      force=specular == "clustered", tol=sub_tol, max_iters=max_iters, dtype=dt,
                                      chunk=chunk, weighting=weighting, seed=seed, relabel=relabel)
            run.decisions += [d.to_dict() for d in sel.decisions]
            if sel.k == 1:
                run.skipped.append(f"specular clusters: not kept ({sel.reason})")
    labeler: Labeler | None = sel.labeler if sel is not None and sel.k > 1 else None
    spec = glob
    if labeler is not None:
        with run.stage("refine"):
            sub = build_observations(capture, lobe=lobe, stride=stride, dtype=dt, chunk=chunk, ref=Reference(glob.s, glob.alpha),
                                     weighting=weighting, labeler=labeler, want_tmin=True)
            spec = fit_clustered(sub, labeler, glob, tol=sub_tol, max_iters=max_iters)
    # 4b. gloss maps (from the global or clustered fit): forced, or kept when they beat it on the held-out shot
    with run.stage("choice.gloss maps"):
        use_maps, maps_info = _maps_decision(capture, run, glob, sel, specular=specular, s_fixed=s_fixed, plan=plan,
                                             sel_stride=sel_stride, tol=sub_tol, max_iters=max_iters, dt=dt, chunk=chunk,
                                             weighting=weighting, lobe=lobe, started=start is not None, base=spec,
                                             labeler=labeler)
    if maps_info is not None and maps_info.get("decision") is not None:
        run.decisions.append(maps_info["decision"])
    with run.stage("choice.specular colour"):
        if start is not None:  # the model's colour, not tested again
            white = start.white and glob is not None and labeler is None and s_fixed is None and not use_maps
        else:
            white = colour and _colour_decision(capture, run, glob, sel, specular=specular, s_fixed=s_fixed,
                                                use_maps=use_maps, labeler=labeler, plan=plan, grids=grids, tol=sub_tol,
                                                max_iters=max_iters, weighting=weighting)
    return SubsampleDecisions(spec, labeler, s_fixed, sel, use_maps, maps_info, weighting, white, plan,
                              per_channel=start is not None and start.per_channel)


@dataclass(frozen=True)
class _Grids:
    """The subsample's pixel strides and the observations' dtype, chunk size and lobe."""

    stride: int  # the init / refine subsample
    sel_stride: int  # the selection subsample
    dtype: torch.dtype
    chunk: int
    lobe: str

    def build(self, capture: Capture, stride: int, **kw) -> Observations:
        return build_observations(capture, lobe=self.lobe, stride=stride, dtype=self.dtype, chunk=self.chunk, **kw)


def _initial_fit(capture, run: FitRun, g: _Grids, *, specular, tol, sub_tol, max_iters,
                 start: Start | None = None) -> tuple[Observations, SpecFit | None]:
    """1–2: the paper's scheme (loose tolerance) and a coarse α grid on the selection subsample (``start``: its α
    instead), then the variable projection on the subsample. Returns (subsample observations, global fit or None)."""
    with run.stage("init"):
        sub = g.build(capture, g.stride)
    if specular == "none":
        run.skipped.append("specular: disabled by the caller (specular='none')")
        return sub, None
    if start is not None:
        with run.stage("refine"):
            glob = fit_specular(sub, _start_beta(sub, start), tol=sub_tol, max_iters=max_iters,
                                on_iter=run.logger("refine.sub", sub.num_pixels))
        return sub, glob
    with run.stage("init"):
        coarse = sub if g.sel_stride == g.stride else g.build(capture, g.sel_stride)
    if g.lobe == "phong":
        n_coarse = coarse.num_pixels
        with run.stage("paper"):
            pf = paper_scheme(coarse, tol=max(tol, INIT_TOL), max_iters=min(max_iters, INIT_ITERS),
                              on_iter=lambda st, it, r, a: run.log(st, it, r, a, n_coarse))
    with run.stage("init"):  # other lobes: no paper scheme (its control points are Phong's), a finer α grid
        beta0 = grid_beta(coarse, 1, extra=pf.alpha.view(1, 3)) if g.lobe == "phong" else grid_beta(coarse, 1, grid=LOBE_GRID)
        del coarse
    with run.stage("refine"):
        glob = fit_specular(sub, beta0, tol=sub_tol, max_iters=max_iters, on_iter=run.logger("refine.sub", sub.num_pixels))
    return sub, glob


def _started_fit(capture, run: FitRun, g: _Grids, start: Start, *, noise: bool, sub_tol,
                 max_iters) -> tuple[Observations, SpecFit, Weighting | None]:
    """1–2b from ``start``: the subsample weighted by its noise model at its lobe (``noise``; else uniform), fitted
    from its α. Returns (observations, fit, weighting or None). A start without a noise model and weights asked for
    estimate one instead (:func:`_weighted_refit`)."""
    weighting = None
    if noise:  # σ only scales robust weights and outlier cuts, neither asked for
        weighting = Weighting(sigma=torch.ones(3, dtype=torch.float64, device=start.s.device), variance=start.variance)
    with run.stage("init"):
        sub = g.build(capture, g.stride, ref=Reference(start.s, start.alpha[:1]), weighting=weighting)
    with run.stage("refine"):
        glob = fit_specular(sub, _start_beta(sub, start), tol=sub_tol, max_iters=max_iters,
                            on_iter=run.logger("refine.sub", sub.num_pixels))
    return sub, glob, weighting


def _start_beta(sub: Observations, start: Start) -> Tensor:
    """(1, 3) log α: the start's α, or (several) per channel the one of least cost on ``sub``."""
    alpha = start.alpha
    return torch.log(alpha) if alpha.shape[0] == 1 else grid_beta(sub, 1, extra=alpha, grid=())


def _weighted_refit(capture, run: FitRun, g: _Grids, sub: Observations, glob: SpecFit | None, *, robust, outliers,
                    noise, sub_tol, max_iters) -> tuple[Observations, SpecFit | None, Weighting | None]:
    """2b: residual scale (and noise model) at the subsample fit, the weighted observations and a refit.
    Returns (observations, fit, weighting; None when outlier masking finds too few outliers to matter)."""
    dev = capture.images.device
    with run.stage("refine"):
        if glob is None:
            glob0 = evaluate_specular(sub, torch.zeros(1, 3, dtype=torch.float64, device=dev),
                                      torch.ones(1, 3, dtype=torch.float64, device=dev))
        else:
            glob0 = glob
        floor = _sigma_floor(capture)
        sigma = residual_scale(sub, glob0.s, glob0.alpha, glob0.eb).clamp_min(floor)
        variance = noise_model(sub, glob0.s, glob0.alpha, glob0.eb, floor=floor**2) if noise else None
        weighting = Weighting(sigma=sigma, robust=robust, outlier_k=outliers, variance=variance)
        n_base = float(sub.n.sum())
        for _ in range(2 if robust is not None else 1):
            sub = g.build(capture, g.stride, ref=Reference(glob0.s, glob0.alpha), weighting=weighting)
            if glob is None:
                break
            glob = fit_specular(sub, torch.log(glob.alpha), tol=sub_tol, max_iters=max_iters,
                                on_iter=run.logger("refine.sub", sub.num_pixels))
            glob0 = glob
    if robust is None and outliers is not None:
        frac = 1.0 - float(sub.n.sum()) / max(n_base, 1.0)
        if frac < OUTLIER_SKIP:
            run.skipped.append(f"outliers: {frac:.1e} of the subsample's observations beyond {outliers:g}·σ; "
                               "full-resolution outlier masking skipped")
            weighting = None if weighting.variance is None else replace(weighting, outlier_k=None)
    return sub, glob, weighting


def _weights_decision(capture, run: FitRun, g: _Grids, sub: Observations, glob: SpecFit | None, *, robust, outliers,
                      sub_tol, max_iters, plan: ShotPlan | None) -> tuple[Observations, SpecFit | None, Weighting | None]:
    """2a. Uniform or noise weights (each observation by the inverse of its expected variance,
    :func:`~torchmetal.fit.refine.noise_model`), on the shot with the most specular energy left out of both
    fits and scored unweighted by the paired rule; uniform is the reference. Without a specular fit or with
    fewer than 3 shots, uniform. Returns what :func:`_weighted_refit` returns for the winner (robust weights
    and outlier masks, when asked, on top)."""
    n_shots = int(capture.images.shape[0])
    plain = (sub, glob, None)
    if robust is not None or outliers is not None:
        plain = _weighted_refit(capture, run, g, sub, glob, robust=robust, outliers=outliers, noise=False,
                                sub_tol=sub_tol, max_iters=max_iters)
    if glob is None or n_shots < 3:
        return plain
    weighted = _weighted_refit(capture, run, g, sub, glob, robust=robust, outliers=outliers, noise=True, sub_tol=sub_tol,
                               max_iters=max_iters)
    if weighted[1] is None:
        return plain
    hold = plan.hold
    with run.stage("select"):
        errors = {}
        for name, (_, fit, weighting) in (("uniform", plain), ("noise", weighted)):
            obs, ho, f = fit_without_hold(capture, fit, stride=g.sel_stride, hold=hold, tol=sub_tol, max_iters=max_iters,
                                          dtype=g.dtype, chunk=g.chunk, weighting=weighting)
            errors[name] = heldout_errors(ho, texture_map(obs, f.s, f.eb), f.s, f.alpha)
        if not errors["uniform"].numel():  # every observation of the shot saturated, masked or unlit
            run.skipped.append(f"weights: held-out shot {hold} has no valid observation; uniform")
            return plain
        d = paired_choice("weights", errors, "uniform", floor=MIN_GAIN_ABS * mean_square(ho))
        d.holds, d.pixels = [hold], ho.num_pixels
    run.decisions.append(d.to_dict())
    return weighted if d.chosen == "noise" else plain


def _highlight_evidence(capture, run: FitRun, g: _Grids, glob: SpecFit | None, *, sub_tol, max_iters,
                        weighting, plan: ShotPlan | None, tested: bool = True) -> tuple[SpecFit | None, Tensor | None]:
    """3: highlight evidence, in sample, then (``tested``) on a held-out shot (a sharp lobe can fit noise).
    Returns (the global fit, None without evidence; ``s_fixed`` (1, 3): 0 in channels without evidence)."""
    if glob is None:
        return None, None
    n_shots = int(capture.images.shape[0])
    ev = evidence(glob)[0]
    reason = None
    if not bool(ev.any()):
        one = " (one shot cannot separate diffuse and specular)" if n_shots == 1 else ""
        frac = float(((glob.A - glob.cost) / glob.Y.clamp_min(1e-300)).max().clamp_min(0.0))
        reason = (f"no highlight evidence{one}: the best specular term explains {frac:.1e} of the image energy "
                  f"({float(glob.explained().max()):.1%} of the diffuse-only residual)")
    elif n_shots >= 3 and tested:
        with run.stage("select"):
            ev_decision = heldout_evidence(capture, glob, stride=g.sel_stride, hold=plan.hold, tol=sub_tol,
                                           max_iters=max_iters, dtype=g.dtype, chunk=g.chunk, weighting=weighting)
        run.decisions.append(ev_decision.to_dict())
        if ev_decision.chosen != "specular":
            reason = f"no highlight evidence on a held-out shot ({ev_decision.reason})"
    if reason is not None:
        run.skipped.append(f"specular: {reason}; s = 0")
        return None, None
    if bool(ev.all()):
        return glob, None
    chans = [c for c, e in zip("RGB", ev.tolist()) if not e]
    run.skipped.append(f"specular: no highlight evidence in channel(s) {', '.join(chans)}; s = 0 there")
    return glob, torch.where(ev, torch.full_like(glob.s[0], math.nan), torch.zeros_like(glob.s[0])).view(1, 3)


def _colour_decision(capture: Capture, run: FitRun, glob: SpecFit | None, sel: Selection | None, *, specular: str,
                     s_fixed: Tensor | None, use_maps: bool, labeler: Labeler | None, plan: ShotPlan | None, grids: _Grids,
                     tol: float, max_iters: int, weighting: Weighting | None) -> bool:
    """4c. White specular (one s for the three channels) against per-channel s on the selection's held-out
    shot (:func:`~torchmetal.fit.colour.choose_colour`): tried for a global lobe of specular="auto" with
    highlights in every channel. Returns whether white won."""
    n_shots = int(capture.images.shape[0])
    if glob is None or specular != "auto" or use_maps or labeler is not None or s_fixed is not None or n_shots < 3:
        return False
    hold = sel.hold if sel is not None and sel.hold >= 0 else plan.hold
    with run.stage("select"):
        d = choose_colour(capture, glob, stride=grids.sel_stride, hold=hold, tol=tol, max_iters=max_iters,
                          dtype=grids.dtype, chunk=grids.chunk, weighting=weighting)
    run.decisions.append(d.to_dict())
    return d.chosen == "white"


def _maps_decision(capture, run: FitRun, glob, sel, *, specular, s_fixed, plan, sel_stride, tol, max_iters, dt, chunk,
                   weighting, lobe, started: bool = False, base: SpecFit | None = None,
                   labeler: Labeler | None = None) -> tuple[bool, dict | None]:
    """Whether the full-resolution fit gets gloss maps (and the held-out evidence behind it).

    The maps start from the kept specular structure ``base`` (default ``glob``): the global fit, or the subsample's
    clustered fit with its ``labeler`` where clusters were kept: a sample of several materials whose gloss also
    varies inside each needs both.
    With specular="auto" they must beat that structure on the shot plan's first :data:`~torchmetal.fit.gloss.HOLDS`
    shots, each left out in turn (the selection's held-out shot first); ``started`` (a refit of a maps model,
    :mod:`torchmetal.fit.start`): kept untried."""
    n_shots = int(capture.images.shape[0])
    if glob is None or specular not in ("auto", "maps"):
        return False, None
    if started and specular == "maps":
        return True, {"kept": True, "hold": -1, "mse": {}, "reason": "the model's gloss maps (a refit from its start)"}
    if n_shots < 3:
        if specular == "auto":
            run.skipped.append(f"gloss maps: a held-out test needs >= 3 shots, found {n_shots}")
            return False, None
        return True, {"kept": True, "hold": -1, "mse": {}, "reason": "forced (specular='maps'); no shot to hold out"}
    if s_fixed is not None and specular == "auto":
        run.skipped.append("gloss maps: not tried (some channels show no highlight)")
        return False, None
    have_sel = sel is not None and sel.hold >= 0 and sel.errors is not None
    hold = sel.hold if have_sel else plan.hold
    base_errors = sel.errors if have_sel else None  # the kept candidate's errors on the same held-out shot
    base = glob if base is None else base
    with run.stage("select"):
        ms = choose_maps(capture, Reference(base.s, base.alpha), stride=sel_stride, hold=hold, force=specular == "maps",
                         tol=tol, max_iters=max_iters, dtype=dt, chunk=chunk, weighting=weighting, lobe=lobe,
                         base_errors=base_errors, labeler=labeler, pinned=base.pinned,
                         more_holds=plan.holds(MAPS_HOLDS))
    if not ms.kept:
        run.skipped.append(f"gloss maps: not kept ({ms.reason})")
    return ms.kept, ms.to_dict()
