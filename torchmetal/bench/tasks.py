"""Units of benchmark work, each run in its own child process by :mod:`torchmetal.bench.runner`.

Every task takes a JSON-able config dict and returns a JSON-able dict. A task that needs a stage
that is not importable yet raises :class:`~torchmetal.bench.available.NotAvailable`; the worker
reports it as ``{"not_available": reason}`` and the runner prints "not available: <reason>".

This module holds the tasks on synthetic captures and :data:`TASKS`, the registry the worker runs;
the tasks on real capture directories are in :mod:`torchmetal.bench.real_tasks`, the scoring
helpers in :mod:`torchmetal.bench.scoring`.

Run one by hand: ``python -m torchmetal.bench.worker TASK '{"size": 64, ...}' result.json``.
"""

from __future__ import annotations

import gc
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.bench import baselines
from torchmetal.bench.available import NotAvailable, need
from torchmetal.bench.memory import PeakMemory
from torchmetal.bench.real_tasks import task_real, task_realflakes
from torchmetal.bench.scoring import (
    capture_nbytes_f32,
    holdout_indices,
    psnr_or_nan,
    rel_err,
    render_params,
    to_numpy,
    valid_mask,
)

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture


def task_prepare(cfg: dict) -> dict:
    """Synthesise a capture (fit shots + held-out shots) and save it with its truth to ``cfg['path']``."""
    import torch

    synth_capture = need("torchmetal.synth", "synth_capture")
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
        FlakeModel = need("torchmetal.flakes.model", "FlakeModel")
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
    fit_phong = need("torchmetal.fit", "fit_phong")
    kw = dict(scheme=cfg.get("scheme", "refine"), specular=cfg.get("specular", "auto"),
              tol=float(cfg.get("tol", 1e-6)), max_iters=int(cfg.get("max_iters", 100)))
    extra = cfg.get("fit_kwargs") or {}
    return fit_phong(fit_cap, **kw, **extra)


def task_method(cfg: dict) -> dict:
    """Fit one method on a prepared capture: wall time, stage times, peak memory, errors.

    cfg: path, method ∈ {torchmetal, torchmetal-paper, paper-numpy, adam}, tol, max_iters,
    adam_steps, adam_budget.
    """
    cap, truth, fit_idx, hold_idx = _load_prepared(cfg["path"])
    fit_cap = cap.subset(fit_idx)
    hold_cap = cap.subset(hold_idx) if hold_idx else None
    method = cfg["method"]
    if method.startswith("torchmetal"):
        need("torchmetal.fit", "fit_phong")  # import before the clock starts, like the others
    gc.collect()
    out: dict = {"method": method, "capture_f32_bytes": capture_nbytes_f32(fit_cap)}
    with PeakMemory() as pm:
        t0 = time.perf_counter()
        fit = _fit_method(method, fit_cap, cfg)
        wall = time.perf_counter() - t0
    out.update(wall_s=wall, peak_bytes=pm.peak, peak_abs_bytes=pm.peak_abs, memory_method=pm.method)
    out["peak_over_capture"] = pm.peak / max(out["capture_f32_bytes"], 1)
    out["iterations"] = int(getattr(fit, "iterations", 0) or 0)
    out["status"] = str(getattr(fit, "status", ""))
    st = getattr(fit, "stage_times", {}) or {}
    out["stage_times"] = {k: float(v) for k, v in st.items() if isinstance(v, (int, float))}
    out["skipped"] = [str(x) for x in (getattr(fit, "skipped", None) or [])]
    if hold_cap is not None:
        out.update(_holdout_scores(fit, method, truth, hold_cap))
    out.update(_parameter_errors(fit.texture, fit.s, fit.alpha, truth))
    return out


def _fit_method(method: str, fit_cap: Capture, cfg: dict) -> FitResult | baselines.BaselineResult:
    if method == "torchmetal":
        return _fit_torchmetal(fit_cap, cfg)
    if method == "torchmetal-paper":
        return _fit_torchmetal(fit_cap, {**cfg, "scheme": "paper", "specular": "global"})
    if method == "paper-numpy":
        return baselines.paper_scheme_numpy(fit_cap, tol=float(cfg.get("tol", 1e-6)), max_iters=int(cfg.get("max_iters", 100)))
    if method == "adam":
        return baselines.adam_fit(fit_cap, steps=int(cfg.get("adam_steps", 2000)), time_budget=cfg.get("adam_budget"))
    raise ValueError(f"unknown method {method!r}")


