"""The whole reconstruction: Phong fit → flake stage → material, with a report of what ran.

Each stage is skipped when the scene does not need it, and the report says so:
no highlights → no specular fit (inside :func:`~torchmetal.fit.fit_phong`), no flakes → the flake
stage returns no model and the material stores ``flakes: null``. Detections that pass the noise
tests but do not bring left-out shots' sparkle statistics closer give the flake-free material
(:func:`~torchmetal.flakes.choice.keep_flakes`).

The Phong fit is least squares by default (``robust="auto"``), weighted by the expected noise where a
held-out shot prefers it (``weights="auto"``). The flake stage
first asks whether the detections are glints at all: misfit gives residuals of both signs, glints positive
ones, so detections must exceed those of the mirrored residual
(:func:`~torchmetal.flakes.estimate.null_test.glint_excess`), counting spots only (a sheen band, the streak of a
highlight, the mask's rim are misfit). Only then is the Phong fit redone with Huber weights for the flake
statistics (glints are outliers of the Phong model), while the material's coating is refitted by least
squares without the detected observations (glints seen again in a held-out shot would make a "glinty"
specular cluster win the selection), and before the flake statistics the texture under the detections is
re-solved without the shots where it glints (:mod:`torchmetal.flakes.estimate.texture`); otherwise the per-pixel
texture absorbs part of every glint and the statistics see weakened glints. docs/design.md §6 has the
measurements behind each step.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import torch

from torchmetal.clipping import CLIPPING_MODES, with_clipping
from torchmetal.errors import InputError
from torchmetal.fit import FitResult, fit_phong
from torchmetal.fit.uncertainty import fit_uncertainty
from torchmetal.fit.shot_plan import ShotPlan, flake_holds
from torchmetal.flakes.choice import HELD as FLAKE_HOLDS
from torchmetal.flakes.choice import choose_observed, keep_flakes
from torchmetal.flakes.density_choice import choose_density_map
from torchmetal.flakes.estimate.lobe_core import drop_core
from torchmetal.flakes.estimate.null_test import drop_extended, glint_excess, glint_snr
from torchmetal.flakes.estimate.observed_flakes import observed_flakes as measure_observed
from torchmetal.flakes.estimate.prescreen import screen_fit
from torchmetal.flakes.estimate.results import FlakeStageResult, Particles
from torchmetal.flakes.estimate.rim import drop_rim
from torchmetal.flakes.estimate.texture import glint_energy_share, grown_detections, texture_without_glints
from torchmetal.flakes.stage import detect_capture, flake_stage
from torchmetal.io.capture import Capture
from torchmetal.lightcal import LIGHT_MODES, LightCalibration, with_light
from torchmetal.material import Material
from torchmetal.normals import with_normals

FLAKE_MODES = ("auto", "on", "off")
OBSERVED_MODES = ("auto", "on", "off")
WEIGHTS = ("auto", "noise", "uniform")
ROBUST_GLINTS = "huber"  # robust="auto": the Phong fit's weights once the detections are glints
CLEAN_MIN_PARTICLES = 20  # fewer first-round detections: no statistics (flake_statistics' min_flakes)


@dataclass
class PipelineResult:
    """Outcome of :func:`fit_material`: the material plus the stage results behind it."""

    material: Material
    fit: FitResult
    flakes: FlakeStageResult | None  # None when the stage was off
    report: dict = field(default_factory=dict)
    light: LightCalibration = field(default_factory=LightCalibration)  # the capture's, where chosen


def render_shots(fit: FitResult, capture: Capture, *, chunk: int = 4) -> torch.Tensor:
    """Phong renders of every shot of ``capture`` (N, 3, H, W), a few shots at a time."""
    parts = [
        fit.render(capture.lights[k : k + chunk], capture.intensities[k : k + chunk], capture.cameras[k : k + chunk])
        for k in range(0, capture.num_shots, chunk)
    ]
    return torch.cat(parts)


def _without_glints(capture, labels: torch.Tensor):
    """The capture with every detected observation (a detection grown by 1 px, in the shot where it was
    detected) left out of the fit, as a saturated one is; the pixel's other shots still count (masking the
    pixel in every shot takes a foil out of its own specular fit: docs/design.md §6)."""
    hit = grown_detections(labels)
    sat = capture.saturated if capture.saturated is not None else torch.zeros_like(capture.images, dtype=torch.bool)
    return replace(capture, saturated=sat | hit)


#: the detections' share of the first fit's squared residual from which the coating is refitted without them
#: (least squares). Measured: the zoo's flake scenes 20–37 %, the shared real captures 0.6 % (card) and 1.1 %
#: (gold paper), where that refit cost 5.6 s of ~45 s
REFIT_ENERGY_SHARE = 0.05
#: the first fit's renders are kept through the statistics' refit up to this size (1024² × 48 shots)
KEEP_RENDERS_BYTES = 576 << 20
FLAKE_CHOICES = ("observed_choice", "flakes_choice", "density_map_choice")  # flake report entries holding a decision
FIRST_FIT_CHOICES = ("lobe", "weights")  # made by the first fit alone: the flake stage's refits keep them


def decision_records(first: FitResult, fit: FitResult, normals_report: dict | None, flake_result: FlakeStageResult | None,
                     light_report: dict | None = None, clipping_report: dict | None = None) -> list[dict]:
    """Every choice made on left-out shots, in the order made, as :class:`~torchmetal.fit.decision.Decision`
    dicts: the clipping, normals, the light calibration, the lobe and the weights (``first``, the first fit, chose
    them), the final fit's specular choices (evidence, clusters, relabelling, gloss maps), then the flake choices."""
    stages = ((clipping_report, "decision"), (normals_report, "decision"), (normals_report, "relief_decision"),
              (light_report, "decision"))
    out = [report[k] for report, k in stages if (report or {}).get(k)]
    out += [d for d in first.decisions if d["name"] in FIRST_FIT_CHOICES]  # the refits keep these
    out += [d for d in fit.decisions if d["name"] not in FIRST_FIT_CHOICES]
    flakes = {} if flake_result is None else flake_result.report
    out += [flakes[k]["decision"] for k in FLAKE_CHOICES if (flakes.get(k) or {}).get("decision")]
    return out


