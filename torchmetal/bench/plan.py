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

``python -m torchmetal.bench.plan [N]`` runs it alone.
"""

from __future__ import annotations

import math
import sys
import tempfile

import numpy as np

SEED0 = 43500
HELD = 8
DRAWS = 3
RANDOM = 3


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


def score_scene(i: int, work: str, options=None) -> dict:
    """One scene: held-out MSE of the 4 shots, and (mean over the noise draws) of each added shot."""
    from torchmetal.fit import fit_phong
    from torchmetal.fit.uncertainty import UncertaintyOptions, estimate_uncertainty
    from torchmetal.io.capture import load_capture
    from torchmetal.plan.core import PlanOptions, plan_shots, reachable
    from torchmetal.plan.run import scene_from_fit
    from torchmetal.synth.zoo import make_case

    sc = _scene(i)
    case = make_case(sc, work)
    cap = load_capture(case.capture_dir)
    fit = fit_phong(cap, specular="global", lobe="phong")
    noise = estimate_uncertainty(fit, cap, UncertaintyOptions(jackknife="off")).noise
    scene = scene_from_fit(fit, cap, noise)
    o = options or PlanOptions(shots=1)
    plan = plan_shots(scene, o)
    lights, cams, inten, _ = reachable(scene, o)
    held = held_views(case, lights, cams, inten, np.random.default_rng([SEED0, i, 3]))
    rng = np.random.default_rng([SEED0, i, 1])
    rand = [int(j) for j in rng.choice(lights.shape[0], RANDOM, replace=False)]
    top = int(((cams[:, 0] ** 2 + cams[:, 1] ** 2) + 10.0 * (cams[:, 2] - float(cams[:, 2].median())).abs()).argmin())
    plan_j = int(((cams - plan.cameras[0]).abs().sum(-1)).argmin())

    dropped = {"planned": 0, "random": 0, "fixed": 0}

    def added(k: int, name: str) -> float:
        got = [held_mse(_with_shot(cap, case, lights[k].float(), inten[k].float(), cams[k].float(),
                                   np.random.default_rng([SEED0, i, 2, d])), held) for d in range(DRAWS)]
        dropped[name] += sum(g[1] for g in got)
        return float(np.mean([g[0] for g in got]))

    base, base_none = held_mse(cap, held)
    return {"scene": sc.name, "base": base, "planned": added(plan_j, "planned"), "random": [added(j, "random") for j in rand],
            "fixed": added(top, "fixed"), "plan_drop": float(plan.error_drop[0]), "plan_cover": float(plan.cover_gain[0]),
            "base_none": bool(base_none), "dropped": dropped}


def run_section(n: int = 30, say=print, options=None) -> dict:
    rows = []
    for i in range(n):
        with tempfile.TemporaryDirectory(prefix="tm-plan-") as d:
            try:
                rows.append(score_scene(i, d, options))
            except Exception as e:  # noqa: BLE001 - a bench row records any failure and goes on
                rows.append({"scene": f"plan{i}", "error": f"{type(e).__name__}: {e}".splitlines()[0]})
        r = rows[-1]
        if say is not None and "error" not in r:
            say(f"  {r['scene']}: base {r['base']:.3g}, planned {r['planned']:.3g}, random "
                f"{' '.join(f'{v:.3g}' for v in r['random'])}, fixed {r['fixed']:.3g}")
    ok = [r for r in rows if "error" not in r]
    med = {k: float(np.median([r[k] for r in ok])) if ok else math.nan for k in ("base", "planned", "fixed")}
    med["random"] = float(np.median([v for r in ok for v in r["random"]])) if ok else math.nan
    drops = {k: sum(r["dropped"][k] for r in ok) for k in ("planned", "random", "fixed")}
    refits = {"planned": DRAWS * len(ok), "random": DRAWS * RANDOM * len(ok), "fixed": DRAWS * len(ok)}
    return {"rows": rows, "median": med, "errors": len(rows) - len(ok), "dropped": drops, "refits": refits,
            "base_none": sum(r["base_none"] for r in ok),
            "beats_random": float(np.mean([r["planned"] < v for r in ok for v in r["random"]])) if ok else math.nan,
            "beats_random_scenes": float(np.mean([r["planned"] < np.median(r["random"]) for r in ok])) if ok else math.nan,
            "beats_fixed": float(np.mean([r["planned"] < r["fixed"] for r in ok])) if ok else math.nan}


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
    return "\n".join(lines)


if __name__ == "__main__":
    res = run_section(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
    print(markdown(res))
