"""``torchmetal demo``: the whole method on an embedded synthetic sample, in under a minute.

No files or downloads are needed: the sample is rendered by :func:`torchmetal.synth.synth_capture`
(seeded procedural texture, Phong highlights, metallic flakes with known statistics, 0.5 % noise,
16-bit quantisation). One shot is held back; the rest are fitted with
:func:`torchmetal.pipeline.fit_material`, and the result is written to a report folder::

    OUT/
      report.png      input shots · fitted texture vs truth · specular lobe · detected flakes ·
                      re-render beside the held-out photo · error map
      metrics.json    the numbers below, plus per-stage times and what was skipped
      material/       the material directory (docs/design.md §2.3) with its ONNX renderer

Metrics (all PSNRs are :func:`torchmetal.metrics.psnr` — linear values clipped to [0, 1], peak 1 —
and leave out pixels saturated in the photo; "clean" pixels are also free of flakes — there the
Phong model is the whole truth):

- ``phong_psnr_db``: fitted Phong re-render vs the fitted photos, clean pixels.
- ``heldout_psnr_db``: the same on the held-out shot; ``heldout_truth_psnr_db`` renders the true
  parameters instead — the ceiling set by noise and quantisation.
- ``texture_psnr_db``: fitted texture vs the true texture.
- ``s_rel_err``, ``alpha_rel_err``: per-channel relative errors of the global specular terms.
- ``flakes``: detections and fitted statistics against the truth.
- ``md_heldout`` / ``md_heldout_no_flakes``: the paper's Metallic Difference between the held-out
  photo and the full render with and without the sparkle term (lower is better);
  ``full_render_psnr_db`` / ``full_render_psnr_no_flakes_db``: PSNR of the same two renders — the
  paper's point that PSNR prefers the sparkle-free image of a statistical field (the sample's own
  flakes, kept where the fit shots saw them, can win on PSNR too).

Nothing is caught and hidden: a failing stage raises, and ``torchmetal demo`` exits non-zero.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torchmetal import pipeline
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.md import metallic_difference
from torchmetal.material import json_finite, save_material
from torchmetal.metrics import psnr
from torchmetal.onnx_export import export_onnx
from torchmetal.phong import phong_render
from torchmetal.renderer import MaterialRenderer
from torchmetal.report.page import _num_particles, report_figure
from torchmetal.synth import synth_capture

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture
    from torchmetal.material import Material
    from torchmetal.pipeline import PipelineResult
    from torchmetal.synth import SynthResult

__all__ = ["run_demo", "demo_capture", "DEMO_FLAKES"]

#: flake statistics of the embedded sample (densities are per pixel)
DEMO_FLAKES = dict(density=0.003, area_log_mean=math.log(8.0), area_log_std=0.35, aspect_mean=0.7,
                   aspect_std=0.12, color_mean=(0.9, 0.85, 0.7), tilt_sigma=0.12, glint_sigma=0.04)


def demo_capture(size: int = 256, shots: int = 12, *, seed: int = 0, flake_seed: int = 11) -> SynthResult:
    """The embedded sample: a :class:`~torchmetal.synth.SynthResult` with ``shots`` shots.

    Procedural texture, global Phong specular, metallic flakes (:data:`DEMO_FLAKES`), 0.5 %
    noise and 16-bit quantisation, point lights on a ring around the camera; exposed so that only
    the brightest highlights clip.
    """
    flakes = FlakeModel(**DEMO_FLAKES, seed=flake_seed)
    return synth_capture(size=size, shots=shots, seed=seed, texture="procedural", noise=0.005, bits=16,
                         exposure=0.8, flakes=flakes, layout="ring")


def _rel(a, b) -> list[float]:
    a = torch.as_tensor(a, dtype=torch.float64)
    b = torch.as_tensor(b, dtype=torch.float64)
    return ((a - b).abs() / b.abs().clamp_min(1e-12)).tolist()


def _flake_stats(result, truth_model, truth_field) -> dict:
    fl = result.flakes
    model = result.material.flakes
    particles = getattr(fl, "particles", None) if fl is not None else None

    out = {
        "detected": _num_particles(particles),
        "truth_count": int(truth_field.count) if truth_field is not None else 0,
        "fitted": model is not None,
        "truth": None if truth_model is None else {
            "density": truth_model.density, "median_area": truth_model.median_area,
            "color_mean": list(truth_model.color_mean), "tilt_sigma": truth_model.tilt_sigma,
        },
    }
    if model is not None and truth_model is not None:
        out["model"] = {
            "density": model.density, "median_area": model.median_area,
            "color_mean": list(model.color_mean), "tilt_sigma": model.tilt_sigma,
        }
        out["density_rel_err"] = abs(model.density - truth_model.density) / truth_model.density
        out["median_area_rel_err"] = abs(model.median_area - truth_model.median_area) / truth_model.median_area
        out["color_mean_abs_err"] = max(abs(a - b) for a, b in zip(model.color_mean, truth_model.color_mean))
        out["tilt_sigma_rel_err"] = abs(model.tilt_sigma - truth_model.tilt_sigma) / truth_model.tilt_sigma
    return out


def run_demo(out_dir: str | os.PathLike = "torchmetal-demo", *, size: int = 256, quick: bool = False,
             verbose: bool = True) -> dict:
    """Synthetic capture → fit → render → report. Returns the metrics dictionary.

    Args:
        out_dir: report folder (created; files in it are replaced).
        size: image size of the embedded sample (``quick`` caps it at 128).
        quick: fewer, smaller shots — for tests and a first look.
        verbose: print the summary.

    Raises:
        whatever a stage raises: the demo never hides a failure.
    """
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if quick:
        size = min(size, 128)
    shots = 8 if quick else 12
    times: dict[str, float] = {}

    t = time.perf_counter()
    synth = demo_capture(size, shots + 1)
    held = [shots // 2]  # a shot from the middle of the ring, not the end
    fit_idx = [k for k in range(shots + 1) if k not in held]
    capture, heldout = synth.capture.subset(fit_idx), synth.capture.subset(held)
    times["synth"] = time.perf_counter() - t

    t = time.perf_counter()
    result = pipeline.fit_material(capture, scheme="refine", flakes="auto", seed=0, progress=False)
    times["fit"] = time.perf_counter() - t
    material = result.material

    # ---- numbers
    t = time.perf_counter()
    renderer = MaterialRenderer(material).eval()

    def render_fn(light, intensity, camera):
        with torch.inference_mode():
            return renderer(light, intensity, camera)

    metrics = _metrics(synth, capture, heldout, result, render_fn, size=size, shots=shots, held=held[0])
    times["metrics"] = time.perf_counter() - t

    # ---- files
    t = time.perf_counter()
    _write_material(out, renderer, material, times, t)

    t = time.perf_counter()
    report_figure(capture, result, out / "report.png", truth=synth.truth, heldout=heldout, heldout_name=f"held-out shot {held[0]}",
                  render_fn=render_fn,
                  title=f"torchmetal demo — synthetic {size}×{size} sample, {shots} shots fitted, shot {held[0]} held out")
    times["figure"] = time.perf_counter() - t
    times["total"] = time.perf_counter() - t_start
    metrics["demo_times"] = times
    metrics["files"] = {"figure": "report.png", "material": "material", "onnx": "material/renderer.onnx"}
    (out / "metrics.json").write_text(json.dumps(json_finite(metrics), indent=2, allow_nan=False) + "\n")
    if verbose:
        print(summary(metrics, out))
    return metrics


def _metrics(synth: SynthResult, capture: Capture, heldout: Capture, result: PipelineResult, render_fn, *, size: int,
             shots: int, held: int) -> dict:
    """The demo's numbers: PSNR of the fit and of the held-out shot, the specular and flake errors against
    the truth, MD of the held-out shot with and without flakes, the fit's status."""
    material, fit, truth, full = result.material, result.fit, synth.truth, synth.capture
    field = truth["flake_field"]
    no_flake = (field.weight == 0) if field is not None else torch.ones(1, full.height, full.width, dtype=torch.bool)
    ok_fit = no_flake.unsqueeze(0) & ~capture.saturated.any(1, keepdim=True)  # (N, 1, H, W)
    ok_h = no_flake.unsqueeze(0) & ~heldout.saturated.any(1, keepdim=True)
    unsat_h = ~heldout.saturated.any(1, keepdim=True)
    phong_fit = pipeline.render_shots(fit, capture)
    phong_psnr = psnr(phong_fit, capture.images, mask=ok_fit)
    del phong_fit
    photo_h = heldout.images
    phong_h = pipeline.render_shots(fit, heldout)
    heldout_psnr = psnr(phong_h, photo_h, mask=ok_h)
    heldout_truth_psnr = psnr(_truth_phong(synth, heldout), photo_h, mask=ok_h)
    full_h = render_fn(heldout.lights, heldout.intensities, heldout.cameras)
    md = float(metallic_difference(full_h, photo_h))
    md_no = float(metallic_difference(phong_h, photo_h))
    return {
        "sample": {"size": size, "shots_fitted": shots, "heldout_shot": held, "params": synth.params},
        "phong_psnr_db": phong_psnr,
        "heldout_psnr_db": heldout_psnr,
        "heldout_truth_psnr_db": heldout_truth_psnr,
        "texture_psnr_db": psnr(material.texture, truth["texture"]),
        "s": material.s.tolist(), "alpha": material.alpha.tolist(),
        "s_truth": truth["s"].tolist(), "alpha_truth": truth["alpha"].tolist(),
        "s_rel_err": _rel(material.s, truth["s"]),
        "alpha_rel_err": _rel(material.alpha, truth["alpha"]),
        "flakes": _flake_stats(result, truth["flakes"], field),
        "md_heldout": md,
        "md_heldout_no_flakes": md_no,
        "full_render_psnr_db": psnr(full_h, photo_h, mask=unsat_h),
        "full_render_psnr_no_flakes_db": psnr(phong_h, photo_h, mask=unsat_h),
        "fit_status": fit.status,
        "fit_iterations": getattr(fit, "iterations", None),
        "stage_times": dict(result.report.get("stage_times", {})),
        "skipped": list(result.report.get("skipped", [])),
    }


