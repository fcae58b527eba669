"""``fit_phong``: the paper's scheme, or the paper's scheme as init plus a joint refinement.

scheme="refine" (default), on an H×W capture:
  1. observations on a strided pixel subsample (≤ ``sub_pixels``): the paper's scheme (4.1.6,
     4.1.1–4.1.5, loose tolerance) and a coarse α grid give β⁰;
  2. variable-projection LM (:mod:`torchmetal.fit.refine`) on the subsample; residual scale σ,
     then outlier masks / robust weights (IRLS) and a refit;
  3. highlight evidence: channels whose specular term explains nothing get s = 0 (all channels
     → the specular fit is skipped and reported);
  4. specular="auto"/"clustered": held-out comparison of global vs clustered specular
     (:mod:`torchmetal.fit.clusters`) on a smaller subsample;
  5. full resolution: one pass builds the geometry and the weights at the subsample solution,
     then LM from there until the tolerance; texture in closed form.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor

from torchmetal.errors import FitError, InputError
from torchmetal.fit.clusters import (
    Labeler, Selection, choose_specular, evidence, fit_clustered, heldout_evidence, heldout_mse, relabel_pixels,
)
from torchmetal.fit.gloss import choose_maps, fit_gloss_maps
from torchmetal.fit.lobe_choice import LOBE_GRID, choose_lobe
from torchmetal.fit.lobes import lobe_factor
from torchmetal.fit.paper import paper_scheme
from torchmetal.fit.problem import (
    ROBUST, Observations, Reference, Weighting, build_observations, compute_dtype, grid_stride,
)
from torchmetal.fit.refine import (
    ALPHA_MIN, SpecFit, evaluate_specular, fill_unobserved, fit_specular, grid_beta, pixel_map, residual_scale, texture_map,
    pinned_terms, share_alpha, unobserved,
)
from torchmetal.fit.result import FitResult, IterationCounts
from torchmetal.lobes import LOBES, check_lobe

SCHEMES = ("paper", "refine")
SPECULARS = ("auto", "global", "clustered", "maps", "none")
SIGMA_FLOOR = 1e-5  # residual scale floor, relative to the largest pixel value
INIT_TOL = 1e-3  # the paper's scheme as init: |ΔErr| ≤ 1e-3·Err …
INIT_ITERS = 10  # … or 10 iterations
OUTLIER_SKIP = 1e-5  # fewer outliers than this on the subsample: none are looked for at full resolution


# ------------------------------------------------------------------------------- checks


def _check_args(capture, scheme, specular, tol, max_iters, robust, outliers, clusters) -> None:
    if scheme not in SCHEMES:
        raise InputError(f"scheme: expected one of {list(SCHEMES)}, found {scheme!r}")
    if specular not in SPECULARS:
        raise InputError(f"specular: expected one of {list(SPECULARS)}, found {specular!r}")
    if scheme == "paper" and specular in ("clustered", "maps"):
        raise InputError("specular: expected 'auto', 'global' or 'none' with scheme='paper' (the paper's specular is "
                         f"global), found {specular!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise InputError(f"tol: expected a finite number > 0, found {tol!r}")
    if not (isinstance(max_iters, int) and max_iters >= 1):
        raise InputError(f"max_iters: expected an int >= 1, found {max_iters!r}")
    if robust not in (None, *ROBUST):
        raise InputError(f"robust: expected None or one of {list(ROBUST)}, found {robust!r}")
    if outliers is not None and not (isinstance(outliers, (int, float)) and outliers > 0):
        raise InputError(f"outliers: expected None or a number > 0 (cut at k·σ), found {outliers!r}")
    if not all(isinstance(k, int) and k >= 2 for k in clusters):
        raise InputError(f"clusters: expected cluster counts >= 2, found {clusters!r}")
    for name in ("images", "normals", "lights", "intensities", "cameras"):
        t = getattr(capture, name, None)
        if not isinstance(t, Tensor) or not t.is_floating_point():
            found = t.dtype if isinstance(t, Tensor) else type(t).__name__
            raise FitError(f"capture.{name}: expected a floating-point tensor, found {found}")
        bad = ~torch.isfinite(t)
        if bool(bad.any()):
            raise FitError(f"capture.{name}: expected finite values, found {int(bad.sum())} non-finite of {t.numel()}")
    x = capture.images
    if x.dim() != 4 or x.shape[1] != 3 or x.shape[0] < 1:
        raise FitError(f"capture.images: expected shape (N, 3, H, W), found {tuple(x.shape)}")


def _check_finite(name: str, *xs: Tensor) -> None:
    for x in xs:
        if x is not None and not bool(torch.isfinite(x).all()):
            raise FitError(f"{name}: expected finite fit values, found NaN/Inf (non-finite residuals)")


# ------------------------------------------------------------------------------- the fit


class FitRun:
    """Timers, history and the progress bar of one fit."""

    def __init__(self, progress: bool) -> None:
        self.times: dict[str, float] = {}
        self.history: list[dict] = []
        self.iterations = IterationCounts()
        self.skipped: list[str] = []
        self.bar = None
        if progress:
            from tqdm.auto import tqdm

            self.bar = tqdm(desc="fit_phong", unit="it", leave=False)

    @contextmanager
    def stage(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - t0

    def log(self, stage: str, it: int, rmse: float, active: float, pixels: int) -> None:
        self.history.append({"stage": stage, "iter": int(it), "rmse": float(rmse), "active": float(active),
                             "pixels": int(pixels)})
        self.iterations[stage] = max(self.iterations.get(stage, 0), int(it))
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(stage=stage, rmse=f"{rmse:.3g}")

    def logger(self, stage: str, pixels: int):
        return lambda it, rmse, active: self.log(stage, it, rmse, active, pixels)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _rmse(fit: SpecFit, obs: Observations) -> float:
    return math.sqrt(float(fit.cost.sum()) / max(1.0, float(obs.n.double().sum())))


def _grid_maps(x: Tensor, h: int, w: int) -> Tensor:
    return x.reshape(*x.shape[:-1], h, w)


def _sigma(obs: Observations, fit: SpecFit, capture) -> Tensor:
    sig = residual_scale(obs, fit.s, fit.alpha, fit.eb)
    floor = SIGMA_FLOOR * float(capture.images.detach().abs().amax().clamp_min(1e-30))
    return sig.clamp_min(floor)


def fit_phong(
    capture,
    *,
    scheme: str = "refine",
    specular: str = "auto",
    tol: float = 1e-6,
    max_iters: int = 100,
    robust: str | None = None,
    progress: bool = False,
    outliers: float | None = None,
    clusters: tuple[int, ...] = (2, 3, 4),
    max_pixels_per_chunk: int = 4096,
    sub_pixels: int = 1 << 16,
    select_pixels: int = 1 << 13,
    seed: int = 0,
    lobe: str = "phong",
) -> FitResult:
    """Fit the Phong model of DESIGN 2.2 (texture d(p), s, α per channel) to a capture.

    Args:
        capture: a :class:`~torchmetal.io.capture.Capture` (images (N,3,H,W) linear, normals,
            mask, saturated, lights, intensities, cameras, size). Only mask pixels count;
            saturated observations and n·l ≤ 0 are left out.
        scheme: "paper" (section 4.1 only) or "refine" (the paper's scheme as init, then the
            joint variable-projection refinement).
        specular: "auto" (global, or clustered / gloss maps only when they win on a held-out shot),
            "global", "clustered", "maps" (per-pixel s, α with an edge-aware smoothness prior,
            :mod:`torchmetal.fit.gloss`) or "none".
        tol: relative tolerance of the stopping rules (|ΔErr| ≤ tol·Err; β step ≤ tol).
        max_iters: iteration cap per stage.
        robust: None (least squares), "huber" or "cauchy" (IRLS weights).
        progress: show a tqdm bar.
        outliers: observations with |residual| > outliers·σ (σ = 1.4826·MAD) are left out
            (flakes, glints); None (default) keeps all. Only with scheme="refine". Off by default:
            on real foils a 5·σ cut also removes genuine highlights the global model misfits
            (cards_blue leave-one-out: 18.9 dB without, 18.2 dB with, clustered specular).
        clusters: cluster counts tried for clustered specular.
        max_pixels_per_chunk: pixels per processing chunk (memory of temporaries:
            ~N·3·chunk values each); results do not depend on it.
        sub_pixels, select_pixels: pixel budgets of the init and selection subsamples.
        seed: k-means seed.
        lobe: the specular lobe (:mod:`torchmetal.lobes`): "phong" (DESIGN 2.2, the default),
            "blinn", "ggx", or "auto" (the lowest error on held-out shots,
            :mod:`torchmetal.fit.lobe_choice`; phong unless another lobe wins by 1 %). Other
            lobes than phong need scheme="refine".

    Returns:
        :class:`FitResult`.

    Raises:
        InputError: bad arguments. FitError: non-finite input or a fit that went non-finite.
    """
    clusters = tuple(clusters)
    _check_args(capture, scheme, specular, tol, max_iters, robust, outliers, clusters)
    check_lobe(lobe, (*LOBES, "auto"))
    if scheme == "paper" and lobe != "phong":
        raise InputError(f"lobe: expected 'phong' with scheme='paper' (the paper's lobe), found {lobe!r}")
    run = FitRun(progress)
    lobe_sel = None
    try:
        if lobe == "auto" and specular != "none":
            h, w = capture.images.shape[-2:]
            with run.stage("lobe"):
                lobe_sel = choose_lobe(capture, stride=grid_stride(h, w, select_pixels), tol=max(tol, 1e-4),
                                       max_iters=max_iters, dtype=compute_dtype(capture.images), chunk=max_pixels_per_chunk)
            lobe = lobe_sel.lobe
        elif lobe == "auto":
            lobe = "phong"
            run.skipped.append("lobe: specular='none', no lobe to choose; phong")
        if scheme == "paper":
            res = _fit_paper(capture, run, specular=specular, tol=tol, max_iters=max_iters, chunk=max_pixels_per_chunk,
                             robust=robust)
        else:
            res = _fit_refine(capture, run, specular=specular, tol=tol, max_iters=max_iters, robust=robust,
                              outliers=outliers, clusters=clusters, chunk=max_pixels_per_chunk, sub_pixels=sub_pixels,
                              select_pixels=select_pixels, seed=seed, lobe=lobe)
    finally:
        run.close()
    res.lobe = lobe
    res.lobe_selection = None if lobe_sel is None else lobe_sel.to_dict()
    _check_finite("fit_phong", res.texture, res.s, res.alpha, torch.tensor(res.rmse))
    return res


def _result(capture, run: FitRun, texture: Tensor, s: Tensor, alpha: Tensor, **kw) -> FitResult:
    normals = capture.normals
    flat = bool((normals[0] == 0).all() and (normals[1] == 0).all() and (normals[2] == 1).all())
    dt = texture.dtype
    return FitResult(
        texture=texture, s=s.to(dt), alpha=alpha.to(dt), normals=normals.to(dt), size=tuple(float(v) for v in capture.size),
        history=run.history, stage_times=run.times, iterations=run.iterations, skipped=run.skipped, flat=flat, **kw,
    )


def _no_specular_texture(obs: Observations) -> Tensor:
    return torch.where(obs.saa > 0, obs.d0, obs.fallback)


def _finish_texture(tex: Tensor, obs: Observations, capture, run: FitRun) -> Tensor:
    """(3, P) → (3, H, W), ≥ 0; mask pixels the shots do not determine are inpainted (reported)."""
    h, w = capture.images.shape[-2:]
    bad = unobserved(obs, capture.mask.reshape(-1).bool())
    n_bad = int(bad.any(0).sum())
    tex = _grid_maps(tex, h, w)
    if n_bad:
        run.skipped.append(f"texture: {n_bad} mask pixel(s) never observed usefully (grazing, shadowed or saturated in "
                           "every shot) are inpainted from their neighbours")
        tex = fill_unobserved(tex, _grid_maps(bad, h, w))
    return tex.clamp_min(0.0)


def _fit_paper(capture, run: FitRun, *, specular: str, tol: float, max_iters: int, chunk: int, robust: str | None) -> FitResult:
    dt = compute_dtype(capture.images)
    h, w = capture.images.shape[-2:]
    with run.stage("geometry"):
        obs = build_observations(capture, dtype=dt, chunk=chunk)
    n_obs = max(1.0, float(obs.n.double().sum()))
    A = float(obs.A.double().sum())
    if specular == "none":
        run.skipped.append("specular: disabled by the caller (specular='none')")
        with run.stage("texture"):
            tex = _finish_texture(_no_specular_texture(obs), obs, capture, run)
        rmse = math.sqrt(A / n_obs)
        run.log("texture", 0, rmse, 1.0, obs.num_pixels)
        z = torch.zeros(3, dtype=dt, device=tex.device)
        return _result(capture, run, tex, z, torch.full_like(z, ALPHA_MIN), status="converged",
                       rmse=rmse, scheme="paper", specular="none")
    if specular == "auto":
        run.skipped.append("specular clusters: scheme='paper' fits the paper's global specular only")
    if robust is not None:
        run.skipped.append(f"robust: scheme='paper' is plain least squares ({robust!r} applies to scheme='refine')")
    with run.stage("paper"):
        pf = paper_scheme(obs, tol=tol, max_iters=max_iters,
                          on_iter=lambda st, it, r, a: run.log(st, it, r, a, obs.num_pixels))
    tex, s, alpha, err, status = pf.texture, pf.s, pf.alpha, pf.err, pf.status
    if not math.isfinite(err):
        raise FitError(f"fit_phong(scheme='paper'): expected finite residuals, found Err = {err}")
    if A <= 0 or (A - err) <= max(1e-3 * A, 1e-6 * float(obs.Y.double().sum())):
        explained = max(0.0, (A - err) / max(A, 1e-300))
        run.skipped.append(f"specular: no highlight evidence (the paper's fit explains {explained:.1%} "
                           "of the diffuse-only residual); s = 0")
        tex, err = _no_specular_texture(obs), A
        s, alpha = torch.zeros_like(s), torch.full_like(alpha, ALPHA_MIN)
    _check_finite("fit_phong(scheme='paper')", tex)
    with run.stage("texture"):
        tex = _finish_texture(tex, obs, capture, run)
    return _result(capture, run, tex, s, alpha, status=status,
                   rmse=math.sqrt(max(err, 0.0) / n_obs), scheme="paper", specular="global")


def _hold_shot(obs: Observations, fit: SpecFit) -> int:
    """The shot whose observations carry the most specular energy (the most telling to hold out)."""
    alpha = fit.alpha
    energy = torch.zeros(obs.num_shots, dtype=torch.float64, device=alpha.device)
    s3, a3 = fit.s[0].to(obs.dtype).view(1, 3, 1), alpha[0].to(obs.dtype).view(1, 3, 1)
    for j in range(len(obs.chunks)):
        y, g, u, L, w, inten = obs.chunk(j)
        b = s3 * inten * u * lobe_factor(L, a3, obs.geo_chunk(j), obs.lobe)
        energy += (w * b * b).sum((1, 2)).double()
    return int(energy.argmax())


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


def subsample_decisions(capture, run: FitRun, *, specular, tol, max_iters, robust, outliers, clusters, chunk,
                        sub_pixels, select_pixels, seed, lobe="phong") -> SubsampleDecisions:
    """Steps 1–4b of the refine scheme (module docstring) on strided pixel subsamples of ``capture``
    (any object with ``images`` (N, 3, H, W) readable by :func:`~torchmetal.fit.problem.build_observations`,
    such as the tiled fit's memory-mapped capture): the same values bit for bit for the same pixels."""
    imgs = capture.images
    dt = compute_dtype(imgs)
    n_shots, _, h, w = imgs.shape
    stride = grid_stride(h, w, sub_pixels)
    sub_tol = max(tol, 1e-4)
    weigh = outliers is not None or robust is not None

    # 1. init on a small subsample: the paper's scheme (loose tolerance) + a coarse α grid
    with run.stage("init"):
        sub = build_observations(capture, lobe=lobe, stride=stride, dtype=dt, chunk=chunk)
        sel_stride = grid_stride(h, w, select_pixels)
        coarse = sub if sel_stride == stride else build_observations(capture, lobe=lobe, stride=sel_stride, dtype=dt, chunk=chunk)
    if specular == "none":
        glob = None
        run.skipped.append("specular: disabled by the caller (specular='none')")
    else:
        if lobe == "phong":
            with run.stage("paper"):
                pf = paper_scheme(coarse, tol=max(tol, INIT_TOL), max_iters=min(max_iters, INIT_ITERS),
                                  on_iter=lambda st, it, r, a: run.log(st, it, r, a, coarse.num_pixels))
        with run.stage("init"):  # other lobes: no paper scheme (its control points are Phong's), a finer α grid
            beta0 = grid_beta(coarse, 1, extra=pf.alpha.view(1, 3)) if lobe == "phong" else grid_beta(coarse, 1, grid=LOBE_GRID)
            del coarse
        # 2. variable projection on the subsample, then weights and a refit
        with run.stage("refine"):
            glob = fit_specular(sub, beta0, tol=sub_tol, max_iters=max_iters, on_iter=run.logger("refine.sub", sub.num_pixels))
    weighting = None
    if weigh:
        with run.stage("refine"):
            if glob is None:
                glob0 = evaluate_specular(sub, torch.zeros(1, 3, dtype=torch.float64, device=imgs.device),
                                          torch.ones(1, 3, dtype=torch.float64, device=imgs.device))
            else:
                glob0 = glob
            sigma = _sigma(sub, glob0, capture)
            weighting = Weighting(sigma=sigma, robust=robust, outlier_k=outliers)
            n_base = float(sub.n.double().sum())
            for _ in range(2 if robust is not None else 1):
                sub = build_observations(capture, lobe=lobe, stride=stride, dtype=dt, chunk=chunk, ref=Reference(glob0.s, glob0.alpha),
                                         weighting=weighting)
                if glob is None:
                    break
                glob = fit_specular(sub, torch.log(glob.alpha), tol=sub_tol, max_iters=max_iters,
                                    on_iter=run.logger("refine.sub", sub.num_pixels))
                glob0 = glob

        if robust is None and weighting is not None:
            frac = 1.0 - float(sub.n.double().sum()) / max(n_base, 1.0)
            if frac < OUTLIER_SKIP:
                run.skipped.append(f"outliers: {frac:.1e} of the subsample's observations beyond {outliers:g}·σ; "
                                   "full-resolution outlier masking skipped")
                weighting = None

    # 3. highlight evidence: in sample, then on a held-out shot (a sharp lobe can fit noise)
    s_fixed = None
    if glob is not None:
        ev = evidence(glob)[0]
        reason = None
        if not bool(ev.any()):
            one = " (one shot cannot separate diffuse and specular)" if n_shots == 1 else ""
            frac = float(((glob.A - glob.cost) / glob.Y.clamp_min(1e-300)).max().clamp_min(0.0))
            reason = (f"no highlight evidence{one}: the best specular term explains {frac:.1e} of the image energy "
                      f"({float(glob.explained().max()):.1%} of the diffuse-only residual)")
        elif n_shots >= 3:
            with run.stage("select"):
                kept, mse_s, mse_d = heldout_evidence(capture, glob, stride=sel_stride, hold=_hold_shot(sub, glob),
                                                      tol=sub_tol, max_iters=max_iters, dtype=dt, chunk=chunk,
                                                      weighting=weighting)
            if not kept:
                reason = (f"no highlight evidence on a held-out shot (MSE {mse_s:.4g} with the specular term vs "
                          f"{mse_d:.4g} diffuse only)")
        if reason is not None:
            run.skipped.append(f"specular: {reason}; s = 0")
            glob = None
        elif not bool(ev.all()):
            chans = [c for c, e in zip("RGB", ev.tolist()) if not e]
            run.skipped.append(f"specular: no highlight evidence in channel(s) {', '.join(chans)}; s = 0 there")
            s_fixed = torch.where(ev, torch.full_like(glob.s[0], math.nan), torch.zeros_like(glob.s[0])).view(1, 3)

    # 4. global vs clustered
    sel: Selection | None = None
    if glob is not None and specular in ("auto", "clustered"):
        if n_shots < 3 and specular == "auto":
            run.skipped.append(f"specular clusters: a held-out test needs >= 3 shots, found {n_shots}")
        elif s_fixed is not None and specular == "auto":
            run.skipped.append("specular clusters: not tried (some channels show no highlight)")
        else:
            with run.stage("select"):
                hold = _hold_shot(sub, glob) if n_shots >= 3 else None
                sel = choose_specular(capture, glob, candidates=clusters, stride=sel_stride, hold=hold,
                                      force=specular == "clustered", tol=sub_tol, max_iters=max_iters, dtype=dt,
                                      chunk=chunk, weighting=weighting, seed=seed)
            if sel.k == 1:
                run.skipped.append(f"specular clusters: not kept ({sel.reason})")
    labeler: Labeler | None = sel.labeler if sel is not None and sel.k > 1 else None
    # 4b. gloss maps (from the global fit): forced, or kept when they beat global/clustered on the held-out shot
    use_maps, maps_info = _maps_decision(capture, run, glob, sel, specular=specular, s_fixed=s_fixed, sub=sub,
                                         sel_stride=sel_stride, tol=sub_tol, max_iters=max_iters, dt=dt, chunk=chunk,
                                         weighting=weighting, lobe=lobe)
    if use_maps:
        labeler = None
    if labeler is not None:
        with run.stage("refine"):
            sub = build_observations(capture, lobe=lobe, stride=stride, dtype=dt, chunk=chunk, ref=Reference(glob.s, glob.alpha),
                                     weighting=weighting, labeler=labeler, want_tmin=True)
            spec = fit_clustered(sub, labeler, glob, tol=sub_tol, max_iters=max_iters)
    else:
        spec = glob
    return SubsampleDecisions(spec, labeler, s_fixed, sel, use_maps, maps_info, weighting)


def _fit_refine(capture, run: FitRun, *, specular, tol, max_iters, robust, outliers, clusters, chunk, sub_pixels,
                select_pixels, seed, lobe="phong") -> FitResult:
    d = subsample_decisions(capture, run, specular=specular, tol=tol, max_iters=max_iters, robust=robust,
                            outliers=outliers, clusters=clusters, chunk=chunk, sub_pixels=sub_pixels,
                            select_pixels=select_pixels, seed=seed, lobe=lobe)
    spec, labeler, s_fixed, sel, use_maps, maps_info, weighting = (
        d.spec, d.labeler, d.s_fixed, d.sel, d.use_maps, d.maps_info, d.weighting)
    imgs = capture.images
    dt = compute_dtype(imgs)
    h, w = imgs.shape[-2:]

    # 5. full resolution
    with run.stage("geometry"):
        ref = None if spec is None else Reference(spec.s, spec.alpha)
        if ref is None and weighting is not None:
            ref = Reference(torch.zeros(1, 3, dtype=torch.float64, device=imgs.device),
                            torch.ones(1, 3, dtype=torch.float64, device=imgs.device))
        full = build_observations(capture, lobe=lobe, dtype=dt, chunk=chunk, ref=ref, weighting=weighting, labeler=labeler,
                                  with_stats=spec is not None, want_tmin=use_maps)
    n_obs = max(1.0, float(full.n.double().sum()))
    if spec is None:
        with run.stage("texture"):
            tex = _finish_texture(_no_specular_texture(full), full, capture, run)
        rmse = math.sqrt(float(full.A.double().sum()) / n_obs)
        run.log("texture", 0, rmse, 1.0, full.num_pixels)
        z = torch.zeros(3, dtype=dt, device=imgs.device)
        return _result(capture, run, tex, z, torch.full_like(z, ALPHA_MIN),
                       status="converged", rmse=rmse, scheme="refine", specular="none")
    with run.stage("refine"):
        k = spec.k
        s_fix, b_fix = None, None
        if labeler is not None:  # clusters without evidence keep the global terms
            s_fix, b_fix = pinned_terms(spec.pinned, spec.s, spec.alpha)
        elif s_fixed is not None:
            s_fix = s_fixed
        fit = fit_specular(full, torch.log(spec.alpha), tol=tol, max_iters=max_iters, s_fixed=s_fix, beta_fixed=b_fix,
                           on_iter=run.logger("refine", full.num_pixels), first=full.first_stats)
        full.first_stats = None
    if labeler is not None and sel is not None and sel.relabel:
        with run.stage("relabel"):
            fit, moved = relabel_pixels(full, fit, lambda obs, f: fit_specular(
                obs, torch.log(f.alpha), tol=tol, max_iters=max_iters, s_fixed=s_fix, beta_fixed=b_fix))
            run.log("relabel", 1, math.sqrt(float(fit.cost.sum()) / max(1.0, float(full.n.double().sum()))), 1.0, moved)
    if lobe == "ggx" and not use_maps and s_fix is None:  # one roughness for the three channels, where the data allow it
        with run.stage("refine"):
            fit, shared = share_alpha(full, fit)
        if shared["shared"]:
            run.skipped.append(f"specular: per-channel α not kept (GGX: one α for the three channels; they lower the "
                               f"cost by {shared['cost_rise']:.3g}, below the χ² bound {shared['bound']:.3g})")
    if use_maps:
        return _finish_maps(capture, run, full, fit, k, tol=tol, max_iters=max_iters, sel_info=sel, maps_info=maps_info)
    with run.stage("texture"):
        tex = _finish_texture(texture_map(full, fit.s, fit.eb), full, capture, run)
    _check_finite("fit_phong(scheme='refine')", tex, fit.s, fit.alpha, fit.cost)
    rmse = _rmse(fit, full)
    sel_info = None if sel is None else {"k": sel.k, "hold": sel.hold, "mse": sel.mse, "reason": sel.reason,
                                         "relabel": sel.relabel}
    if k == 1:
        return _result(capture, run, tex, fit.s[0], fit.alpha[0], status=fit.status, rmse=rmse, scheme="refine",
                       specular="global", selection=sel_info, maps_selection=maps_info)
    labels = _grid_maps(full.labels, h, w)
    area = torch.bincount(full.labels, minlength=k).to(torch.float64)
    area = area / area.sum().clamp_min(1.0)
    return _result(capture, run, tex, (area @ fit.s).to(dt), (area @ fit.alpha).to(dt), spec_labels=labels,
                   cluster_s=fit.s.to(dt), cluster_alpha=fit.alpha.to(dt), status=fit.status, rmse=rmse,
                   scheme="refine", specular="clustered", selection=sel_info, maps_selection=maps_info)


def _maps_decision(capture, run: FitRun, glob, sel, *, specular, s_fixed, sub, sel_stride, tol, max_iters, dt, chunk,
                   weighting, lobe) -> tuple[bool, dict | None]:
    """Whether the full-resolution fit gets gloss maps (and the held-out evidence behind it).

    The maps start from the global fit (they carry the spatial variation themselves). With
    specular="auto" they are tried only when clusters were not kept, and must beat global on the
    selection's held-out shot."""
    n_shots = int(capture.images.shape[0])
    if glob is None or specular not in ("auto", "maps"):
        return False, None
    if n_shots < 3:
        if specular == "auto":
            run.skipped.append(f"gloss maps: a held-out test needs >= 3 shots, found {n_shots}")
            return False, None
        return True, {"kept": True, "hold": -1, "mse": {}, "reason": "forced (specular='maps'); no shot to hold out"}
    if s_fixed is not None and specular == "auto":
        run.skipped.append("gloss maps: not tried (some channels show no highlight)")
        return False, None
    if specular == "auto" and sel is not None and sel.k > 1:  # a kept clustered result stays as it was
        run.skipped.append("gloss maps: not tried (clustered specular kept)")
        return False, None
    have_sel = sel is not None and sel.hold >= 0 and sel.mse
    hold = sel.hold if have_sel else _hold_shot(sub, glob)
    base_mse = min(sel.mse.values()) if have_sel and sel.k > 1 else (sel.mse.get("global") if have_sel else None)
    with run.stage("select"):
        ms = choose_maps(capture, Reference(glob.s, glob.alpha), stride=sel_stride, hold=hold, force=specular == "maps",
                         tol=tol, max_iters=max_iters, dtype=dt, chunk=chunk, weighting=weighting, lobe=lobe,
                         base_mse=base_mse)
    if not ms.kept:
        run.skipped.append(f"gloss maps: not kept ({ms.reason})")
    return ms.kept, ms.to_dict()


def _finish_maps(capture, run: FitRun, full: Observations, fit: SpecFit, k: int, *, tol, max_iters, sel_info, maps_info) -> FitResult:
    """Full-resolution gloss maps from the global/clustered fit ``fit``; texture at the maps."""
    h, w = capture.images.shape[-2:]
    dt = full.dtype
    labels = full.labels if k > 1 else None
    with run.stage("maps"):
        maps = fit_gloss_maps(full, pixel_map(fit.s, labels), pixel_map(fit.alpha, labels), stride=1, tol=max(tol, 1e-4),
                              max_iters=max_iters)
        run.log("maps", maps.iterations, 0.0, 1.0, full.num_pixels)
    with run.stage("texture"):
        tex = _finish_texture(maps.texture(full), full, capture, run)
    s_p, a_p, ar = maps.per_pixel()
    rmse = math.sqrt(heldout_mse(full, maps.texture(full), s_p, a_p, ar))
    _check_finite("fit_phong(specular='maps')", tex, maps.s, maps.alpha)
    inside = capture.mask.reshape(-1).bool() & (full.n.sum(0) > 0)
    wgt = inside.to(torch.float64) / inside.sum().clamp_min(1)
    s_mean = (maps.s.double() @ wgt) if bool(inside.any()) else fit.s[0].double()
    a_mean = (maps.alpha.double() @ wgt) if bool(inside.any()) else fit.alpha[0].double()
    sel = None if sel_info is None else {"k": sel_info.k, "hold": sel_info.hold, "mse": sel_info.mse, "reason": sel_info.reason}
    return _result(capture, run, tex, s_mean.to(dt), a_mean.to(dt), gloss_s=_grid_maps(maps.s.to(dt), h, w),
                   gloss_alpha=_grid_maps(maps.alpha.to(dt), h, w), status=fit.status, rmse=rmse, scheme="refine",
                   specular="maps", selection=sel, maps_selection=maps_info)
