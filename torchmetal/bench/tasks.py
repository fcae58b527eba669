"""Units of benchmark work, each run in its own child process by :mod:`torchmetal.bench.runner`.

Every task takes a JSON-able config dict and returns a JSON-able dict. A task that needs a stage
that is not importable yet raises :class:`NotAvailable`; the worker reports it as
``{"not_available": reason}`` and the runner prints "not available: <reason>".

Run one by hand: ``python -m torchmetal.bench.worker TASK '{"size": 64, ...}' result.json``.
"""

from __future__ import annotations

import gc
import os
import time
from pathlib import Path

import numpy as np

from torchmetal.bench.memory import PeakMemory


class NotAvailable(Exception):
    """A stage this task needs cannot be imported or does not have the expected API."""


def _need(module: str, *names: str):
    """Import ``names`` from ``module`` or raise :class:`NotAvailable` with the reason."""
    import importlib

    try:
        mod = importlib.import_module(module)
    except Exception as e:  # ImportError, or a half-written module failing at import
        raise NotAvailable(f"{module} not importable ({type(e).__name__}: {e})") from None
    out = []
    for n in names:
        if not hasattr(mod, n):
            raise NotAvailable(f"{module}.{n} does not exist")
        out.append(getattr(mod, n))
    return out[0] if len(out) == 1 else out


# ----------------------------------------------------------------------------- helpers


def holdout_indices(n_total: int, n_hold: int) -> list[int]:
    """``n_hold`` shot indices spread evenly over ``n_total`` (never the same one twice)."""
    if n_hold <= 0:
        return []
    idx = sorted({min(n_total - 1, int((i + 0.5) * n_total / n_hold)) for i in range(n_hold)})
    return idx


def psnr_or_nan(pred, ref, valid=None) -> float:
    """:func:`torchmetal.metrics.psnr` (linear values clipped to [0, 1], peak 1) over ``valid``.

    A benchmark records a failed method instead of stopping: NaN when ``valid`` selects nothing
    or a compared value of ``pred`` is not finite.
    """
    from torchmetal.errors import InputError
    from torchmetal.metrics import psnr as _psnr  # torch: imported when a task needs it

    try:
        return _psnr(pred, ref, mask=valid)
    except InputError:
        return float("nan")


def rel_err(est, true) -> float:
    """max over channels of |est − true| / |true| (absolute where true is 0); NaN if shapes differ."""
    e = np.asarray(est, np.float64).reshape(-1)
    t = np.asarray(true, np.float64).reshape(-1)
    if e.shape != t.shape:
        return float("nan")
    den = np.where(np.abs(t) > 0, np.abs(t), 1.0)
    return float(np.max(np.abs(e - t) / den))


def _np(x):
    if x is None:
        return None
    if hasattr(x, "detach"):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, np.float64)


def valid_mask(capture):
    """(N, 3, H, W) bool: finite, inside the mask and not saturated."""
    import torch

    img = capture.images
    v = torch.isfinite(img)
    mask = getattr(capture, "mask", None)
    if mask is not None:
        v = v & mask.bool().reshape(1, 1, *img.shape[-2:])
    sat = getattr(capture, "saturated", None)
    if sat is not None:
        sat = sat.bool()
        if sat.dim() == 3:
            sat = sat[:, None]
        v = v & ~sat.expand_as(img)
    return v


def capture_nbytes_f32(capture) -> int:
    return int(capture.images.numel()) * 4


def _normals(capture):
    import torch

    n = getattr(capture, "normals", None)
    h, w = capture.images.shape[-2:]
    if n is None:
        n = torch.zeros(3, h, w)
        n[2] = 1.0
    if n.dim() == 4:
        n = n[0]
    if n.shape[-1] == 3 and n.shape[0] != 3:
        n = n.permute(2, 0, 1)
    return n.float()


def render_params(texture, s, alpha, capture):
    """torch Phong render of all shots of ``capture`` for plain (texture, s, α) parameters."""
    import torch

    from torchmetal.phong import phong_render

    t = torch.as_tensor(np.asarray(texture), dtype=torch.float32) if not hasattr(texture, "detach") else texture.detach().float()
    s_ = torch.as_tensor(np.asarray(s), dtype=torch.float32) if not hasattr(s, "detach") else s.detach().float()
    a_ = torch.as_tensor(np.asarray(alpha), dtype=torch.float32) if not hasattr(alpha, "detach") else alpha.detach().float()
    with torch.no_grad():
        return phong_render(t, s_, a_, _normals(capture), capture.lights.float(), capture.intensities.float(),
                            capture.cameras.float(), tuple(float(v) for v in capture.size))


