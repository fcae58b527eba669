"""Export a material's renderer to one self-contained ONNX file (docs/design.md §2.4), and time it.

```python
from torchmetal.onnx_export import export_onnx, time_renderer
path = export_onnx(material, "renderer.onnx")          # checker + parity check vs torch
print(time_renderer(path))                              # {'ms_median': ..., 'fps': ..., ...}
```
The file has inputs ``light`` (B, 4), ``light_intensity`` (B, 3), ``camera`` (B, 4), float32,
B dynamic, and the output ``image`` (B, 3, H, W). Parameters are initializers in the file (no
external data), there are no random ops, and it loads with onnxruntime alone (see ``export/``).

Exporter choices (shared/notes/tooling.md §4): the dynamo exporter at opset 20,
``external_data=False``, ``dynamic_shapes`` with one shared batch ``Dim``; its progress lines and
"torchvision is not installed" log records are swallowed (and shown only if the export fails).
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

import torchmetal
from torchmetal.errors import ExportError, MaterialError
from torchmetal.material import Material, load_material
from torchmetal.renderer import MaterialRenderer

if TYPE_CHECKING:
    import onnxruntime

__all__ = ["export_onnx", "verify_onnx", "parity_inputs", "time_renderer", "session_options", "scaled_error", "INPUT_NAMES", "OUTPUT_NAME", "PARITY_TOL"]

INPUT_NAMES = ("light", "light_intensity", "camera")
OUTPUT_NAME = "image"
PARITY_TOL = 1e-4  # max |onnxruntime − torch| on images scaled to [0, 1] by their maximum
_QUIET_LOGGERS = ("torch.onnx", "torch.export", "torch._export", "onnxscript", "torch.fx.experimental.symbolic_shapes")


def _as_renderer(model: Material | MaterialRenderer | str | os.PathLike) -> MaterialRenderer:
    if isinstance(model, MaterialRenderer):
        return model
    if isinstance(model, Material):
        return MaterialRenderer(model)
    if isinstance(model, (str, os.PathLike)) and Path(model).is_dir():
        return MaterialRenderer(load_material(model))
    raise ExportError(f"model: expected a Material, a MaterialRenderer or a material directory, found {type(model).__name__} {model!r}"[:300])


@contextlib.contextmanager
def _quiet():
    """Swallow the exporter's progress prints, warnings and log records; yield the captured text."""
    buf = io.StringIO()
    levels = {}
    for name in _QUIET_LOGGERS:
        lg = logging.getLogger(name)
        levels[name] = lg.level
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            warnings.simplefilter("ignore")
            yield buf
    finally:
        for name, level in levels.items():
            logging.getLogger(name).setLevel(level)


