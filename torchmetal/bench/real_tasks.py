"""Benchmark tasks on real capture directories (the shared captures): leave-one-out PSNR per
specular model or pipeline variant with a chroma-artifact share and an optional gallery
(``real``), and the flake stage on one left-out shot (``realflakes``). Registered in
:data:`torchmetal.bench.tasks.TASKS`.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from torchmetal.bench.available import need
from torchmetal.bench.scoring import SCALES, extrapolation_share, psnr_or_nan, psnr_scales, valid_mask
from torchmetal.bench.zoo import METHODS


def task_real(cfg: dict) -> dict:
    """Leave-one-out PSNR on a real capture directory for each of ``cfg["speculars"]``: "global" and
    "clustered" are :func:`fit_phong` (the refine scheme) with that specular; a name of
    :data:`torchmetal.bench.zoo.METHODS` ("default", "paper") is :func:`fit_material` with those options,
    rendered as the material renders (sparkles included). Beside each PSNR, the chroma-artifact share
    (:func:`torchmetal.metrics.chroma_artifact_share`) of every left-out shot, and the in-sample PSNR
    (``in_sample``: fitted on every shot, scored on the same shots — what the model can explain at all).
    A pipeline variant also gets ``coat`` / ``coat_mean`` / ``coat_in_sample``: the same PSNRs of its material
    rendered without its sparkles, the zoo's coat score (random sparkle positions cost PSNR even where the
    flake statistics are right, so the coatings compare without them; the sparkles are judged by MD), and
    ``light_fitted`` / ``light_fitted_mean`` / ``light_fitted_chroma`` / ``light_fitted_chroma_mean``: the
    left-out scores with each left-out shot's light position fitted to its photo, the material held fixed
    (a phone capture's light positions are off by centimetres: this compares the materials, not them).

    With ``cfg["gallery"]`` (a directory), the default pipeline's first ``cfg["gallery_shots"]`` (3)
    left-out shots are written there as ``{capture}_shot{k}.png``: photo | render | error (|Δ| of the
    sRGB values ×4), sRGB, each panel box-downsampled to ≤ 512 px wide; likewise
    ``{capture}_light_fitted_shot{k}.png`` under the light fitted to the photo, and for every variant of
    ``cfg["gallery_specs"]`` (default: only "default") with ``_{variant}`` after the capture's name, and
    ``{capture}_own_shot{k}.png``: the fit on every shot rendering its own shot k.

    ``scores`` (per variant): the three kinds side by side — ``in_sample`` (own shots), ``left_out`` (as
    captured) and, for a pipeline variant, ``light_fitted`` — each the sRGB PSNR at full size, ¼ and 1/16 (both
    images box-averaged alike, :func:`~torchmetal.bench.scoring.psnr_scales`), its chroma share and the
    extrapolation share (:func:`~torchmetal.bench.scoring.extrapolation_share`; ``extrapolation`` at the top level
    lists it per shot)."""
    load_capture = need("torchmetal.io.capture", "load_capture")
    leave_one_out_with = need("torchmetal.fit.holdout", "leave_one_out_with")
    cap = load_capture(cfg["dir"])
    if cfg.get("max_shots") and cap.num_shots > int(cfg["max_shots"]):
        cap = cap.subset(list(range(int(cfg["max_shots"]))))
    if cfg.get("downsample"):
        cap = cap.downsampled(int(cfg["downsample"]))
    name = Path(cfg["dir"]).name
    out = {"name": name, "shots": int(cap.images.shape[0]), "size": list(cap.images.shape[-2:])}
    gallery = Path(cfg["gallery"]) if cfg.get("gallery") else None
    extrapolation = _extrapolation(cap)
    out["extrapolation"] = extrapolation
    for spec in cfg.get("speculars", ["global", "clustered"]):
        t0 = time.perf_counter()
        coats: list = []  # a pipeline variant's renders without sparkles, one per call
        calibrated: list = []  # a pipeline variant's left-out renders under the light fitted to the shot's photo
        fr = _phong_fit_render(spec) if spec in ("global", "clustered") else _material_fit_render(spec, coats, calibrated)
        renders: list = []

        def keep(train, one, fr=fr, renders=renders):
            pred = fr(train, one)
            renders.append(pred.detach().float().cpu())
            return pred

        vals = [float(v) for v in leave_one_out_with(cap, keep)]
        seconds = time.perf_counter() - t0
        coat = [psnr_or_nan(c, cap.images[k : k + 1], valid_mask(cap.subset([k]))) for k, c in enumerate(coats)]
        chroma = [_chroma(pred[0], cap.subset([k])) for k, pred in enumerate(renders)]
        pred = fr(cap, cap)  # in sample: every shot fitted and rendered
        own = pred.detach().float().cpu()
        in_sample = psnr_or_nan(own, cap.images, valid_mask(cap))
        out[spec] = {"psnr": vals, "mean": float(np.mean(vals)), "seconds": seconds, "chroma": chroma,
                     "chroma_mean": float(np.nanmean(chroma)) if any(c == c for c in chroma) else float("nan"),
                     "in_sample": in_sample}
        if coats:
            out[spec].update(coat=coat, coat_mean=float(np.mean(coat)),
                             coat_in_sample=psnr_or_nan(coats[-1], cap.images, valid_mask(cap)))
        if calibrated:
            cal = [psnr_or_nan(c, cap.images[k : k + 1], valid_mask(cap.subset([k]))) for k, c in enumerate(calibrated)]
            cal_chroma = [_chroma(c[0], cap.subset([k])) for k, c in enumerate(calibrated)]
            out[spec].update(light_fitted=cal, light_fitted_mean=float(np.mean(cal)), light_fitted_chroma=cal_chroma,
                             light_fitted_chroma_mean=float(np.nanmean(cal_chroma)) if any(c == c for c in cal_chroma)
                             else float("nan"))
        out[spec]["scores"] = {"in_sample": _kind_scores(cap, [own[k : k + 1] for k in range(len(own))], None),
                               "left_out": _kind_scores(cap, renders, extrapolation)}
        if calibrated:
            out[spec]["scores"]["light_fitted"] = _kind_scores(cap, calibrated, extrapolation)
        if gallery is not None and spec in cfg.get("gallery_specs", ("default",)):
            tag = "" if spec == "default" else f"_{spec}"
            shots = range(min(len(renders), int(cfg.get("gallery_shots", 3))))
            out[spec]["gallery_own"] = [str(_gallery_png(gallery / f"{name}{tag}_own_shot{k}.png", cap.images[k], own[k]))
                                        for k in shots]
            out[spec]["gallery"] = [str(_gallery_png(gallery / f"{name}{tag}_shot{k}.png", cap.images[k], renders[k][0]))
                                    for k in shots]
            if calibrated:
                out[spec]["gallery_light_fitted"] = [
                    str(_gallery_png(gallery / f"{name}{tag}_light_fitted_shot{k}.png", cap.images[k], calibrated[k][0]))
                    for k in shots]
    return out


def _extrapolation(cap) -> list[float]:
    """Per shot k, :func:`~torchmetal.bench.scoring.extrapolation_share` of photo k against the other shots'
    photos (the ones fitted when k is left out)."""
    n = int(cap.images.shape[0])
    mask = cap.mask[0] if getattr(cap, "mask", None) is not None else None
    return [extrapolation_share(cap.images[k], cap.images[[i for i in range(n) if i != k]], mask) for k in range(n)]


def _kind_scores(cap, renders: list, extrapolation: list | None) -> dict:
    """One score kind of the real section (own shots, left out as captured, left out light fitted): for
    ``renders[k]`` (1, 3, H, W) of shot k, the mean over the shots of the sRGB PSNR at each scale of
    :data:`~torchmetal.bench.scoring.SCALES` (``psnr``: {"1": dB, "4": dB, "16": dB}; ``per_shot``: the
    per-shot dicts), the chroma-artifact share (mean) and, for left-out shots, the extrapolation share of the
    worst left-out shot (the max; None for own shots: a fitted photo is never brighter than itself). Not the mean:
    over a whole leave-one-out each block's brightest shot is the one counted, so the mean is 1/N by construction."""
    per_shot, chroma = [], []
    for k, r in enumerate(renders):
        one = cap.subset([k])
        per_shot.append(psnr_scales(r[0].float(), one.images[0].float(), valid_mask(one)[0]))
        chroma.append(_chroma(r[0], one))
    psnr = {str(f): _nanmean([d[str(f)] for d in per_shot]) for f in SCALES}
    return {"psnr": psnr, "per_shot": per_shot, "chroma": _nanmean(chroma),
            "extrapolation": None if extrapolation is None else max(extrapolation[: len(renders)], default=float("nan"))}


def _nanmean(xs) -> float:
    xs = [float(x) for x in xs if x == x]
    return float(np.mean(xs)) if xs else float("nan")


def _chroma(pred, one) -> float:
    """The chroma-artifact share of a render (3, H, W) of the one-shot capture ``one`` (NaN: no valid pixel)."""
    chroma_artifact_share = need("torchmetal.metrics", "chroma_artifact_share")
    v = valid_mask(one)[0].all(0)
    return chroma_artifact_share(pred, one.images[0].float(), mask=v) if bool(v.any()) else float("nan")


def _phong_fit_render(specular: str):
    """fit_render of :func:`~torchmetal.fit.holdout.leave_one_out` (``fit_phong`` with this specular)."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.fit.api import fit_phong

    def fit_render(train, one):
        fit = fit_phong(train, specular=specular)
        with torch.no_grad():
            return fit.render(one.lights, one.intensities, one.cameras)

    return fit_render


GALLERY_WIDTH = 512


def _gallery_png(path: Path, photo, render) -> Path:
    """photo | render | error (|Δ| of the sRGB values ×4), (3, H, W) linear → one sRGB PNG, panels
    box-downsampled to ≤ :data:`GALLERY_WIDTH` px wide."""
    import cv2
    import torch
    import torch.nn.functional as F

    # on use: loads torch (this module imports numpy only)
    from torchmetal.metrics import srgb_encode

    photo, render = photo.detach().float().cpu(), render.detach().float().cpu()
    f = max(1, -(-int(photo.shape[-1]) // GALLERY_WIDTH))
    small = [F.avg_pool2d(x[None], f)[0] if f > 1 else x for x in (photo, render)]
    enc = [srgb_encode(x.clamp(0.0, 1.0)) for x in small]
    err = ((enc[0] - enc[1]).abs() * 4.0).clamp(0.0, 1.0)
    gap = torch.ones(3, enc[0].shape[-2], 4)
    sheet = torch.cat([enc[0], gap, enc[1], gap, err], -1)
    img = (sheet.permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1]))
    return path


#: more pipelines the real section can score beside the zoo's METHODS: the default before the lobe, the
#: clipping, the normals and the light were chosen on left-out shots (paper_model), the capture's lights as given
#: (light_off), moved by the flash's one move (light_flash) or each to its photo (light_positions), and the
#: richest options
REAL_VARIANTS = {"paper_model": {"normals": "given", "lobe": "phong", "light": "off", "clipping": "channel"},
                 "light_off": {"light": "off"}, "light_flash": {"light": "flash"}, "light_positions": {"light": "positions"},
                 "richest": {"normals": "estimate", "lobe": "auto", "specular": "maps"}}


def _material_fit_render(method: str, coats: list | None = None, calibrated: list | None = None):
    """fit_render for :func:`~torchmetal.fit.holdout.leave_one_out_with`: the whole pipeline with the
    options of the zoo's ``method``, rendered by the material's renderer. With ``coats`` (a list), each
    call also appends the render without the material's sparkles (flake model and observed flakes), on CPU;
    with ``calibrated`` (a list), each call on a left-out shot appends its render under the light position
    fitted to its photo with the material held fixed (:func:`~torchmetal.lightcal.positions.material_offsets`:
    every variant scored under a calibrated light, the capture's light errors aside), on CPU."""
    from dataclasses import replace

    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.lightcal.positions import material_offsets, moved_lights
    from torchmetal.pipeline import fit_material
    from torchmetal.renderer import MaterialRenderer

    variants = {**METHODS, **REAL_VARIANTS}
    if method not in variants:
        raise ValueError(f"real: expected a variant among global, clustered, {', '.join(variants)}; found {method!r}")

    def fit_render(train, one):
        res = fit_material(train, seed=0, **variants[method])
        # the photos' lights: the calibration's falloff (a left-out shot has no gain, no offset)
        seen = one is train
        frame = _photo_frames(res, train, one, seen)
        light = res.light if seen else res.light.for_unseen()
        factor, lights = light.factor(one), light.lights(one)
        renderer = MaterialRenderer(res.material)
        with torch.no_grad():
            pred = renderer(lights, one.intensities, one.cameras)
            if coats is not None:
                m = res.material
                coat = pred if m.flakes is None and m.observed_flakes is None else \
                    MaterialRenderer(replace(m, flakes=None, observed_flakes=None))(lights, one.intensities, one.cameras)
                coats.append(frame(coat * factor).detach().float().cpu())
            if calibrated is not None and not seen:
                fitted = moved_lights(one.lights, material_offsets(res.material, one, factor))
                calibrated.append(frame(renderer(fitted, one.intensities, one.cameras) * factor).detach().float().cpu())
        return frame(pred * factor)

    return fit_render


def _photo_frames(res, train, one, seen: bool):
    """The renders of ``one``'s shots moved into their photos' frames where the fit registered its shots (the
    material lies in their mean frame): a fitted shot by its measured shift, a left-out one by its shift against the
    registered shots (the registration a new photo gets). Pixels with no source keep the unmoved render."""
    import torch

    from torchmetal.registration import moved, registered, shifts_against

    rep = (getattr(res, "report", None) or {}).get("registered") or {}
    if rep.get("chosen") != "shift":
        return lambda pred: pred
    shifts = rep["shifts"] if seen else shifts_against(registered(train, rep["shifts"]).images, one.images)

    def frame(pred):
        m = moved(pred, shifts, sign=1.0)
        return torch.where(torch.isnan(m), pred, m)

    return frame


def task_realflakes(cfg: dict) -> dict:
    """Flake stage on a real capture: fit on all shots but one, MD and PSNR of the one left out
    rendered with and without the flake term, and the detections drawn on a fitted shot (PNG)."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.flakes.estimate.overlay import save_detection_overlay
    from torchmetal.flakes.model.md import metallic_difference
    from torchmetal.io.capture import load_capture
    from torchmetal.pipeline import fit_material
    from torchmetal.renderer import MaterialRenderer

    cap = load_capture(cfg["dir"])
    if cfg.get("downsample"):
        cap = cap.downsampled(int(cfg["downsample"]))
    n = cap.num_shots
    hold = int(cfg.get("holdout", n // 2)) % n
    fit_cap, one = cap.subset([k for k in range(n) if k != hold]), cap.subset([hold])
    t0 = time.perf_counter()
    res = fit_material(fit_cap, flakes="on", seed=0)
    seconds = time.perf_counter() - t0
    model = res.material.flakes
    valid = valid_mask(one)
    out = {"name": Path(cfg["dir"]).name, "shots_fitted": n - 1, "heldout": hold, "size": list(cap.images.shape[-2:]),
           "fit_s": seconds, "flake_stage_s": res.report["stage_times"].get("flakes"),
           "particles": len(res.flakes.particles) if res.flakes is not None else 0,
           "model": None if model is None else {k: v for k, v in model.to_dict().items() if k != "extra"},
           "skipped": (res.flakes.report.get("skipped") if res.flakes is not None else None)}
    with torch.inference_mode():
        for key, flakes in (("with", True), ("without", False)):
            r = MaterialRenderer(res.material, flakes=flakes)
            img = r(one.lights.float(), one.intensities.float(), one.cameras.float())
            out[f"md_{key}"] = float(metallic_difference(img, one.images.float()))
            out[f"psnr_{key}"] = psnr_or_nan(img, one.images, valid)
    if cfg.get("overlay") and res.flakes is not None:
        k = 0
        parts = res.flakes.particles.for_shot(k)
        gain = 0.5 / max(1e-12, float(fit_cap.images[k].float().mean()))
        out["overlay"] = str(save_detection_overlay(cfg["overlay"], fit_cap.images[k], parts, gain=min(gain, 8.0)))
        out["overlay_particles"] = len(parts)
    return out
