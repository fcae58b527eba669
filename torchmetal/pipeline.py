"""The whole reconstruction: Phong fit → flake stage → material, with a report of what ran.

Each stage is skipped when the scene does not need it, and the report says so:
no highlights → no specular fit (inside :func:`~torchmetal.fit.fit_phong`), no flakes → the flake
stage returns no model and the material stores ``flakes: null``. Detections that pass the noise
tests but do not bring left-out shots' sparkle statistics closer give the flake-free material
(:func:`~torchmetal.flakes.choice.keep_flakes`).

The Phong fit is plain least squares by default (``robust="auto"``, ``weights="uniform"``): on the scene zoo
(:mod:`torchmetal.synth.zoo`), Huber weights cost 0.1–0.3 dB against the clean truth on every
flake-free scene. The flake stage first asks whether the detections are glints at all: misfit
gives residuals of both signs, glints positive ones, so detections must exceed those of the
mirrored residual (:func:`~torchmetal.flakes.estimate.null_test.glint_excess`), counting spots only (a sheen band,
the streak of a highlight, the mask's rim are misfit). Only then is the Phong fit
redone with Huber weights for the flake statistics (glints are outliers of the Phong model:
without them the flake density came out up to 60 % high and the colour 30 % high), while the
material's coating is refitted by least squares without the detected observations (glints seen
again in a held-out shot had made a "glinty" specular cluster win the selection: 0.3 dB lost away
from the flakes on the zoo's flakes_b), and before the flake statistics the
texture under a first round of detections is re-solved without the shots where it glints
(:mod:`torchmetal.flakes.estimate.texture`); otherwise the per-pixel texture absorbs part of every glint
and the statistics see weakened glints.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import torch

from torchmetal.errors import InputError
from torchmetal.flakes.choice import choose_observed, keep_flakes
from torchmetal.flakes.density_choice import choose_density_map
from torchmetal.flakes.estimate.lobe_core import drop_core
from torchmetal.flakes.estimate.null_test import drop_extended, glint_excess
from torchmetal.flakes.estimate.observed_flakes import observed_flakes as measure_observed
from torchmetal.flakes.estimate.prescreen import screen_fit
from torchmetal.flakes.estimate.results import FlakeStageResult, Particles
from torchmetal.flakes.estimate.rim import drop_rim
from torchmetal.flakes.estimate.texture import grown_detections, texture_without_glints
from torchmetal.flakes.stage import detect_capture, flake_stage
from torchmetal.material import Material

FLAKE_MODES = ("auto", "on", "off")
OBSERVED_MODES = ("auto", "on", "off")
WEIGHTS = ("noise", "uniform")
ROBUST_GLINTS = "huber"  # robust="auto": the Phong fit's weights once the detections are glints
CLEAN_MIN_PARTICLES = 20  # fewer first-round detections: no statistics (flake_statistics' min_flakes)


@dataclass
class PipelineResult:
    """Outcome of :func:`fit_material`: the material plus the stage results behind it."""

    material: Material
    fit: object  # torchmetal.fit.FitResult
    flakes: object | None  # torchmetal.flakes.estimate.results.FlakeStageResult, None when the stage was off
    report: dict = field(default_factory=dict)


def render_shots(fit, capture, *, chunk: int = 4) -> torch.Tensor:
    """Phong renders of every shot of ``capture`` (N, 3, H, W), a few shots at a time."""
    parts = [
        fit.render(capture.lights[k : k + chunk], capture.intensities[k : k + chunk], capture.cameras[k : k + chunk])
        for k in range(0, capture.num_shots, chunk)
    ]
    return torch.cat(parts)


def _without_glints(capture, labels: torch.Tensor):
    """The capture with every detected observation (a detection grown by 1 px, in the shot where it was
    detected) left out of the fit, as a saturated one is; the pixel's other shots still count.

    Masking the pixel in every shot instead took the real card's foil out of its own specular fit (15 %
    of the pixels are detected in some shot): 1.4 dB lost on a left-out shot, for nothing gained on the
    zoo's flake scenes (coat PSNR away from the flakes equal to 0.001 dB)."""
    hit = grown_detections(labels)
    sat = capture.saturated if capture.saturated is not None else torch.zeros_like(capture.images, dtype=torch.bool)
    return replace(capture, saturated=sat | hit)


FLAKE_CHOICES = ("observed_choice", "flakes_choice", "density_map_choice")  # flake report entries holding a decision


