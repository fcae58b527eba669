"""Flake statistics across shots: the fitted FlakeModel (:func:`flake_statistics`, the public
entry point) and the maximum-likelihood glint fit behind it (:func:`fit_glints`).

:func:`flake_statistics` associates the detections into flakes and measures them
(:mod:`~torchmetal.flakes.estimate.association`), fits the glint likelihood
(:mod:`~torchmetal.flakes.estimate.likelihood`, :mod:`~torchmetal.flakes.estimate.visibility`,
:mod:`~torchmetal.flakes.estimate.glint_model`), then the shape and colour
(:mod:`~torchmetal.flakes.estimate.shape_colour`), and builds the :class:`FlakeModel`.

The true density is profiled out in closed form (ρ̂ = J / ∫P_any dp) and (τ, σ_g, log-A mean
and spread) maximise Σ_j log f_j − J log ∫P_any dp (L-BFGS, float64, log-normal priors: weak on
τ, σ_g and the log-A mean; on the log-A spread a moderate one, LogNormal(log 0.15, 0.5²), since a
hundred flakes barely constrain it while the colour's E[A] depends on it). σ_g is identified by
flakes seen in more than one shot (with none, it stays at its prior mean 0.03 rad), τ by how the
glint rate falls off as h moves away from the normal; ``report["identified"]`` says when either
is not.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace

import torch
from torch import Tensor

from torchmetal import lbfgs
from torchmetal.errors import InputError, MaterialError
from torchmetal.flakes.estimate.association import FlakeObservations, associate, measurable, observe, particle_pixels
from torchmetal.flakes.estimate.detect import Detection
from torchmetal.flakes.estimate.glint_model import GlintData, GlintFit, log_amp_floor, orthonormal_pair
from torchmetal.flakes.estimate.likelihood import objective
from torchmetal.flakes.estimate.shape_colour import fit_colour, fit_shapes
from torchmetal.flakes.estimate.shot_geometry import Geometry
from torchmetal.flakes.estimate.visibility import cell_grid, cell_headroom
from torchmetal.flakes.model import MAX_DENSITY, MIN_CELL, FlakeModel
from torchmetal.flakes.model.field import mean_peak_weight

TILT_RANGE = (0.01, 1.5)  # radians: the flake-normal slope spread the model can hold (a best point at the
# upper bound after DEGENERATE_AFTER evaluations is no flake layer: the likelihood stops, no model)
GLINT_RANGE = (0.003, 0.5)  # radians: a glint narrower than 0.2° is a collapse, not a measurement
SPREAD_RANGE = (0.02, 1.5)  # log-amplitude spread: flakes of one paint are alike within a factor e^1.5
CEILING_MARGIN = 1.0  # the amplitudes stop e× above the brightest detection (seen at most at its peak)
DEGENERATE_DENSITY = 1.0  # flakes per pixel: a best point that needs more is degenerate …
DEGENERATE_AFTER = 6  # … once this many evaluations have run (the start may be far off)


#: model clipped glints in the likelihood (Detection.headroom). Off: it fixes the colour of bright flakes (zoo area-4
#: scenes ×0.75-0.84 → 0.89-1.10) but doubles the density on flakes_orange (0.83 → 1.61) and on the real cards_blue
#: (0.0104 → 0.025/px, glint σ unidentified): docs/measurements.md, issue 41 item 7
MODEL_CLIPS = False


class _Degenerate(Exception):
    """Raised inside the L-BFGS loop to stop a likelihood running off to a degenerate point."""


_PER_FLAKE = ("half", "normal", "anchor", "amp", "detected", "sigma", "observed", "headroom")


def _recast(d: GlintData, index: Tensor | None, dtype: torch.dtype, *, flakes: bool, grid: bool) -> GlintData:
    """Copy of ``d`` with the flake rows ``index`` (all when None) and float fields of the
    flake rows and/or the grid cast to ``dtype``."""
    out = {}
    for f in fields(GlintData):
        v = getattr(d, f.name)
        if v is None:
            pass
        elif f.name in _PER_FLAKE:
            if index is not None:
                v = v[index]
            if flakes and v.is_floating_point():
                v = v.to(dtype)
        elif grid and isinstance(v, Tensor) and f.name != "grid_area":
            v = v.to(dtype)
        out[f.name] = v
    return GlintData(**out)


def _even_subsample(j: int, limit: int, device) -> Tensor:
    """min(j, limit) of j rows, evenly spaced (deterministic; all rows when j ≤ limit)."""
    if j <= limit:
        return torch.arange(j, device=device)
    return torch.floor(torch.arange(limit, device=device, dtype=torch.float64) * (j / limit)).long()


@contextmanager
def _one_thread():
    """Run the enclosed torch work (or decorated function) on one intra-op thread, restoring
    the previous count.

    The statistics work on many small tensors (≲ 10⁵ elements): a second thread saves
    nothing there, but every parallel region waits on it, which on a loaded CPU (other
    processes on the cores) made the fit ~7× slower (measured: 1.6 s vs 0.23 s, 1024² shot).
    """
    prev = torch.get_num_threads()
    if prev == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


@_one_thread()
def fit_glints(
    d: GlintData,
    *,
    max_flakes: int = 300,
    max_iter: int = 30,
    tol: float = 3e-3,
    restarts: int = 2,
    init: dict | None = None,
    nodes: dict | None = None,
    work_dtype: torch.dtype = torch.float32,
    uncertainty: bool = True,
) -> GlintFit:
    """Maximum-likelihood (τ, σ_g, A distribution) and the profiled true density.

    L-BFGS (strong Wolfe) from the start below, restarted from its best point while that still
    gains; the curvature for the standard errors is 4 forward differences of the gradient.

    Args:
        d: likelihood data; max_flakes: flakes in the numerator sum (an even subsample);
        max_iter: L-BFGS iterations per run;
        tol: L-BFGS stops when the loss or the (log-)parameters change less than this;
        restarts: at most this many fresh L-BFGS runs from the best point, while a run still
            gains ≥ 0.05 in log-likelihood;
        init: starting values (tau, glint_sigma, log_amp, log_amp_std; not modified);
        nodes: quadrature sizes {"num": {...}, "any": {...}}; work_dtype: dtype of the
        quadrature tensors (sums and parameters stay float64); uncertainty: compute standard
        errors and identifiability from the curvature (4 extra gradients).
    """
    dev = d.half.device
    nodes = nodes or {}
    j = d.amp.shape[0]
    if j == 0:
        raise InputError("fit_glints: expected at least one associated flake, found 0")
    d = replace(d, log_floor=log_amp_floor(d))  # one floor for the numerator and the float32 grid
    sub = _recast(d, _even_subsample(j, max_flakes, dev), work_dtype, flakes=True, grid=False)
    grid = _recast(d, None, work_dtype, flakes=False, grid=True)
    tau0, sg0, la0, va0, log_ceiling = _start_values(d, dict(init or {}), j, dev)
    prior_sd = torch.tensor([2.0, 2.0, 5.0, 0.5], dtype=torch.float64, device=dev)
    prior = (_prior_mean(la0, dev), prior_sd)
    run = _Run(grid, sub, prior, nodes, d, _free_parameters(d, dev))
    lo, hi = _box(d, log_ceiling, dev)
    th0 = torch.tensor([math.log(tau0), math.log(sg0), la0, math.log(va0)], dtype=torch.float64, device=dev)
    th0 = torch.minimum(torch.maximum(th0, lo), hi)
    best, iters, degenerate = _minimize(run, lo, hi, th0, restarts=restarts, max_iter=max_iter, tol=tol)
    loss, th, expected, grad = best
    prior_h = torch.diag(1.0 / prior_sd**2)
    se, data_h = _curvature(run, th, grad, prior_h, uncertainty and degenerate is None)
    total_area = float(d.grid_area.sum())
    names = ("log_tilt_sigma", "log_glint_sigma", "log_amp_mean", "log_amp_std")
    # a parameter is identified when the data, not the prior, sets its curvature
    ident = {nm: bool(data_h[i] > 4.0 * prior_h[i, i]) and bool(se[i] < 0.15) for i, nm in enumerate(names)}
    return GlintFit(
        tilt_sigma=float(torch.exp(th[0])), glint_sigma=float(torch.exp(th[1])), log_amp_mean=float(th[2]),
        log_amp_std=float(torch.exp(th[3])), density=d.count / expected if expected > 0 else math.inf,
        expected_fraction=expected / max(total_area, 1.0), loglik=-loss,
        std_err={nm: float(se[i]) for i, nm in enumerate(names)}, identified=ident, iterations=iters,
        evaluations=run.evals, log_amp_floor=log_amp_floor(d), log_amp_ceiling=log_ceiling, degenerate=degenerate,
    )


def _start_values(d: GlintData, init: dict, j: int, dev) -> tuple[float, float, float, float, float]:
    """The L-BFGS start (τ, σ_g, log-A mean, log-A spread; ``init``'s where given) and the log-A ceiling."""
    if "tau" not in init:  # detected flakes have m ≈ h*: the RMS slope of h* is a fair start
        h_star = d.half[torch.arange(j, device=dev), d.anchor]
        t1, t2 = orthonormal_pair(d.normal)
        hn = (h_star * d.normal).sum(-1).clamp_min(0.05)
        sl2 = (((h_star * t1).sum(-1) / hn) ** 2 + ((h_star * t2).sum(-1) / hn) ** 2).mean()
        init["tau"] = float(torch.sqrt(0.5 * sl2).clamp(0.02, 1.0))
    tau0 = init["tau"]
    sg0 = init.get("glint_sigma", 0.03)
    # a glint peaks at A only when h meets m, so the brightest detections bound A: log â is
    # roughly uniform on [log T, log A], and its top quantile is a close start for log A
    log_amp = torch.log(d.amp.clamp_min(1e-12)).double()
    log_ceiling = float(log_amp.max()) + CEILING_MARGIN
    la0 = init.get("log_amp", float(torch.quantile(log_amp, 0.98)) + 0.1)
    va0 = init.get("log_amp_std", 0.1)
    return tau0, sg0, la0, va0, log_ceiling


def _prior_mean(la0: float, dev) -> Tensor:
    """The log-normal priors' means of (log τ, log σ_g, ℓ, log v)."""
    # the amplitude spread's prior is the one that matters: with ~100 flakes the likelihood is flat
    # in it within 0.3 nats from 0.1 to 0.6 (demo), and E[A] = exp(ℓ + v²/2), hence the colour,
    # followed it up by 20 %; flakes of one paint are alike, so v ~ LogNormal(log 0.15, 0.5²)
    return torch.tensor([math.log(0.15), math.log(0.03), la0, math.log(0.15)], dtype=torch.float64, device=dev)


def _free_parameters(d: GlintData, dev) -> Tensor:
    """(4,) bool: the parameters the data can move."""
    # no flake seen in two shots (one shot, or shots far apart): nothing in the data sets the
    # glint width, so it stays at its start (the prior's mean unless ``init`` says otherwise)
    # instead of wandering along a flat valley (one 1024² shot: 10 of 23 evaluations)
    free = torch.ones(4, dtype=torch.bool, device=dev)
    free[1] = bool((d.detected.sum(1) > 1).any())
    return free


def _box(d: GlintData, log_ceiling: float, dev) -> tuple[Tensor, Tensor]:
    """Lower and upper bounds of the log-parameters."""
    # every parameter stays in a box the data can speak to (a collapsing glint width or tilt, an amplitude
    # distribution running off above the brightest detection: the estimates that made colours of 1e20)
    lo = torch.tensor([math.log(TILT_RANGE[0]), math.log(GLINT_RANGE[0]), log_amp_floor(d), math.log(SPREAD_RANGE[0])],
                      dtype=torch.float64, device=dev)
    hi = torch.tensor([math.log(TILT_RANGE[1]), math.log(GLINT_RANGE[1]), log_ceiling, math.log(SPREAD_RANGE[1])],
                      dtype=torch.float64, device=dev)
    hi = torch.maximum(hi, lo)
    return lo, hi


class _Run:
    """One likelihood fit's data and its count of objective evaluations."""

    def __init__(self, grid: GlintData, sub: GlintData, prior: tuple[Tensor, Tensor], nodes: dict, d: GlintData,
                 free: Tensor) -> None:
        self.grid, self.sub, self.prior, self.nodes, self.d, self.free = grid, sub, prior, nodes, d, free
        self.idx = torch.nonzero(free, as_tuple=True)[0]
        self.evals = 0

    def value_grad(self, t: Tensor, data_sub: GlintData) -> tuple[Tensor, Tensor, Tensor]:
        t = t.detach().clone().requires_grad_(True)
        loss, expected = objective(self.grid, data_sub, t, self.prior, self.nodes)
        self.evals += 1
        return loss.detach(), expected.detach(), torch.autograd.grad(loss, t)[0]

    def hessian(self, t: Tensor, g0: Tensor) -> Tensor:
        """Forward differences of the gradient (g0 at t), free block."""
        eps = 1e-2
        eye = torch.eye(4, dtype=t.dtype, device=self.free.device)
        idx = self.idx
        hess = torch.stack([(self.value_grad(t + eps * eye[i], self.sub)[2] - g0)[idx] / eps for i in idx.tolist()])
        return 0.5 * (hess + hess.t())


def _minimize(run: _Run, lo: Tensor, hi: Tensor, th0: Tensor, *, restarts: int, max_iter: int,
              tol: float) -> tuple[list, int, str | None]:
    """L-BFGS in the box from ``th0``, restarted: the best point [loss, θ, expected count, gradient], the
    iterations, and why the likelihood stopped as degenerate (None when it did not)."""
    d, free, dev = run.d, run.free, th0.device
    best = [float("inf"), th0.clone(), None, None]  # loss, θ, expected count, gradient
    iters = 0
    degenerate = None
    # L-BFGS may stop on one short line-search step far from the optimum: restart from the best
    # point (fresh curvature memory) until a run gains less than 0.05 in the loss
    for _ in range(restarts + 1):
        start_loss, start = best[0], best[1]

        def loss_grad(z: Tensor) -> tuple[float, Tensor]:
            z = z.detach().requires_grad_(True)
            with torch.enable_grad():  # θ projected onto the box: no gradient pushes past a bound
                theta = torch.minimum(torch.maximum(start + z, lo), hi)
                loss, expected = objective(run.grid, run.sub, theta, run.prior, run.nodes)
                g = torch.autograd.grad(loss, z)[0].masked_fill(~free, 0.0)
            run.evals += 1
            value = float(loss.detach())
            if value < best[0]:  # keep the best point visited (line searches may end off it)
                best[:] = [value, theta.detach().clone(), float(expected.detach()), g.clone()]
            if run.evals >= DEGENERATE_AFTER and d.count > DEGENERATE_DENSITY * best[2]:
                raise _Degenerate("needs")  # the best point needs more flakes than pixels: stop, no model
            if run.evals >= DEGENERATE_AFTER and float(best[1][0]) >= float(hi[0]) - 1e-9:
                raise _Degenerate("tilt")  # flake normals at random: no layer of flakes (TILT_RANGE)
            return value, g

        try:
            _, n = lbfgs.minimize(loss_grad, torch.zeros(4, dtype=torch.float64, device=dev), max_iter=max_iter,
                                  tolerance_grad=1e-5, tolerance_change=tol)
        except _Degenerate as why:
            degenerate = _degenerate_reason(str(why), run.evals, d.count, best[2])
            break
        iters += n
        if start_loss - best[0] < 0.05:
            break
    return best, iters, degenerate


def _degenerate_reason(why: str, evals: int, count: int, expected: float) -> str:
    """Why the likelihood stopped early (``why``: "tilt" or "needs")."""
    if why == "tilt":
        return (f"stopped after {evals} evaluations: the best point has the flake normals' tilt σ "
                f"at its bound {TILT_RANGE[1]:g} rad, normals at random: no layer of flakes (a sheen "
                "or rim the coating misfits)")
    return (f"stopped after {evals} evaluations: the best point explains the detections with "
            f"{count / expected:.3g} flakes per pixel (> {DEGENERATE_DENSITY:g})")


def _curvature(run: _Run, th: Tensor, grad: Tensor, prior_h: Tensor, uncertainty: bool) -> tuple[Tensor, Tensor]:
    """Standard errors of (log τ, log σ_g, ℓ, log v) and the data's share of the curvature (NaN where not computed)."""
    idx, dev = run.idx, th.device
    se = torch.full((4,), float("nan"), dtype=th.dtype, device=dev)
    data_h = torch.full((4,), float("nan"), dtype=th.dtype, device=dev)
    if uncertainty:  # curvature → standard errors of log τ, log σ_g, ℓ, log v (free ones)
        hess = run.hessian(th, grad)
        cov, info = torch.linalg.inv_ex(hess)
        if int(info) == 0 and bool(torch.isfinite(cov).all()):
            se[idx] = torch.sqrt(torch.diagonal(cov).clamp_min(0.0))
        data_h[idx] = torch.diagonal(hess - prior_h[idx][:, idx])
    return se, data_h


@dataclass
class StatsResult:
    """model: the fitted FlakeModel or None; observations; flake_id (P,); report dict."""

    model: FlakeModel | None
    observations: FlakeObservations | None
    flake_id: Tensor
    report: dict = field(default_factory=dict)


@_one_thread()
def flake_statistics(
    det: Detection,
    geometry: Geometry,
    *,
    seed: int = 0,
    assoc_radius: float = 1.5,
    min_flakes: int = 20,
    max_cells: int = 36,
    max_flakes: int = 300,
) -> StatsResult:
    """Fit a :class:`FlakeModel` to the detections of a capture (None when they look like noise).

    Args:
        det: detector output for N shots; geometry: the shots' normals/lights/cameras.
        seed: seed stored in the model (the render field's hash seed).
        assoc_radius: association radius in px (raise it for poorly registered shots).
        min_flakes: fewer associated flakes than this (or than 5× the Gaussian false-alarm
            expectation) means "consistent with noise" and the stage is skipped.
        max_cells, max_flakes: work limits of the likelihood (grid cells, flakes in the sum).
    """
    times = {}
    t0 = time.perf_counter()
    n, _, h, w = det.signal.shape
    if geometry.lights.shape[0] != n:
        raise InputError(f"geometry: expected {n} shots to match the detection, found {geometry.lights.shape[0]}")
    p = det.particles
    ok = measurable(det)
    row, col = particle_pixels(p, h, w)
    keep = ok[p.shot, row, col]
    flake_id = torch.full((len(p),), -1, dtype=torch.int64, device=p.shot.device)
    flake_id[keep], count = associate(p.select(keep), h, w, assoc_radius)
    times["associate"] = time.perf_counter() - t0
    valid_px = float(det.valid.expand(n, -1, -1, -1).sum()) if det.valid.shape[0] == 1 else float(det.valid.sum())
    false_alarms = valid_px * 0.5 * math.erfc(det.k_hi / math.sqrt(2))
    report = {"particles": len(p), "clipped_particles": int((~keep).sum()), "flakes_detected": count,
              "expected_false_alarms": false_alarms}
    threshold = max(min_flakes, 5.0 * false_alarms)
    report["flakes_needed"] = threshold  # fewer associated detections: consistent with noise, skipped
    if count < threshold:
        report["skipped"] = f"{count} associated detections, fewer than {threshold:.3g} expected from real flakes (consistent with noise)"
        report["times"] = times
        return StatsResult(None, None, flake_id, report)
    t1 = time.perf_counter()
    obs = observe(det, flake_id, count, geometry, ok)
    times["measure"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    gfit = fit_glints(_glint_data(det, geometry, obs, count, max_cells, ok), max_flakes=max_flakes)
    times["likelihood"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    if gfit.degenerate is not None or not (math.isfinite(gfit.density) and gfit.density <= DEGENERATE_DENSITY):
        _report_degenerate(report, gfit, times)
        return StatsResult(None, obs, flake_id, report)
    model = _fitted_model(report, obs, gfit, times, t3, count=count, valid_px=valid_px, n=n, seed=seed)
    return StatsResult(model, obs, flake_id, report)


def _glint_data(det: Detection, geometry: Geometry, obs: FlakeObservations, count: int, max_cells: int,
                ok: Tensor) -> GlintData:
    """The likelihood's data: the observed flakes (float64) and the shots' grid of cells."""
    g_half, g_normal, g_sigma, g_area, g_valid = cell_grid(det, geometry, max_cells, ok)
    head = {}
    cells = cell_headroom(det, max_cells, ok) if MODEL_CLIPS else None
    if cells is not None:  # clipped glints are never measured: the likelihood needs where they clip
        head = {"headroom": torch.log(det.headroom[:, 0, obs.row, obs.col].t().double()),
                "grid_headroom": cells[0], "grid_headroom_sd": cells[1]}
    return GlintData(
        half=obs.half.double(), normal=obs.normal.double(), anchor=obs.anchor, amp=obs.amp.double(),
        detected=obs.detected, sigma=obs.sigma.double(), grid_half=g_half, grid_normal=g_normal,
        grid_sigma=g_sigma, grid_area=g_area, k_hi=det.k_hi, count=count, observed=obs.observed,
        grid_valid=g_valid, **head,
    )


def _report_degenerate(report: dict, gfit: GlintFit, times: dict) -> None:
    """Say in ``report`` why a degenerate likelihood gives no model."""
    # the likelihood ran off to a spike or tail that explains the detections with almost no
    # flakes expected anywhere (more flakes than pixels): no trustworthy model (reported, not rendered)
    report["skipped"] = (f"glint likelihood degenerate (density {gfit.density:.3g}/px, tilt σ {gfit.tilt_sigma:.3g}, "
                         f"glint σ {gfit.glint_sigma:.3g}; "
                         f"{gfit.degenerate or f'more flakes than pixels (> {DEGENERATE_DENSITY:g}/px)'}): no flake model")
    report["degenerate"] = {"density": gfit.density, "tilt_sigma": gfit.tilt_sigma,
                            "glint_sigma": gfit.glint_sigma, "evaluations": gfit.evaluations}
    report["times"] = times


def _fitted_model(report: dict, obs: FlakeObservations, gfit: GlintFit, times: dict, t3: float, *, count: int,
                  valid_px: float, n: int, seed: int) -> FlakeModel | None:
    """Shapes and colours on top of the glint fit: the :class:`FlakeModel` (None when it refuses a value),
    its numbers in ``report``."""
    shapes = fit_shapes(obs)
    # the amplitudes are peak pixels: the colour is theirs over the field's own brightest footprint weight
    peak = mean_peak_weight(shapes["area_log_mean"], min(shapes["area_log_std"], 5.0), shapes["aspect_mean"],
                            shapes["aspect_std"])
    cmean, ccov = fit_colour(obs, gfit, peak_weight=peak)
    times["shape_colour"] = time.perf_counter() - t3
    density = min(gfit.density, MAX_DENSITY)
    if gfit.density > MAX_DENSITY:  # a near-solid layer of flakes: drawn as dense as the hash field can
        report["density_clamped"] = (f"fitted density {gfit.density:.3g}/px exceeds the flake field's capacity "
                                     f"{MAX_DENSITY:.3g}/px (one flake per {MIN_CELL}×{MIN_CELL} px cell): rendered at capacity")
    report.update({
        "density": gfit.density, "density_rendered": density, "peak_weight": peak, "tilt_sigma": gfit.tilt_sigma, "glint_sigma": gfit.glint_sigma,
        "detected_fraction": count / max(1.0, gfit.density * valid_px / n),
        "std_err": gfit.std_err, "identified": gfit.identified, "iterations": gfit.iterations,
        "multi_shot_flakes": int((obs.detected.sum(1) > 1).sum()), "times": times,
    })
    return _model_or_reason(
        report, density=density, area_log_mean=shapes["area_log_mean"], area_log_std=min(shapes["area_log_std"], 5.0),
        aspect_mean=shapes["aspect_mean"], aspect_std=shapes["aspect_std"], color_mean=cmean, color_cov=ccov,
        tilt_sigma=min(gfit.tilt_sigma, 1.5), glint_sigma=min(max(gfit.glint_sigma, 1e-4), 1.5),
        shape_lines=shapes["shape_lines"], seed=seed,
        extra={"flakes_detected": count, "density_fitted": gfit.density, "log_amp_mean": gfit.log_amp_mean, "log_amp_std": gfit.log_amp_std,
               "log_amp_floor": gfit.log_amp_floor,
               "std_err": gfit.std_err, "identified": gfit.identified},
    )


def _model_or_reason(report: dict, **values) -> FlakeModel | None:
    """The :class:`FlakeModel` of ``values``, or None with ``report["skipped"]`` saying which value the
    model refuses (every estimate is bounded by construction; this is the last guard, not the fix)."""
    try:
        return FlakeModel(**values)
    except MaterialError as e:
        report["skipped"] = f"flake statistics not identified: {e}"
        return None