# ----------------------------------------------------------------------------- tasks


def task_prepare(cfg: dict) -> dict:
    """Synthesise a capture (fit shots + held-out shots) and save it with its truth to ``cfg['path']``."""
    import torch

    synth_capture = _need("torchmetal.synth", "synth_capture")
    n_fit, n_hold = int(cfg["shots"]), int(cfg.get("holdout", 2))
    kwargs = dict(size=int(cfg["size"]), shots=n_fit + n_hold, seed=int(cfg.get("seed", 0)),
                  noise=float(cfg.get("noise", 0.0)), bits=cfg.get("bits"))
    for k in ("alpha", "s"):
        if cfg.get(k) is not None:
            v = cfg[k]
            kwargs[k] = tuple(float(x) for x in v) if isinstance(v, (list, tuple)) else (float(v),) * 3
    for k in ("layout", "spec_clusters", "texture"):
        if cfg.get(k) is not None:
            kwargs[k] = cfg[k]
    if cfg.get("flakes"):
        FlakeModel = _need("torchmetal.flakes.model", "FlakeModel")
        kwargs["flakes"] = FlakeModel(density=float(cfg.get("flake_density", 0.003)), seed=int(cfg.get("seed", 0)))
    t0 = time.perf_counter()
    res = synth_capture(**kwargs)
    t_synth = time.perf_counter() - t0
    cap = res.capture
    n_total = int(cap.images.shape[0])
    hold = holdout_indices(n_total, n_hold)
    fit_idx = [i for i in range(n_total) if i not in hold]
    truth = {k: v for k, v in dict(res.truth).items()}
    # noise-free, unquantised renders of the truth for the held-out shots: what a fit is scored against
    clean_hold = res.render_clean(hold) if hold else None
    torch.save({"capture": cap, "truth": truth, "fit_idx": fit_idx, "hold_idx": hold, "clean_hold": clean_hold},
               cfg["path"])
    return {"synth_s": t_synth, "capture_f32_bytes": capture_nbytes_f32(cap.subset(fit_idx)), "shots_total": n_total}


def _load_prepared(path: str):
    import torch

    d = torch.load(path, weights_only=False)
    cap = d["capture"]
    truth = dict(d["truth"])
    truth["clean_hold"] = d.get("clean_hold")  # (H, 3, h, w) noise-free held-out renders, or None
    return cap, truth, d["fit_idx"], d["hold_idx"]


def _fit_torchmetal(fit_cap, cfg: dict):
    fit_phong = _need("torchmetal.fit", "fit_phong")
    kw = dict(scheme=cfg.get("scheme", "refine"), specular=cfg.get("specular", "auto"),
              tol=float(cfg.get("tol", 1e-6)), max_iters=int(cfg.get("max_iters", 100)))
    extra = cfg.get("fit_kwargs") or {}
    return fit_phong(fit_cap, **kw, **extra)


