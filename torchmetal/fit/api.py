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

Steps 1–4 (and the gloss-map trial) live in :mod:`torchmetal.fit.decisions`, shared with the tiled
fit; the run's timers and history in :mod:`torchmetal.fit.run`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.checks import check_finite
from torchmetal.errors import FitError, InputError
from torchmetal.fit.clusters import S_RATIO_MAX, heldout_mse, relabel_pixels, runaway
from torchmetal.fit.colour import fit_white
from torchmetal.fit.decisions import subsample_decisions
from torchmetal.fit.gloss import fit_gloss_maps
from torchmetal.fit.lobe_choice import choose_lobe
from torchmetal.fit.paper import paper_scheme
from torchmetal.fit.problem import ROBUST, Observations, Reference, build_observations, compute_dtype, grid_stride
from torchmetal.fit.refine import (
    ALPHA_MIN,
    SpecFit,
    fill_unobserved,
    fit_specular,
    pinned_terms,
    pixel_map,
    share_alpha,
    texture_map,
    unobserved,
)
from torchmetal.fit.result import FitResult
from torchmetal.fit.run import FitRun
from torchmetal.fit.start import Start
from torchmetal.geometry import is_flat
from torchmetal.lobes import LOBES, check_lobe
from torchmetal.memory import pixels_per_chunk, release_free_memory, streams_geometry

if TYPE_CHECKING:
    from torchmetal.fit.decisions import SubsampleDecisions
    from torchmetal.fit.lobe_choice import LobeSelection
    from torchmetal.io.capture import Capture
    from torchmetal.select.plan import ShotPlan

SCHEMES = ("paper", "refine")
SPECULARS = ("auto", "global", "clustered", "maps", "none")


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
        check_finite(t, f"capture.{name}", FitError)  # one reduction unless something is not finite
    x = capture.images
    if x.dim() != 4 or x.shape[1] != 3 or x.shape[0] < 1:
        raise FitError(f"capture.images: expected shape (N, 3, H, W), found {tuple(x.shape)}")


def _check_finite(name: str, *xs: Tensor) -> None:
    for x in xs:
        if x is not None and not bool(torch.isfinite(x).all()):
            raise FitError(f"{name}: expected finite fit values, found NaN/Inf (non-finite residuals)")


# ------------------------------------------------------------------------------- the fit


def _rmse(fit: SpecFit, obs: Observations) -> float:
    return math.sqrt(float(fit.cost.sum()) / obs.n_obs)


def _grid_maps(x: Tensor, h: int, w: int) -> Tensor:
    return x.reshape(*x.shape[:-1], h, w)


WEIGHTS = ("uniform", "noise", "auto")  # fit_phong's weights (fit_material's option of that name)


