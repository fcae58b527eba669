"""The ``onnx_kinds`` section of ``torchmetal bench``: the ONNX renderer per material kind.

Every kind the fit produces — flat or bumpy normals, global or clustered specular, with or
without flakes, and the Blinn and GGX lobes — as a ``size``² material, exported with
:func:`torchmetal.onnx_export.export_onnx` and timed with
:func:`~torchmetal.onnx_export.time_renderer` (one light per frame, onnxruntime CPU) in a fresh
child per kind: ``python -m torchmetal.bench.kinds KIND SIZE REPEATS OUT.json``. A kind slower
than :data:`TARGET_MS` is profiled (onnxruntime's profiler) and its costliest operator types are
reported beside it. Each row also has the process CPU time per frame and the machine's 1-minute
load average: the 2 cores are shared, and wall times grow ~3× at a load of 8–10.
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import replace as dataclasses_replace
from pathlib import Path

from torchmetal.bench.tables import MiB, md_table

TARGET_MS = 20.0  # a 1024² frame of every kind renders within 20 ms on a 2-core CPU
THREADS = 2  # onnxruntime intra-op threads, as the onnx section

#: kind name → (normals, specular, flakes, lobe)
KINDS: dict[str, tuple[str, str, bool, str]] = {
    "flat · global": ("flat", "global", False, "phong"),
    "flat · global · flakes": ("flat", "global", True, "phong"),
    "flat · clustered": ("flat", "clustered", False, "phong"),
    "flat · clustered · flakes": ("flat", "clustered", True, "phong"),
    "bumpy · global": ("bumpy", "global", False, "phong"),
    "bumpy · global · flakes": ("bumpy", "global", True, "phong"),
    "bumpy · clustered": ("bumpy", "clustered", False, "phong"),
    "bumpy · clustered · flakes": ("bumpy", "clustered", True, "phong"),
    "flat · global · blinn": ("flat", "global", False, "blinn"),
    "flat · global · ggx": ("flat", "global", False, "ggx"),
    "flat · global · ggx · one α": ("flat", "global", False, "ggx"),  # what the fit keeps where the channels agree
}


QUICK_KINDS = ["bumpy · clustered · flakes"]  # ``--quick``: the largest graph only (an export costs ~10 s here)

#: kinds of work in progress elsewhere, benchmarked when the Material has the field: name → (field, base kind)
OPTIONAL_KINDS = {"flat · gloss maps": ("gloss_s", "flat · global"),
                  "flat · global · observed flakes": ("observed_flakes", "flat · global · flakes")}


def kinds() -> list[str]:
    """:data:`KINDS`, plus the :data:`OPTIONAL_KINDS` whose Material field exists in this checkout."""
    import dataclasses

    # on use: loads torch (this module imports numpy only)
    from torchmetal.material import Material

    names = {f.name for f in dataclasses.fields(Material)}
    return list(KINDS) + [k for k, (fld, _) in OPTIONAL_KINDS.items() if fld in names]


def _optional(kind: str, mat, size: int, g):
    """The base material of an optional kind with its extra field filled in."""
    import torch
    import torch.nn.functional as F

    if kind == "flat · gloss maps":
        ramp = torch.linspace(0.0, 1.0, size).reshape(1, 1, size).expand(3, size, size)
        return dataclasses_replace(mat, gloss_s=(0.2 + 0.6 * ramp).contiguous(), gloss_alpha=(20.0 + 200.0 * ramp).contiguous())
    # on use: loads torch (this module imports numpy only)
    from torchmetal.flakes.model.observed import ObservedFlakes
    from torchmetal.onnx_export import parity_inputs

    j = max(int(0.003 * size * size), 1)
    light, _, camera = parity_inputs(mat.size, batch=8, seed=2)
    normal = F.normalize(torch.cat([0.15 * torch.randn(j, 2, generator=g), torch.ones(j, 1)], 1), dim=1)
    obs = ObservedFlakes(position=torch.rand(j, 2, generator=g) * size, axes=torch.tensor([[1.5, 1.0]]).expand(j, 2).clone(),
                         angle=torch.rand(j, generator=g) * math.pi, normal=normal, color=torch.full((j, 3), 0.8),
                         probe_lights=light, probe_cameras=camera, shape=(size, size))
    return dataclasses_replace(mat, observed_flakes=obs)


def make_material(kind: str, size: int):
    """A ``size``² :class:`~torchmetal.material.Material` of ``kind`` (see :data:`KINDS`), deterministic."""
    import torch
    import torch.nn.functional as F

    # on use: loads torch (this module imports numpy only)
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.material import Material

    if kind in OPTIONAL_KINDS:
        return _optional(kind, make_material(OPTIONAL_KINDS[kind][1], size), size, torch.Generator().manual_seed(3))
    normals_kind, spec, flakes, lobe = KINDS[kind]
    g = torch.Generator().manual_seed(0)
    texture = 0.1 + 0.5 * torch.rand(3, size, size, generator=g)
    normals = None
    if normals_kind == "bumpy":  # smooth slopes: low-resolution noise upsampled
        slope = F.interpolate(0.2 * torch.randn(1, 2, max(size // 16, 2), max(size // 16, 2), generator=g),
                              size=(size, size), mode="bilinear", align_corners=False)[0]
        normals = F.normalize(torch.cat([-slope, torch.ones(1, size, size)]), dim=0)
    kw = {}
    if spec == "clustered":
        yy = torch.arange(size).reshape(-1, 1).expand(size, size)
        kw = dict(spec_labels=(yy * 3 // size).long(), cluster_s=torch.tensor([[0.5] * 3, [0.2] * 3, [0.9] * 3]),
                  cluster_alpha=torch.tensor([[80.0] * 3, [20.0] * 3, [300.0] * 3]))
    alpha = torch.tensor([100.0] * 3 if kind.endswith("one α") else [80.0, 100.0, 120.0])
    return Material(texture=texture, s=torch.tensor([0.5, 0.45, 0.4]), alpha=alpha,
                    size=(0.1, 0.1), normals=normals, flakes=FlakeModel(density=0.003) if flakes else None,
                    lobe=lobe, **kw)


def profile_ops(path: Path, threads: int = THREADS, frames: int = 5, top: int = 4) -> list[tuple[str, float]]:
    """The ``top`` operator types by mean ms per frame, from onnxruntime's profiler."""
    import onnxruntime as ort

    # on use: loads torch (this module imports numpy only)
    from torchmetal.onnx_export import parity_inputs, session_options

    with tempfile.TemporaryDirectory() as d:
        so = session_options(threads, profile_prefix=str(Path(d) / "prof"))
        sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        meta = sess.get_modelmeta().custom_metadata_map
        size = (float(meta.get("surface_width", 1.0)), float(meta.get("surface_height", 1.0)))
        light, intensity, camera = parity_inputs(size, batch=8, seed=1)
        feeds = {"light": light[1:2].numpy(), "light_intensity": intensity[1:2].numpy(), "camera": camera[1:2].numpy()}
        for _ in range(frames):
            sess.run(None, feeds)
        events = json.loads(Path(sess.end_profiling()).read_text())
    per_op: dict[str, float] = defaultdict(float)
    for e in events:
        if e.get("cat") == "Node" and str(e.get("name", "")).endswith("_kernel_time"):
            per_op[e.get("args", {}).get("op_name", "?")] += float(e.get("dur", 0)) / 1e3 / frames
    return sorted(per_op.items(), key=lambda kv: -kv[1])[:top]