def task_method(cfg: dict) -> dict:
    """Fit one method on a prepared capture: wall time, stage times, peak memory, errors.

    cfg: path, method ∈ {torchmetal, torchmetal-paper, paper-numpy, adam}, tol, max_iters,
    adam_steps, adam_budget.
    """
    import torch

    from torchmetal.bench import baselines

    cap, truth, fit_idx, hold_idx = _load_prepared(cfg["path"])
    fit_cap = cap.subset(fit_idx)
    hold_cap = cap.subset(hold_idx) if hold_idx else None
    method = cfg["method"]
    if method.startswith("torchmetal"):
        _need("torchmetal.fit", "fit_phong")  # import before the clock starts, like the others
    gc.collect()
    out: dict = {"method": method, "capture_f32_bytes": capture_nbytes_f32(fit_cap)}
    with PeakMemory() as pm:
        t0 = time.perf_counter()
        if method == "torchmetal":
            fit = _fit_torchmetal(fit_cap, cfg)
        elif method == "torchmetal-paper":
            fit = _fit_torchmetal(fit_cap, {**cfg, "scheme": "paper", "specular": "global"})
        elif method == "paper-numpy":
            fit = baselines.paper_scheme_numpy(fit_cap, tol=float(cfg.get("tol", 1e-6)), max_iters=int(cfg.get("max_iters", 100)))
        elif method == "adam":
            fit = baselines.adam_fit(fit_cap, steps=int(cfg.get("adam_steps", 2000)), time_budget=cfg.get("adam_budget"))
        else:
            raise ValueError(f"unknown method {method!r}")
        wall = time.perf_counter() - t0
    out.update(wall_s=wall, peak_bytes=pm.peak, peak_abs_bytes=pm.peak_abs, memory_method=pm.method)
    out["peak_over_capture"] = pm.peak / max(out["capture_f32_bytes"], 1)
    out["iterations"] = int(getattr(fit, "iterations", 0) or 0)
    out["status"] = str(getattr(fit, "status", ""))
    st = getattr(fit, "stage_times", {}) or {}
    out["stage_times"] = {k: float(v) for k, v in st.items() if isinstance(v, (int, float))}
    out["skipped"] = [str(x) for x in (getattr(fit, "skipped", None) or [])]

    texture, s, alpha = fit.texture, fit.s, fit.alpha
    # held-out PSNR (same torch renderer for every method; torchmetal's own render when it has one)
    if hold_cap is not None:
        v = valid_mask(hold_cap)
        if hasattr(fit, "render") and method.startswith("torchmetal"):
            with torch.no_grad():
                pred = fit.render(hold_cap.lights, hold_cap.intensities, hold_cap.cameras)
        else:
            pred = render_params(texture, s, alpha, hold_cap)
        # primary: against the noise-free render of the truth; secondary: against the noisy photos
        clean = truth.get("clean_hold")
        if clean is not None:
            out["psnr_truth"] = psnr_or_nan(pred, clean)
        out["psnr_holdout"] = psnr_or_nan(pred, hold_cap.images, v)
        if all(k in truth for k in ("texture", "s", "alpha")):
            ref = render_params(truth["texture"], truth["s"], truth["alpha"], hold_cap)
            out["psnr_holdout_truth"] = psnr_or_nan(ref, hold_cap.images, v)
    # parameter errors against the synthetic truth
    if "texture" in truth:
        tt = _np(truth["texture"])
        out["psnr_texture"] = psnr_or_nan(_np(texture), tt)
    if "s" in truth:
        out["s_rel_err"] = rel_err(_np(s), _np(truth["s"]))
    if "alpha" in truth:
        out["alpha_rel_err"] = rel_err(_np(alpha), _np(truth["alpha"]))
    tex = _np(texture)
    out["texture_sum"] = float(tex.sum())
    out["texture_abs_max"] = float(np.abs(tex).max())
    out["s"] = _np(s).reshape(-1).tolist()[:3] if _np(s).size == 3 else None
    out["alpha"] = _np(alpha).reshape(-1).tolist()[:3] if _np(alpha).size == 3 else None
    return out


def task_prepare_dir(cfg: dict) -> dict:
    """Synthesise a capture and write it as a capture directory (PNG, ``bits``) to ``cfg['dir']``."""
    synth_capture = _need("torchmetal.synth", "synth_capture")
    save_capture = _need("torchmetal.io.capture_save", "save_capture")
    res = synth_capture(size=int(cfg["size"]), shots=int(cfg["shots"]), seed=int(cfg.get("seed", 0)),
                        noise=float(cfg.get("noise", 0.0)), bits=cfg.get("bits"))
    t0 = time.perf_counter()
    save_capture(res.capture, cfg["dir"], bits=int(cfg.get("bits", 16)))
    disk = sum(p.stat().st_size for p in Path(cfg["dir"]).rglob("*") if p.is_file())
    return {"save_s": time.perf_counter() - t0, "disk_bytes": disk}


def task_load(cfg: dict) -> dict:
    """Time ``load_capture`` of a capture directory; peak memory above the RSS before the load."""
    load_capture = _need("torchmetal.io.capture", "load_capture")
    import torch  # noqa: F401  (imported before the clock, as a user's program would have it)

    gc.collect()
    with PeakMemory() as pm:
        t0 = time.perf_counter()
        cap = load_capture(cfg["dir"])
        wall = time.perf_counter() - t0
    f32 = capture_nbytes_f32(cap)
    return {"wall_s": wall, "peak_bytes": pm.peak, "capture_f32_bytes": f32, "peak_over_capture": pm.peak / f32,
            "shots": int(cap.images.shape[0]), "size": list(cap.images.shape[-2:]), "memory_method": pm.method}