def _misfit_only(particles: Particles, counts: dict, t0: float) -> FlakeStageResult:
    """The flake stage's result when the detections do not exceed the mirrored residual's."""
    report = {"skipped": ("detections consistent with the Phong fit's misfit: no SNR at which they exceed the "
                          f"mirrored residual's (locations brighter in the residual {counts['positive']} vs in "
                          f"its mirror {counts['mirrored']}, above SNR {counts['snr']})"),
              "particles": len(particles), "null_test": counts, "times": {"total": time.perf_counter() - t0}}
    return FlakeStageResult(None, particles, report)


def _flake_stage(capture, fit, seed: int, refit=None, coat_fit=None):
    """Detect; stop when the detections do not exceed the mirrored residual's (misfit, not
    glints); otherwise, with ``refit`` given, detect again on ``refit()`` (the Huber fit); re-solve
    the texture under the detections, then the flake stage on the renders with it. With
    ``coat_fit``, the coating is ``coat_fit(capture without the detected observations)`` — glints must
    not steer the specular (a held-out shot shows the same flakes glinting, so a "glinty" specular
    cluster wins there) — where the detections hold :data:`REFIT_ENERGY_SHARE` or more of the first fit's
    squared residual (:func:`~torchmetal.flakes.estimate.texture.glint_energy_share`), else the first fit;
    either way its texture is re-solved under the detections.
    A pixel screen (:func:`~torchmetal.flakes.estimate.prescreen.screen_fit`) goes first: when its
    residual outliers are as often negative as positive, the stage stops before any detection.
    Returns (stage result, the coating's fit, its texture)."""
    t0 = time.perf_counter()
    passed, screen = screen_fit(fit, capture)
    if not passed:
        report = {"skipped": ("residual outliers consistent with noise and misfit: no SNR at which positive pixels "
                              f"exceed negative ones ({screen['positive']} vs {screen['negative']} of "
                              f"{screen['pixels']} sampled pixels, above SNR {screen['snr']})"),
                  "screen": screen, "times": {"total": time.perf_counter() - t0}}
        return FlakeStageResult(None, Particles.empty(capture.images.device), report), fit, fit.texture
    phong_images = render_shots(fit, capture)
    det = detect_capture(capture, phong_images)
    if len(det.particles) < CLEAN_MIN_PARTICLES:  # fewer particles than the statistics' minimum flake count
        report = {"skipped": (f"{len(det.particles)} detections, fewer than {CLEAN_MIN_PARTICLES} (the flake "
                              "statistics' minimum): consistent with noise"),
                  "particles": len(det.particles), "times": {"total": time.perf_counter() - t0, **det.times}}
        return FlakeStageResult(None, det.particles, report), fit, fit.texture
    # the core of the coating's own highlight is left out of both sides: a lobe of the wrong shape leaves
    # compact positive peaks there (a sharp highlight on a sphere), glints are counted everywhere else
    mirror = detect_capture(capture, phong_images, mirrored=True)
    # and so is the rim of the sample's mask (partial pixels, unreliable normals: flakes.estimate.rim)
    positive, core_pos = drop_core(fit, capture, det.particles)
    mirrored, core_mir = drop_core(fit, capture, mirror.particles)
    positive, rim_pos = drop_rim(capture, positive)
    mirrored, rim_mir = drop_rim(capture, mirrored)
    # and so are extended detections: a glint is a spot (null_test.drop_extended)
    positive, ext_pos = drop_extended(positive)
    mirrored, ext_mir = drop_extended(mirrored)
    kept, counts = glint_excess(positive, mirrored, tuple(capture.images.shape[-2:]))
    counts["highlight_core"] = {"positive": core_pos, "mirrored": core_mir}
    counts["mask_rim"] = {"positive": rim_pos, "mirrored": rim_mir}
    counts["extended"] = {"positive": ext_pos, "mirrored": ext_mir}
    if not kept:
        return _misfit_only(det.particles, counts, t0), fit, fit.texture
    # the statistics detect where the detections are glints, not misfit (null_test.glint_snr)
    k_hi = glint_snr(counts, det.k_hi)
    first = fit
    # its renders (N, 3, H, W) are kept for the coating below rather than rendered again (1.6 s at 1024² × 7),
    # up to KEEP_RENDERS_BYTES: beyond, a second copy of the images through the refit costs more than the render
    first_images = phong_images if phong_images.numel() * 4 <= KEEP_RENDERS_BYTES else None
    if refit is not None:
        fit = refit()
        phong_images = render_shots(fit, capture)
        det = detect_capture(capture, phong_images, k_hi=k_hi)
    elif k_hi != det.k_hi:
        det = detect_capture(capture, phong_images, k_hi=k_hi)
    texture, phong_images, _ = texture_without_glints(capture, fit.texture, phong_images, det.labels)
    result = flake_stage(capture, phong_images, seed=seed, detect={"k_hi": k_hi})
    result.report["null_test"] = counts
    result.report["detection_snr"] = k_hi
    coat = first
    if coat_fit is not None and result.model is not None:  # the coating: least squares away from the glints
        coat_images = render_shots(first, capture) if first_images is None else first_images
        # glints with a small share of the first fit's squared residual cannot steer its least squares
        share = glint_energy_share(capture, coat_images, det.labels)
        result.report["glint_energy_share"] = share
        if share >= REFIT_ENERGY_SHARE:
            coat = coat_fit(_without_glints(capture, det.labels))
            coat_images = render_shots(coat, capture)
        texture, _, _ = texture_without_glints(capture, coat.texture, coat_images, det.labels, guard=False)
        result.report["robust_fit"] = {"s": fit.s.tolist(), "alpha": fit.alpha.tolist()}
    return result, coat, texture


