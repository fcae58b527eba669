"""The flake stage of the default fit, as the pipeline runs it: detection, the noise tests, the refits away
from the glints, the flake statistics, then the flake choices on shots left out (observed flakes, flakes or
none, the density map).

The flake stage first asks whether the detections are glints at all: misfit gives residuals of both signs,
glints positive ones, so detections must exceed those of the mirrored residual
(:func:`~torchmetal.flakes.estimate.null_test.glint_excess`), counting spots only (a sheen band, the streak of a
highlight, the mask's rim are misfit). Only then is the Phong fit redone with Huber weights for the flake
statistics (glints are outliers of the Phong model), while the material's coating is refitted by least
squares without the detected observations (glints seen again in a held-out shot would make a "glinty"
specular cluster win the selection), and before the flake statistics the texture under the detections is
re-solved without the shots where it glints (:mod:`torchmetal.flakes.estimate.texture`); otherwise the per-pixel
texture absorbs part of every glint and the statistics see weakened glints.

The stage functions take the pipeline's state (``st``: options ``st.opts``, the first fit ``st.first``, the
material, the shot plan) and return it, as every stage of :data:`torchmetal.pipeline.STAGES` does.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from torchmetal.fit import FitResult, fit_phong
from torchmetal.fit.start import refit_options
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
from torchmetal.flakes.stage import detect_capture, flake_stage, irradiance_maps
from torchmetal.select.plan import ShotPlan, flake_holds

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

ROBUST_GLINTS = "huber"  # robust="auto": the Phong fit's weights once the detections are glints
CLEAN_MIN_PARTICLES = 20  # fewer first-round detections: no statistics (flake_statistics' min_flakes)


def render_shots(fit: FitResult, capture: Capture, *, chunk: int = 4) -> torch.Tensor:
    """Phong renders of every shot of ``capture`` (N, 3, H, W), a few shots at a time."""
    parts = [
        fit.render(capture.lights[k : k + chunk], capture.intensities[k : k + chunk], capture.cameras[k : k + chunk])
        for k in range(0, capture.num_shots, chunk)
    ]
    return torch.cat(parts)



def without_glints(capture, labels: torch.Tensor):
    """The capture with every detected observation (a detection grown by 1 px, in the shot where it was
    detected) left out of the fit, as a saturated one is; the pixel's other shots still count (masking the
    pixel in every shot takes a foil out of its own specular fit: docs/measurements.md)."""
    hit = grown_detections(labels)
    sat = capture.saturated if capture.saturated is not None else torch.zeros_like(capture.images, dtype=torch.bool)
    return replace(capture, saturated=sat | hit)



#: the detections' share of the first fit's squared residual from which the coating is refitted without them
#: (least squares). Measured: the zoo's flake scenes 20–37 %, the shared real captures 0.6 % (card) and 1.1 %
#: (gold paper), where that refit cost 5.6 s of ~45 s
REFIT_ENERGY_SHARE = 0.05
#: the first fit's renders are kept through the statistics' refit up to this size (1024² × 48 shots)
KEEP_RENDERS_BYTES = 576 << 20

def _misfit_only(particles: Particles, counts: dict, t0: float) -> FlakeStageResult:
    """The flake stage's result when the detections do not exceed the mirrored residual's."""
    report = {"skipped": ("detections consistent with the Phong fit's misfit: no SNR at which they exceed the "
                          f"mirrored residual's (locations brighter in the residual {counts['positive']} vs in "
                          f"its mirror {counts['mirrored']}, above SNR {counts['snr']})"),
              "particles": len(particles), "null_test": counts, "times": {"total": time.perf_counter() - t0}}
    return FlakeStageResult(None, particles, report)



def flake_stage_with_refits(capture, fit, seed: int, refit=None, coat_fit=None):
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
    irr = irradiance_maps(capture, dtype=capture.images.dtype)  # the same for each of the stage's detections
    det = detect_capture(capture, phong_images, irradiance=irr)
    if len(det.particles) < CLEAN_MIN_PARTICLES:  # fewer particles than the statistics' minimum flake count
        report = {"skipped": (f"{len(det.particles)} detections, fewer than {CLEAN_MIN_PARTICLES} (the flake "
                              "statistics' minimum): consistent with noise"),
                  "particles": len(det.particles), "times": {"total": time.perf_counter() - t0, **det.times}}
        return FlakeStageResult(None, det.particles, report), fit, fit.texture
    # the core of the coating's own highlight is left out of both sides: a lobe of the wrong shape leaves
    # compact positive peaks there (a sharp highlight on a sphere), glints are counted everywhere else
    mirror = detect_capture(capture, phong_images, mirrored=True, irradiance=irr)
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
        det = detect_capture(capture, phong_images, k_hi=k_hi, irradiance=irr)
    elif k_hi != det.k_hi:
        det = detect_capture(capture, phong_images, k_hi=k_hi, irradiance=irr)
    gains: dict = {}  # the shots' diffuse gains, formed by the first texture re-solve for the second
    texture, phong_images, _ = texture_without_glints(capture, fit.texture, phong_images, det.labels, gains=gains)
    result = flake_stage(capture, phong_images, seed=seed, detect={"k_hi": k_hi, "irradiance": irr})
    result.report["null_test"] = counts
    result.report["detection_snr"] = k_hi
    coat = first
    if coat_fit is not None and result.model is not None:  # the coating: least squares away from the glints
        coat_images = render_shots(first, capture) if first_images is None else first_images
        # glints with a small share of the first fit's squared residual cannot steer its least squares
        share = glint_energy_share(capture, coat_images, det.labels)
        result.report["glint_energy_share"] = share
        if share >= REFIT_ENERGY_SHARE:
            coat = coat_fit(without_glints(capture, det.labels))
            coat_images = render_shots(coat, capture)
        texture, _, _ = texture_without_glints(capture, coat.texture, coat_images, det.labels, guard=False, gains=gains)
        result.report["robust_fit"] = {"s": fit.s.tolist(), "alpha": fit.alpha.tolist()}
    return result, coat, texture



def stage_flakes(capture: Capture, st):
    """Detection, noise tests, the refits away from the glints and the flake statistics (:func:`flake_stage_with_refits`)."""
    o = st.opts
    if o.flakes.mode == "off":
        st.skipped.append("flakes: disabled by the caller")
        st.stage_times["flakes"] = 0.0
        return capture, st
    t = time.perf_counter()
    # refits keep the lobe and the weights the first fit chose, start from its values, and hold out the same shots
    model = refit_options(st.first)
    kw = {**o.fit_kwargs(), **{k: model[k] for k in ("lobe", "weights", "start")}, "plan": st.first.shot_plan}
    two_fits = o.solver.robust == "auto" and o.solver.scheme == "refine"
    # the statistics' Huber refit keeps the first fit's specular structure (the trials of clusters and gloss
    # maps again cost more than the rest of the refit): its cluster count, and relabelling only where the first
    # fit relabelled (at full resolution it cost 10 s of the real card's 18 s refit); the coating's refit below
    # chooses it again, glints out
    same = {**kw, **model} if o.choices.specular == "auto" else {**kw, "specular": o.choices.specular}
    refit = (lambda: fit_phong(capture, robust=ROBUST_GLINTS, **same)) if two_fits else None
    coat_fit = (lambda cap: fit_phong(cap, robust=None, **kw)) if two_fits else None
    st.flake_result, coat, texture = flake_stage_with_refits(capture, st.first, o.flakes.seed, refit, coat_fit)
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


def stage_observed(capture: Capture, st):
    """The sample's own flakes where the fit shots saw them: always ("on"), never, or where left-out shots
    render better with them ("auto", :func:`~torchmetal.flakes.choice.choose_observed`)."""
    mode, fr, m = st.opts.flakes.observed, st.flake_result, st.material
    if m.flakes is None or mode == "off":
        return capture, st
    t = time.perf_counter()
    if mode == "on":
        m.observed_flakes = measure_observed(capture, fr.particles, fr.flake_id, m.flakes)
    else:
        m.observed_flakes, fr.report["observed_choice"] = choose_observed(capture, m, fr, shots=list(st.plan.flakes),
                                                                          renders=st.held_renders)
    st.stage_times["choice.observed flakes" if mode == "auto" else "flakes.observed"] = time.perf_counter() - t
    return capture, st


def stage_keep(capture: Capture, st):
    """flakes="auto": flakes or none, by the left-out shots' sparkle statistics (MD,
    :func:`~torchmetal.flakes.choice.keep_flakes`); none gives the first fit's material, as flakes="off"."""
    fr = st.flake_result
    if st.material.flakes is None or st.opts.flakes.mode != "auto":
        return capture, st
    t = time.perf_counter()
    plain = st.first.to_material(report_extra=st.report(st.first, list(st.first.skipped)))
    keep, fr.report["flakes_choice"] = keep_flakes(capture, st.material, plain, fr, fr.report.get("observed_choice"),
                                                   shots=list(st.plan.flakes))
    st.stage_times["choice.flakes"] = time.perf_counter() - t
    if not keep:
        fr.report["skipped"] = f"detections found, but not kept: {fr.report['flakes_choice']['reason']}"
        st.flake_result = replace(fr, model=None)
        plain.report["skipped"].append(f"flakes: {st.flake_result.report['skipped']}")
        st.fit, st.material = st.first, plain
    return capture, st


def stage_density(capture: Capture, st):
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
    st.stage_times["choice.density map"] = time.perf_counter() - t
    return capture, st