def _write_material(out: Path, renderer: MaterialRenderer, material: Material, times: dict, t: float) -> None:
    """Export the renderer to ONNX (timed into ``times`` from ``t``) and save the material with it."""
    onnx_tmp = out / ".renderer.onnx.tmp"
    export_onnx(renderer, onnx_tmp)
    times["export_onnx"] = time.perf_counter() - t
    try:
        save_material(material, out / "material", extra_files={"renderer.onnx": onnx_tmp})
    finally:
        onnx_tmp.unlink(missing_ok=True)


def _truth_phong(synth, cap) -> torch.Tensor:
    """The true Phong part (no flakes, no noise) of the shots of ``cap``."""
    t = synth.truth
    s, a = synth.specular_maps()
    return phong_render(t["texture"], s, a, cap.normals, cap.lights, cap.intensities, cap.cameras, cap.size)


def summary(m: dict, out: Path | None = None) -> str:
    """A few lines with the headline numbers of :func:`run_demo`'s metrics."""
    f = m["flakes"]
    lines = [
        f"torchmetal demo: {m['sample']['size']}² synthetic sample, {m['sample']['shots_fitted']} shots fitted "
        f"in {m['demo_times']['fit']:.1f} s (total {m['demo_times']['total']:.1f} s), status {m['fit_status']}",
        f"  Phong re-render PSNR {m['phong_psnr_db']:.1f} dB; held-out shot {m['heldout_psnr_db']:.1f} dB "
        f"(true parameters: {m['heldout_truth_psnr_db']:.1f} dB); texture vs truth {m['texture_psnr_db']:.1f} dB",
        f"  s = {_fmt(m['s'])} (rel. err ≤ {max(m['s_rel_err']):.1e}), "
        f"α = {_fmt(m['alpha'], 1)} (rel. err ≤ {max(m['alpha_rel_err']):.1e})",
    ]
    if f.get("fitted") and "model" in f:
        lines.append(
            f"  flakes: {f['detected']} detections; density {f['model']['density']:.2e}/px "
            f"(truth {f['truth']['density']:.2e}, err {f['density_rel_err']:.0%}), median area "
            f"{f['model']['median_area']:.1f} px² (err {f['median_area_rel_err']:.0%}), colour err "
            f"{f['color_mean_abs_err']:.3f}, tilt err {f['tilt_sigma_rel_err']:.0%}")
    else:
        lines.append(f"  flakes: {f['detected']} detections, no flake model fitted")
    lines.append(
        f"  held-out MD {m['md_heldout']:.2f} with sparkles vs {m['md_heldout_no_flakes']:.2f} without "
        f"(PSNR {m['full_render_psnr_db']:.1f} vs {m['full_render_psnr_no_flakes_db']:.1f} dB — PSNR prefers "
        f"{'no sparkles' if m['full_render_psnr_no_flakes_db'] > m['full_render_psnr_db'] else 'the sparkles the shots saw'})")
    if m["skipped"]:
        lines.append("  skipped: " + "; ".join(m["skipped"]))
    if out is not None:
        lines.append(f"  report: {out / 'report.png'}, {out / 'metrics.json'}, {out / 'material'}")
    return "\n".join(lines)


def _fmt(v, nd: int = 4) -> str:
    return "[" + ", ".join(f"{x:.{nd}f}" for x in v) + "]"
