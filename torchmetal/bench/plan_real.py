"""Leave-shot-in on the shared real captures: does the plan's ranking of which shot to add next agree with the
shot that actually lowers the left-out error most?

For a capture of N shots (downsampled to at most :data:`SIDE` pixels a side, its shots as they are): a base of
:data:`BASE` shots is fitted (``fit_phong``, global Phong specular: the plan's own quick fit); every other shot
is a candidate. The plan scores each candidate at its real position as the one next shot
(:func:`torchmetal.plan.core.score_shots`: the I-optimal drop of the expected held-out variance plus the
coverage term). The truth of the ranking: the base plus each candidate is refitted, and the candidate's gain is
the mean over the *other* candidates of log(MSE after / MSE of the base fit) on their photos (valid pixels:
inside the mask, unsaturated) — the error on shots the refit did not see, each normalised by the base fit's
error on it, so candidates are compared on the same footing. Spearman ρ between the plan's score and −gain,
per base set (every base set for ≤ :data:`MAX_SPLITS` of them, else a seeded draw), then summarised per
capture: mean and median ρ, how often the plan's first is the actual best (against chance 1/candidates), and
the actual gain of the plan's pick against the mean candidate's and the best's. A diagnostic column: ρ of
the same criterion integrated over the held-back shots' own views (the set the actual gain averages over)
instead of the reachable set's.

Captures: :data:`CAPTURES` under the shared-data directory; a capture that is absent is reported as skipped.
Nothing is copied from the shared data. ``python -m torchmetal.bench.plan_real [SPLITS]`` runs it alone.
"""

from __future__ import annotations

import itertools
import math
import sys
from pathlib import Path

import numpy as np

CAPTURES = ("cards_blue", "yellow_box", "uw_gray_sphere", "bath_tile")
SIDE = 64
BASE = 3
MAX_SPLITS = 35
SEED = 43700


def spearman(x, y) -> float:
    """Spearman's ρ (average ranks for ties); NaN where either side is constant."""
    from scipy.stats import rankdata

    rx, ry = rankdata(np.asarray(x, float)), rankdata(np.asarray(y, float))
    if np.ptp(rx) == 0 or np.ptp(ry) == 0:
        return math.nan
    return float(np.corrcoef(rx, ry)[0, 1])


def shot_mse(fit, cap, k: int) -> float:
    """MSE of ``fit``'s render of shot ``k`` of ``cap`` against its photo over valid pixels (linear, clipped to [0, 1])."""
    from torchmetal.bench.scoring import valid_mask

    one = cap.subset([k])
    out = fit.render(one.lights, one.intensities, one.cameras).double().clamp(0, 1)
    ref = one.images.double().clamp(0, 1)
    v = valid_mask(one)
    return float(((out - ref) ** 2)[v].mean())


def splits(n: int, base: int, limit: int, seed: int) -> list[tuple[int, ...]]:
    """Base sets: all ``base``-subsets of range(n) when there are at most ``limit``, else ``limit`` drawn (seeded)."""
    every = list(itertools.combinations(range(n), base))
    if len(every) <= limit:
        return every
    rng = np.random.default_rng(seed)
    return [every[i] for i in sorted(rng.choice(len(every), limit, replace=False))]


def score_split(cap, base: tuple[int, ...], options=None) -> dict:
    """One base set: the plan's scores and the actual gains of every other shot of ``cap``."""
    import torch

    from torchmetal.fit import fit_phong
    from torchmetal.fit.uncertainty import UncertaintyOptions, estimate_uncertainty
    from torchmetal.plan.core import PlanOptions, score_shots
    from torchmetal.plan.run import scene_from_fit

    cand = [k for k in range(cap.num_shots) if k not in base]
    sub = cap.subset(list(base))
    fit = fit_phong(sub, specular="global", lobe="phong")
    noise = estimate_uncertainty(fit, sub, UncertaintyOptions(jackknife="off")).noise
    scene = scene_from_fit(fit, sub, noise)
    idx = torch.tensor(cand)
    shots = (cap.lights[idx].double(), cap.cameras[idx].double(), cap.intensities[idx].double())
    sc = score_shots(scene, *shots, options or PlanOptions())
    # a diagnostic: the criterion integrated over the capture's own held-back views (the set the truth averages
    # over) instead of the reachable set's
    own = score_shots(scene, *shots, options or PlanOptions(), reference=shots)["score"].tolist()
    base_err = {k: shot_mse(fit, cap, k) for k in cand}
    gain = []
    for c in cand:
        refit = fit_phong(cap.subset([*base, c]), specular="global", lobe="phong")
        gain.append(float(np.mean([math.log(max(shot_mse(refit, cap, k), 1e-300) / max(base_err[k], 1e-300))
                                   for k in cand if k != c])))
    score = sc["score"].tolist()
    return {"base": list(base), "candidates": cand, "score": score, "gain": gain,
            "rho": spearman(score, [-g for g in gain]), "rho_own_views": spearman(own, [-g for g in gain]),
            "specular": fit.specular,
            "top_is_best": int(np.argmax(score)) == int(np.argmin(gain)),
            "pick_gain": gain[int(np.argmax(score))], "best_gain": min(gain), "mean_gain": float(np.mean(gain))}


