"""The ``plan`` section of ``torchmetal bench``: does the planned shot help more than another?

Random synthetic scenes (seeds 43500 + i, apart from the zoo's and the uncertainty section's): 4 shots,
a global Phong truth. From the fit on them, one more shot is added three ways — the plan's first
(:func:`torchmetal.plan.core.plan_shots`), random reachable positions (the plan's own candidate set, drawn
uniformly; :data:`RANDOM` of them per scene), and a fixed one (straight above the sample at the past
shots' median distance: the position a fixed rig or a habit would give) — rendered from the truth with the
scene's noise and encoding, refitted, and scored against the clean truth (MSE, linear).

**Held-out views** are :data:`HELD` reachable flash views (the plan's candidate set, drawn at random apart
from the added shots' draw): the renders a phone user would next look at. (The zoo's own held-out shots put
the light 25–80° away from an overhead camera — views no flash photo gives, and not the set the plan's
criterion integrates over; on them the ranking was the same in a check of 3 scenes × 12 shots, but they are
not what this bench is for.)

**Noise.** The added shot's noise is one draw; the differences between good positions are a few per cent
of the held-out MSE, the size of one draw's effect, so each choice is scored as the mean over :data:`DRAWS`
draws, the same draws for every choice (paired). "Planned beats random" counts (scene, random position)
pairs.

**K planned vs 2K random** (:data:`KS`): the plan's first K shots (greedy, one plan) against 2K random reachable
ones (:data:`RANDOM` draws of positions per scene, the scene's value their median) and against K and 2K shots of
a fixed rig of the seed paper's kind (:func:`paper_positions`; the paper asks only that every photo show the
glare), all added at once and refitted; the table gives the median over scenes of each arm's held-out MSE over
the 4 shots'.

**Real captures** (:mod:`torchmetal.bench.plan_real`, leave-shot-in): the plan's ranking of a capture's own
held-back shots against the one that lowers the left-out error most (Spearman ρ); skipped without the shared
data.

``python -m torchmetal.bench.plan [N [SPLITS]]`` runs it alone.
"""

from __future__ import annotations

import math
import sys
import tempfile
from dataclasses import replace

import numpy as np

SEED0 = 43500
HELD = 8
DRAWS = 3
RANDOM = 3
KS = (1, 2)  # K planned shots against 2K random ones
PAPER_RADIUS = 0.25


def _scene(i: int):
    from torchmetal.synth.zoo import Scene

    rng = np.random.default_rng([SEED0, i])
    return Scene(f"plan{i}", size=64, shots=4, held=1, layout=str(rng.choice(["hemisphere", "ring"])),
                 encoding="srgb8", noise=float(rng.choice([0.01, 0.02])), s=float(rng.uniform(0.2, 0.8)),
                 alpha=float(math.exp(rng.uniform(math.log(20.0), math.log(300.0)))), seed=SEED0 + i)


def _with_shot(cap, case, light, inten, camera, rng):
    """The capture with one more shot rendered from the truth (noise, clipping, encoding as the scene's)."""
    from torchmetal.plan.synthetic import take_shots

    return take_shots(cap, case, light.view(1, 4), camera.view(1, 4), inten.view(1, 3), rng, names=["added"])


def held_views(case, lights, cams, inten, rng, n: int = HELD) -> dict:
    """``n`` reachable views drawn with ``rng``: lights, intensities, cameras (n, 4/3/4) float32 and their clean
    renders (n, 3, H, W) from the truth."""
    import torch

    from torchmetal.synth.zoo_render import render_clean

    pick = torch.as_tensor(rng.choice(lights.shape[0], n, replace=False))
    lt, it, cm = lights[pick].float(), inten[pick].float(), cams[pick].float()
    clean = np.stack([render_clean(case.truth, lt[k].numpy(), it[k].numpy(), cm[k].numpy()) for k in range(n)])
    return {"lights": lt, "intensities": it, "cameras": cm, "clean": torch.as_tensor(clean)}


def held_mse(cap, held: dict) -> tuple[float, bool]:
    """Refit ``cap`` (global Phong): (the MSE of its renders of the held-out views against the clean truth,
    whether the refit dropped the specular — its held-out highlight evidence failed: a 10–100× error)."""
    from torchmetal.fit import fit_phong

    fit = fit_phong(cap, specular="global", lobe="phong")
    out = fit.render(held["lights"], held["intensities"], held["cameras"])
    return float(((out.double().clamp(0, 1) - held["clean"].double().clamp(0, 1)) ** 2).mean()), fit.specular == "none"


