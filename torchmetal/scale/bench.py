"""Scale benchmarks (not tests): ``python -m torchmetal.scale.bench [--quick] [-o results.json]``.

1. fit-many throughput: captures per minute on the local engine with 1 and 2 workers.
2. Tiled vs in-memory fit of a ``--size``² × 8 capture: times, peak memory, largest relative
   difference of s, α and texture.
3. A ``--big``² × 8 capture fitted tiled (``--tile``): time and peak memory; the in-memory fit's
   peak is measured too when ``--big-in-memory`` (it needs ~49 bytes per pixel per shot: 8192² × 8 ≈ 25 GiB).

Each fit runs in its own process (``python -m torchmetal.scale.bench _fit ...``), so peak memory
is that process's alone: VmHWM (peak resident set, which counts the pages of memory-mapped files
the process has touched) and the peak of RssAnon (its own allocations), sampled every 20 ms.
Captures are generated tile by tile by :func:`write_plane_capture` (docs/design.md §2.2's model rendered
band by band into .npy memmaps), so generating them needs no more memory than a fit.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

SHOTS = 8


def write_plane_capture(path: str | os.PathLike, size: int, shots: int = SHOTS, *, seed: int = 0, noise: float = 0.002,
                        band: int = 256) -> Path:
    """A flat sample (0.1 × 0.1) under a ring of ``shots`` point lights, rendered with docs/design.md §2.2's
    Phong model (s = 0.6, α = 40/60/80) band by band into ``images/*.npy`` (H, W, 3) float32."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.geometry import grid_shading_terms, pixel_axes

    path = Path(path)
    (path / "images").mkdir(parents=True, exist_ok=True)
    ang = np.arange(shots) * 2 * np.pi / shots
    lights = [[0.04 * math.cos(a), 0.04 * math.sin(a), 0.25, 1.0] for a in ang]
    cams = [[0.002 * math.cos(a + 1), 0.002 * math.sin(a + 1), 0.3, 1.0] for a in ang]
    inten = [[0.06, 0.06, 0.06]] * shots
    meta = {"format": "torchmetal-capture", "version": 1, "color_space": "linear",
            "surface": {"width": 0.1, "height": 0.1},
            "shots": [{"image": f"images/{k:03d}.npy", "light": lights[k], "light_intensity": inten[k], "camera": cams[k]}
                      for k in range(shots)]}
    out = [np.lib.format.open_memmap(path / f"images/{k:03d}.npy", mode="w+", dtype=np.float32, shape=(size, size, 3))
           for k in range(shots)]
    f32 = torch.float32
    L, C = torch.tensor(lights, dtype=f32), torch.tensor(cams, dtype=f32)
    E = torch.tensor(inten, dtype=f32).view(shots, 3, 1, 1)
    s = torch.tensor([0.6, 0.6, 0.6], dtype=f32).view(1, 3, 1, 1)
    alpha = torch.tensor([40.0, 60.0, 80.0], dtype=f32).view(1, 3, 1, 1)
    for r0 in range(0, size, band):
        rows = slice(r0, min(size, r0 + band))
        x, y = pixel_axes(size, size, (0.1, 0.1), rows=rows, dtype=torch.float32)
        ii, jj = torch.meshgrid(torch.arange(rows.start, rows.stop, dtype=torch.float32),
                                torch.arange(size, dtype=torch.float32), indexing="ij")
        u, v = ii / size, jj / size
        tex = torch.stack([0.35 + 0.15 * torch.sin(23 * u) * torch.cos(17 * v), 0.3 + 0.1 * torch.cos(31 * u + 5 * v),
                           0.25 + 0.1 * torch.sin(13 * v - 7 * u)])
        nl, q, d2 = grid_shading_terms(L, C, x, y)
        lit = (nl > 0).unsqueeze(1)
        rv = (1 - q).clamp_min(0).unsqueeze(1)
        img = E / d2.unsqueeze(1) * (tex.unsqueeze(0) * nl.clamp_min(0).unsqueeze(1) + lit * s * rv.pow(alpha))
        g = torch.Generator().manual_seed(seed * 1_000_003 + r0)
        img = (img + noise * float(img.mean()) * torch.randn(img.shape, generator=g, dtype=f32)).clamp_min(0)
        for k in range(shots):
            out[k][rows] = img[k].permute(1, 2, 0).float().numpy()
    for m in out:
        m.flush()
    (path / "capture.json").write_text(json.dumps(meta, indent=1))
    return path


# ------------------------------------------------------------------ one measured fit per process


def _peak_sampler():
    peak = {"anon_kb": 0}
    stop = threading.Event()

    def sample():
        while not stop.is_set():
            try:
                for line in Path("/proc/self/status").read_text().splitlines():
                    if line.startswith("RssAnon:"):
                        peak["anon_kb"] = max(peak["anon_kb"], int(line.split()[1]))
            except OSError:
                pass
            stop.wait(0.02)

    t = threading.Thread(target=sample, daemon=True)
    t.start()
    return peak, stop


def _hwm_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    return 0


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and its finished children (tile workers)."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _fit_child(argv: list[str]) -> int:
    """``_fit MODE CAPTURE OUT [TILE]``: fit, save s/α/texture to OUT, print measurements (JSON)."""
    import torch

    mode, capture, out = argv[0], argv[1], Path(argv[2])
    peak, stop = _peak_sampler()
    t0, c0 = time.perf_counter(), _cpu_s()
    if mode == "tiled":
        # on use: loads torch (this module imports numpy only)
        from torchmetal.scale.tiled import fit_tiled

        res = fit_tiled(capture, tile=int(argv[3]), scratch=out / "scratch")
    else:
        # on use: loads torch (this module imports numpy only)
        from torchmetal.fit import fit_phong
        from torchmetal.io.capture import load_capture

        res = fit_phong(load_capture(capture))
    dt, cpu = time.perf_counter() - t0, _cpu_s() - c0
    stop.set()
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "s_alpha.npy", torch.stack([res.s.double(), res.alpha.double()]).numpy())
    if mode != "tiled":
        np.save(out / "scratch_texture.npy", res.texture.permute(1, 2, 0).numpy())
    print(json.dumps({"mode": mode, "time_s": dt, "cpu_s": cpu, "load_average_1min": os.getloadavg()[0],
                      "peak_rss_mib": _hwm_kb() / 1024, "peak_anon_mib": peak["anon_kb"] / 1024,
                      "rmse": res.rmse, "iterations": dict(res.iterations), "tiled": getattr(res, "tiled", None),
                      "stage_s": {k: round(v, 2) for k, v in res.stage_times.items()}}))
    return 0


def measure_fit(mode: str, capture: Path, out: Path, tile: int | None = None, timeout: float | None = None) -> dict:
    cmd = [sys.executable, "-m", "torchmetal.scale.bench", "_fit", mode, str(capture), str(out)] + ([str(tile)] if tile else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        return {"mode": mode, "error": (proc.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _texture(out: Path, mode: str) -> np.ndarray:
    return np.load(out / ("scratch/texture.npy" if mode == "tiled" else "scratch_texture.npy"), mmap_mode="r")


def compare(mem_out: Path, tiled_out: Path) -> dict:
    """Largest relative differences tiled vs in-memory (s, α, texture; texture band by band)."""
    a, b = np.load(mem_out / "s_alpha.npy"), np.load(tiled_out / "s_alpha.npy")
    rel = lambda x, y: float(np.max(np.abs(x.astype(np.float64) - y) / np.maximum(np.abs(y.astype(np.float64)), 1e-12)))  # noqa: E731
    ta, tb = _texture(mem_out, "memory"), _texture(tiled_out, "tiled")
    tex = max(rel(tb[r:r + 512], ta[r:r + 512]) for r in range(0, ta.shape[0], 512))
    return {"s_rel": rel(b[0], a[0]), "alpha_rel": rel(b[1], a[1]), "texture_rel": tex}


def bench_fit_many(root: Path, n: int, size: int, engines: tuple[str, ...] = ("local",)) -> dict:
    """Captures per minute of ``fit-many`` (``--flakes off``, 1 torch thread per fit) with 1 and 2 workers
    per engine (Ray: a local cluster started per run, its start-up included); CPU seconds of this process
    and its reaped children (the local pool's workers; Ray's workers are not counted fully)."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.scale.fit_many import fit_many

    caps = [write_plane_capture(root / f"many{k}", size, seed=k) for k in range(n)]
    out = {}
    for engine in engines:
        for workers in (1, 2):
            t0, c0 = time.perf_counter(), _cpu_s()
            recs = fit_many(caps, root / f"out-{engine}{workers}", fit_args=["--flakes", "off"], engine=engine,
                            workers=workers, threads=1, progress=False, resume=False)
            dt = time.perf_counter() - t0
            key = f"workers_{workers}" if engine == "local" else f"{engine}_workers_{workers}"
            out[key] = {"engine": engine, "captures": n, "size": size, "seconds": dt, "cpu_s": _cpu_s() - c0,
                        "captures_per_min": 60 * n / dt, "ok": sum(r.status == "ok" for r in recs),
                        "load_average_1min": os.getloadavg()[0]}  # other work on the machine
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "_fit":
        return _fit_child(argv[1:])
    p = argparse.ArgumentParser(prog="python -m torchmetal.scale.bench", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    p.add_argument("--many", type=int, default=6, help="captures for the throughput run")
    p.add_argument("--many-size", type=int, default=128)
    p.add_argument("--engines", nargs="+", default=["local"], choices=["local", "ray"], help="fit-many engines to time")
    p.add_argument("--size", type=int, default=2048, help="tiled vs in-memory comparison size")
    p.add_argument("--big", type=int, default=8192, help="tiled-only size (0: skip)")
    p.add_argument("--big-in-memory", action="store_true", help="also fit the big capture in memory")
    p.add_argument("--tile", type=int, default=1024)
    p.add_argument("--skip", nargs="*", default=[], choices=["many", "compare", "big"])
    p.add_argument("--workdir", default=None, help="where captures go (default: a temporary folder)")
    p.add_argument("-o", "--output", default=None, help="write the results as JSON")
    args = p.parse_args(argv)
    if args.quick:
        args.many, args.many_size, args.size, args.big, args.tile = 2, 48, 256, 512, 64
    root = Path(args.workdir or tempfile.mkdtemp(prefix="torchmetal-scale-bench-"))
    root.mkdir(parents=True, exist_ok=True)
    results: dict = {"cpu_count": os.cpu_count(), "tile": args.tile, "load_average_at_start": os.getloadavg()[0]}

    def report():
        print(json.dumps(results, indent=1), flush=True)
        if args.output:
            Path(args.output).write_text(json.dumps(results, indent=1))

    if "many" not in args.skip:
        results["fit_many"] = bench_fit_many(root, args.many, args.many_size, tuple(args.engines))
        report()
    if "compare" not in args.skip:
        t0 = time.perf_counter()
        cap = write_plane_capture(root / f"cap{args.size}", args.size)
        gen = time.perf_counter() - t0
        mem = measure_fit("memory", cap, root / "mem")
        til = measure_fit("tiled", cap, root / "til", args.tile)
        results["compare"] = {"size": args.size, "shots": SHOTS, "generate_s": gen, "memory": mem, "tiled": til,
                              **(compare(root / "mem", root / "til") if "error" not in mem and "error" not in til else {})}
        report()
    if args.big and "big" not in args.skip:
        t0 = time.perf_counter()
        cap = write_plane_capture(root / f"cap{args.big}", args.big)
        big = {"size": args.big, "shots": SHOTS, "generate_s": time.perf_counter() - t0,
               "tiled": measure_fit("tiled", cap, root / "bigtil", args.tile)}
        if args.big_in_memory:
            big["memory"] = measure_fit("memory", cap, root / "bigmem")
            if "error" not in big["memory"] and "error" not in big["tiled"]:
                big.update(compare(root / "bigmem", root / "bigtil"))
        results["big"] = big
        report()
    return 0


if __name__ == "__main__":
    sys.exit(main())