def parity_inputs(size: tuple[float, float] = (1.0, 1.0), *, batch: int = 8, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Lights, intensities and cameras that cover the shading regimes, scaled to the surface.

    The first shots are fixed cases — overhead directional light with an orthographic camera,
    a near point light, a grazing point light, a far point light, a light below the surface,
    a camera near the mirror direction — the rest are random points on hemispheres.

    Returns:
        light (batch, 4), light_intensity (batch, 3), camera (batch, 4), float32.
    """
    ext = max(size)
    fixed_l = [
        [0.0, 0.0, 1.0, 0.0],  # overhead directional
        [0.1 * ext, 0.05 * ext, 0.6 * ext, 1.0],  # near point
        [1.5 * ext, 0.2 * ext, 0.02 * ext, 1.0],  # grazing point
        [20 * ext, -10 * ext, 30 * ext, 1.0],  # far point
        [0.3, 0.2, -0.5, 0.0],  # below the surface (unlit)
        [0.2 * ext, 0.1 * ext, 1.0 * ext, 1.0],  # near-mirror pair with camera below
    ]
    fixed_c = [
        [0.0, 0.0, 1.0, 0.0],  # orthographic overhead
        [-0.1 * ext, -0.05 * ext, 0.8 * ext, 1.0],
        [-1.0 * ext, 0.0, 0.3 * ext, 1.0],
        [0.0, 0.0, 2.0 * ext, 1.0],
        [0.1, 0.0, 1.0, 0.0],
        [-0.2 * ext, -0.1 * ext, 1.0 * ext, 1.0],
    ]
    g = np.random.default_rng(seed)
    light, camera = [], []
    for k in range(batch):
        if k < len(fixed_l):
            light.append(fixed_l[k])
            camera.append(fixed_c[k])
            continue
        for out in (light, camera):
            theta = g.uniform(0.0, 0.48 * math.pi)
            phi = g.uniform(0.0, 2 * math.pi)
            d = [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]
            if g.uniform() < 0.3:
                out.append(d + [0.0])
            else:
                r = ext * g.uniform(0.3, 5.0)
                out.append([r * d[0], r * d[1], r * d[2], 1.0])
    light_t = torch.tensor(light, dtype=torch.float32)
    camera_t = torch.tensor(camera, dtype=torch.float32)
    # irradiance of order 1 at the sample: I ≈ dist² for point lights
    dist2 = (light_t[:, :3] ** 2).sum(1, keepdim=True)
    scale = torch.where(light_t[:, 3:] > 0.5, dist2, torch.ones_like(dist2))
    intensity = scale * torch.tensor(g.uniform(0.5, 1.0, size=(batch, 3)), dtype=torch.float32)
    return light_t, intensity, camera_t


def scaled_error(got: np.ndarray, ref: np.ndarray) -> float:
    """max |got − ref| per image divided by that image's max |ref| (images scaled to [0, 1])."""
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if got.shape != ref.shape:
        return math.inf
    if not np.isfinite(got).all():
        return math.inf
    b = ref.shape[0]
    diff = np.abs(got - ref).reshape(b, -1).max(1)
    scale = np.abs(ref).reshape(b, -1).max(1)
    return float((diff / np.where(scale > 0, scale, 1.0)).max())


def session_options(threads: int | None = None, *, profile_prefix: str | None = None) -> onnxruntime.SessionOptions:
    """onnxruntime CPU session options for the renderer: all graph optimisations, no spinning.

    Worker threads that spin-wait between ops steal the cores they share with other processes:
    on this 2-core machine under a load of ~2.5, a 1024² frame took 2–3× longer with spinning
    on (onnxruntime's default) than off. ``threads``: intra-op threads (None: one per core);
    ``profile_prefix``: turn on onnxruntime's profiler, writing files with that prefix.
    """
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.log_severity_level = 3
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if threads:
        so.intra_op_num_threads = int(threads)
    if profile_prefix is not None:
        so.enable_profiling = True
        so.profile_file_prefix = profile_prefix
    return so


def _session(path_or_bytes, threads: int | None = None):
    import onnxruntime as ort

    so = session_options(threads)
    return ort.InferenceSession(str(path_or_bytes) if isinstance(path_or_bytes, Path) else path_or_bytes, so, providers=["CPUExecutionProvider"])


def verify_onnx(
    path: str | os.PathLike,
    renderer: MaterialRenderer,
    *,
    tol: float = PARITY_TOL,
    batch: int = 8,
    seed: int = 0,
) -> float:
    """Run the file in onnxruntime and the renderer in torch on :func:`parity_inputs`.

    Checks batch ``batch`` and batch 1, and that two runs give identical bytes.

    Returns:
        the largest scaled error. Raises :class:`ExportError` (one line) above ``tol``.
    """
    sess = _session(Path(path))
    light, intensity, camera = parity_inputs(renderer.size, batch=batch, seed=seed)
    worst = 0.0
    for sl in (slice(0, batch), slice(1, 2)):
        feeds = {"light": light[sl].numpy(), "light_intensity": intensity[sl].numpy(), "camera": camera[sl].numpy()}
        got = sess.run([OUTPUT_NAME], feeds)[0]
        again = sess.run([OUTPUT_NAME], feeds)[0]
        if not np.array_equal(got, again):
            raise ExportError(f"{path}: expected identical outputs from run to run, found max difference {np.abs(got - again).max():.3g}")
        with torch.inference_mode():
            ref = renderer(light[sl], intensity[sl], camera[sl]).numpy()
        err = scaled_error(got, ref)
        if not err <= tol:
            raise ExportError(
                f"{path}: expected onnxruntime == torch within {tol:g} (images scaled to [0, 1]), "
                f"found {err:.3g} at batch {got.shape[0] if got.ndim else '?'} (shape {got.shape} vs {ref.shape})"
            )
        worst = max(worst, err)
    return worst


def export_onnx(
    model: Material | MaterialRenderer | str | os.PathLike,
    path: str | os.PathLike,
    *,
    opset: int = 20,
    check: bool = True,
    flakes: bool = True,
    tol: float = PARITY_TOL,
) -> Path:
    """Export the renderer of ``model`` to ONNX at ``path`` (written atomically).

    Args:
        model: a :class:`Material`, a :class:`MaterialRenderer` or a material directory.
        path: output ``.onnx`` file; parent directories are created.
        opset: ONNX opset (default 20; 18 or newer).
        check: after ``onnx.checker`` (always run), verify onnxruntime against torch on
            :func:`parity_inputs` (batch 8 and 1, identical run to run) within ``tol``.
        flakes: include sparkles when ``model`` is a material (a renderer keeps its own choice).
        tol: parity tolerance on [0, 1]-scaled images.

    Returns:
        the path. Raises :class:`ExportError` (one line) when export, checker or parity fail.
    """
    import onnx

    renderer = _export_renderer(model, flakes)
    if not isinstance(opset, int) or opset < 18:
        raise ExportError(f"opset: expected an integer >= 18 (dynamo exporter), found {opset!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    was_training = renderer.training
    renderer.eval()
    light, intensity, camera = parity_inputs(renderer.size, batch=2)
    batch = torch.export.Dim("B", min=1, max=1 << 20)
    dyn = {"light": {0: batch}, "light_intensity": {0: batch}, "camera": {0: batch}}
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        proto = _dynamo_export(renderer, (light, intensity, camera), dyn, opset).model_proto
        _annotate(proto, renderer, opset)
        try:
            onnx.checker.check_model(proto, full_check=True)
        except Exception as e:
            raise ExportError(f"onnx.checker: expected a valid model, found {str(e).strip().splitlines()[0][:300]}") from None
        _check_interface(proto)
        onnx.save_model(proto, str(tmp), save_as_external_data=False)
        if check:
            verify_onnx(tmp, renderer, tol=tol)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        renderer.train(was_training)
    return path


def _export_renderer(model: Material | MaterialRenderer | str | os.PathLike, flakes: bool) -> MaterialRenderer:
    """The renderer :func:`export_onnx` exports (:class:`ExportError` when ``model`` names none)."""
    if isinstance(model, Material):
        return MaterialRenderer(model, flakes=flakes)
    try:
        return _as_renderer(model)
    except MaterialError as e:
        raise ExportError(f"model: {e}") from None


def _dynamo_export(renderer: MaterialRenderer, inputs: tuple[torch.Tensor, ...], dyn: dict, opset: int):
    """The ONNX program of ``renderer`` traced on ``inputs`` by the dynamo exporter (its log kept quiet;
    a failure raises :class:`ExportError` in one line)."""
    with _quiet() as log:
        try:
            program = torch.onnx.export(
                renderer, inputs, dynamo=True, opset_version=opset,
                input_names=list(INPUT_NAMES), output_names=[OUTPUT_NAME], dynamic_shapes=dyn,
                external_data=False, verbose=False, report=False, optimize=True,
            )
        except Exception as e:  # the exporter raises many types; report one line
            first = (str(e).strip().splitlines() or [type(e).__name__])[0]
            tail = " | ".join(x for x in log.getvalue().strip().splitlines()[-2:])
            raise ExportError(f"torch.onnx.export: expected a successful dynamo export, found {type(e).__name__}: {first[:300]}" + (f" ({tail[:200]})" if tail else "")) from None
    return program


def _annotate(proto, renderer: MaterialRenderer, opset: int) -> None:
    proto.producer_name = "torchmetal"
    proto.producer_version = torchmetal.__version__
    proto.doc_string = (
        "torchmetal material renderer: inputs light (B,4), light_intensity (B,3), camera (B,4) float32 "
        f"(homogeneous, w=1 position, w=0 direction); output image (B,3,{renderer.height},{renderer.width}) linear radiance."
    )
    meta = {
        "format": "torchmetal-renderer",
        "version": "1",
        "height": str(renderer.height),
        "width": str(renderer.width),
        "surface_width": repr(renderer.size[0]),
        "surface_height": repr(renderer.size[1]),
        "flat_normals": str(renderer.flat).lower(),
        "clustered_specular": str(renderer.clustered).lower(),
        "gloss_maps": str(getattr(renderer, "mapped", False)).lower(),
        "lobe": renderer.lobe,
        "flakes": "none" if not renderer.has_flakes else ("dense" if renderer.flake_pixels < 0 else f"sparse:{renderer.flake_pixels}"),
        "opset": str(opset),
    }
    del proto.metadata_props[:]
    for k, v in meta.items():
        p = proto.metadata_props.add()
        p.key, p.value = k, v


def _check_interface(proto) -> None:
    """The docs/design.md §2.4 names, ranks and dtypes, with a symbolic batch dimension."""
    import onnx

    want = {"light": 4, "light_intensity": 3, "camera": 4}
    got = {i.name: i for i in proto.graph.input}
    for name, c in want.items():
        if name not in got:
            raise ExportError(f"interface: expected input {name!r}, found {sorted(got)}")
        t = got[name].type.tensor_type
        dims = [d.dim_value if d.HasField("dim_value") else d.dim_param for d in t.shape.dim]
        if t.elem_type != onnx.TensorProto.FLOAT or len(dims) != 2 or dims[1] != c or not isinstance(dims[0], str):
            raise ExportError(f"interface: expected {name} float32 (B, {c}) with symbolic B, found elem_type {t.elem_type} dims {dims}")
    outs = [o.name for o in proto.graph.output]
    if outs != [OUTPUT_NAME]:
        raise ExportError(f"interface: expected one output 'image', found {outs}")
    if any(n.op_type.startswith("Random") for n in proto.graph.node):
        raise ExportError("interface: expected no random ops, found " + ", ".join(sorted({n.op_type for n in proto.graph.node if n.op_type.startswith("Random")})))


def time_renderer(
    renderer: str | os.PathLike | onnxruntime.InferenceSession | MaterialRenderer | Material,
    *,
    batch: int = 1,
    repeats: int = 20,
    warmup: int = 3,
    threads: int | None = None,
    seed: int = 1,
) -> dict:
    """Frame time of a renderer for ``batch`` random lights (one light per frame by default).

    Args:
        renderer: an ONNX file path, an ``onnxruntime.InferenceSession``, or a torch
            :class:`MaterialRenderer` / material (timed in eager mode under ``inference_mode``).
        batch: shots per call; repeats: timed calls; warmup: untimed calls first.
        threads: onnxruntime intra-op threads (None: onnxruntime's default, one per core);
            for torch, ``torch.set_num_threads`` during the timing.

    Returns:
        dict with backend, height, width, batch, repeats, threads, ms_median, ms_min, ms_mean,
        cpu_ms (this process's CPU time per call, all threads: the work, nearly independent of
        other processes on the cores), load_1min (the 1-minute load average after the timing),
        ms_per_shot (median / batch), fps (shots per second at the median).
    """
    if repeats < 1 or batch < 1:
        raise ExportError(f"time_renderer: expected repeats >= 1 and batch >= 1, found {repeats}, {batch}")
    if isinstance(renderer, Material):
        renderer = MaterialRenderer(renderer)
    if isinstance(renderer, torch.nn.Module):
        backend, used_threads, shape, times, cpu = _time_torch(renderer, batch, repeats, warmup, threads, seed)
    else:
        backend, used_threads, shape, times, cpu = _time_onnxruntime(renderer, batch, repeats, warmup, threads, seed)
    med = statistics.median(times) * 1e3
    return {
        "backend": backend,
        "height": int(shape[2]),
        "width": int(shape[3]),
        "batch": batch,
        "repeats": repeats,
        "threads": int(used_threads),
        "ms_median": med,
        "ms_min": min(times) * 1e3,
        "ms_mean": statistics.fmean(times) * 1e3,
        "cpu_ms": cpu / repeats * 1e3,
        "load_1min": os.getloadavg()[0],
        "ms_per_shot": med / batch,
        "fps": 1e3 * batch / med,
    }


def _timed_calls(call, warmup: int, repeats: int) -> tuple[list[float], float, object]:
    """``warmup`` untimed calls, then ``repeats`` timed ones: their wall times (s), the process's CPU time
    over them (s) and the last output."""
    for _ in range(warmup):
        out = call()
    times = []
    cpu0 = time.process_time()
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = call()
        times.append(time.perf_counter() - t0)
    cpu = time.process_time() - cpu0
    return times, cpu, out


def _time_torch(renderer: torch.nn.Module, batch: int, repeats: int, warmup: int, threads: int | None,
                seed: int) -> tuple[str, int, tuple, list[float], float]:
    """:func:`time_renderer` of a torch module in eager mode: backend, threads, output shape, times, CPU time."""
    size = getattr(renderer, "size", (1.0, 1.0))
    light, intensity, camera = parity_inputs(size, batch=max(batch, 8), seed=seed)
    sl = slice(1, 1 + batch) if batch <= 7 else slice(0, batch)  # a near point light first
    args = (light[sl], intensity[sl], camera[sl])
    old = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        with torch.inference_mode():
            times, cpu, out = _timed_calls(lambda: renderer(*args), warmup, repeats)
    finally:
        torch.set_num_threads(old)
    return "torch-eager", threads or old, tuple(out.shape), times, cpu


def _time_onnxruntime(renderer, batch: int, repeats: int, warmup: int, threads: int | None,
                      seed: int) -> tuple[str, int, tuple, list[float], float]:
    """:func:`time_renderer` of an ONNX file or session: backend, threads, output shape, times, CPU time."""
    import onnxruntime as ort

    sess = renderer if isinstance(renderer, ort.InferenceSession) else _session(Path(renderer), threads)
    shape_out = sess.get_outputs()[0].shape
    size = (1.0, 1.0)
    meta = sess.get_modelmeta().custom_metadata_map
    if "surface_width" in meta:
        size = (float(meta["surface_width"]), float(meta["surface_height"]))
    light, intensity, camera = parity_inputs(size, batch=max(batch, 8), seed=seed)
    sl = slice(1, 1 + batch) if batch <= 7 else slice(0, batch)
    feeds = {"light": light[sl].numpy(), "light_intensity": intensity[sl].numpy(), "camera": camera[sl].numpy()}
    times, cpu, out = _timed_calls(lambda: sess.run(None, feeds)[0], warmup, repeats)
    opts = sess.get_session_options()
    used_threads = threads or opts.intra_op_num_threads or os.cpu_count()
    return "onnxruntime-cpu", used_threads, tuple(out.shape) if shape_out else (), times, cpu