def fit_material(
    capture: Capture,
    *,
    scheme: str = "refine",
    specular: str = "auto",
    flakes: str = "auto",
    tol: float = 1e-6,
    max_iters: int = 100,
    robust: str | None = "auto",
    seed: int = 0,
    observed_flakes: str | bool = "auto",
    progress: bool = False,
    lobe: str = "auto",
    normals: str = "auto",
    weights: str = "auto",
    light: str = "auto",
    clipping: str = "auto",
) -> PipelineResult:
    """Fit a full material to a capture.

    Args:
        capture: a :class:`~torchmetal.io.capture.Capture`.
        scheme, specular, tol, max_iters: passed to :func:`~torchmetal.fit.fit_phong`.
        flakes: "auto" (fit a flake model when detections exceed noise, kept when the left-out shots'
            sparkle statistics are no further from the photos with it than with the flake-free material:
            :func:`~torchmetal.flakes.choice.keep_flakes`; else the material is the one "off" gives),
            "on" (a model whenever detections exceed noise; the report says when none was found),
            "off" (skip the stage).
        robust: IRLS weights of the Phong fit (see :func:`~torchmetal.fit.fit_phong`); "auto" is
            plain least squares, refitted with Huber weights when the flake stage finds glints
            (see the module docstring).
        seed: seed of the material's flake field.
        observed_flakes: keep the flakes the fit shots saw where they are
            (:mod:`torchmetal.flakes.estimate.observed_flakes`), the field filling the rest: "auto" when left-out
            shots render better with them on PSNR and MD (:func:`~torchmetal.flakes.choice.choose_observed`), "on"/True
            always, "off"/False never.
        progress: show progress bars.
        lobe: the specular lobe, "auto" (the default: chosen on held-out shots by the first fit,
            :mod:`~torchmetal.fit.lobe_choice`; phong, docs/design.md §2.2, unless another lobe predicts them
            better beyond noise; the refits keep that choice), "phong", "blinn" or "ggx".
        normals: "auto" (the default: the capture's normals.npy when it has one; else estimated, or else the
            embossing's relief, where left-out shots prefer them to the flat plane, :mod:`~torchmetal.normals.choice`),
            "given" (the capture's normals.npy; flat without one), "flat" (0, 0, 1), "estimate" (photometric
            stereo with the Phong terms, :func:`~torchmetal.normals.estimate_normals`) or "relief" (a high-passed
            height field fitted with global Phong terms, :mod:`~torchmetal.normals.relief`); the material keeps them.
        weights: "auto" (the default: noise weights where the first fit's held-out shot predicts better with
            them, else plain least squares; the refits keep that choice), "uniform" (plain least squares) or
            "noise" (each observation weighted by the inverse of its expected noise variance,
            ``fit_phong(noise_weights=True)``).
        light: the light calibration (:mod:`torchmetal.lightcal`: the flash's move, per-shot light
            positions, the flash's falloff from its axis and per-shot gains, nuisances of the capture, not
            the material): "auto" (the default: every point light moved alike — a flash beside the lens
            where the capture put it elsewhere — where left-out shots, their lights moved the same way,
            prefer it with Phong and GGX fits alike, docs/design.md §4), "off" (the capture's lights),
            "flash" (that move always), "positions" (each shot's light moved to fit its photo), "falloff"
            or "gains" (falloff and per-shot gains). ``result.light`` holds it: a
            render compared with the capture's photos uses ``result.light.lights(capture)`` and is multiplied
            by ``result.light.factor(capture)``.
        clipping: how an observation with a clipped channel is read (:mod:`torchmetal.clipping`): "auto" (the
            default: chosen on left-out shots), "channel" (the other channels stay valid: a linear sensor's
            honest clip) or "pixel" (dropped in all three: a phone's processing leaves them wrong too).

    Returns:
        :class:`PipelineResult`; ``result.material.report`` holds per-stage times, iterations,
        errors, the list of skipped stages and every choice's ``Decision`` record ("decisions").

    The stages run in order (:data:`STAGES`), each ``(capture, state) → (capture, state)``: the clipping, normals,
    the light calibration, the Phong fit, the flake stage, the material, then the flake choices (observed flakes, flakes or
    none, the density map), each on shots left out; every choice's record ends in the report's "decisions"
    (:func:`decision_records`).
    """
    t0 = time.perf_counter()
    state = State(Options.checked(scheme=scheme, specular=specular, flakes=flakes, tol=tol, max_iters=max_iters,
                                  robust=robust, seed=seed, observed=observed_flakes, progress=progress, lobe=lobe,
                                  normals=normals, weights=weights, light=light, clipping=clipping))
    for stage in STAGES:
        capture, state = stage(capture, state)
    material = state.material
    material.report["light"] = state.light_report
    material.report["clipping"] = state.clipping_report
    material.report["uncertainty"] = fit_uncertainty(state.fit, capture)  # issue 43: intervals of s, α, the texture
    material.report["decisions"] = decision_records(state.first, state.fit, state.normals_report, state.flake_result,
                                                    state.light_report, state.clipping_report)
    material.report["total_time"] = time.perf_counter() - t0  # the flake choices included
    return PipelineResult(material=material, fit=state.fit, flakes=state.flake_result, report=material.report,
                          light=state.light)