def task_skip(cfg: dict) -> dict:
    """Per-stage times and the skipped list of the full pipeline on one prepared scene."""
    import torch  # noqa: F401

    cap, truth, fit_idx, hold_idx = _load_prepared(cfg["path"])
    fit_cap = cap.subset(fit_idx)
    try:
        fit_material = _need("torchmetal.pipeline", "fit_material")
        _need("torchmetal.flakes.stage", "flake_stage")
        _need("torchmetal.fit", "fit_phong")
        t0 = time.perf_counter()
        res = fit_material(fit_cap, flakes=cfg.get("flakes_mode", "auto"))
        wall = time.perf_counter() - t0
        rep = dict(res.report)
        fl = res.material.flakes
        return {"wall_s": wall, "stage_times": {k: float(v) for k, v in rep.get("stage_times", {}).items()},
                "skipped": [str(x) for x in rep.get("skipped", [])], "flakes_found": fl is not None,
                "flake_density": None if fl is None else float(fl.density), "pipeline": "fit_material"}
    except NotAvailable as e:
        reason = str(e)
    # fall back to the Phong fit alone, so skip evidence for the specular stage still shows
    fit = _fit_torchmetal(fit_cap, {"tol": cfg.get("tol", 1e-6)})
    return {"wall_s": float(sum(v for v in fit.stage_times.values() if isinstance(v, (int, float)))),
            "stage_times": {f"phong.{k}": float(v) for k, v in fit.stage_times.items() if isinstance(v, (int, float))},
            "skipped": [str(x) for x in fit.skipped], "flakes_found": None,
            "pipeline": f"fit_phong only (flake stage not available: {reason})"}


def task_flakes(cfg: dict) -> dict:
    """Flake detection + statistics time on one shot of a prepared flake capture."""
    import torch

    flake_stage = _need("torchmetal.flakes.stage", "flake_stage")
    cap, truth, fit_idx, hold_idx = _load_prepared(cfg["path"])
    shot = cap.subset([fit_idx[0]])
    phong = render_params(truth["texture"], truth["s"], truth["alpha"], shot)
    flake_stage(shot.subset([0]), phong)  # warm-up (first-call import and allocation costs)
    times = []
    res = None
    for _ in range(int(cfg.get("repeats", 3))):
        t0 = time.perf_counter()
        res = flake_stage(shot, phong)
        times.append(time.perf_counter() - t0)
    out = {"shot_size": list(shot.images.shape[-2:]), "best_s": min(times), "median_s": float(np.median(times)),
           "particles": None, "model": res.model is not None}
    rt = (getattr(res, "report", None) or {}).get("times", {})
    out["detect_s"] = rt.get("detect")
    out["statistics_s"] = rt.get("statistics")
    parts = getattr(res, "particles", None)
    if parts is not None:
        try:
            out["particles"] = int(len(parts)) if not hasattr(parts, "num") else int(parts.num)
        except TypeError:
            out["particles"] = None
    # the whole N-shot stage, for reference
    all_fit = cap.subset(fit_idx)
    phong_all = render_params(truth["texture"], truth["s"], truth["alpha"], all_fit)
    t0 = time.perf_counter()
    res_all = flake_stage(all_fit, phong_all)
    out["all_shots_s"] = time.perf_counter() - t0
    out["all_shots"] = len(fit_idx)
    out["all_shots_particles"] = len(getattr(res_all, "particles", []) or [])
    out["all_shots_skipped"] = (getattr(res_all, "report", None) or {}).get("skipped")
    if res_all.model is not None and cfg.get("true_density") is not None:
        out["density_fit"] = float(res_all.model.density)
        out["density_true"] = float(cfg["true_density"])
    return out


