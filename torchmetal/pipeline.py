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

from torchmetal.clipping import CLIPPING_MODES, with_clipping
from torchmetal.errors import InputError
from torchmetal.fit import FitResult, fit_phong
from torchmetal.fit.uncertainty import fit_uncertainty
from torchmetal.flakes.estimate.results import FlakeStageResult
from torchmetal.flakes.run import render_shots, stage_density, stage_flakes, stage_keep, stage_observed
from torchmetal.io.capture import Capture
from torchmetal.lightcal import LIGHT_MODES, LightCalibration, with_light
from torchmetal.material import Material
from torchmetal.normals import with_normals
from torchmetal.select.choices import CLIPPING, LIGHT, NORMALS, RELIEF, reference_context
from torchmetal.select.harness import decide
from torchmetal.select.plan import ShotPlan
from torchmetal.select.rule import Decision

__all__ = ["STAGES", "PipelineResult", "decision_records", "fit_material", "render_shots"]

FLAKE_MODES = ("auto", "on", "off")
OBSERVED_MODES = ("auto", "on", "off")
WEIGHTS = ("auto", "noise", "uniform")


@dataclass
class PipelineResult:
    """Outcome of :func:`fit_material`: the material plus the stage results behind it."""

    material: Material
    fit: FitResult
    flakes: FlakeStageResult | None  # None when the stage was off
    report: dict = field(default_factory=dict)
    light: LightCalibration = field(default_factory=LightCalibration)  # the capture's, where chosen


FLAKE_CHOICES = ("observed_choice", "flakes_choice", "density_map_choice")  # flake report entries holding a decision
FIRST_FIT_CHOICES = ("lobe", "weights")  # made by the first fit alone: the flake stage's refits keep them


def decision_records(first: FitResult, fit: FitResult, normals_report: dict | None, flake_result: FlakeStageResult | None,
                     light_report: dict | None = None, clipping_report: dict | None = None) -> list[dict]:
    """Every choice made on left-out shots, in the order made, as :class:`~torchmetal.select.rule.Decision`
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
    plan: ShotPlan | None = None  # the shots every choice on left-out shots held out (torchmetal.select.plan)
    held_renders: dict = field(default_factory=dict)  # the statistical flake material's renders of the plan's flake shots

    def report(self, fit: FitResult, skipped: list) -> dict:
        """The material report's pipeline entries for ``fit`` (the stage times dict is shared and grows)."""
        plan = self.plan if self.plan is not None else self.first.shot_plan
        return {"stage_times": self.stage_times, "skipped": skipped, "status": fit.status,
                "iterations": fit.iterations, "rmse": fit.rmse, "normals": self.normals_report,
                "flakes": None if self.flake_result is None else self.flake_result.report, "lobe": fit.lobe,
                "lobe_selection": self.first.lobe_selection, "shot_plan": None if plan is None else plan.to_dict()}


def stage_choices(capture: Capture, st: State) -> tuple[Capture, State]:
    """The choices before the Phong fit (:data:`torchmetal.select.choices.PREFIT`): clipping, normals, relief,
    light, each as its option says or, "auto", decided on left-out shots with the model a reference fit chose."""
    o = st.opts
    t = time.perf_counter()
    ctx = None
    if "auto" in (o.clipping, o.normals, o.light):
        ctx, st.stage_times["choices.reference"] = reference_context(capture, {**o.fit_kwargs(), "lobe": o.lobe})
    fit_kwargs = ctx.model if ctx is not None else {"tol": o.tol, "max_iters": o.max_iters}

    def auto(choice, cap):
        d = decide(choice, cap, ctx)
        st.stage_times[f"choice.{choice.name}"] = d.seconds
        ctx.chosen[choice.name] = d.chosen
        return d

    if o.clipping == "auto":
        d = auto(CLIPPING, capture)
        capture, st.clipping_report = with_clipping(capture, d.chosen)
        st.clipping_report |= {"mode": "auto", "decision": d.to_dict()}
    else:
        capture, st.clipping_report = with_clipping(capture, o.clipping)
    if o.normals == "auto" and capture.normals_given:
        chosen, record = "given", {"decision": Decision("normals", ("given",), "given",
                                                        reason="the capture's own normals (normals.npy)").to_dict()}
    elif o.normals == "auto":
        d = auto(NORMALS, capture)
        chosen, record = d.chosen, {"decision": d.to_dict()}
        if chosen == "flat":
            r = auto(RELIEF, capture)
            chosen, record["relief_decision"] = r.chosen, r.to_dict()
    else:
        chosen, record = o.normals, {}
    t2 = time.perf_counter()
    capture, st.normals_report = with_normals(capture, chosen, fit_kwargs=fit_kwargs)
    st.normals_report |= {"mode": o.normals, "chosen": chosen, **record}
    st.stage_times["normals"] = time.perf_counter() - t2
    if o.light == "auto":
        d = auto(LIGHT, capture)
        capture, st.light, st.light_report = with_light(capture, d.chosen, fit_kwargs=fit_kwargs)
        st.light_report |= {"mode": "auto", "chosen": d.chosen, "decision": d.to_dict()}
    else:
        capture, st.light, st.light_report = with_light(capture, o.light, fit_kwargs=fit_kwargs)
    st.stage_times["light"] = st.light_report["time"]
    st.stage_times["choices"] = time.perf_counter() - t  # the reference fit, every choice, applying them
    return capture, st


def stage_phong(capture: Capture, st: State) -> tuple[Capture, State]:
    """The first Phong fit (lobe, specular structure: chosen on left-out shots)."""
    o = st.opts
    st.first = st.fit = fit_phong(capture, robust=None if o.robust == "auto" else o.robust, lobe=o.lobe, **o.fit_kwargs())
    st.stage_times.update({f"phong.{k}": v for k, v in st.first.stage_times.items()})
    st.skipped = list(st.first.skipped)
    return capture, st


def stage_material(capture: Capture, st: State) -> tuple[Capture, State]:
    """The material of the fit, with the flake model when the stage gave one."""
    st.material = st.fit.to_material(report_extra=st.report(st.fit, st.skipped))
    st.material.flakes = None if st.flake_result is None else st.flake_result.model
    return capture, st



STAGES = (stage_choices, stage_phong, stage_flakes, stage_material, stage_observed, stage_keep, stage_density)