@dataclass
class Options:
    """:func:`fit_material`'s arguments, checked."""

    scheme: str
    specular: str
    flakes: str
    tol: float
    max_iters: int
    robust: str | None
    seed: int
    observed: str
    progress: bool
    lobe: str
    normals: str
    weights: str
    light: str = "auto"
    clipping: str = "auto"

    @classmethod
    def checked(cls, *, observed: str | bool, **kw) -> Options:
        """The options, each checked against its allowed values (one-line :class:`InputError` otherwise);
        ``observed`` may be a bool (True: "on")."""
        if kw["flakes"] not in FLAKE_MODES:
            raise InputError(f"flakes: expected one of {FLAKE_MODES}, found {kw['flakes']!r}")
        mode = {True: "on", False: "off"}.get(observed, observed) if isinstance(observed, (bool, str)) else None
        if mode not in OBSERVED_MODES:
            raise InputError(f"observed_flakes: expected one of {OBSERVED_MODES} or a bool, found {observed!r}")
        if kw["weights"] not in WEIGHTS:
            raise InputError(f"weights: expected one of {WEIGHTS}, found {kw['weights']!r}")
        if kw["light"] not in LIGHT_MODES:
            raise InputError(f"light: expected one of {list(LIGHT_MODES)}, found {kw['light']!r}")
        if kw["clipping"] not in CLIPPING_MODES:
            raise InputError(f"clipping: expected one of {list(CLIPPING_MODES)}, found {kw['clipping']!r}")
        return cls(observed=mode, **kw)

    def fit_kwargs(self) -> dict:
        """:func:`~torchmetal.fit.fit_phong` arguments every fit of the run shares (``robust`` aside)."""
        return dict(scheme=self.scheme, specular=self.specular, tol=self.tol, max_iters=self.max_iters,
                    progress=self.progress, noise_weights="auto" if self.weights == "auto" else self.weights == "noise")