def run_kind(kind: str, size: int, repeats: int = 10) -> dict:
    """Export one kind and time it: file size, export seconds, onnxruntime ms per frame (and ops when slow)."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.onnx_export import export_onnx, time_renderer

    mat = make_material(kind, size)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "renderer.onnx"
        t0 = time.perf_counter()
        export_onnx(mat, path)
        out = {"kind": kind, "size": size, "export_s": time.perf_counter() - t0,
               "file_bytes": sum(p.stat().st_size for p in Path(d).iterdir()),
               "files": sorted(p.name for p in Path(d).iterdir())}
        t = time_renderer(path, batch=1, repeats=repeats, threads=THREADS)
        out.update(ms_median=float(t["ms_median"]), ms_min=float(t["ms_min"]), cpu_ms=float(t["cpu_ms"]),
                   load_1min=float(t["load_1min"]), threads=t.get("threads"))
        if out["ms_median"] > TARGET_MS:
            out["top_ops"] = profile_ops(path)
    return out


def markdown(rows: list[dict]) -> str:
    table = []
    for r in rows:
        if "error" in r or "not_available" in r:
            table.append([r.get("kind", "?"), r.get("error") or r.get("not_available"), "", "", "", "", "", "", ""])
            continue
        ok = "yes" if r["ms_median"] <= TARGET_MS else "no"
        ops = ", ".join(f"{op} {ms:.1f}" for op, ms in r.get("top_ops", [])) or "–"
        table.append([r["kind"], f"{r['file_bytes'] / MiB:.1f}", f"{r['export_s']:.1f}", f"{r['ms_median']:.1f}",
                      f"{r['ms_min']:.1f}", f"{r['cpu_ms']:.1f}", f"{r['load_1min']:.1f}", ok, ops])
    size = next((r["size"] for r in rows if "size" in r), "?")
    return (md_table(["kind (normals · specular · flakes · lobe)", "files MiB", "export s", "onnxruntime ms/frame (median)",
                      "min ms", "CPU ms/frame", "load", f"≤ {TARGET_MS:.0f} ms", "slowest ops, ms/frame (profiled where over)"], table)
            + f"\n\n{size}² material, one light per frame, onnxruntime CPU with {THREADS} intra-op threads, no spinning "
            f"(`torchmetal.onnx_export.session_options`). CPU ms: this process's CPU time per frame, both threads "
            f"together (the work; wall times grow with the load, the 1-minute load average of the machine, "
            f"{os.cpu_count()} cores, shared with other processes).")


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 4 or args[0] not in kinds():
        print(f"usage: python -m torchmetal.bench.kinds KIND SIZE REPEATS OUT.json (KIND one of {kinds()})",
              file=sys.stderr)
        return 2
    try:
        out = run_kind(args[0], int(args[1]), int(args[2]))
    except Exception as e:  # one kind failing is a row, not the end of the bench
        out = {"kind": args[0], "error": f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"}
    Path(args[3]).write_text(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