def run_capture(path: Path, max_splits: int = MAX_SPLITS, options=None) -> dict:
    from torchmetal.io.capture import load_capture

    cap = load_capture(path)
    cap = cap.downsampled(max(1, math.ceil(max(cap.height, cap.width) / SIDE)))
    rows = [score_split(cap, b, options) for b in splits(cap.num_shots, BASE, max_splits, SEED)]
    rho = [r["rho"] for r in rows if not math.isnan(r["rho"])]
    own = [r["rho_own_views"] for r in rows if not math.isnan(r["rho_own_views"])]
    return {"capture": path.name, "shots": cap.num_shots, "side": max(cap.height, cap.width), "splits": len(rows),
            "candidates": cap.num_shots - BASE, "rho_mean": float(np.mean(rho)) if rho else math.nan,
            "rho_median": float(np.median(rho)) if rho else math.nan,
            "rho_positive": float(np.mean([v > 0 for v in rho])) if rho else math.nan,
            "rho_own_views_mean": float(np.mean(own)) if own else math.nan,
            "top_is_best": float(np.mean([r["top_is_best"] for r in rows])),
            "pick_gain": float(np.mean([r["pick_gain"] for r in rows])),
            "mean_gain": float(np.mean([r["mean_gain"] for r in rows])),
            "best_gain": float(np.mean([r["best_gain"] for r in rows])),
            "no_specular": sum(r["specular"] == "none" for r in rows), "rows": rows}


def run_section(data_dir: Path | None = None, max_splits: int = MAX_SPLITS, captures=CAPTURES, say=print) -> dict:
    """Every capture of ``captures`` found under ``data_dir`` (default: the shared-data directory)."""
    from torchmetal.io.shared_data import shared_data_dir

    root = Path(data_dir) if data_dir is not None else shared_data_dir()
    out = {}
    for name in captures:
        d = root / name
        if not (d / "capture.json").is_file():
            out[name] = {"capture": name, "skipped": f"not available: no capture at {d}"}
            continue
        try:
            out[name] = run_capture(d, max_splits)
        except Exception as e:  # noqa: BLE001 - a bench row records any failure and goes on
            out[name] = {"capture": name, "error": f"{type(e).__name__}: {e}".splitlines()[0]}
        r = out[name]
        if say is not None and "rho_mean" in r:
            say(f"  {name}: {r['splits']} base sets, mean ρ {r['rho_mean']:+.2f}, plan's first is the best in "
                f"{r['top_is_best']:.0%} (chance {1 / r['candidates']:.0%})")
    return out


def markdown(res: dict) -> str:
    lines = [f"Leave-shot-in on the shared captures (downsampled to ≤ {SIDE} px a side, `fit_phong` global Phong): from "
             f"{BASE} shots, the plan's score of each other shot against its actual gain (mean log MSE ratio on the other "
             "candidates' photos after the refit; negative = better). Spearman ρ per base set.", "",
             "| capture | shots | base sets | candidates | mean ρ | median ρ | ρ > 0 | plan's first is best (chance) | "
             "gain: plan's pick / mean / best | base fits without specular | mean ρ, own views as reference |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
    for name, r in res.items():
        if "rho_mean" not in r:
            lines.append(f"| {name} | {r.get('skipped') or r.get('error')} | | | | | | | | | |")
            continue
        lines.append(f"| {name} | {r['shots']} | {r['splits']} | {r['candidates']} | {r['rho_mean']:+.2f} | "
                     f"{r['rho_median']:+.2f} | {r['rho_positive']:.0%} | {r['top_is_best']:.0%} ({1 / r['candidates']:.0%}) | "
                     f"{r['pick_gain']:+.3f} / {r['mean_gain']:+.3f} / {r['best_gain']:+.3f} | {r['no_specular']}/{r['splits']} | "
                     f"{r['rho_own_views_mean']:+.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    res = run_section(max_splits=int(sys.argv[1]) if len(sys.argv) > 1 else MAX_SPLITS)
    print(markdown(res))
