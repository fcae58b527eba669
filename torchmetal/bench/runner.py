"""``torchmetal bench``: run time against error, torchmetal beside its baselines.

Every measurement runs in a child process (:mod:`torchmetal.bench.worker`), one per
configuration and method, so each peak-memory number belongs to that run alone. ``--quick``
batches a section's jobs into one child instead (one interpreter start, < 60 s in all).

Sections (``--sections``):

========  ==================================================================================
sweep     resolution, shot count, noise and tolerance sweeps; torchmetal, its paper scheme,
          the numpy/scipy paper scheme and per-pixel Adam on the same captures
load      ``load_capture`` of a 1024² × 16-shot 16-bit capture: time and peak memory
fit1024   1024² × 16-shot fit: wall time and peak memory, torchmetal vs the paper's scheme
skip      per-stage times and the skipped list: flake-free, specular-free and full scenes
flakes    flake detection + statistics time on one 1024² shot
onnx      ONNX renderer of a 1024² material: frame time (onnxruntime and torch) and file size
real      leave-one-out PSNR on the real captures in shared/data (when present)
realflakes  cards_blue: flake statistics, MD and PSNR of a left-out shot with and without the
          flake term, detections drawn on a shot (``flakes_<capture>.png``)
zoo       the scene zoo (torchmetal.synth.zoo), one child per scene: default pipeline vs the paper
          scheme against the noise-free truth, oracle dB, s/α and flake errors (``zoo.json``)
command   the whole ``torchmetal fit`` command (fresh process) beside the in-process fit and the numpy
          paper scheme's whole process, held-out error against the clean truth; start-up; peak
          memory (torchmetal.bench.command)
onnx_kinds  ONNX frame time and file size per material kind at 1024² (torchmetal.bench.kinds)
gpu       fit 4096²×16, flake stage, renderer, ONNX CUDA provider where CUDA is present, else one
          line saying why not (torchmetal.bench.gpu)
========  ==================================================================================

Outputs in ``--out`` (default ``bench-results/``): ``results.md``, ``results.csv``,
``results.json``, ``time_vs_error.png`` and ``zoo.json``. Sweep errors are scored against the
noise-free render of the truth (``torchmetal.metrics.psnr``: linear, clipped, peak 1).
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from torchmetal.bench.zoo_section import scene_sizes, zoo_jobs, zoo_markdown, zoo_scene_names

SECTIONS = ("sweep", "load", "fit1024", "skip", "flakes", "onnx", "real", "realflakes", "zoo", "command", "onnx_kinds",
            "gpu")
METHODS = ("torchmetal", "torchmetal-paper", "paper-numpy", "adam")
EQUAL_DB = 0.1  # "equal error": held-out PSNR within this many dB
MiB = 2**20


# ----------------------------------------------------------------------------- plans


@dataclass
class Plan:
    """Sizes and budgets of one benchmark mode."""

    name: str
    base: dict
    resolutions: list[int]
    shot_counts: list[int]
    noises: list[tuple[float, int | None]]
    tols: list[float]
    adam_steps: int
    adam_max_work: int  # Adam runs its full step count only where H·W·N ≤ this
    adam_budget_s: float  # wall-clock cap for Adam elsewhere (None → not run there)
    load_size: int = 1024
    load_shots: int = 16
    fit_size: int = 1024
    fit_shots: int = 16
    skip_size: int = 512
    skip_shots: int = 12
    flake_size: int = 1024
    onnx_size: int = 1024
    real_downsample: int = 1
    real_captures: tuple[str, ...] = ("cards_blue", "uw_gray_sphere")
    real_max_shots: int | None = None
    real_speculars: tuple[str, ...] = ("global", "clustered")
    realflakes_captures: tuple[str, ...] = ("cards_blue",)
    isolate: bool = True
    timeout_s: float = 1800.0
    holdout: int = 2
    paper_axes: tuple[str, ...] = ("resolution", "tol")  # where torchmetal's own paper scheme also runs
    adam_axes: tuple[str, ...] = ("resolution",)  # where Adam runs (it needs minutes per run at 512²)
    threads: int | None = None  # intra-op threads of every child (None: torch's default)
    zoo_ci: bool = False  # zoo scenes at their ci_scenes() size
    zoo_scenes: tuple[str, ...] | None = None  # None: every scene of the zoo
    full_rows: bool = False  # ``--full`` given: the command section's 2048² rows too


def full_plan() -> Plan:
    return Plan(
        name="full",
        base=dict(size=512, shots=12, noise=0.01, bits=None, tol=1e-6),
        resolutions=[256, 512, 1024, 2048],
        shot_counts=[4, 8, 12, 16, 32],
        noises=[(0.0, None), (0.01, None), (0.01, 8), (0.03, None)],
        tols=[1e-3, 1e-4, 1e-6, 1e-8],
        adam_steps=2000,
        adam_max_work=512 * 512 * 12,
        adam_budget_s=0.0,
    )


def quick_plan() -> Plan:
    return Plan(
        name="quick",
        base=dict(size=32, shots=6, noise=0.01, bits=None, tol=1e-6),
        resolutions=[32, 48],
        shot_counts=[6],
        noises=[(0.01, None)],
        tols=[1e-6],
        adam_steps=100,
        adam_max_work=48 * 48 * 8,
        adam_axes=("resolution", "shots", "noise"),
        adam_budget_s=0.0,
        load_size=64, load_shots=4, fit_size=48, fit_shots=4, skip_size=32, skip_shots=6,
        flake_size=64, onnx_size=32, real_downsample=8, real_captures=("uw_gray_sphere",), real_max_shots=5,
        real_speculars=("global",), realflakes_captures=("uw_gray_sphere",), isolate=False, timeout_s=120.0, threads=1,
        zoo_ci=True,  # every scene at its ci_scenes() size: ~25 s in all on 2 cores
    )


def sweep_configs(plan: Plan) -> list[dict]:
    """One-factor-at-a-time sweeps around ``plan.base``; identical configs run once."""
    out: list[dict] = []
    seen: dict[tuple, dict] = {}

    def add(axis: str, **kw) -> None:
        cfg = {**plan.base, **kw}
        key = (cfg["size"], cfg["shots"], cfg["noise"], cfg["bits"], cfg["tol"])
        if key in seen:
            seen[key]["axes"].append(axis)
            return
        cfg["axes"] = [axis]
        seen[key] = cfg
        out.append(cfg)

    for r in plan.resolutions:
        add("resolution", size=r)
    for n in plan.shot_counts:
        add("shots", shots=n)
    for nz, bits in plan.noises:
        add("noise", noise=nz, bits=bits)
    for t in plan.tols:
        add("tol", tol=t)
    return out


# ----------------------------------------------------------------------------- children


THREADS_ENV = "TORCHMETAL_BENCH_THREADS"


def _env(threads: int | None = None) -> dict:
    env = dict(os.environ)
    threads = threads or (int(env[THREADS_ENV]) if env.get(THREADS_ENV) else None)
    if threads:
        for k in (THREADS_ENV, "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[k] = str(threads)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PYTHONWARNINGS", "ignore")
    return env


class Server:
    """One long-lived worker child (``--serve``) that runs jobs one after another.

    Used by ``--quick``: one interpreter start for the whole benchmark. A job that exceeds its
    timeout kills the child; the next job starts a fresh one.
    """

    def __init__(self, threads: int | None = None) -> None:
        self.proc: subprocess.Popen | None = None
        self.threads = threads
        self._buf = b""

    def _start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "torchmetal.bench.worker", "--serve"], env=_env(self.threads),
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        )
        self._buf = b""

    def run(self, task: str, cfg: dict, timeout: float) -> dict:
        import selectors

        from torchmetal.bench.worker import MARKER

        if self.proc is None or self.proc.poll() is not None:
            self._start()
        assert self.proc is not None and self.proc.stdin is not None and self.proc.stdout is not None
        t0 = time.perf_counter()
        try:
            self.proc.stdin.write((json.dumps([task, cfg]) + "\n").encode())
            self.proc.stdin.flush()
        except BrokenPipeError:
            self.close()
            return {"error": "worker process died"}
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        fd = self.proc.stdout.fileno()
        try:
            while True:
                if b"\n" in self._buf:
                    line, self._buf = self._buf.split(b"\n", 1)
                    text = line.decode(errors="replace")
                    if text.startswith(MARKER):
                        r = json.loads(text[len(MARKER):])
                        r.setdefault("child_s", time.perf_counter() - t0)
                        return r
                    continue
                left = timeout - (time.perf_counter() - t0)
                if left <= 0 or not sel.select(left):
                    self.close()
                    return {"error": f"timed out after {timeout:.0f} s"}
                chunk = os.read(fd, 1 << 16)
                if not chunk:
                    self.close()
                    return {"error": "worker process exited"}
                self._buf += chunk
        finally:
            sel.close()

    def close(self) -> None:
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
            for f in (self.proc.stdin, self.proc.stdout):
                if f is not None:
                    f.close()
        self.proc = None


def run_jobs(jobs: list[tuple[str, dict]], *, isolate: bool, timeout: float, log=None,
             server: Server | None = None, threads: int | None = None) -> list[dict]:
    """Run ``[(task, cfg), ...]``: one child process per job (``isolate``), else on ``server``.

    A child that times out or dies yields ``{"error": ...}`` for that job; the rest still run.
    """
    results: list[dict] = []
    own = None
    if not isolate and server is None:
        server = own = Server(threads)
    try:
        for task, cfg in jobs:
            if isolate:
                r = _run_isolated(task, cfg, timeout, threads)
            else:
                r = server.run(task, cfg, timeout)
            results.append(r)
            if log:
                log(task, cfg, r)
    finally:
        if own is not None:
            own.close()
    return results


def _run_isolated(task: str, cfg: dict, timeout: float, threads: int | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="tmbench-") as d:
        res_path = Path(d) / "result.json"
        cmd = [sys.executable, "-m", "torchmetal.bench.worker", task, json.dumps(cfg), str(res_path)]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, env=_env(threads), capture_output=True, text=True, timeout=timeout)
            failure = None if proc.returncode == 0 else f"child exited {proc.returncode}: {proc.stderr.strip()[-300:]}"
        except subprocess.TimeoutExpired:
            failure = f"timed out after {timeout:.0f} s"
        if res_path.exists() and failure is None:
            r = json.loads(res_path.read_text())
            r.setdefault("child_s", time.perf_counter() - t0)
            return r
        return {"error": failure or "child produced no result"}


# ----------------------------------------------------------------------------- formatting


def fmt(x, spec: str = ".3g", none: str = "–") -> str:
    if x is None:
        return none
    if isinstance(x, str):
        try:
            x = float(x)
        except ValueError:
            return x
    if isinstance(x, float) and math.isnan(x):
        return none
    if isinstance(x, float) and math.isinf(x):
        return "∞"
    return format(x, spec)


def md_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def problem(r: dict) -> str | None:
    """'not available: …' / 'error: …' for a failed result, else None."""
    if "not_available" in r:
        return f"not available: {r['not_available']}"
    if "error" in r:
        return f"error: {r['error']}"
    return None


def _num(x) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return v


ERR = "psnr_truth"  # the sweep's primary error: held-out PSNR against the noise-free render of the truth


def primary(r: dict):
    """A result's held-out PSNR against the clean truth, else (old results) against the photos."""
    return r.get(ERR, r.get("psnr_holdout"))