def fit_phong(
    capture: Capture, *, scheme: str = "refine", specular: str = "auto", tol: float = 1e-6, max_iters: int = 100,
    robust: str | None = None, progress: bool = False, outliers: float | None = None,
    clusters: tuple[int, ...] = (2, 3, 4), max_pixels_per_chunk: int | None = None, sub_pixels: int = 1 << 16,
    select_pixels: int = 1 << 13, seed: int = 0, lobe: str = "phong", weights: str = "uniform",
    relabel: bool = True, plan: ShotPlan | None = None, start: Start | None = None,
) -> FitResult:
    """Fit the Phong model of docs/design.md §2.2 (texture d(p), s, α per channel) to a capture.

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
            ~N·3·chunk values each); results do not depend on it. None: 4096 on the CPU, larger on an
            accelerator (:func:`~torchmetal.memory.pixels_per_chunk`).
        sub_pixels, select_pixels: pixel budgets of the init and selection subsamples.
        seed: k-means seed.
        lobe: the specular lobe (:mod:`torchmetal.lobes`): "phong" (docs/design.md §2.2, the default here),
            "blinn", "ggx", or "auto" (the lowest error on held-out shots,
            :mod:`torchmetal.fit.lobe_choice`; phong unless another lobe wins beyond noise; phong with
            scheme="paper"). Other lobes than phong need scheme="refine".
        weights: the least-squares weights (the name and values of ``fit_material``'s option, :mod:`torchmetal.config`):
            "uniform" (the default here: every observation alike), "noise" (each observation by the inverse of its
            expected noise variance, a + b·ŷ per channel fitted to the residuals,
            :func:`~torchmetal.fit.refine.noise_model`: read noise, shot noise, the 8-bit sRGB step that grows with
            the value), or "auto": noise weights where the shot with the most specular energy, left out of both fits,
            is predicted better with them (the paired rule of :mod:`torchmetal.select.rule`; a "weights"
            decision; ``fit_material``'s default). Only with scheme="refine". The residuals also hold misfit
            (see :func:`~torchmetal.fit.refine.noise_model`): the held-out shot is what tells the two apart.
        relabel: for kept clusters, try moving pixels between them (:func:`~torchmetal.fit.clusters.relabel_pixels`,
            kept where the held-out shot prefers it); False: never (a refit keeping an earlier fit's structure).
        plan: the shots the choices leave out (:mod:`torchmetal.select.plan`), e.g. an earlier fit's
            ``shot_plan`` for a refit of the same capture; None: planned from this fit's first subsample fit.
        start: a refit of a model another fit chose (:class:`~torchmetal.fit.start.Start`, ``Start.of(fit)``; with
            that fit's ``lobe``, ``specular`` and ``weights``): it starts from that fit's values and does not test
            its highlight or specular colour again (it still splits its own clusters). Ignored where the lobe or the
            specular structure differs or ``weights`` is "auto".

    Returns:
        :class:`FitResult`.

    Raises:
        InputError: bad arguments. FitError: non-finite input or a fit that went non-finite.
    """
    clusters = tuple(clusters)
    if weights not in WEIGHTS:
        raise InputError(f"weights: expected one of {list(WEIGHTS)}, found {weights!r}")
    _check_args(capture, scheme, specular, tol, max_iters, robust, outliers, clusters)
    _check_lobe_arg(lobe, scheme)
    if max_pixels_per_chunk is None:
        max_pixels_per_chunk = pixels_per_chunk(capture)
    kw = dict(specular=specular, tol=tol, max_iters=max_iters, robust=robust, outliers=outliers, clusters=clusters,
              chunk=max_pixels_per_chunk, sub_pixels=sub_pixels, select_pixels=select_pixels, seed=seed,
              noise="auto" if weights == "auto" else weights == "noise", relabel=relabel, plan=plan, start=start)
    run = FitRun(progress)
    try:
        res, lobe, lobe_sel = _fit_scheme(capture, run, scheme, lobe, kw)
    finally:
        run.close()
    res.lobe = lobe
    res.lobe_selection = None if lobe_sel is None else lobe_sel.to_dict()
    _check_finite("fit_phong", res.texture, res.s, res.alpha, torch.tensor(res.rmse))
    return res


def _check_lobe_arg(lobe: str, scheme: str) -> None:
    check_lobe(lobe, (*LOBES, "auto"))
    if scheme == "paper" and lobe not in ("phong", "auto"):
        raise InputError(f"lobe: expected 'phong' or 'auto' with scheme='paper' (the paper's lobe), found {lobe!r}")


def _fit_scheme(capture: Capture, run: FitRun, scheme: str, lobe: str,
                kw: dict) -> tuple[FitResult, str, LobeSelection | None]:
    """The fit by ``scheme`` with the refine scheme's options ``kw``: (result, lobe, lobe selection or None)."""
    lobe = _settled_lobe(lobe, scheme, kw["specular"], run)
    if scheme == "paper":
        res = _fit_paper(capture, run, specular=kw["specular"], tol=kw["tol"], max_iters=kw["max_iters"],
                         chunk=kw["chunk"], robust=kw["robust"])
        return res, lobe, None
    return _fit_refine_lobe(capture, run, lobe, kw)


def _settled_lobe(lobe: str, scheme: str, specular: str, run: FitRun) -> str:
    """lobe="auto" where there is nothing to choose (scheme="paper", specular="none") is phong (reported)."""
    if lobe == "auto" and scheme == "paper":
        lobe = "phong"
        run.skipped.append("lobe: scheme='paper' fits the paper's lobe; phong")
    elif lobe == "auto" and specular == "none":
        lobe = "phong"
        run.skipped.append("lobe: specular='none', no lobe to choose; phong")
    return lobe