def _holdout_scores(fit: FitResult | baselines.BaselineResult, method: str, truth: dict, hold_cap: Capture) -> dict:
    """Held-out PSNR (same torch renderer for every method; torchmetal's own render when it has one)."""
    import torch

    out: dict = {}
    texture, s, alpha = fit.texture, fit.s, fit.alpha
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
    return out


def _parameter_errors(texture, s, alpha, truth: dict) -> dict:
    """Parameter errors against the synthetic truth, and the fitted values."""
    out: dict = {}
    if "texture" in truth:
        tt = to_numpy(truth["texture"])
        out["psnr_texture"] = psnr_or_nan(to_numpy(texture), tt)
    if "s" in truth:
        out["s_rel_err"] = rel_err(to_numpy(s), to_numpy(truth["s"]))
    if "alpha" in truth:
        out["alpha_rel_err"] = rel_err(to_numpy(alpha), to_numpy(truth["alpha"]))
    tex = to_numpy(texture)
    out["texture_sum"] = float(tex.sum())
    out["texture_abs_max"] = float(np.abs(tex).max())
    out["s"] = to_numpy(s).reshape(-1).tolist()[:3] if to_numpy(s).size == 3 else None
    out["alpha"] = to_numpy(alpha).reshape(-1).tolist()[:3] if to_numpy(alpha).size == 3 else None
    return out


def task_prepare_dir(cfg: dict) -> dict:
    """Synthesise a capture and write it as a capture directory (PNG, ``bits``) to ``cfg['dir']``."""
    synth_capture = need("torchmetal.synth", "synth_capture")
    save_capture = need("torchmetal.io.capture_save", "save_capture")
    res = synth_capture(size=int(cfg["size"]), shots=int(cfg["shots"]), seed=int(cfg.get("seed", 0)),
                        noise=float(cfg.get("noise", 0.0)), bits=cfg.get("bits"))
    t0 = time.perf_counter()
    save_capture(res.capture, cfg["dir"], bits=int(cfg.get("bits", 16)))
    disk = sum(p.stat().st_size for p in Path(cfg["dir"]).rglob("*") if p.is_file())
    return {"save_s": time.perf_counter() - t0, "disk_bytes": disk}


def task_load(cfg: dict) -> dict:
    """Time ``load_capture`` of a capture directory; peak memory above the RSS before the load."""
    load_capture = need("torchmetal.io.capture", "load_capture")
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
        fit_material = need("torchmetal.pipeline", "fit_material")
        need("torchmetal.flakes.stage", "flake_stage")
        need("torchmetal.fit", "fit_phong")
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
    flake_stage = need("torchmetal.flakes.stage", "flake_stage")
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

    export_onnx = need("torchmetal.onnx_export", "export_onnx")
    # on use: loads torch (this module imports numpy only)
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
        time_renderer = need("torchmetal.onnx_export", "time_renderer")
        reps = int(cfg.get("repeats", 10))
        t_ort = time_renderer(path, batch=1, repeats=reps, threads=2)
        t_torch = time_renderer(mat, batch=1, repeats=max(3, reps // 2))
        out["timing"] = {"ort_ms": float(t_ort["ms_median"]), "ort_ms_min": float(t_ort["ms_min"]),
                         "torch_ms": float(t_torch["ms_median"]), "torch_ms_min": float(t_torch["ms_min"]),
                         "ort_threads": t_ort.get("threads"), "torch_threads": t_torch.get("threads")}
    return out


def task_zoo(cfg: dict) -> dict:
    """One scene of the zoo (``cfg['scene']``; its CI size when ``cfg['ci']``) fitted with each of
    ``cfg['methods']`` (name → ``fit_material`` options) and scored against the noise-free truth."""
    SCENES, ci_scenes = need("torchmetal.synth.zoo", "SCENES", "ci_scenes")
    run_scene, METHODS = need("torchmetal.bench.zoo", "run_scene", "METHODS")
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
            need(cfg["missing"], "anything")
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