@dataclass
class State:
    """What the stages have made so far."""

    opts: Options
    clipping_report: dict | None = None
    normals_report: dict | None = None
    light: LightCalibration = field(default_factory=LightCalibration)
    light_report: dict | None = None
    first: FitResult | None = None  # the first Phong fit: the flake-free material's
    fit: FitResult | None = None  # the fit the material is made from
    flake_result: FlakeStageResult | None = None
    material: Material | None = None
    stage_times: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    plan: ShotPlan | None = None  # the shots every choice on left-out shots held out (torchmetal.fit.shot_plan)
    held_renders: dict = field(default_factory=dict)  # the statistical flake material's renders of the plan's flake shots

    def report(self, fit: FitResult, skipped: list) -> dict:
        """The material report's pipeline entries for ``fit`` (the stage times dict is shared and grows)."""
        plan = self.plan if self.plan is not None else self.first.shot_plan
        return {"stage_times": self.stage_times, "skipped": skipped, "status": fit.status,
                "iterations": fit.iterations, "rmse": fit.rmse, "normals": self.normals_report,
                "flakes": None if self.flake_result is None else self.flake_result.report, "lobe": fit.lobe,
                "lobe_selection": self.first.lobe_selection, "shot_plan": None if plan is None else plan.to_dict()}