def _fit_refine_lobe(capture: Capture, run: FitRun, lobe: str, kw: dict) -> tuple[FitResult, str, LobeSelection | None]:
    """scheme="refine" with ``kw`` (:func:`_fit_refine`'s options); lobe="auto": the structure (clusters) with
    Phong first, then the lobes compete on it. Returns (result, lobe, lobe selection or None)."""
    decided = None
    lobe_sel = None
    if lobe == "auto":
        n_skipped, n_decided = len(run.skipped), len(run.decisions)
        decided = subsample_decisions(capture, run, lobe="phong", **kw)
        lobe, lobe_sel = _choose_lobe(capture, run, decided, tol=kw["tol"], max_iters=kw["max_iters"],
                                      select_pixels=kw["select_pixels"], chunk=kw["chunk"])
        if lobe != "phong":
            kw = {**kw, "plan": decided.plan}  # the same shots held out
            decided = None  # the decisions again, with the chosen lobe (Phong's notes no longer apply)
            del run.skipped[n_skipped:]
            run.decisions[n_decided:] = run.decisions[-1:]  # the lobe's own record stays
    return _fit_refine(capture, run, lobe=lobe, decided=decided, **kw), lobe, lobe_sel


def _choose_lobe(capture, run: FitRun, d, *, tol, max_iters, select_pixels, chunk):
    """lobe="auto": :func:`~torchmetal.fit.lobe_choice.choose_lobe` on the specular structure the Phong
    decisions ``d`` kept (global, or its clusters; global when Phong showed no highlight on its held-out
    shot: a highlight of another shape may, and the decisions are then made again with that lobe).
    Returns (lobe, selection)."""
    h, w = capture.images.shape[-2:]
    with run.stage("lobe"), run.stage("choice.lobe"):
        sel = choose_lobe(capture, stride=grid_stride(h, w, select_pixels), tol=max(tol, 1e-4), max_iters=max_iters,
                          dtype=compute_dtype(capture.images), chunk=chunk,
                          labeler=d.labeler if d.spec is not None else None, plan=d.plan)
    if sel.decision is not None:
        run.decisions.append(sel.decision)
    return sel.lobe, sel