def paper_positions(scene, n: int, radius: float = PAPER_RADIUS):
    """The seed paper's kind of fixed rig: ``n`` flash shots whose glare lies on a ring of ``radius`` × the sample's
    width around its centre at evenly spaced azimuths (the paper asks only that every photo shows the glare; a fixed
    rig gives the same positions to every sample), the camera at the past shots' median distance looking at the
    centre, the flash at the capture's offset. (lights, cameras, intensities) (n, 4), (n, 4), (n, 3) float64."""
    import torch

    from torchmetal.plan.core import _intensity, camera_frame, flash_offset

    off, _ = flash_offset(scene.lights, scene.cameras)
    dist = float(scene.cameras[:, :3].double().norm(dim=-1).median())
    r = radius * float(max(scene.size))
    ph = 2 * math.pi * torch.arange(n, dtype=torch.float64) / n
    # a flash beside the lens puts the glare near the camera's foot point: the camera above the ring's point
    foot = torch.stack([r * torch.cos(ph), r * torch.sin(ph)], 1)
    z = torch.full((n, 1), math.sqrt(max(dist * dist - r * r, 1e-12)), dtype=torch.float64)
    cam = torch.cat([foot, z], 1)
    rot = camera_frame(cam, torch.zeros(3, dtype=torch.float64))
    light = cam + torch.einsum("nji,j->ni", rot, off)
    ones = torch.ones(n, 1, dtype=torch.float64)
    return torch.cat([light, ones], 1), torch.cat([cam, ones], 1), _intensity(scene, light)


def score_scene(i: int, work: str, options=None, multi: bool = True) -> dict:
    """One scene: held-out MSE of the 4 shots, and (mean over the noise draws) of each added shot; with ``multi``
    also of K planned shots against 2K random reachable ones and K, 2K of the paper's fixed rig (K in :data:`KS`)."""
    import torch

    from torchmetal.fit import fit_phong
    from torchmetal.fit.uncertainty import UncertaintyOptions, estimate_uncertainty
    from torchmetal.io.capture import load_capture
    from torchmetal.plan.core import PlanOptions, plan_shots, reachable
    from torchmetal.plan.run import scene_from_fit
    from torchmetal.plan.synthetic import take_shots
    from torchmetal.synth.zoo import make_case

    sc = _scene(i)
    case = make_case(sc, work)
    cap = load_capture(case.capture_dir)
    fit = fit_phong(cap, specular="global", lobe="phong")
    noise = estimate_uncertainty(fit, cap, UncertaintyOptions(jackknife="off")).noise
    scene = scene_from_fit(fit, cap, noise)
    o = options or PlanOptions(shots=1)
    if multi:
        o = replace(o, shots=max(o.shots, *KS))
    plan = plan_shots(scene, o)
    lights, cams, inten, _ = reachable(scene, o)
    held = held_views(case, lights, cams, inten, np.random.default_rng([SEED0, i, 3]))
    rng = np.random.default_rng([SEED0, i, 1])
    rand = [int(j) for j in rng.choice(lights.shape[0], RANDOM, replace=False)]
    top = int(((cams[:, 0] ** 2 + cams[:, 1] ** 2) + 10.0 * (cams[:, 2] - float(cams[:, 2].median())).abs()).argmin())
    plan_idx = [int(((cams - c).abs().sum(-1)).argmin()) for c in plan.cameras]

    dropped = {"planned": 0, "random": 0, "fixed": 0}
    drop_k: dict = {}

    def added(k: int, name: str) -> float:
        got = [held_mse(_with_shot(cap, case, lights[k].float(), inten[k].float(), cams[k].float(),
                                   np.random.default_rng([SEED0, i, 2, d])), held) for d in range(DRAWS)]
        dropped[name] += sum(g[1] for g in got)
        return float(np.mean([g[0] for g in got]))

    def added_set(lt, cm, it, name: str) -> float:
        """Mean held-out MSE over the draws after adding the shots (n, 4), (n, 4), (n, 3) at once."""
        got = [held_mse(take_shots(cap, case, lt.float(), cm.float(), it.float(), np.random.default_rng([SEED0, i, 4, d])),
                        held) for d in range(DRAWS)]
        drop_k[name] = drop_k.get(name, 0) + sum(g[1] for g in got)
        return float(np.mean([g[0] for g in got]))

    base, base_none = held_mse(cap, held)
    row = {"scene": sc.name, "base": base, "planned": added(plan_idx[0], "planned"),
           "random": [added(j, "random") for j in rand], "fixed": added(top, "fixed"),
           "plan_drop": float(plan.error_drop[0]), "plan_cover": float(plan.cover_gain[0]),
           "base_none": bool(base_none), "dropped": dropped}
    if multi:
        multi_rows = {}
        for k in KS:
            sets = [[int(j) for j in np.random.default_rng([SEED0, i, 5, k, r]).choice(lights.shape[0], 2 * k, replace=False)]
                    for r in range(RANDOM)]
            pl = torch.tensor(plan_idx[:k])
            multi_rows[k] = {
                "planned": added_set(lights[pl], cams[pl], inten[pl], f"planned{k}@{k}"),
                "random2k": [added_set(lights[s], cams[s], inten[s], f"random{2 * k}@{k}") for s in map(torch.tensor, sets)],
                "paper": added_set(*paper_positions(scene, k), f"paper{k}@{k}"),
                "paper2k": added_set(*paper_positions(scene, 2 * k), f"paper{2 * k}@{k}")}
        row["multi"] = multi_rows
        row["multi_dropped"] = drop_k
    return row