def stage_clipping(capture: Capture, st: State) -> tuple[Capture, State]:
    """How a clipped channel is read (:mod:`torchmetal.clipping`): alone, or as the whole observation's."""
    t0 = time.perf_counter()
    capture, st.clipping_report = with_clipping(capture, st.opts.clipping,
                                                fit_kwargs=dict(tol=st.opts.tol, max_iters=st.opts.max_iters))
    st.stage_times["clipping"] = time.perf_counter() - t0
    return capture, st


def stage_normals(capture: Capture, st: State) -> tuple[Capture, State]:
    """The capture's normals: given, flat, estimated, or chosen on left-out shots ("auto")."""
    capture, st.normals_report = with_normals(capture, st.opts.normals,
                                              fit_kwargs=dict(tol=st.opts.tol, max_iters=st.opts.max_iters))
    return capture, st


def stage_light(capture: Capture, st: State) -> tuple[Capture, State]:
    """The light calibration (:mod:`torchmetal.lightcal`): the capture's photos as isotropic lights of
    constant power would have recorded them, when left-out shots prefer it ("auto")."""
    capture, st.light, st.light_report = with_light(capture, st.opts.light,
                                                    fit_kwargs=dict(tol=st.opts.tol, max_iters=st.opts.max_iters))
    st.stage_times["light"] = st.light_report["time"]
    return capture, st


def stage_phong(capture: Capture, st: State) -> tuple[Capture, State]:
    """The first Phong fit (lobe, specular structure: chosen on left-out shots)."""
    o = st.opts
    st.first = st.fit = fit_phong(capture, robust=None if o.robust == "auto" else o.robust, lobe=o.lobe, **o.fit_kwargs())
    st.stage_times.update({f"phong.{k}": v for k, v in st.first.stage_times.items()})
    st.skipped = list(st.first.skipped)
    return capture, st


def _same_clusters(first: FitResult) -> dict:
    """fit_phong options that keep ``first``'s clusters: their count, and relabelling only where it relabelled."""
    sel = first.selection or {}
    if first.specular != "clustered" or not sel.get("k"):
        return {}
    return {"clusters": (int(sel["k"]),), "relabel": bool(sel.get("relabel"))}


def stage_flakes(capture: Capture, st: State) -> tuple[Capture, State]:
    """Detection, noise tests, the refits away from the glints and the flake statistics (:func:`_flake_stage`)."""
    o = st.opts
    if o.flakes == "off":
        st.skipped.append("flakes: disabled by the caller")
        st.stage_times["flakes"] = 0.0
        return capture, st
    t = time.perf_counter()
    # refits keep the lobe and the weights the first fit chose, and hold out the same shots
    kw = {**o.fit_kwargs(), "lobe": st.first.lobe, "noise_weights": st.first.noise is not None,
          "plan": st.first.shot_plan}
    two_fits = o.robust == "auto" and o.scheme == "refine"
    # the statistics' Huber refit keeps the first fit's specular structure (the trials of clusters and gloss
    # maps again cost more than the rest of the refit): its cluster count, and relabelling only where the first
    # fit relabelled (at full resolution it cost 10 s of the real card's 18 s refit); the coating's refit below
    # chooses it again, glints out
    same = {**kw, "specular": st.first.specular if o.specular == "auto" else o.specular, **_same_clusters(st.first)}
    refit = (lambda: fit_phong(capture, robust=ROBUST_GLINTS, **same)) if two_fits else None
    coat_fit = (lambda cap: fit_phong(cap, robust=None, **kw)) if two_fits else None
    st.flake_result, coat, texture = _flake_stage(capture, st.first, o.seed, refit, coat_fit)
    st.stage_times["flakes"] = time.perf_counter() - t
    if st.flake_result.model is not None:
        if coat is not st.first:
            st.skipped.append(f"phong: refitted away from the detected glints (least squares); the flake statistics "
                              f"use a {ROBUST_GLINTS}-weighted refit")
        elif two_fits:
            share = st.flake_result.report["glint_energy_share"]
            st.skipped.append(f"phong: not refitted away from the detected glints (they hold {share:.1%} of its "
                              f"squared residual, under {REFIT_ENERGY_SHARE:.0%}): texture re-solved under them; the "
                              f"flake statistics use a {ROBUST_GLINTS}-weighted refit")
        st.fit = replace(coat, texture=texture)  # the sparkles now carry the glints
        fr = st.flake_result  # the flake choices hold out the shots with the most glints of a flake
        holds = flake_holds(fr.particles.shot, fr.flake_id, capture.num_shots, FLAKE_HOLDS)
        st.plan = (st.first.shot_plan or ShotPlan(())).with_flakes(holds)
    else:
        st.skipped.append(f"flakes: {st.flake_result.report.get('skipped', 'detections consistent with noise')}")
    return capture, st