def speed_ratio(tm: dict, base: dict) -> tuple[float | None, str]:
    """Baseline time / torchmetal time when torchmetal's held-out PSNR (against the clean truth,
    :data:`ERR`; the noisy photos where a result lacks it) is equal or better."""
    if problem(tm) or problem(base):
        return None, "n/a"
    p_tm, p_b = _num(primary(tm)), _num(primary(base))
    if math.isnan(p_tm) or math.isnan(p_b):
        return None, "n/a (no PSNR)"
    if p_tm + EQUAL_DB < p_b:
        return None, f"worse error ({p_tm - p_b:+.2f} dB)"
    ratio = _num(base.get("wall_s")) / max(_num(tm.get("wall_s")), 1e-9)
    return ratio, f"{ratio:.1f}×"


# ----------------------------------------------------------------------------- sections


@dataclass
class Bench:
    plan: Plan
    out: Path
    data_dir: Path | None
    verbose: bool = True
    md: list[str] = field(default_factory=list)
    raw: dict = field(default_factory=dict)
    csv_rows: list[dict] = field(default_factory=list)
    tmp: Path | None = None
    server: Server | None = None

    def say(self, text: str = "") -> None:
        if self.verbose:
            print(text, flush=True)

    def section(self, title: str) -> None:
        self.say(f"\n== {title} ==")
        self.md.append(f"\n## {title}\n")
        try:
            la = os.getloadavg()
            self.md.append(f"_load average at start: {la[0]:.2f} {la[1]:.2f} {la[2]:.2f} on {os.cpu_count()} CPUs_\n")
        except OSError:  # pragma: no cover - not on every platform
            pass

    def add(self, text: str) -> None:
        self.say(text)
        self.md.append(text)

    def jobs(self, jobs: list[tuple[str, dict]]) -> list[dict]:
        def log(task, cfg, r):
            msg = problem(r)
            if msg and self.verbose:
                print(f"  [{task}] {msg}", flush=True)

        if not self.plan.isolate and self.server is None:
            self.server = Server(self.plan.threads)
        return run_jobs(jobs, isolate=self.plan.isolate, timeout=self.plan.timeout_s, log=log, server=self.server,
                        threads=self.plan.threads)

    # -- sweep ----------------------------------------------------------------------------

    def _adam_cfg(self, cfg: dict) -> dict | None:
        work = cfg["size"] ** 2 * cfg["shots"]
        if work <= self.plan.adam_max_work:
            return {"adam_steps": self.plan.adam_steps, "adam_budget": None}
        if self.plan.adam_budget_s > 0:
            return {"adam_steps": self.plan.adam_steps, "adam_budget": self.plan.adam_budget_s}
        return None

    def run_sweep(self) -> None:
        self.section("Sweep: time vs error, torchmetal vs baselines (same captures)")
        configs = sweep_configs(self.plan)
        rows: list[dict] = []
        for i, cfg in enumerate(configs):
            path = str(self.tmp / f"sweep{i}.pt")
            label = f"{cfg['size']}² × {cfg['shots']} shots, noise {cfg['noise']}{' 8-bit' if cfg['bits'] == 8 else ''}, tol {cfg['tol']:g}"
            self.say(f"- [{i + 1}/{len(configs)}] {label} ({'/'.join(cfg['axes'])})")
            prep = {"path": path, "size": cfg["size"], "shots": cfg["shots"], "noise": cfg["noise"], "bits": cfg["bits"],
                    "holdout": self.plan.holdout, "seed": 0}
            jobs: list[tuple[str, dict]] = [("prepare", prep)]
            methods = []
            tol_only = cfg["axes"] == ["tol"]
            for m in METHODS:
                if m == "torchmetal-paper" and not set(cfg["axes"]) & set(self.plan.paper_axes):
                    continue
                mc = {"path": path, "method": m, "tol": cfg["tol"], "max_iters": 100}
                if m == "adam":
                    if tol_only:
                        continue  # Adam has no tolerance: the tol sweep is torchmetal vs the paper scheme
                    extra = self._adam_cfg(cfg)
                    if extra is None or not set(cfg["axes"]) & set(self.plan.adam_axes):
                        continue
                    mc.update(extra)
                jobs.append(("method", mc))
                methods.append(m)
            res = self.jobs(jobs)
            Path(path).unlink(missing_ok=True)  # up to ~1 GB at 2048²
            prep_r, method_r = res[0], res[1:]
            if problem(prep_r):
                self.say(f"  capture: {problem(prep_r)}")
                for m in methods:
                    rows.append({**cfg, "method": m, **prep_r})
                continue
            for m, r in zip(methods, method_r):
                rows.append({**cfg, "method": m, **r})
                if not problem(r):
                    self.say(f"  {m:17s} {fmt(r.get('wall_s'), '.2f'):>8s} s  held-out vs truth {fmt(r.get(ERR), '.2f')} dB "
                             f"(vs noisy photos {fmt(r.get('psnr_holdout'), '.2f')})  texture {fmt(r.get('psnr_texture'), '.1f')} dB  "
                             f"peak {fmt(_num(r.get('peak_bytes')) / MiB, '.0f')} MiB  it {r.get('iterations')}")
            if "adam" not in methods and not tol_only and set(cfg["axes"]) & set(self.plan.adam_axes):
                rows.append({**cfg, "method": "adam", "not_run": f"not run: H·W·N > {self.plan.adam_max_work} "
                             f"({self.plan.adam_steps} full-batch steps would take too long on this CPU)"})
        self.raw["sweep"] = rows
        self._sweep_report(rows)

    def _sweep_report(self, rows: list[dict]) -> None:
        header = ["axis", "size", "shots", "noise", "tol", "method", "wall s", "iters", "peak MiB", "peak/capture",
                  "held-out PSNR vs truth dB", "vs noisy photos dB", "truth vs noisy photos dB", "texture PSNR dB", "s rel err", "α rel err", "vs torchmetal"]
        table = []
        by_cfg: dict[tuple, dict[str, dict]] = {}
        for r in rows:
            key = (r["size"], r["shots"], r["noise"], r["bits"], r["tol"])
            by_cfg.setdefault(key, {})[r["method"]] = r
        for r in rows:
            key = (r["size"], r["shots"], r["noise"], r["bits"], r["tol"])
            tm = by_cfg[key].get("torchmetal", {})
            msg = problem(r) or r.get("not_run")
            ratio = "" if r["method"] == "torchmetal" or msg else speed_ratio(tm, r)[1]
            noise = f"{r['noise']:g}" + (" (8-bit)" if r["bits"] == 8 else "")
            base = ["/".join(r["axes"]), f"{r['size']}²", r["shots"], noise, f"{r['tol']:g}", r["method"]]
            if msg:
                table.append(base + [msg] + [""] * (len(header) - len(base) - 1))
                continue
            table.append(base + [
                fmt(r.get("wall_s"), ".2f"), r.get("iterations", ""), fmt(_num(r.get("peak_bytes")) / MiB, ".0f"),
                fmt(r.get("peak_over_capture"), ".2f"), fmt(r.get(ERR), ".2f"), fmt(r.get("psnr_holdout"), ".2f"),
                fmt(r.get("psnr_holdout_truth"), ".2f"),
                fmt(r.get("psnr_texture"), ".2f"), fmt(r.get("s_rel_err"), ".2e"), fmt(r.get("alpha_rel_err"), ".2e"), ratio,
            ])
            self.csv_rows.append({k: (json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in r.items()
                                  if k not in ("traceback", "path")})
        self.add(md_table(header, table))
        self.add("\n*held-out PSNR vs truth*: shots left out of the fit, rendered from the fitted parameters, "
                 "against the noise-free render of the true scene (the primary error; torchmetal.metrics.psnr: "
                 "linear values clipped to [0, 1], peak 1). *vs noisy photos*: the same renders against the "
                 "captured (noisy) images; *truth vs noisy photos*: the true parameters against them (the noise "
                 "ceiling of that column). *vs torchmetal*: baseline wall time / torchmetal wall "
                 f"time when torchmetal's held-out PSNR vs truth is equal (within {EQUAL_DB} dB) or better. "
                 "Peak memory: child-process RSS high-water mark above the RSS before the fit (capture loaded).")
        self._summary(by_cfg)
        self._plot(rows)

    def _summary(self, by_cfg: dict) -> None:
        lines = ["", "### Summary: torchmetal vs baselines (speed ratio at equal-or-better held-out error vs truth)", ""]
        header = ["config", "torchmetal s / dB", "paper scheme (torch) s / dB", "paper-numpy s / dB", "adam s / dB",
                  "speed-up vs paper-numpy", "speed-up vs adam"]
        table = []
        ratios: dict[str, list[float]] = {"paper-numpy": [], "adam": [], "torchmetal-paper": []}
        for key, ms in by_cfg.items():
            size, shots, noise, bits, tol = key
            tm = ms.get("torchmetal", {})

            def cell(m):
                r = ms.get(m)
                if r is None or problem(r) or r.get("not_run"):
                    return "–"
                return f"{fmt(r.get('wall_s'), '.2f')} / {fmt(primary(r), '.1f')}"

            row = [f"{size}²×{shots} n{noise:g}{' 8b' if bits == 8 else ''} tol {tol:g}", cell("torchmetal"),
                   cell("torchmetal-paper"), cell("paper-numpy"), cell("adam")]
            for m in ("paper-numpy", "adam"):
                r = ms.get(m)
                if r is None or r.get("not_run"):
                    row.append("–")
                    continue
                v, txt = speed_ratio(tm, r)
                row.append(txt)
                if v is not None:
                    ratios[m].append(v)
            v, _ = speed_ratio(tm, ms.get("torchmetal-paper", {"error": "missing"}))
            if v is not None:
                ratios["torchmetal-paper"].append(v)
            table.append(row)
        lines.append(md_table(header, table))
        for m, vs in ratios.items():
            if vs:
                geo = math.exp(sum(math.log(v) for v in vs) / len(vs))
                lines.append(f"\n- torchmetal vs {m}: geometric-mean speed-up {geo:.1f}× over {len(vs)} configs "
                             f"at equal-or-better held-out error (min {min(vs):.1f}×, max {max(vs):.1f}×)")
        self.add("\n".join(lines))

    def _plot(self, rows: list[dict]) -> None:
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except Exception as e:  # pragma: no cover - matplotlib is a dependency
            self.add(f"plot: not available: {e}")
            return
        fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
        markers = {"torchmetal": "o", "torchmetal-paper": "s", "paper-numpy": "^", "adam": "x"}
        for m in METHODS:
            pts = [r for r in rows if r["method"] == m and not problem(r) and not r.get("not_run")]
            if not pts:
                continue
            t = [_num(r.get("wall_s")) for r in pts]
            for ax, vals in zip(axes[:2], ([primary(r) for r in pts], [r.get("psnr_texture") for r in pts])):
                ax.scatter(t, [_num(v) for v in vals], marker=markers[m], label=m, s=36)
            for r in pts:
                if "resolution" in r["axes"]:
                    axes[0].annotate(f"{r['size']}", (_num(r.get("wall_s")), _num(primary(r))), fontsize=6,
                                     xytext=(3, 3), textcoords="offset points")
            scal = sorted((r["size"] ** 2 * r["shots"], _num(r.get("wall_s"))) for r in pts
                          if set(r["axes"]) & {"resolution", "shots"})
            if scal:
                axes[2].plot([x for x, _ in scal], [y for _, y in scal], marker=markers[m], label=m)
        titles = ("held-out-shot PSNR vs clean truth (dB) vs wall time", "texture PSNR vs truth (dB) vs wall time",
                  "wall time vs pixels × shots (resolution and shot sweeps)")
        for ax, title in zip(axes, titles):
            ax.set_xscale("log")
            ax.set_title(title, fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
        for ax in axes[:2]:
            ax.set_xlabel("wall time (s, log)")
        axes[2].set_yscale("log")
        axes[2].set_xlabel("pixels × fitted shots (log)")
        axes[2].set_ylabel("wall time (s, log)")
        fig.suptitle(f"torchmetal bench ({self.plan.name}) — every sweep configuration; up and left is better", fontsize=10)
        fig.tight_layout()
        path = self.out / "time_vs_error.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        self.add(f"\n![time vs error](time_vs_error.png)  (`{path}`)")

    # -- load -----------------------------------------------------------------------------

    def run_load(self) -> None:
        p = self.plan
        self.section(f"Capture load: {p.load_size}² × {p.load_shots} shots, 16-bit PNG")
        d = str(self.tmp / "load_capture")
        res = self.jobs([("prepare_dir", {"dir": d, "size": p.load_size, "shots": p.load_shots, "bits": 16}),
                         ("load", {"dir": d})])
        self.raw["load"] = res
        msg = problem(res[0]) or problem(res[1])
        if msg:
            self.add(msg)
            return
        r = res[1]
        self.add(md_table(["capture", "on disk MiB", "load_capture s", "peak MiB", "float32 capture MiB", "peak / capture"], [[
            f"{p.load_size}²×{p.load_shots} 16-bit", fmt(res[0]["disk_bytes"] / MiB, ".1f"), fmt(r["wall_s"], ".3f"),
            fmt(r["peak_bytes"] / MiB, ".0f"), fmt(r["capture_f32_bytes"] / MiB, ".0f"), fmt(r["peak_over_capture"], ".2f")]]))

    # -- fit1024 --------------------------------------------------------------------------

    def run_fit1024(self) -> None:
        p = self.plan
        self.section(f"Phong fit {p.fit_size}² × {p.fit_shots} shots: wall time and peak memory vs the paper's scheme")
        path = str(self.tmp / "fit1024.pt")
        jobs = [("prepare", {"path": path, "size": p.fit_size, "shots": p.fit_shots, "noise": 0.01, "holdout": p.holdout})]
        methods = ["torchmetal", "torchmetal-paper", "paper-numpy"]
        jobs += [("method", {"path": path, "method": m, "tol": 1e-6, "max_iters": 100}) for m in methods]
        res = self.jobs(jobs)
        self.raw["fit1024"] = res
        if problem(res[0]):
            self.add(f"capture: {problem(res[0])}")
            return
        rows = []
        for m, r in zip(methods, res[1:]):
            msg = problem(r)
            if msg:
                rows.append([m, msg, "", "", "", "", "", "", ""])
                continue
            stages = ", ".join(f"{k} {v:.2f}" for k, v in r.get("stage_times", {}).items() if k != "lm_evaluations")
            rows.append([m, fmt(r["wall_s"], ".2f"), r.get("iterations"), fmt(r["peak_bytes"] / MiB, ".0f"),
                         fmt(r["peak_over_capture"], ".2f"), fmt(r.get(ERR), ".2f"), fmt(r.get("psnr_holdout"), ".2f"),
                         fmt(r.get("psnr_texture"), ".2f"), stages])
        cap = _num(res[1].get("capture_f32_bytes")) if not problem(res[1]) else float("nan")
        self.add(md_table(["method", "wall s", "iters", "peak MiB", "peak / capture f32", "held-out PSNR vs truth dB",
                           "vs noisy photos dB", "texture PSNR dB", "stage times (s)"], rows))
        self.add(f"\ncapture float32 size {fmt(cap / MiB, '.0f')} MiB; targets (issue 3): wall ≤ 3 s, peak ≤ 3× capture.")

    # -- skip -----------------------------------------------------------------------------

    def run_skip(self) -> None:
        p = self.plan
        self.section(f"Skip evidence: per-stage times, {p.skip_size}² × {p.skip_shots} shots")
        scenes = [("flake-free", {"flakes": False}), ("specular-free (s=0)", {"flakes": False, "s": 0.0}),
                  ("full (specular + flakes)", {"flakes": True})]
        jobs = []
        for i, (_, kw) in enumerate(scenes):
            path = str(self.tmp / f"skip{i}.pt")
            jobs.append(("prepare", {"path": path, "size": p.skip_size, "shots": p.skip_shots, "noise": 0.01,
                                     "holdout": 0, **kw}))
            jobs.append(("skip", {"path": path}))
        res = self.jobs(jobs)
        self.raw["skip"] = res
        rows = []
        stage_names: list[str] = []
        for i in range(len(scenes)):
            r = res[2 * i + 1]
            if not problem(res[2 * i]) and not problem(r):
                for k in r.get("stage_times", {}):
                    if k not in stage_names:
                        stage_names.append(k)
        for i, (name, _) in enumerate(scenes):
            msg = problem(res[2 * i]) or problem(res[2 * i + 1])
            if msg:
                rows.append([name, msg] + [""] * (len(stage_names) + 1))
                continue
            r = res[2 * i + 1]
            st = r.get("stage_times", {})
            rows.append([name, fmt(r.get("wall_s"), ".3f")] + [fmt(st.get(k), ".4f") for k in stage_names]
                        + ["; ".join(r.get("skipped", [])) or "nothing"])
        self.add(md_table(["scene", "total s"] + [f"{k} s" for k in stage_names] + ["skipped (as reported)"], rows))
        pipes = {r.get("pipeline") for r in res[1::2] if not problem(r)}
        if pipes:
            self.add(f"\npipeline: {', '.join(sorted(str(x) for x in pipes))}")

    # -- flakes ---------------------------------------------------------------------------

    def run_flakes(self) -> None:
        p = self.plan
        self.section(f"Flake detection + statistics on one {p.flake_size}² shot")
        path = str(self.tmp / "flakes.pt")
        dens = 0.003
        res = self.jobs([("prepare", {"path": path, "size": p.flake_size, "shots": 8, "noise": 0.01, "holdout": 0,
                                      "flakes": True, "flake_density": dens}),
                         ("flakes", {"path": path, "repeats": 7, "true_density": dens})])
        self.raw["flakes"] = res
        msg = problem(res[0]) or problem(res[1])
        if msg:
            self.add(msg)
            return
        r = res[1]
        ms = lambda v: fmt(None if v is None else 1e3 * _num(v), ".1f")  # noqa: E731
        self.add(md_table(["shot", "detection+stats best ms", "median ms", "of which detect ms", "statistics ms", "particles",
                           "all 8 shots s", "particles (8 shots)", "density fit / true"], [[
            f"{r['shot_size'][0]}²", ms(r["best_s"]), ms(r["median_s"]), ms(r.get("detect_s")), ms(r.get("statistics_s")),
            fmt(r.get("particles")), fmt(r.get("all_shots_s"), ".2f"), fmt(r.get("all_shots_particles")),
            f"{fmt(r.get('density_fit'), '.4g')} / {fmt(r.get('density_true'), '.4g')}"]]))
        if r.get("all_shots_skipped"):
            self.add(f"\n8-shot stage skipped: {r['all_shots_skipped']}")
        self.add("\ntarget (issue 4): ≤ 200 ms per 1024² shot.")

    # -- onnx -----------------------------------------------------------------------------

    def run_onnx(self) -> None:
        p = self.plan
        self.section(f"ONNX renderer: {p.onnx_size}² material, one light")
        res = self.jobs([("onnx", {"size": p.onnx_size, "repeats": 10 if p.name == "full" else 3})])
        self.raw["onnx"] = res
        msg = problem(res[0])
        if msg:
            self.add(msg)
            return
        r = res[0]
        t = r.get("timing", {})
        if "not_available" in t:
            timing = [f"not available: {t['not_available']}", ""]
        else:
            ort_ms = t.get("ort_ms", t.get("onnxruntime_ms"))
            torch_ms = t.get("torch_ms", t.get("torch_eager_ms"))
            timing = [fmt(ort_ms, ".1f"), fmt(torch_ms, ".1f")]
        self.add(md_table(["material", "file MiB", "files written", "export s", "onnxruntime ms/frame", "torch eager ms/frame"], [[
            f"{r['size']}²{' + flakes' if r.get('flakes') else ''}", fmt(r["file_bytes"] / MiB, ".1f"),
            ", ".join(r.get("files", [])), fmt(r.get("export_s"), ".1f")] + timing]))
        self.add("\ntarget (issue 5): ≤ 33 ms per frame in onnxruntime on this 2-core CPU.")
        extra = {k: v for k, v in t.items() if k not in ("ort_ms", "torch_ms", "onnxruntime_ms", "torch_eager_ms")}
        if extra:
            self.add(f"timer details: {json.dumps(extra)}")

    # -- real -----------------------------------------------------------------------------

    def run_real(self) -> None:
        p = self.plan
        self.section("Real captures: leave-one-out PSNR (fit on all shots but one, render that one)")
        if self.data_dir is None or not self.data_dir.is_dir():
            self.add(f"not available: no shared data directory ({self.data_dir})")
            return
        jobs = []
        names = []
        for name in p.real_captures:
            d = self.data_dir / name
            if (d / "capture.json").is_file():
                jobs.append(("real", {"dir": str(d), "downsample": p.real_downsample, "max_shots": p.real_max_shots,
                                      "speculars": list(p.real_speculars)}))
                names.append(name)
        if not jobs:
            self.add(f"not available: no capture in {self.data_dir}")
            return
        res = self.jobs(jobs)
        self.raw["real"] = res
        rows = []
        for name, r in zip(names, res):
            msg = problem(r)
            if msg:
                rows.append([name, msg, "", "", ""])
                continue
            for spec in ("global", "clustered"):
                v = r.get(spec)
                if not v:
                    continue
                rows.append([f"{name} ({r['size'][0]}×{r['size'][1]}, {r['shots']} shots)", spec, fmt(v["mean"], ".2f"),
                             " ".join(fmt(x, ".2f") for x in v["psnr"]), fmt(v["seconds"], ".1f")])
        self.add(md_table(["capture", "specular", "mean PSNR dB", "per left-out shot (dB)", "seconds"], rows))
        if p.real_downsample > 1 or p.real_max_shots:
            self.add(f"\n(quick mode: captures box-downsampled {p.real_downsample}×, first {p.real_max_shots} shots)")

    def run_realflakes(self) -> None:
        p = self.plan
        self.section("Real captures: flake statistics, MD and PSNR of a left-out shot with and without the flake term")
        dirs = [self.data_dir / name for name in p.realflakes_captures] if self.data_dir is not None else []
        dirs = [d for d in dirs if (d / "capture.json").is_file()]
        if not dirs:
            self.add(f"not available: no capture of {list(p.realflakes_captures)} in {self.data_dir}")
            return
        res = self.jobs([("realflakes", {"dir": str(d), "downsample": p.real_downsample,
                                         "overlay": str(self.out / f"flakes_{d.name}.png")}) for d in dirs])
        self.raw["realflakes"] = res
        rows = []
        for d, r in zip(dirs, res):
            msg = problem(r)
            if msg:
                rows.append([d.name, msg] + [""] * 8)
                continue
            m = r["model"]
            stats = "none (" + str(r["skipped"]) + ")" if m is None else (
                f"density {m['density']:.3g}/px, median area {math.exp(m['area_log_mean']):.2f} px², aspect "
                f"{m['aspect_mean']:.2f}, colour {', '.join(f'{c:.3f}' for c in m['color_mean'])}, tilt σ "
                f"{m['tilt_sigma']:.3f} rad, glint σ {m['glint_sigma']:.3f} rad")
            rows.append([f"{d.name} ({r['size'][0]}×{r['size'][1]}, {r['shots_fitted']} shots fitted, shot {r['heldout']} left out)",
                         str(r["particles"]), stats, fmt(r["md_with"], ".2f"), fmt(r["md_without"], ".2f"),
                         fmt(r["psnr_with"], ".2f"), fmt(r["psnr_without"], ".2f"), fmt(r["fit_s"], ".1f"),
                         fmt(r.get("flake_stage_s"), ".2f"), Path(r.get("overlay", "")).name or "–"])
        self.add(md_table(["capture", "detections", "fitted flake model", "MD with flakes", "MD without", "PSNR with dB",
                           "PSNR without dB", "fit s", "flake stage s", "overlay"], rows))
        self.add("\nMD compares sparkle statistics block by block; PSNR prefers no sparkle at all (new flakes land in new "
                 "places). The model's density is uniform over the sample, so a sample whose glitter covers only part "
                 "of it (cards_blue: grey glitter scales between gold and teal foil) keeps an MD well above the "
                 "synthetic ≤ 4.")

    # -- zoo ------------------------------------------------------------------------------

    def run_zoo(self) -> None:
        p = self.plan
        names = zoo_scene_names(p.zoo_scenes)
        self.section(f"Scene zoo: default pipeline vs the paper scheme against the noise-free truth "
                     f"({len(names)} scenes{', CI sizes' if p.zoo_ci else ''})")
        res = self.jobs(zoo_jobs(p.zoo_ci, names))
        self.raw["zoo"] = [{"scene": n, **r} for n, r in zip(names, res)]
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "zoo.json").write_text(json.dumps(self.raw["zoo"], indent=1, default=str))
        self.add(zoo_markdown(names, res, scene_sizes(p.zoo_ci, names)))

    # -- command, onnx_kinds, gpu (issue 13) ----------------------------------------------

    def _child_json(self, argv: list[str], out: Path) -> dict:
        from torchmetal.bench.command import timed_process

        r = timed_process([sys.executable, "-m", *argv, str(out)], _env(self.plan.threads), self.plan.timeout_s)
        return json.loads(out.read_text()) if "error" not in r else r

    def run_command(self) -> None:
        from torchmetal.bench import command

        self.section("Whole command as the user runs it: torchmetal fit vs the numpy paper process (fresh processes)")
        res = command.run_section(self.plan.name, self.plan.full_rows, self.tmp, _env(self.plan.threads),
                                  self.plan.timeout_s, say=self.say)
        self.raw["command"] = res
        self.add(command.markdown(res))

    def run_onnx_kinds(self) -> None:
        from torchmetal.bench import kinds

        size = self.plan.onnx_size
        self.section(f"ONNX renderer per material kind, {size}²")
        names = kinds.kinds() if self.plan.name == "full" else kinds.QUICK_KINDS
        rows = [{"kind": k, "size": size, **self._child_json(["torchmetal.bench.kinds", k, str(size),
                                                                "10" if self.plan.name == "full" else "2"],
                                                               self.tmp / f"kind{i}.json")} for i, k in enumerate(names)]
        self.raw["onnx_kinds"] = rows
        self.add(kinds.markdown(rows))

    def run_gpu(self) -> None:
        from torchmetal.bench import gpu

        self.section("GPU: fit, flake stage, renderer, ONNX CUDA provider")
        reason = gpu.skip_reason()
        size = 4096 if self.plan.name == "full" else 64
        res = {"skipped": reason} if reason else self._child_json(["torchmetal.bench.gpu", "cuda", str(size), "16"],
                                                                   self.tmp / "gpu.json")
        self.raw["gpu"] = res
        self.add(gpu.markdown(res))

    # -- output ---------------------------------------------------------------------------

    def write(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        head = [f"# torchmetal bench ({self.plan.name})", "",
                f"{time.strftime('%Y-%m-%d %H:%M:%S')} · {_machine(self.plan.threads)}",
                "", "Every run is a child process of its own (``--quick``: one shared child, so its peak-memory "
                "numbers are not isolated). Timings are wall-clock on a shared machine: see the load average "
                "printed under each section."]
        (self.out / "results.md").write_text("\n".join(head + self.md) + "\n")
        (self.out / "results.json").write_text(json.dumps(self.raw, indent=1, default=str))
        if self.csv_rows:
            keys: list[str] = []
            for r in self.csv_rows:
                keys += [k for k in r if k not in keys]
            with open(self.out / "results.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=keys)
                w.writeheader()
                w.writerows(self.csv_rows)


def _machine(threads: int | None = None) -> str:
    import platform

    try:
        import torch

        tv = f"torch {torch.__version__}, {threads or torch.get_num_threads()} intra-op threads per run"
    except ImportError:  # pragma: no cover
        tv = "torch n/a"
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, {tv}"


def default_data_dir() -> Path | None:
    env = os.environ.get("TORCHMETAL_DATA")
    if env:
        return Path(env)
    for cand in (Path(__file__).resolve().parents[3] / "shared" / "data", Path("/work/shared/data")):
        if cand.is_dir():
            return cand
    return None


def run(plan: Plan, out: Path, sections: list[str], *, data_dir: Path | None = None, verbose: bool = True) -> Bench:
    """Run the chosen sections and write the outputs; returns the :class:`Bench` with raw results."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bench = Bench(plan=plan, out=out, data_dir=data_dir, verbose=verbose)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tmbench-data-") as tmp:
        bench.tmp = Path(tmp)
        try:
            for s in sections:
                getattr(bench, f"run_{s}")()
                bench.write()  # keep what is done so far on disk
        finally:
            if bench.server is not None:
                bench.server.close()
    bench.add(f"\n_total bench time {time.perf_counter() - t0:.1f} s_")
    bench.write()
    bench.say(f"\nwrote {out / 'results.md'}, results.csv, results.json, time_vs_error.png, zoo.json")
    return bench
