"""The whole reconstruction: the capture's nuisances → Phong fit → flake stage → material, with a report of what ran.

The pipeline is an ordered list of stages (:data:`STAGES`), each ``(capture, state) → (capture, state)``.
Each stage is skipped when the scene does not need it, and the report says so: no highlights → no specular
fit (inside :func:`~torchmetal.fit.fit_phong`), no flakes → the flake stage (:mod:`torchmetal.flakes.run`)
returns no model and the material stores ``flakes: null``. Every choice beyond the paper's model is made on
shots left out of the fit, and its record lands in the report's "decisions" (docs/design.md §4).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from torchmetal.clipping import with_clipping
from torchmetal.config import FitConfig
from torchmetal.fit import FitResult, fit_phong
from torchmetal.fit.uncertainty import fit_uncertainty
from torchmetal.flakes.estimate.results import FlakeStageResult
from torchmetal.flakes.run import render_shots, stage_density, stage_flakes, stage_keep, stage_observed
from torchmetal.io.capture import Capture
from torchmetal.lightcal import LightCalibration, with_light
from torchmetal.material import Material
from torchmetal.normals import with_normals
from torchmetal.registration import with_registration
from torchmetal.select.choices import CLIPPING, LIGHT, NORMALS, REGISTRATION, RELIEF, reference_context
from torchmetal.select.harness import Context, decide
from torchmetal.select.plan import ShotPlan
from torchmetal.select.rule import Decision

__all__ = ["STAGES", "PipelineResult", "decision_records", "fit_material", "render_shots"]



@dataclass
class PipelineResult:
    """Outcome of :func:`fit_material`: the material plus the stage results behind it."""

    material: Material
    fit: FitResult
    flakes: FlakeStageResult | None  # None when the stage was off
    report: dict = field(default_factory=dict)
    light: LightCalibration = field(default_factory=LightCalibration)  # the capture's, where chosen


FLAKE_CHOICES = ("observed_choice", "flakes_choice", "density_map_choice")  # flake report entries holding a decision
FIRST_FIT_CHOICES = ("lobe", "weights")  # made once (the lobe by the reference fit where it stands): later fits keep them


def decision_records(first: FitResult, fit: FitResult, normals_report: dict | None, flake_result: FlakeStageResult | None,
                     light_report: dict | None = None, clipping_report: dict | None = None,
                     lobe: FitResult | None = None, registration_report: dict | None = None) -> list[dict]:
    """Every choice made on left-out shots, in the order made, as :class:`~torchmetal.select.rule.Decision`
    dicts: the registration, the clipping, normals, the light calibration, the lobe and the weights (``first``, the
    first fit, chose them; ``lobe``: the fit that chose the lobe where not the first, the selection's reference fit),
    the final fit's specular choices (evidence, clusters, relabelling, gloss maps), then the flake choices."""
    stages = ((registration_report, "decision"), (clipping_report, "decision"), (normals_report, "decision"),
              (normals_report, "relief_decision"), (light_report, "decision"))
    out = [report[k] for report, k in stages if (report or {}).get(k)]
    chooser = {"lobe": lobe or first, "weights": first}
    out += [d for name in FIRST_FIT_CHOICES for d in chooser[name].decisions if d["name"] == name]  # the refits keep these
    out += [d for d in fit.decisions if d["name"] not in FIRST_FIT_CHOICES]
    flakes = {} if flake_result is None else flake_result.report
    out += [flakes[k]["decision"] for k in FLAKE_CHOICES if (flakes.get(k) or {}).get("decision")]
    return out


def fit_material(capture: Capture, config: FitConfig | None = None, **options: Any) -> PipelineResult:
    """Fit a full material to a capture.

    Args:
        capture: a :class:`~torchmetal.io.capture.Capture`.
        config: a :class:`~torchmetal.config.FitConfig` (default: every option at its default: the automatic
            choices decided on shots left out of the fit, docs/design.md §4).
        options: flat keywords replacing ``config``'s (``normals="flat"``, ``lobe="ggx"``, ``flakes="off"``,
            ``observed_flakes=True``, ``progress=True``, …: :meth:`FitConfig.of <torchmetal.config.FitConfig.of>`;
            the README's option table lists them all, from the config).

    Returns:
        :class:`PipelineResult`; ``result.material.report`` holds per-stage times, iterations,
        errors, the list of skipped stages and every choice's ``Decision`` record ("decisions"). ``result.light``
        holds the light calibration: a render compared with the capture's photos uses
        ``result.light.lights(capture)`` and is multiplied by ``result.light.factor(capture)``.

    The stages run in order (:data:`STAGES`), each ``(capture, state) → (capture, state)``: the choices before the
    fit (registration, clipping, normals, relief, light), the Phong fit, the flake stage, the material, then the flake choices
    (observed flakes, flakes or none, the density map), each on shots left out; every choice's record ends in the
    report's "decisions" (:func:`decision_records`).
    """
    t0 = time.perf_counter()
    state = State(FitConfig.of(config, **options))
    for stage in STAGES:
        capture, state = stage(capture, state)
    material = state.material
    material.report["light"] = state.light_report
    material.report["clipping"] = state.clipping_report
    material.report["registered"] = state.registration_report
    t1 = time.perf_counter()
    material.report["uncertainty"] = fit_uncertainty(state.fit, capture)  # the intervals of s, α and the texture
    state.stage_times["uncertainty"] = time.perf_counter() - t1
    material.report["decisions"] = decision_records(state.first, state.fit, state.normals_report, state.flake_result,
                                                    state.light_report, state.clipping_report, lobe=state.lobe_chooser,
                                                    registration_report=state.registration_report)
    material.report["total_time"] = time.perf_counter() - t0  # the flake choices included
    return PipelineResult(material=material, fit=state.fit, flakes=state.flake_result, report=material.report,
                          light=state.light)


@dataclass
class State:
    """What the stages have made so far."""

    opts: FitConfig
    ctx: Context | None = None  # the selection's context (its reference fit and the model's fits)
    registration_report: dict | None = None
    clipping_report: dict | None = None
    normals_report: dict | None = None
    light: LightCalibration = field(default_factory=LightCalibration)
    light_report: dict | None = None
    first: FitResult | None = None  # the first Phong fit: the flake-free material's
    chooser: FitResult | None = None  # the fit that chose the lobe where not the first (the reference fit)
    source: Capture | None = None  # the capture as the choices before the fit found it
    fit: FitResult | None = None  # the fit the material is made from
    flake_result: FlakeStageResult | None = None
    material: Material | None = None
    stage_times: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    plan: ShotPlan | None = None  # the shots every choice on left-out shots held out (torchmetal.select.plan)
    held_renders: dict = field(default_factory=dict)  # the statistical flake material's renders of the plan's flake shots

    def report(self, fit: FitResult, skipped: list) -> dict:
        """The material report's pipeline entries for ``fit`` (the stage times dict is shared and grows)."""
        plan = self.plan if self.plan is not None else self.first.shot_plan
        return {"stage_times": self.stage_times, "skipped": skipped, "status": fit.status,
                "iterations": fit.iterations, "rmse": fit.rmse, "normals": self.normals_report,
                "flakes": None if self.flake_result is None else self.flake_result.report, "lobe": fit.lobe,
                "lobe_selection": self.lobe_chooser.lobe_selection,
                "shot_plan": None if plan is None else plan.to_dict()}

    @property
    def lobe_chooser(self) -> FitResult:
        """The fit whose records hold the lobe choice."""
        return self.chooser if self.chooser is not None else self.first


def stage_choices(capture: Capture, st: State) -> tuple[Capture, State]:
    """The choices before the Phong fit (:data:`torchmetal.select.choices.PREFIT`): registration, clipping, normals,
    relief, light, each as its option says or, "auto", decided on left-out shots with the model a reference fit chose."""
    o = st.opts
    t = time.perf_counter()
    st.source = capture
    # the reference fit, made on first use, has the first Phong fit's options: on a capture small enough to be its
    # own grid, and left unchanged by the choices, it is the first Phong fit (stage_phong)
    st.ctx = ctx = reference_context(capture, {**o.fit_kwargs(), "lobe": o.choices.lobe, "robust": None})

    def auto(choice, cap):
        was = ctx.resolved
        d = decide(choice, cap, ctx)  # its seconds without the reference fit, which the first choice to need it makes
        st.stage_times[f"choice.{choice.name}"] = d.seconds - (ctx.seconds if ctx.resolved and not was else 0.0)
        ctx.chosen[choice.name] = d.chosen
        return d

    def applied(choice, mode: str, apply, cap):
        """A choice whose outcome one function applies: as ``mode`` says, or "auto" decided first. Applying it is
        a stage of its own (``stage_times[NAME]``: the registration resamples every shot at full size)."""
        d = auto(choice, cap) if mode == "auto" else None
        t1 = time.perf_counter()
        cap, report = apply(cap, mode if d is None else d.chosen)
        st.stage_times[choice.name] = time.perf_counter() - t1
        return cap, report if d is None else report | {"mode": "auto", "decision": d.to_dict()}

    capture, st.registration_report = applied(REGISTRATION, o.choices.registration, with_registration, capture)
    capture, st.clipping_report = applied(CLIPPING, o.choices.clipping, with_clipping, capture)
    if o.choices.normals == "auto" and capture.normals_given:
        chosen, record = "given", {"decision": Decision("normals", ("given",), "given",
                                                        reason="the capture's own normals (normals.npy)").to_dict()}
    elif o.choices.normals == "auto":
        d = auto(NORMALS, capture)
        chosen, record = d.chosen, {"decision": d.to_dict()}
        if chosen == "flat":
            r = auto(RELIEF, capture)
            chosen, record["relief_decision"] = r.chosen, r.to_dict()
    else:
        chosen, record = o.choices.normals, {}
    t2 = time.perf_counter()
    # the fits that apply a choice use the reference's model where a test made it, else the plain options
    fit_kwargs = ctx.model if ctx.resolved else {"tol": o.solver.tol, "max_iters": o.solver.max_iters}
    capture, st.normals_report = with_normals(capture, chosen, fit_kwargs=fit_kwargs)
    st.normals_report |= {"mode": o.choices.normals, "chosen": chosen, **record}
    st.stage_times["normals"] = time.perf_counter() - t2
    if o.choices.light == "auto":
        d = auto(LIGHT, capture)
        capture, st.light, st.light_report = with_light(capture, d.chosen, fit_kwargs=ctx.model if ctx.resolved else fit_kwargs)
        st.light_report |= {"mode": "auto", "chosen": d.chosen, "decision": d.to_dict()}
    else:
        capture, st.light, st.light_report = with_light(capture, o.choices.light, fit_kwargs=fit_kwargs)
    st.stage_times["light"] = st.light_report["time"]
    if ctx.resolved:
        st.stage_times["choices.reference"] = ctx.seconds
    st.stage_times["choices"] = time.perf_counter() - t  # the reference fit, every choice, applying them
    return capture, st


def stage_phong(capture: Capture, st: State) -> tuple[Capture, State]:
    """The first Phong fit (lobe, specular structure: chosen on left-out shots); the reference fit where that was
    this very capture with the same options; else with the reference's lobe where the capture is as it saw it."""
    o = st.opts
    robust = None if o.solver.robust in ("auto", "none") else o.solver.robust
    ctx = st.ctx
    same = ctx.reference_fit(capture) if ctx is not None and robust is None else None
    kw = {**o.fit_kwargs(), "lobe": o.choices.lobe}
    if same is None and ctx is not None and ctx.resolved and capture is st.source:
        # the choices left the capture as the reference fit saw it: its lobe stands, not chosen again (the weights
        # are: their test gains power with the pixels, and the zoo's 8-bit photo_srgb8 lost them on the grid, z 2.7)
        kw["lobe"] = ctx.model["lobe"]
        st.chooser = ctx.reference_result
    st.first = st.fit = same if same is not None else fit_phong(capture, robust=robust, **kw)
    # the fit's own choices keep their names (choice.weights, choice.lobe, …), beside the choices made before it
    st.stage_times.update({k if k.startswith("choice.") else f"phong.{k}": v for k, v in st.first.stage_times.items()})
    st.skipped = list(st.first.skipped)
    if st.chooser is not None:
        st.skipped.append(f"lobe: the selection's reference fit chose it ({kw['lobe']}) on its grid; the Phong fit "
                          f"does not choose it again")
    if same is not None:  # its time is the Phong fit's, not the choices'
        st.stage_times["choices"] -= st.stage_times.pop("choices.reference", 0.0)
        st.skipped.append("phong: not fitted again: the selection's reference fit was this capture with these options")
    return capture, st


def stage_material(capture: Capture, st: State) -> tuple[Capture, State]:
    """The material of the fit, with the flake model when the stage gave one."""
    st.material = st.fit.to_material(report_extra=st.report(st.fit, st.skipped))
    st.material.flakes = None if st.flake_result is None else st.flake_result.model
    return capture, st



STAGES = (stage_choices, stage_phong, stage_flakes, stage_material, stage_observed, stage_keep, stage_density)