def task_onnx(cfg: dict) -> dict:
    """Export a ``size``² material (with flakes) and time one-light frames in onnxruntime and torch."""
    import tempfile

    import torch

    export_onnx = _need("torchmetal.onnx_export", "export_onnx")
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.material import Material

    size = int(cfg["size"])
    g = torch.Generator().manual_seed(0)
    texture = 0.1 + 0.5 * torch.rand(3, size, size, generator=g)
    mat = Material(texture=texture, s=torch.tensor([0.5, 0.45, 0.4]), alpha=torch.tensor([80.0, 100.0, 120.0]),
                   size=(0.1, 0.1), flakes=FlakeModel(density=0.003) if cfg.get("flakes", True) else None)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "renderer.onnx"
        t0 = time.perf_counter()
        export_onnx(mat, path)
        export_s = time.perf_counter() - t0
        nbytes = path.stat().st_size
        siblings = sorted(p.name for p in Path(d).iterdir())
        out = {"size": size, "file_bytes": nbytes, "files": siblings, "export_s": export_s, "flakes": mat.flakes is not None}
        time_renderer = _need("torchmetal.onnx_export", "time_renderer")
        reps = int(cfg.get("repeats", 10))
        t_ort = time_renderer(path, batch=1, repeats=reps, threads=2)
        t_torch = time_renderer(mat, batch=1, repeats=max(3, reps // 2))
        out["timing"] = {"ort_ms": float(t_ort["ms_median"]), "ort_ms_min": float(t_ort["ms_min"]),
                         "torch_ms": float(t_torch["ms_median"]), "torch_ms_min": float(t_torch["ms_min"]),
                         "ort_threads": t_ort.get("threads"), "torch_threads": t_torch.get("threads")}
    return out


def task_real(cfg: dict) -> dict:
    """Leave-one-out PSNR on a real capture directory for each of ``cfg["speculars"]``: "global" and
    "clustered" are :func:`fit_phong` (the refine scheme) with that specular; a name of
    :data:`torchmetal.bench.zoo.METHODS` ("default", "paper") is :func:`fit_material` with those options,
    rendered as the material renders (sparkles included). Beside each PSNR, the chroma-artifact share
    (:func:`torchmetal.metrics.chroma_artifact_share`) of every left-out shot.

    With ``cfg["gallery"]`` (a directory), the default pipeline's first ``cfg["gallery_shots"]`` (3)
    left-out shots are written there as ``{capture}_shot{k}.png``: photo | render | error (|Δ| of the
    sRGB values ×4), sRGB, each panel box-downsampled to ≤ 512 px wide."""
    load_capture = _need("torchmetal.io.capture", "load_capture")
    leave_one_out_with = _need("torchmetal.fit.holdout", "leave_one_out_with")
    chroma_artifact_share = _need("torchmetal.metrics", "chroma_artifact_share")
    cap = load_capture(cfg["dir"])
    if cfg.get("max_shots") and cap.num_shots > int(cfg["max_shots"]):
        cap = cap.subset(list(range(int(cfg["max_shots"]))))
    if cfg.get("downsample"):
        cap = _downsample(cap, int(cfg["downsample"]))
    name = Path(cfg["dir"]).name
    out = {"name": name, "shots": int(cap.images.shape[0]), "size": list(cap.images.shape[-2:])}
    gallery = Path(cfg["gallery"]) if cfg.get("gallery") else None
    for spec in cfg.get("speculars", ["global", "clustered"]):
        t0 = time.perf_counter()
        fr = _phong_fit_render(spec) if spec in ("global", "clustered") else _material_fit_render(spec)
        renders: list = []

        def keep(train, one, fr=fr, renders=renders):
            pred = fr(train, one)
            renders.append(pred.detach().float().cpu())
            return pred

        vals = [float(v) for v in leave_one_out_with(cap, keep)]
        seconds = time.perf_counter() - t0
        chroma = []
        for k, pred in enumerate(renders):
            one = cap.subset([k])
            v = valid_mask(one)[0].all(0)
            chroma.append(chroma_artifact_share(pred[0], one.images[0].float(), mask=v) if bool(v.any()) else float("nan"))
        out[spec] = {"psnr": vals, "mean": float(np.mean(vals)), "seconds": seconds, "chroma": chroma,
                     "chroma_mean": float(np.nanmean(chroma)) if any(c == c for c in chroma) else float("nan")}
        if gallery is not None and spec == "default":
            out[spec]["gallery"] = [str(_gallery_png(gallery / f"{name}_shot{k}.png", cap.images[k], renders[k][0]))
                                    for k in range(min(len(renders), int(cfg.get("gallery_shots", 3))))]
    return out


def _phong_fit_render(specular: str):
    """fit_render of :func:`~torchmetal.fit.holdout.leave_one_out` (``fit_phong`` with this specular)."""
    import torch

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


#: more pipelines the real section can score beside the zoo's METHODS: the default before the lobe and the
#: normals were chosen on left-out shots (issue 27), and the richest options
REAL_VARIANTS = {"paper_model": {"normals": "given", "lobe": "phong"},
                 "richest": {"normals": "estimate", "lobe": "auto", "specular": "maps"}}


def _material_fit_render(method: str):
    """fit_render for :func:`~torchmetal.fit.holdout.leave_one_out_with`: the whole pipeline with the
    options of the zoo's ``method``, rendered by the material's renderer."""
    import torch

    from torchmetal.bench.zoo import METHODS
    from torchmetal.pipeline import fit_material
    from torchmetal.renderer import MaterialRenderer

    variants = {**METHODS, **REAL_VARIANTS}
    if method not in variants:
        raise ValueError(f"real: expected a variant among global, clustered, {', '.join(variants)}; found {method!r}")

    def fit_render(train, one):
        material = fit_material(train, seed=0, **variants[method]).material
        with torch.no_grad():
            return MaterialRenderer(material)(one.lights, one.intensities, one.cameras)

    return fit_render


def task_realflakes(cfg: dict) -> dict:
    """Flake stage on a real capture: fit on all shots but one, MD and PSNR of the one left out
    rendered with and without the flake term, and the detections drawn on a fitted shot (PNG)."""
    import torch

    from torchmetal.flakes.md import metallic_difference
    from torchmetal.flakes.report import save_detection_overlay
    from torchmetal.io.capture import load_capture
    from torchmetal.pipeline import fit_material
    from torchmetal.renderer import MaterialRenderer

    cap = load_capture(cfg["dir"])
    if cfg.get("downsample"):
        cap = _downsample(cap, int(cfg["downsample"]))
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


def _downsample(cap, factor: int):
    """Box-downsample a capture by an integer factor (for --quick runs on real data)."""
    import dataclasses

    import torch.nn.functional as F

    if factor <= 1:
        return cap
    changes = {"images": F.avg_pool2d(cap.images, factor)}
    for name in ("normals",):
        v = getattr(cap, name, None)
        if v is not None:
            changes[name] = F.normalize(F.avg_pool2d(v[None] if v.dim() == 3 else v, factor), dim=-3).reshape(3, *changes["images"].shape[-2:])
    mask = getattr(cap, "mask", None)
    if mask is not None:
        mm = F.avg_pool2d(mask.float().reshape(1, 1, *mask.shape[-2:]), factor) > 0.999
        changes["mask"] = mm.reshape(*mask.shape[:-2], *changes["images"].shape[-2:]).to(mask.dtype)
    sat = getattr(cap, "saturated", None)
    if sat is not None:
        changes["saturated"] = F.max_pool2d(sat.float().reshape(-1, 1, *sat.shape[-2:]), factor).reshape(
            *sat.shape[:-2], *changes["images"].shape[-2:]).to(sat.dtype)
    return dataclasses.replace(cap, **changes)


def task_zoo(cfg: dict) -> dict:
    """One scene of the zoo (``cfg['scene']``; its CI size when ``cfg['ci']``) fitted with each of
    ``cfg['methods']`` (name → ``fit_material`` options) and scored against the noise-free truth."""
    SCENES, ci_scenes = _need("torchmetal.synth.zoo", "SCENES", "ci_scenes")
    run_scene, METHODS = _need("torchmetal.bench.zoo", "run_scene", "METHODS")
    scenes = {s.name: s for s in ci_scenes()} if cfg.get("ci") else dict(SCENES)
    scene = scenes[cfg["scene"]]
    r = run_scene(scene, cfg.get("methods") or METHODS)
    r["size"], r["shots"] = int(scene.size), int(scene.shots)
    return r


def task_selftest(cfg: dict) -> dict:
    """Harness self-test: sleep, allocate ``mib`` MiB, or fail, as ``cfg`` says."""
    with PeakMemory() as pm:
        if cfg.get("mib"):
            buf = np.ones(int(cfg["mib"]) * 2**20 // 8)
            del buf
        time.sleep(float(cfg.get("sleep", 0.0)))
        if cfg.get("missing"):
            _need(cfg["missing"], "anything")
        if cfg.get("fail"):
            raise RuntimeError(cfg["fail"])
    import torch

    return {"peak_bytes": pm.peak, "memory_method": pm.method, "pid": os.getpid(), "torch_threads": torch.get_num_threads()}


TASKS = {
    "selftest": task_selftest,
    "prepare": task_prepare,
    "method": task_method,
    "prepare_dir": task_prepare_dir,
    "load": task_load,
    "skip": task_skip,
    "flakes": task_flakes,
    "onnx": task_onnx,
    "real": task_real,
    "realflakes": task_realflakes,
    "zoo": task_zoo,
}
