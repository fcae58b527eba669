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
real      leave-one-out PSNR on the shared real captures ($TORCHMETAL_SHARED_DATA, when present): fit_phong global /
          clustered, the paper's scheme and the default pipeline (default ≥ paper verdict)
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
robust    every fit option set on the zoo's flake scenes, the sharp-highlight sphere and the shared real
          captures: a material each, wall time against the numpy paper process; the flake stage's share
          of the fit on flake-free captures (torchmetal.bench.robust)
uncertainty  coverage of the clean truth by the fit's 90 % intervals (s, α, texture) on random synthetic
          scenes, and by ``torchmetal intervals``' leave-out ones (flake statistics, estimated normals) on
          torchmetal.synth.random_scenes draws (torchmetal.bench.uncertainty)
plan      the capture plan's next shot against a random reachable and a fixed one: held-out error after the
          refit on random synthetic scenes (torchmetal.bench.plan)
selection the default's choices on randomized scenes with known truth: false positives, misses, the default
          against the best fixed option set and the paper scheme (torchmetal.bench.selection)
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
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from torchmetal.bench import command, gpu, kinds, robust
from torchmetal.bench.children import Server, _env, run_jobs
from torchmetal.bench.command import timed_process
from torchmetal.bench.plans import Plan
from torchmetal.bench.sweep_section import SweepSection
from torchmetal.bench.tables import ERR, MiB, _num, fmt, md_table, problem
from torchmetal.bench.zoo_section import scene_sizes, zoo_jobs, zoo_markdown, zoo_scene_names

SECTIONS = ("sweep", "load", "fit1024", "skip", "flakes", "onnx", "real", "realflakes", "zoo", "command", "onnx_kinds",
            "gpu", "robust", "uncertainty", "selection", "plan")


def _light_fitted(v: dict) -> str:
    """The real table's light-fitted cell: mean PSNR and chroma share, or empty."""
    if v.get("light_fitted_mean") is None:
        return ""
    return f"{fmt(v['light_fitted_mean'], '.2f')}, {fmt(v.get('light_fitted_chroma_mean'), '.1%')}"


#: the real section's score kinds, in table order: (key in a variant's "scores", row label)
SCORE_KINDS = (("in_sample", "own shots"), ("light_fitted", "left out, light refined"),
               ("left_out", "left out, as captured"))


def real_scales_table(r: dict, specs) -> str:
    """One capture's scores side by side (a ``real`` task result): rows = variant × score kind (own shots, left out
    with the light refined to the photo, left out as captured), columns = sRGB PSNR at full size, ¼ and 1/16 (box
    averages), the chroma-artifact share and the extrapolation share (left-out blocks brighter than every fitted
    photo)."""
    rows = []
    for spec in specs:
        scores = (r.get(spec) or {}).get("scores") or {}
        for key, label in SCORE_KINDS:
            v = scores.get(key)
            if v is None:
                continue
            rows.append([spec, label, *(fmt(v["psnr"].get(str(f)), ".2f") for f in (1, 4, 16)),
                         fmt(v.get("chroma"), ".1%"), fmt(v.get("extrapolation"), ".1%")])
    size = r.get("size", ["?", "?"])
    return (f"**{r.get('name', '?')}** ({size[0]}×{size[1]}, {r.get('shots', '?')} shots), sRGB PSNR dB:\n\n"
            + md_table(["fit", "score", "full", "1/4", "1/16", "chroma", "extrapolation (worst shot)"], rows))


# ----------------------------------------------------------------------------- sections