def decision_records(first, fit, normals_report: dict | None, flake_result) -> list[dict]:
    """Every choice made on left-out shots, in the order made, as :class:`~torchmetal.fit.decision.Decision`
    dicts: normals, the lobe (``first``, the first fit, chose it), the final fit's specular choices
    (evidence, clusters, relabelling, gloss maps), then the flake choices."""
    out = []
    if normals_report and normals_report.get("decision"):
        out.append(normals_report["decision"])
    out += [d for d in first.decisions if d["name"] == "lobe"]
    out += [d for d in fit.decisions if d["name"] != "lobe"]
    flakes = {} if flake_result is None else flake_result.report
    out += [flakes[k]["decision"] for k in FLAKE_CHOICES if (flakes.get(k) or {}).get("decision")]
    return out


def _flake_stage(capture, fit, seed: int, refit=None, coat_fit=None):
    """Detect; stop when the detections do not exceed the mirrored residual's (misfit, not
    glints); otherwise, with ``refit`` given, detect again on ``refit()`` (the Huber fit); re-solve
    the texture under the detections, then the flake stage on the renders with it. With
    ``coat_fit``, the coating is ``coat_fit(capture without the detected observations)`` — glints must
    not steer the specular (a held-out shot shows the same flakes glinting, so a "glinty" specular
    cluster wins there) — and its texture is re-solved under the detections.
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
        report = {"skipped": ("detections consistent with the Phong fit's misfit: no SNR at which they exceed the "
                              f"mirrored residual's (locations brighter in the residual {counts['positive']} vs in "
                              f"its mirror {counts['mirrored']}, above SNR {counts['snr']})"),
                  "particles": len(det.particles), "null_test": counts,
                  "times": {"total": time.perf_counter() - t0}}
        return FlakeStageResult(None, det.particles, report), fit, fit.texture
    coat = fit
    if refit is not None:
        fit = refit()
        phong_images = render_shots(fit, capture)
        det = detect_capture(capture, phong_images)
    texture, phong_images, _ = texture_without_glints(capture, fit.texture, phong_images, det.labels)
    result = flake_stage(capture, phong_images, seed=seed)
    result.report["null_test"] = counts
    if coat_fit is not None and result.model is not None:  # the coating: least squares away from the glints
        coat = coat_fit(_without_glints(capture, det.labels))
        texture, _, _ = texture_without_glints(capture, coat.texture, render_shots(coat, capture), det.labels,
                                               guard=False)
        result.report["robust_fit"] = {"s": fit.s.tolist(), "alpha": fit.alpha.tolist()}
    return result, coat, texture


def fit_material(
    capture,
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
    weights: str = "uniform",
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
            shots render better with them on PSNR and MD (:func:`~torchmetal.flakes.choice.choose_observed`;
            zoo flakes_b: kept, +5.7 dB and MD 12.1 → 8.3 against the clean truth), "on"/True
            always, "off"/False never.
        progress: show progress bars.
        lobe: the specular lobe, "auto" (the default: chosen on held-out shots by the first fit,
            :mod:`~torchmetal.fit.lobe_choice`; phong, docs/design.md §2.2, unless another lobe predicts them
            better beyond noise; the refits keep that choice), "phong", "blinn" or "ggx".
        normals: "auto" (the default: the capture's normals.npy when it has one; else estimated where
            left-out shots prefer them to the flat plane, :mod:`~torchmetal.normals.choice`), "given"
            (the capture's normals.npy; flat without one), "flat" (0, 0, 1), or "estimate" (photometric
            stereo with the Phong terms, :func:`~torchmetal.normals.estimate_normals`; the material keeps them).
        weights: "uniform" (the default: plain least squares) or "noise" (each observation weighted by the
            inverse of its expected noise variance, ``fit_phong(noise_weights=True)``).

    Returns:
        :class:`PipelineResult`; ``result.material.report`` holds per-stage times, iterations,
        errors and the list of skipped stages.
    """
    from torchmetal.fit import fit_phong

    if flakes not in FLAKE_MODES:
        raise InputError(f"flakes: expected one of {FLAKE_MODES}, found {flakes!r}")
    mode = {True: "on", False: "off"}.get(observed_flakes, observed_flakes) if isinstance(observed_flakes, (bool, str)) else None
    if mode not in OBSERVED_MODES:
        raise InputError(f"observed_flakes: expected one of {OBSERVED_MODES} or a bool, found {observed_flakes!r}")
    if weights not in WEIGHTS:
        raise InputError(f"weights: expected one of {WEIGHTS}, found {weights!r}")
    auto = robust == "auto"
    t0 = time.perf_counter()
    from torchmetal.normals import with_normals

    capture, normals_report = with_normals(capture, normals, fit_kwargs=dict(tol=tol, max_iters=max_iters))
    kw = dict(scheme=scheme, specular=specular, tol=tol, max_iters=max_iters, progress=progress,
              noise_weights=weights == "noise")
    fit = fit_phong(capture, robust=None if auto else robust, lobe=lobe, **kw)
    first = fit  # the flake-free material's fit, should the flakes be dropped
    kw["lobe"] = fit.lobe  # refits keep the lobe the first fit chose
    lobe_selection = fit.lobe_selection
    stage_times = {f"phong.{k}": v for k, v in fit.stage_times.items()}
    skipped = list(fit.skipped)
    flake_result = None
    flake_model = None
    if flakes == "off":
        skipped.append("flakes: disabled by the caller")
        stage_times["flakes"] = 0.0
    else:
        t = time.perf_counter()
        two_fits = auto and scheme == "refine"
        # the statistics' Huber refit keeps the first fit's specular structure (the trials of clusters and gloss
        # maps again cost more than the rest of the refit); the coating's refit below chooses it again, glints out
        same = {**kw, "specular": fit.specular if specular == "auto" else specular}
        refit = (lambda: fit_phong(capture, robust=ROBUST_GLINTS, **same)) if two_fits else None
        coat_fit = (lambda cap: fit_phong(cap, robust=None, **kw)) if two_fits else None
        flake_result, coat, texture = _flake_stage(capture, fit, seed, refit, coat_fit)
        stage_times["flakes"] = time.perf_counter() - t
        flake_model = flake_result.model
        if flake_model is not None:
            if coat is not fit:
                skipped.append(f"phong: refitted away from the detected glints (least squares); the flake statistics "
                               f"use a {ROBUST_GLINTS}-weighted refit")
            fit = replace(coat, texture=texture)  # the sparkles now carry the glints
        else:
            reason = flake_result.report.get("skipped", "detections consistent with noise")
            skipped.append(f"flakes: {reason}")

    def report_of(fit, skipped) -> dict:
        return {
            "stage_times": stage_times,
            "skipped": skipped,
            "status": fit.status,
            "iterations": fit.iterations,
            "rmse": fit.rmse,
            "normals": normals_report,
            "flakes": None if flake_result is None else flake_result.report,
            "lobe": fit.lobe,
            "lobe_selection": lobe_selection,
        }

    material = fit.to_material(report_extra=report_of(fit, skipped))
    material.flakes = flake_model
    if flake_model is not None:
        t = time.perf_counter()
        observed_report = None
        if mode == "on":  # the sample's own flakes, where the fit shots saw them
            material.observed_flakes = measure_observed(capture, flake_result.particles, flake_result.flake_id, flake_model)
        elif mode == "auto":
            material.observed_flakes, observed_report = choose_observed(capture, material, flake_result)
            flake_result.report["observed_choice"] = observed_report
        if mode != "off":
            stage_times["flakes.observed"] = time.perf_counter() - t
        if flakes == "auto":  # flakes or none: the left-out shots' sparkle statistics (MD) decide
            t = time.perf_counter()
            plain = first.to_material(report_extra=report_of(first, list(first.skipped)))
            keep, flake_result.report["flakes_choice"] = keep_flakes(capture, material, plain, flake_result,
                                                                      observed_report)
            stage_times["flakes.choice"] = time.perf_counter() - t
            if not keep:
                flake_result.report["skipped"] = ("detections found, but not kept: "
                                                  f"{flake_result.report['flakes_choice']['reason']}")
                flake_result = replace(flake_result, model=None)
                plain.report["skipped"].append(f"flakes: {flake_result.report['skipped']}")
                fit, material = first, plain
    if material.flakes is not None and flake_result is not None:  # glitter where it is: a density map, chosen left out
        t = time.perf_counter()
        material.flakes, flake_result.report["density_map_choice"] = choose_density_map(capture, material, flake_result)
        stage_times["flakes.density_map"] = time.perf_counter() - t
    material.report["decisions"] = decision_records(first, fit, normals_report, flake_result)
    material.report["total_time"] = time.perf_counter() - t0  # the flake choices included
    return PipelineResult(material=material, fit=fit, flakes=flake_result, report=material.report)