def run_section(n: int = 30, say=print, options=None, multi: bool = True, real_splits: int | None = None,
                data_dir=None) -> dict:
    """``n`` scenes; with ``multi`` the K vs 2K table; the real captures' leave-shot-in with ``real_splits`` base sets
    per capture (None: every capture with all 35 when ``n`` ≥ 30, the full bench's count, else yellow_box with 3;
    0: none) under ``data_dir`` (default: the shared-data directory)."""
    rows = []
    for i in range(n):
        with tempfile.TemporaryDirectory(prefix="tm-plan-") as d:
            try:
                rows.append(score_scene(i, d, options, multi))
            except Exception as e:  # noqa: BLE001 - a bench row records any failure and goes on
                rows.append({"scene": f"plan{i}", "error": f"{type(e).__name__}: {e}".splitlines()[0]})
        r = rows[-1]
        if say is not None and "error" not in r:
            say(f"  {r['scene']}: base {r['base']:.3g}, planned {r['planned']:.3g}, random "
                f"{' '.join(f'{v:.3g}' for v in r['random'])}, fixed {r['fixed']:.3g}"
                + "".join(f"; K={k}: planned {m['planned']:.3g}, random 2K {' '.join(f'{v:.3g}' for v in m['random2k'])}, "
                          f"paper {m['paper']:.3g} / 2K {m['paper2k']:.3g}" for k, m in r.get("multi", {}).items()))
    ok = [r for r in rows if "error" not in r]
    med = {k: float(np.median([r[k] for r in ok])) if ok else math.nan for k in ("base", "planned", "fixed")}
    med["random"] = float(np.median([v for r in ok for v in r["random"]])) if ok else math.nan
    drops = {k: sum(r["dropped"][k] for r in ok) for k in ("planned", "random", "fixed")}
    refits = {"planned": DRAWS * len(ok), "random": DRAWS * RANDOM * len(ok), "fixed": DRAWS * len(ok)}
    res = {"rows": rows, "median": med, "errors": len(rows) - len(ok), "dropped": drops, "refits": refits,
           "base_none": sum(r["base_none"] for r in ok),
           "beats_random": float(np.mean([r["planned"] < v for r in ok for v in r["random"]])) if ok else math.nan,
           "beats_random_scenes": float(np.mean([r["planned"] < np.median(r["random"]) for r in ok])) if ok else math.nan,
           "beats_fixed": float(np.mean([r["planned"] < r["fixed"] for r in ok])) if ok else math.nan}
    if multi and ok:
        res["multi"] = multi_summary(ok)
    if real_splits != 0:
        from torchmetal.bench import plan_real

        full = n >= 30
        splits = real_splits or (plan_real.MAX_SPLITS if full else 3)
        res["real"] = plan_real.run_section(data_dir, splits, plan_real.CAPTURES if full else ("yellow_box",), say=say)
    return res