@dataclass
class Bench(SweepSection):
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
        self.add(f"\ncapture float32 size {fmt(cap / MiB, '.0f')} MiB; targets: wall ≤ 3 s, peak ≤ 3× capture.")

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
        self.add("\ntarget: ≤ 200 ms per 1024² shot.")

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
        self.add("\ntarget: ≤ 33 ms per frame in onnxruntime on this 2-core CPU.")
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
                                      "speculars": list(p.real_speculars), "gallery": str(self.out / "real_gallery"),
                                      "gallery_shots": 3}))
                names.append(name)
        if not jobs:
            self.add(f"not available: no capture in {self.data_dir}")
            return
        res = self.jobs(jobs)
        self.raw["real"] = res
        rows = []
        verdicts = []
        galleries: list[str] = []
        for name, r in zip(names, res):
            msg = problem(r)
            if msg:
                rows.append([name, msg, "", "", "", "", "", "", ""])
                continue
            for spec in p.real_speculars:
                v = r.get(spec)
                if not v:
                    continue
                rows.append([f"{name} ({r['size'][0]}×{r['size'][1]}, {r['shots']} shots)", spec, fmt(v["mean"], ".2f"),
                             " ".join(fmt(x, ".2f") for x in v["psnr"]), fmt(v.get("coat_mean"), ".2f"),
                             fmt(v.get("chroma_mean"), ".1%"), _light_fitted(v), fmt(v.get("in_sample"), ".2f"),
                             fmt(v["seconds"], ".1f")])
                galleries += [Path(g).name for g in v.get("gallery", []) + v.get("gallery_own", [])]
            if r.get("default") and r.get("paper"):
                d, q = r["default"]["mean"], r["paper"]["mean"]
                worse = sum(a < b for a, b in zip(r["default"]["psnr"], r["paper"]["psnr"]))
                c = r["default"].get("coat_mean", d)
                verdicts.append(f"{name}: default {d:.2f} dB (coat {c:.2f}), paper {q:.2f} dB → default ≥ paper: "
                                f"{'yes' if d >= q else 'NO'} (mean), coat ≥ paper: {'yes' if c >= q else 'NO'}; "
                                f"worse on {worse} of {len(r['paper']['psnr'])} left-out shots")
        self.add(md_table(["capture", "fit", "mean PSNR dB", "per left-out shot (dB)", "coat PSNR dB", "chroma artifacts",
                           "light fitted: PSNR dB, chroma", "in-sample PSNR dB", "seconds"], rows))
        self.add("\n*fit*: global / clustered are `fit_phong` (refine scheme) with that specular; default is "
                 "`fit_material` as `torchmetal fit` runs it (flakes, lobe, normals, maps and the light decided by it), paper_model "
                 "the same with the paper's model forced (`--normals given --lobe phong --light off`, the default before the lobe, "
                 "the normals and the light were chosen on left-out shots) "
                 "and paper the paper's scheme (`--scheme paper --flakes off --light off`), all rendered by the material's renderer. "
                 "PSNR: linear, peak 1, mask pixels not saturated. *coat PSNR*: the pipeline's material rendered "
                 "without its sparkles (mean over the left-out shots), the zoo's coat score: random sparkle positions "
                 "cost PSNR even where the flake statistics are right. *chroma artifacts*: share of 8×8-px blocks of the "
                 "left-out shots where photo and render differ by a CIELAB chroma distance > 15 (sRGB block means, "
                 "`torchmetal.metrics.chroma_artifact_share`), mean over the shots. *in-sample*: the same fit on every shot, "
                 "scored on those shots (what the model explains at all). *light fitted*: a pipeline's left-out shots "
                 "rendered with each shot's light position fitted to its photo, the material held fixed (a phone "
                 "capture's light positions are off by centimetres; this compares the materials, not them). "
                 "light_off: the default with the capture's lights as given (`--light off`). "
                 "*seconds*: the leave-one-out fits.")
        for r in res:
            if not problem(r):
                self.add("\n" + real_scales_table(r, p.real_speculars))
        self.add("\n*full, 1/4, 1/16*: sRGB PSNR (peak 1, mask pixels not saturated) of photo and render box-averaged "
                 "alike to that fraction of each side (linear averages of the valid pixels, then encoded), mean over the "
                 "shots; *own shots*: the fit on every shot rendering those shots; *chroma*: the chroma-artifact share "
                 "at full size; *extrapolation*: share of 32×32-px blocks where the left-out photo's mean luminance "
                 "exceeds every fitted photo's (a highlight no fitted shot showed), the worst left-out shot's (their mean "
                 "over a whole leave-one-out is 1/N by construction).")
        if galleries:
            self.add(f"\nGallery (default pipeline; photo | render | error ×4, sRGB; `_own_` the fit's own shots): `real_gallery/` — "
                     f"{', '.join(galleries)}")
        for line in verdicts:
            self.add(f"\n{line}")
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

    # -- command, onnx_kinds, gpu: speed of the command, of each material kind, on a GPU --

    def _child_json(self, argv: list[str], out: Path) -> dict:
        r = timed_process([sys.executable, "-m", *argv, str(out)], _env(self.plan.threads), self.plan.timeout_s)
        return json.loads(out.read_text()) if "error" not in r else r

    def run_command(self) -> None:
        self.section("Whole command as the user runs it: torchmetal fit vs the numpy paper process (fresh processes)")
        res = command.run_section(self.plan.name, self.plan.full_rows, self.tmp, _env(self.plan.threads),
                                  self.plan.timeout_s, say=self.say)
        self.raw["command"] = res
        self.add(command.markdown(res))

    def run_onnx_kinds(self) -> None:
        size = self.plan.onnx_size
        self.section(f"ONNX renderer per material kind, {size}²")
        names = kinds.kinds() if self.plan.name == "full" else kinds.QUICK_KINDS
        rows = [{"kind": k, "size": size, **self._child_json(["torchmetal.bench.kinds", k, str(size),
                                                                "10" if self.plan.name == "full" else "2"],
                                                               self.tmp / f"kind{i}.json")} for i, k in enumerate(names)]
        self.raw["onnx_kinds"] = rows
        self.add(kinds.markdown(rows))

    def run_gpu(self) -> None:
        self.section("GPU: fit, flake stage, renderer, ONNX CUDA provider")
        reason = gpu.skip_reason()
        size = 4096 if self.plan.name == "full" else 64
        res = {"skipped": reason} if reason else self._child_json(["torchmetal.bench.gpu", "cuda", str(size), "16"],
                                                                   self.tmp / "gpu.json")
        self.raw["gpu"] = res
        self.add(gpu.markdown(res))

    def run_robust(self) -> None:
        p = self.plan
        self.section("Robustness: every option set ends with a material; the flake stage's share on flake-free captures")
        res = robust.run_section(self.tmp, self.data_dir if p.robust_real else None, _env(p.threads), p.timeout_s,
                                 ci=p.zoo_ci, options=p.robust_options, scenes=p.robust_scenes, share=p.robust_share,
                                 say=self.say)
        self.raw["robust"] = res
        self.add(robust.markdown(res))

    def run_plan(self) -> None:
        # on use: loads torch (torchmetal.bench.plan: the planned shot against a random and a fixed one, issue 43)
        from torchmetal.bench import plan as plan_bench

        self.section("Capture plan: one more shot, planned vs random reachable vs fixed overhead, held-out error")
        res = plan_bench.run_section(30 if self.plan.name == "full" else 4, say=self.say)
        self.raw["plan"] = res
        self.add(plan_bench.markdown(res))

    def run_uncertainty(self) -> None:
        # on use: loads torch (torchmetal.bench.uncertainty: calibration of the fit's intervals, issue 43)
        from torchmetal.bench import uncertainty

        self.section("Uncertainty: coverage of the truth by the fit's 90 % intervals on random synthetic scenes")
        res = uncertainty.run_section(100 if self.plan.name == "full" else 30, say=self.say)
        self.raw["uncertainty"] = res
        self.add(uncertainty.markdown(res))
        # the leave-out intervals: N + 1 fits a scene, about 5 s a normals scene and 25–80 s a 64² flake one (2 CPUs);
        # --quick (CI: the section's plumbing) two normals scenes, tests/bench/test_uncertainty.py the flake part
        full = self.plan.name == "full"
        lo = uncertainty.run_leave_out(40 if full else 2, kinds=uncertainty.LEAVE_OUT_KINDS if full else ("normals",),
                                       say=self.say)
        self.raw["uncertainty_leave_out"] = lo
        self.add(uncertainty.leave_out_markdown(lo))

    def run_selection(self) -> None:
        from torchmetal.bench import selection  # the random scenes' fits (torchmetal.bench.selection)

        seeds = selection.section_seeds(self.plan.name == "quick")
        self.section(f"Selection: the default's choices on {len(seeds)} random scenes, seeds {seeds.start}–{seeds.stop - 1} "
                     f"(torchmetal.synth.random_scenes)")
        if self.plan.threads:
            import torch

            torch.set_num_threads(self.plan.threads)
        res = selection.run_section(seeds, workdir=self.tmp, say=self.say, jsonl=self.out / "selection.jsonl")
        self.raw["selection"] = res["choices"] | {"overall": res["overall"]}
        (self.out / "selection.json").write_text(json.dumps(res, indent=1, default=str))
        self.add(selection.markdown(res))

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
    """The shared real captures (:func:`torchmetal.io.shared_data.shared_data_dir`), None when absent."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.shared_data import shared_data_dir

    d = shared_data_dir()
    return d if d.is_dir() else None


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