def stage_material(capture: Capture, st: State) -> tuple[Capture, State]:
    """The material of the fit, with the flake model when the stage gave one."""
    st.material = st.fit.to_material(report_extra=st.report(st.fit, st.skipped))
    st.material.flakes = None if st.flake_result is None else st.flake_result.model
    return capture, st


def stage_observed(capture: Capture, st: State) -> tuple[Capture, State]:
    """The sample's own flakes where the fit shots saw them: always ("on"), never, or where left-out shots
    render better with them ("auto", :func:`~torchmetal.flakes.choice.choose_observed`)."""
    mode, fr, m = st.opts.observed, st.flake_result, st.material
    if m.flakes is None or mode == "off":
        return capture, st
    t = time.perf_counter()
    if mode == "on":
        m.observed_flakes = measure_observed(capture, fr.particles, fr.flake_id, m.flakes)
    else:
        m.observed_flakes, fr.report["observed_choice"] = choose_observed(capture, m, fr, shots=list(st.plan.flakes),
                                                                          renders=st.held_renders)
    st.stage_times["flakes.observed"] = time.perf_counter() - t
    return capture, st


def stage_keep(capture: Capture, st: State) -> tuple[Capture, State]:
    """flakes="auto": flakes or none, by the left-out shots' sparkle statistics (MD,
    :func:`~torchmetal.flakes.choice.keep_flakes`); none gives the first fit's material, as flakes="off"."""
    fr = st.flake_result
    if st.material.flakes is None or st.opts.flakes != "auto":
        return capture, st
    t = time.perf_counter()
    plain = st.first.to_material(report_extra=st.report(st.first, list(st.first.skipped)))
    keep, fr.report["flakes_choice"] = keep_flakes(capture, st.material, plain, fr, fr.report.get("observed_choice"),
                                                   shots=list(st.plan.flakes))
    st.stage_times["flakes.choice"] = time.perf_counter() - t
    if not keep:
        fr.report["skipped"] = f"detections found, but not kept: {fr.report['flakes_choice']['reason']}"
        st.flake_result = replace(fr, model=None)
        plain.report["skipped"].append(f"flakes: {st.flake_result.report['skipped']}")
        st.fit, st.material = st.first, plain
    return capture, st


def stage_density(capture: Capture, st: State) -> tuple[Capture, State]:
    """Glitter where it is: a flake-density map, when left-out shots prefer it
    (:func:`~torchmetal.flakes.density_choice.choose_density_map`)."""
    m, fr = st.material, st.flake_result
    if m.flakes is None or fr is None:
        return capture, st
    t = time.perf_counter()
    # the observed choice's renders are this material's only while it has no observed flakes
    renders = st.held_renders if m.observed_flakes is None else None
    m.flakes, fr.report["density_map_choice"] = choose_density_map(capture, m, fr, shots=list(st.plan.flakes),
                                                                   renders=renders)
    st.held_renders = {}
    st.stage_times["flakes.density_map"] = time.perf_counter() - t
    return capture, st


STAGES = (stage_clipping, stage_normals, stage_light, stage_phong, stage_flakes, stage_material, stage_observed, stage_keep, stage_density)