def multi_summary(rows: list[dict]) -> dict:
    """Per K: the median over scenes of each arm's held-out MSE / the 4 shots' (a random arm's scene value: the
    median of its draws of positions), and on how many scenes K planned shots did at least as well as 2K random."""
    out = {}
    for k in rows[0]["multi"]:
        ms = [r["multi"][k] for r in rows]
        base = np.array([r["base"] for r in rows])
        planned = np.array([m["planned"] for m in ms])
        rand = np.array([np.median(m["random2k"]) for m in ms])
        paper, paper2k = np.array([m["paper"] for m in ms]), np.array([m["paper2k"] for m in ms])
        out[int(k)] = {"planned": float(np.median(planned / base)), "random2k": float(np.median(rand / base)),
                       "paper": float(np.median(paper / base)), "paper2k": float(np.median(paper2k / base)),
                       "planned_vs_random2k": float(np.median(planned / rand)),
                       "planned_le_random2k": float(np.mean(planned <= rand)),
                       "planned_le_paper2k": float(np.mean(planned <= paper2k)),
                       "dropped": {name: sum(r["multi_dropped"].get(f"{name}@{k}", 0) for r in rows)
                                   for name in (f"planned{k}", f"random{2 * k}", f"paper{k}", f"paper{2 * k}")},
                       "scenes": len(rows)}
    return out


def markdown(res: dict) -> str:
    m = res["median"]
    lines = [f"{len(res['rows'])} random scenes (4 shots + 1; seeds {SEED0}+i), {res['errors']} failed. Held-out MSE against "
             f"the clean truth (linear) on {HELD} reachable flash views, mean of {DRAWS} paired noise draws. Planned beats a "
             f"random reachable shot in {res['beats_random']:.0%} of (scene, random) pairs ({RANDOM} per scene; beats the "
             f"scene's median random shot on {res['beats_random_scenes']:.0%} of scenes), fixed (overhead) on "
             f"{res['beats_fixed']:.0%}.", "",
             "| | 4 shots | + planned | + random | + fixed |", "|---|---:|---:|---:|---:|",
             f"| median held-out MSE | {m['base']:.3g} | {m['planned']:.3g} | {m['random']:.3g} | {m['fixed']:.3g} |",
             f"| refits without specular | {res['base_none']}/{len(res['rows']) - res['errors']} | "
             + " | ".join(f"{res['dropped'][k]}/{res['refits'][k]}" for k in ("planned", "random", "fixed")) + " |"]
    if res.get("multi"):
        lines += ["", f"K planned shots vs 2K random reachable ({RANDOM} draws of positions per scene, their median) vs the "
                  f"paper's fixed ring (glare at {PAPER_RADIUS:g} × the width from the centre): median over scenes of held-out "
                  "MSE / the 4 shots' (lower is better). Target: K planned ≤ 2K random (median).", "",
                  "| K | K planned | 2K random | K paper | 2K paper | planned / 2K random (median) | scenes planned ≤ 2K random "
                  "| ≤ 2K paper | target met |", "|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
        for k, s in res["multi"].items():
            lines.append(f"| {k} | {s['planned']:.3f} | {s['random2k']:.3f} | {s['paper']:.3f} | {s['paper2k']:.3f} | "
                         f"{s['planned_vs_random2k']:.3f} | {s['planned_le_random2k']:.0%} | {s['planned_le_paper2k']:.0%} | "
                         f"{'yes' if s['planned'] <= s['random2k'] else 'no'} |")
        lines.append("Refits without specular: " + "; ".join(
            ", ".join(f"{name} {v}/{DRAWS * (RANDOM if name.startswith('random') else 1) * s['scenes']}"
                      for name, v in s["dropped"].items()) for s in res["multi"].values()) + ".")
    if res.get("real"):
        from torchmetal.bench import plan_real

        lines += ["", plan_real.markdown(res["real"])]
    return "\n".join(lines)


if __name__ == "__main__":
    res = run_section(int(sys.argv[1]) if len(sys.argv) > 1 else 20, real_splits=int(sys.argv[2]) if len(sys.argv) > 2 else None)
    print(markdown(res))
