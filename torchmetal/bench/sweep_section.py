"""The ``sweep`` section of ``torchmetal bench`` (time vs error, torchmetal beside its baselines on
the same captures), as a mixin of :class:`torchmetal.bench.runner.Bench`."""

from __future__ import annotations

import json
import math
from pathlib import Path

from torchmetal.bench.plans import sweep_configs
from torchmetal.bench.tables import EQUAL_DB, ERR, MiB, _num, fmt, md_table, primary, problem, speed_ratio

METHODS = ("torchmetal", "torchmetal-paper", "paper-numpy", "adam")


class SweepSection:
    """``run_sweep`` and its report; needs the Bench's plan, tmp, say/add/jobs, csv_rows, raw, out."""

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
