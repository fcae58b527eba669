"""The ``gpu`` section of ``torchmetal bench``: the fit, the flake stage, the renderer and the default
``fit_material`` on CUDA, with no code change (the same calls as on the CPU, on tensors that live on the
device; the pipeline also on the CPU, to compare), and the ONNX renderer with onnxruntime's CUDA provider
where it is installed.

Runs wherever ``torch.cuda.is_available()``; elsewhere :func:`skip_reason` says why in one line.
:func:`run_gpu` takes any device, so the tests run the very same code with ``device="cpu"`` at a
tiny size. In a child: ``python -m torchmetal.bench.gpu DEVICE SIZE SHOTS OUT.json``.
Goal on a datacentre GPU: fit 4096² × 16 ≤ 1 s.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from torchmetal.bench.scoring import psnr_or_nan, rel_err
from torchmetal.bench.tables import md_table

FIT_TARGET_S = 1.0
S_TRUE = (0.6, 0.55, 0.5)
ALPHA_TRUE = (40.0, 60.0, 80.0)


def skip_reason() -> str | None:
    """None where CUDA is usable, else the one-line reason the section skips."""
    try:
        import torch
    except ImportError as e:  # pragma: no cover - torch is a dependency
        return f"torch not importable ({e})"
    if not torch.cuda.is_available():
        return (f"no CUDA device (torch {torch.__version__}, CUDA build {torch.version.cuda or 'none'}: "
                "torch.cuda.is_available() is False)")
    return None


def _sync(device) -> None:
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def device_capture(size: int, shots: int, device, seed: int = 0):
    """A ``size``² × ``shots`` flat global-Phong capture rendered on ``device`` (1 % noise), and its texture.

    The shot geometry comes from :func:`torchmetal.synth.synth_capture` at 16² (it does not depend
    on the resolution); the images are rendered where they are fitted, so 4096² × 16 never crosses
    the bus.
    """
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.capture import Capture
    from torchmetal.phong import phong_render
    from torchmetal.synth import synth_capture

    geo = synth_capture(size=16, shots=shots, seed=seed, layout="ring").capture.to(device)
    g = torch.Generator(device=device).manual_seed(seed)
    texture = 0.1 + 0.5 * torch.rand(3, size, size, generator=g, device=device)
    normals = torch.zeros(3, size, size, device=device)
    normals[2] = 1.0
    s, alpha = torch.tensor(S_TRUE, device=device), torch.tensor(ALPHA_TRUE, device=device)
    images = phong_render(texture, s, alpha, normals, geo.lights, geo.intensities, geo.cameras, geo.size)
    images = images + 0.01 * images.mean() * torch.randn(images.shape, generator=g, device=device)
    cap = Capture(images=images.clamp_min_(0.0), normals=normals, lights=geo.lights, intensities=geo.intensities,
                  cameras=geo.cameras, size=geo.size)
    return cap, texture


def _timed(fn, device, repeats: int) -> tuple[float, object]:
    best, out = math.inf, None
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        out = fn()
        _sync(device)
        best = min(best, time.perf_counter() - t0)
    return best, out


def run_gpu(device: str = "cuda", size: int = 4096, shots: int = 16, flake_size: int = 1024, render_size: int = 1024,
            repeats: int = 2, pipeline_size: int = 512) -> dict:
    """Fit, flake-stage, renderer, ONNX and default-pipeline timings on ``device``; every tensor lives there.

    Each part runs on its own: one that fails is reported as ``{"error": ..., "at": "file:line"}`` and the
    others still run.
    """
    import torch

    from torchmetal.fit import fit_phong

    dev = torch.device(device)
    out: dict = {"device": str(dev), "name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"}
    warm, _ = device_capture(32, shots, dev)
    fit_phong(warm)  # first-call costs (CUDA context, kernels) out of the timing
    held: dict = {}
    parts = (("fit", lambda: _fit_part(dev, size, shots, repeats, held)),
             ("flakes", lambda: _flake_part(dev, flake_size, repeats, held)),
             ("renderer", lambda: _renderer_part(dev, shots, size, render_size, repeats, held)),
             ("onnx", lambda: _onnx_cuda(held["material"])),
             ("pipeline", lambda: _pipeline_part(dev, pipeline_size)))
    for name, part in parts:
        try:
            out[name] = part()
        except Exception as e:  # reported as the part's row; the other parts still run
            out[name] = _failure(e)
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    return out


def _failure(e: Exception) -> dict:
    """The exception in one line, and the innermost torchmetal frame it came from."""
    import traceback

    frames = [f for f in traceback.extract_tb(e.__traceback__) if "torchmetal" in f.filename]
    at = f"{Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else "?"
    return {"error": f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}", "at": at}


def _fit_part(dev, size: int, shots: int, repeats: int, held: dict) -> dict:
    from torchmetal.fit import fit_phong

    cap, texture = device_capture(size, shots, dev)
    fit_s, fit = _timed(lambda: fit_phong(cap, specular="global"), dev, repeats)
    held["fit"] = fit
    return {"size": size, "shots": shots, "seconds": fit_s, "device": str(fit.texture.device),
            "s_err": rel_err(fit.s.cpu().numpy(), S_TRUE), "alpha_err": rel_err(fit.alpha.cpu().numpy(), ALPHA_TRUE),
            "texture_psnr": psnr_or_nan(fit.texture, texture)}


def _flake_part(dev, flake_size: int, repeats: int, held: dict) -> dict:
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.flakes.stage import flake_stage
    from torchmetal.phong import phong_render
    from torchmetal.synth import synth_capture

    syn = synth_capture(size=flake_size, shots=8, seed=1, noise=0.01, flakes=FlakeModel(density=0.003, seed=1))
    held["flake_truth"] = syn.truth["flakes"]
    fcap = syn.capture.to(dev)
    tr = {k: syn.truth[k].to(dev) for k in ("texture", "s", "alpha", "normals")}
    phong = phong_render(tr["texture"], tr["s"], tr["alpha"], tr["normals"], fcap.lights, fcap.intensities,
                         fcap.cameras, fcap.size)
    fl_s, fl = _timed(lambda: flake_stage(fcap, phong), dev, repeats)
    return {"size": flake_size, "shots": 8, "seconds": fl_s, "model": fl.model is not None,
            "density_fit": None if fl.model is None else float(fl.model.density), "density_true": 0.003}


def _renderer_part(dev, shots: int, size: int, render_size: int, repeats: int, held: dict) -> dict:
    import torch

    from torchmetal.fit import fit_phong
    from torchmetal.onnx_export import parity_inputs
    from torchmetal.renderer import MaterialRenderer

    fit = held.get("fit") if render_size == size else None
    if fit is None:
        fit = fit_phong(device_capture(render_size, shots, dev)[0], specular="global")
    mat = fit.to_material()
    if "flake_truth" in held:
        mat = replace(mat, flakes=held["flake_truth"])  # the renderer with its flake field
    held["material"] = mat
    rend = MaterialRenderer(mat).to(dev)
    light, inten, cam = (t.to(dev) for t in parity_inputs(mat.size, batch=8, seed=1))
    with torch.inference_mode():
        rend(light[1:2], inten[1:2], cam[1:2])
        r_s, frame = _timed(lambda: rend(light[1:2], inten[1:2], cam[1:2]), dev, max(repeats, 5))
    return {"size": render_size, "ms_per_frame": 1e3 * r_s, "device": str(frame.device),
            "finite": bool(torch.isfinite(frame).all())}


def _pipeline_part(dev, size: int) -> dict:
    """The default ``fit_material`` (every choice on auto) on a flaky synthetic capture, on ``dev`` and on the
    CPU: its time on each and the largest texture difference between them."""
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.pipeline import fit_material
    from torchmetal.synth import synth_capture

    syn = synth_capture(size=size, shots=8, seed=3, noise=0.01, flakes=FlakeModel(density=0.002, seed=3))
    runs = {}
    for d in dict.fromkeys((str(dev), "cpu")):
        _sync(dev)
        t0 = time.perf_counter()
        res = fit_material(syn.capture.to(d))
        _sync(dev)
        runs[d] = (time.perf_counter() - t0, res.material)
    here, cpu = runs[str(dev)], runs["cpu"]
    return {"size": size, "shots": 8, "seconds": here[0], "cpu_seconds": cpu[0],
            "texture_psnr": psnr_or_nan(here[1].texture.cpu(), syn.truth["texture"]),
            "max_texture_diff_vs_cpu": float((here[1].texture.cpu() - cpu[1].texture).abs().max()),
            "flakes": here[1].flakes is not None, "flakes_cpu": cpu[1].flakes is not None}


def _onnx_cuda(material) -> dict:
    """Export and time with onnxruntime's CUDA provider, or say why not."""
    try:
        import onnxruntime as ort
    except ImportError as e:
        return {"not_available": f"onnxruntime not importable ({e})"}
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        return {"not_available": f"onnxruntime {ort.__version__} has no CUDAExecutionProvider "
                                 f"(providers: {', '.join(ort.get_available_providers())}; onnxruntime-gpu provides it)"}
    # on use: loads torch (this module imports numpy only)
    from torchmetal.onnx_export import export_onnx, time_renderer

    with tempfile.TemporaryDirectory() as d:
        path = export_onnx(material.to("cpu"), Path(d) / "renderer.onnx")
        so = ort.SessionOptions()
        so.log_severity_level = 3
        sess = ort.InferenceSession(str(path), so, providers=["CUDAExecutionProvider", "CPUExecutionProvider"])
        t = time_renderer(sess, batch=1, repeats=20)
        return {"ms_median": float(t["ms_median"]), "ms_min": float(t["ms_min"]), "providers": sess.get_providers(),
                "file_bytes": Path(path).stat().st_size}