def _result(capture, run: FitRun, texture: Tensor, s: Tensor, alpha: Tensor, **kw) -> FitResult:
    dt = texture.dtype
    return FitResult(
        texture=texture, s=s.to(dt), alpha=alpha.to(dt), normals=capture.normals.to(dt), size=tuple(float(v) for v in capture.size),
        history=run.history, stage_times=run.times, iterations=run.iterations, skipped=run.skipped,
        decisions=run.decisions, flat=is_flat(capture.normals), shot_plan=run.plan, **kw,
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
    return tex.clamp_min_(0.0)  # tex is this function's own (3, H, W)


def _fit_paper(capture, run: FitRun, *, specular: str, tol: float, max_iters: int, chunk: int, robust: str | None) -> FitResult:
    dt = compute_dtype(capture.images)
    h, w = capture.images.shape[-2:]
    with run.stage("geometry"):
        obs = build_observations(capture, dtype=dt, chunk=chunk)
    n_obs = obs.n_obs
    A = float(obs.A.sum(dtype=torch.float64))
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
    if A <= 0 or (A - err) <= max(1e-3 * A, 1e-6 * float(obs.energy().sum())):
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


def _fit_refine(capture, run: FitRun, *, specular, tol, max_iters, robust, outliers, clusters, chunk, sub_pixels,
                select_pixels, seed, lobe="phong", decided=None, noise=False, relabel=True, plan=None, start=None) -> FitResult:
    d = decided if decided is not None else subsample_decisions(
        capture, run, specular=specular, tol=tol, max_iters=max_iters, robust=robust, outliers=outliers,
        clusters=clusters, chunk=chunk, sub_pixels=sub_pixels, select_pixels=select_pixels, seed=seed, lobe=lobe,
        noise=noise, relabel=relabel, plan=plan, start=start)
    run.plan = d.plan
    weighting = d.weighting
    noise_info = None if weighting is None or weighting.variance is None else \
        {"a": weighting.variance[0].tolist(), "b": weighting.variance[1].tolist()}
    dt = compute_dtype(capture.images)
    full = _full_observations(capture, run, d, lobe=lobe, dt=dt, chunk=chunk)
    if d.spec is None:
        return _no_specular_refine(capture, run, full, dt, noise_info)
    fit, s_fix = _refine_full(full, run, d, tol=tol, max_iters=max_iters)
    if full.source is not None:  # a large capture: the LM's freed temporaries go back before the texture's
        release_free_memory()
    # one roughness for the three channels, where the data allow it (a refit of a model with three keeps them: Start)
    if lobe == "ggx" and not d.use_maps and s_fix is None and not d.per_channel:
        with run.stage("refine"):
            fit, shared = share_alpha(full, fit)
        if shared["shared"]:
            run.skipped.append(f"specular: per-channel α not kept (GGX: one α for the three channels; they lower the "
                               f"cost by {shared['cost_rise']:.3g}, below the χ² bound {shared['bound']:.3g})")
    if d.use_maps:
        return _finish_maps(capture, run, full, fit, d.spec.k, tol=tol, max_iters=max_iters, sel_info=d.sel,
                            maps_info=d.maps_info, noise=noise_info)
    with run.stage("texture"):
        tex = texture_map(full, fit.s, fit.eb)
        fit = replace(fit, eb=None)  # e_b (3, P) is spent: the texture's peak need not hold it
        tex = _finish_texture(tex, full, capture, run)
    return _refine_result(capture, run, full, fit, tex, d.spec.k, sel=d.sel, maps_info=d.maps_info, noise_info=noise_info)


def _full_observations(capture, run: FitRun, d: SubsampleDecisions, *, lobe: str, dt: torch.dtype,
                       chunk: int) -> Observations:
    """5. full resolution: the observations at the subsample's solution ``d`` (weights, labels, first stats).

    A capture over :data:`~torchmetal.memory.STREAM_BYTES` streams the geometry (stored, it would weigh
    1.25× the images): one geometry evaluation more per pass over the pixels (1024² × 8: +0.14 s on a
    0.16 s pass, −0.05 s on the build); a smaller one stores it (the memory is not worth that time).
    """
    imgs = capture.images
    spec, weighting = d.spec, d.weighting
    with run.stage("geometry"):
        ref = None if spec is None else Reference(spec.s, spec.alpha)
        if ref is None and weighting is not None:
            ref = Reference(torch.zeros(1, 3, dtype=torch.float64, device=imgs.device),
                            torch.ones(1, 3, dtype=torch.float64, device=imgs.device))
        full = build_observations(capture, lobe=lobe, dtype=dt, chunk=chunk, ref=ref, weighting=weighting, labeler=d.labeler,
                                  with_stats=spec is not None, want_tmin=d.use_maps, stream=streams_geometry(capture))
    return full


def _no_specular_refine(capture, run: FitRun, full: Observations, dt: torch.dtype, noise_info: dict | None) -> FitResult:
    """The refine scheme's result when the decisions dropped the specular term: the diffuse-only texture."""
    n_obs = full.n_obs
    with run.stage("texture"):
        tex = _finish_texture(_no_specular_texture(full), full, capture, run)
    rmse = math.sqrt(float(full.A.sum(dtype=torch.float64)) / n_obs)
    run.log("texture", 0, rmse, 1.0, full.num_pixels)
    z = torch.zeros(3, dtype=dt, device=capture.images.device)
    return _result(capture, run, tex, z, torch.full_like(z, ALPHA_MIN),
                   status="converged", rmse=rmse, scheme="refine", specular="none", noise=noise_info)


def _refine_full(full: Observations, run: FitRun, d: SubsampleDecisions, *, tol: float,
                 max_iters: int) -> tuple[SpecFit, Tensor | None]:
    """The full-resolution LM from the subsample's specular ``d.spec`` (then the pixels relabelled when the
    selection chose it). Returns (fit, s_fixed or None)."""
    spec, labeler, sel = d.spec, d.labeler, d.sel
    with run.stage("refine"):
        s_fix, b_fix = None, None
        if labeler is not None:  # clusters without evidence keep the global terms
            s_fix, b_fix = pinned_terms(spec.pinned, spec.s, spec.alpha)
        elif d.s_fixed is not None:
            s_fix = d.s_fixed
        first, full.first_stats = full.first_stats, None  # its e_b lives only as long as the LM needs it
        fit = fit_specular(full, torch.log(spec.alpha), tol=tol, max_iters=max_iters, s_fixed=s_fix, beta_fixed=b_fix,
                           on_iter=run.logger("refine", full.num_pixels), first=first)
        del first
        if labeler is not None:
            fit, s_fix, b_fix = _bounded(full, run, fit, spec, s_fix, b_fix, tol=tol, max_iters=max_iters)
        if d.white:  # one s for the three channels (fit.colour), chosen on the held-out shot
            fit = fit_white(full, fit, tol=tol, max_iters=max_iters, on_iter=run.logger("refine", full.num_pixels))
            s_fix = fit.s  # GGX's shared α would re-solve s per channel
    if labeler is not None and sel is not None and sel.relabel:
        with run.stage("relabel"):
            fit, moved = relabel_pixels(full, fit, lambda obs, f: fit_specular(
                obs, torch.log(f.alpha), tol=tol, max_iters=max_iters, s_fixed=s_fix, beta_fixed=b_fix))
            run.log("relabel", 1, math.sqrt(float(fit.cost.sum()) / full.n_obs), 1.0, moved)
            fit, s_fix, _ = _bounded(full, run, fit, spec, s_fix, b_fix, tol=tol, max_iters=max_iters)
    return fit, s_fix


def _bounded(full: Observations, run: FitRun, fit: SpecFit, spec: SpecFit, s_fix: Tensor | None, b_fix: Tensor | None,
             *, tol: float, max_iters: int) -> tuple[SpecFit, Tensor | None, Tensor | None]:
    """The clustered ``fit`` with its runaway elements (:func:`~torchmetal.fit.clusters.runaway`: a cluster's lobe
    its shots saw only in the tail) held at the subsample fit ``spec``'s terms. Returns (fit, s_fixed, beta_fixed)."""
    bad = runaway(fit.s, spec.s)
    if not bool(bad.any()):
        return fit, s_fix, b_fix
    pin = bad if fit.pinned is None else bad | fit.pinned
    run.skipped.append(f"specular clusters: {int(bad.any(1).sum())} cluster(s) whose s ran beyond {S_RATIO_MAX:g}× "
                       "the subsample fit's largest keep the subsample fit's terms")
    s_fix, b_fix = pinned_terms(pin, spec.s, spec.alpha)
    fit = fit_specular(full, torch.where(pin, b_fix, torch.log(fit.alpha)), tol=tol, max_iters=max_iters, s_fixed=s_fix,
                       beta_fixed=b_fix, on_iter=run.logger("refine", full.num_pixels))
    fit.pinned = pin
    return fit, s_fix, b_fix


def _refine_result(capture, run: FitRun, full: Observations, fit: SpecFit, tex: Tensor, k: int, *, sel,
                   maps_info: dict | None, noise_info: dict | None) -> FitResult:
    """The result of the global (k = 1) or clustered specular ``fit`` and its texture ``tex`` (3, H, W)."""
    dt = compute_dtype(capture.images)
    h, w = capture.images.shape[-2:]
    _check_finite("fit_phong(scheme='refine')", tex, fit.s, fit.alpha, fit.cost)
    rmse = _rmse(fit, full)
    sel_info = None if sel is None else {"k": sel.k, "hold": sel.hold, "mse": sel.mse, "reason": sel.reason,
                                         "relabel": sel.relabel}
    if k == 1:
        return _result(capture, run, tex, fit.s[0], fit.alpha[0], status=fit.status, rmse=rmse, scheme="refine", noise=noise_info,
                       specular="global", selection=sel_info, maps_selection=maps_info)
    labels = _grid_maps(full.labels, h, w)
    area = torch.bincount(full.labels, minlength=k).to(torch.float64)
    area = area / area.sum().clamp_min(1.0)
    return _result(capture, run, tex, (area @ fit.s).to(dt), (area @ fit.alpha).to(dt), spec_labels=labels, noise=noise_info,
                   cluster_s=fit.s.to(dt), cluster_alpha=fit.alpha.to(dt), status=fit.status, rmse=rmse,
                   scheme="refine", specular="clustered", selection=sel_info, maps_selection=maps_info)


def _finish_maps(capture, run: FitRun, full: Observations, fit: SpecFit, k: int, *, tol, max_iters, sel_info, maps_info,
                 noise=None) -> FitResult:
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
    return _result(capture, run, tex, s_mean.to(dt), a_mean.to(dt), noise=noise, gloss_s=_grid_maps(maps.s.to(dt), h, w),
                   gloss_alpha=_grid_maps(maps.alpha.to(dt), h, w), status=fit.status, rmse=rmse, scheme="refine",
                   specular="maps", selection=sel, maps_selection=maps_info)