def _row(part: dict, label: str, timing, check, target: str = "–") -> list[str]:
    if "error" in part:
        return [label, "error", f"{part['error']} (at {part.get('at', '?')})", target]
    return [label, timing(part), check(part), target]


def markdown(res: dict) -> str:
    if "skipped" in res:
        return f"skipped: {res['skipped']}"
    if "error" in res:
        return f"error: {res['error']}"
    f, fl, r, o, p = (res.get(k, {"error": "not run"}) for k in ("fit", "flakes", "renderer", "onnx", "pipeline"))
    rows = [_row(f, f"fit_phong {f.get('size', '?')}² × {f.get('shots', '?')} (global)", lambda x: f"{x['seconds']:.3f} s",
                 lambda x: f"s err {x['s_err']:.2%}, α err {x['alpha_err']:.2%}, texture PSNR {x['texture_psnr']:.1f} dB",
                 f"≤ {FIT_TARGET_S:.0f} s"),
            _row(fl, f"flake stage {fl.get('size', '?')}² × {fl.get('shots', '?')}", lambda x: f"{x['seconds']:.3f} s",
                 lambda x: f"model {'yes' if x['model'] else 'no'}, density {x['density_fit'] or float('nan'):.4g} / "
                           f"{x['density_true']:.4g}"),
            _row(r, f"MaterialRenderer {r.get('size', '?')}² (torch)", lambda x: f"{x['ms_per_frame']:.2f} ms/frame",
                 lambda x: f"finite {x['finite']}, on {x['device']}"),
            _row(o, "ONNX, onnxruntime CUDA provider",
                 lambda x: x.get("not_available") or f"{x['ms_median']:.2f} ms/frame ({', '.join(x['providers'])})",
                 lambda x: ""),
            _row(p, f"fit_material default {p.get('size', '?')}² × {p.get('shots', '?')} (flakes)",
                 lambda x: f"{x['seconds']:.2f} s (CPU {x['cpu_seconds']:.2f} s)",
                 lambda x: f"texture PSNR {x['texture_psnr']:.1f} dB, |Δ texture| vs CPU {x['max_texture_diff_vs_cpu']:.2g}, "
                           f"flakes {'yes' if x['flakes'] else 'no'} (CPU {'yes' if x['flakes_cpu'] else 'no'})")]
    return md_table(["stage", "time (best)", "error / check", "target"], rows) + f"\n\ndevice: {res['device']} ({res['name']})"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 4:
        print("usage: python -m torchmetal.bench.gpu DEVICE SIZE SHOTS OUT.json", file=sys.stderr)
        return 2
    device, size, shots, path = args[0], int(args[1]), int(args[2]), Path(args[3])
    reason = skip_reason() if device.startswith("cuda") else None
    if reason:
        out = {"skipped": reason}
    else:
        try:
            out = run_gpu(device, size, shots, flake_size=min(1024, size), render_size=min(1024, size),
                          pipeline_size=min(512, size))
        except Exception as e:  # reported as the section's row
            out = _failure(e)
    path.write_text(json.dumps(out, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
