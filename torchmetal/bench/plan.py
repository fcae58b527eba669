"""The ``plan`` section of ``torchmetal bench``: does the planned shot help more than another?

Random synthetic scenes (seeds 43500 + i, apart from the zoo's and the uncertainty section's): 4 shots,
a global Phong truth. From the fit on them, one more shot is added three ways — the plan's first
(:func:`torchmetal.plan.core.plan_shots`), a random reachable position (the plan's own candidate set, drawn
uniformly), and a fixed one (straight above the sample at the past shots' median distance: the position
a fixed rig or a habit would give) — rendered from the truth with the scene's noise and encoding, refitted,
and scored on held-out views against the clean truth (MSE, linear). Reported: how often planned beats
random, and the medians.

``python -m torchmetal.bench.plan [N]`` runs it alone.
"""

from __future__ import annotations

import math
import sys
import tempfile

import numpy as np

SEED0 = 43500


def _scene(i: int):
    from torchmetal.synth.zoo import Scene

    rng = np.random.default_rng([SEED0, i])
    return Scene(f"plan{i}", size=64, shots=4, held=4, layout=str(rng.choice(["hemisphere", "ring"])),
                 encoding="srgb8", noise=float(rng.choice([0.01, 0.02])), s=float(rng.uniform(0.2, 0.8)),
                 alpha=float(math.exp(rng.uniform(math.log(20.0), math.log(300.0)))), seed=SEED0 + i)


def _with_shot(cap, case, light, inten, camera, rng):
    """The capture with one more shot rendered from the truth (noise, clipping, encoding as the scene's)."""
    import torch

    from torchmetal.io.capture import Capture
    from torchmetal.synth.zoo_render import _encode, decode, render_clean

    img = render_clean(case.truth, light.numpy(), inten.numpy(), camera.numpy())
    lin, sat = decode(_encode(img, case.scene, rng), case.scene.encoding)
    dt = cap.images.dtype
    add = lambda t, x: torch.cat([t, torch.as_tensor(np.asarray(x), dtype=t.dtype).unsqueeze(0)])  # noqa: E731
    return Capture(images=add(cap.images, lin.astype(np.float32)), normals=cap.normals, mask=cap.mask,
                   lights=add(cap.lights, light), intensities=add(cap.intensities, inten), cameras=add(cap.cameras, camera),
                   size=cap.size, saturated=torch.cat([cap.saturated, torch.as_tensor(sat).unsqueeze(0)]),
                   names=[*cap.names, "added"], color_space=cap.color_space).to(dtype=dt)


def _held_mse(cap, case) -> float:
    import torch

    from torchmetal.fit import fit_phong

    fit = fit_phong(cap, specular="global", lobe="phong")
    out = fit.render(torch.as_tensor(case.held_lights, dtype=torch.float32), torch.as_tensor(case.held_intensities, dtype=torch.float32),
                     torch.as_tensor(case.held_cameras, dtype=torch.float32))
    return float(((out.double().clamp(0, 1) - torch.as_tensor(case.clean).double().clamp(0, 1)) ** 2).mean())


def score_scene(i: int, work: str) -> dict:
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
    o = PlanOptions(shots=1)
    plan = plan_shots(scene, o)
    lights, cams, inten, _ = reachable(scene, o)
    rng = np.random.default_rng([SEED0, i, 1])
    j = int(rng.integers(lights.shape[0]))
    top = int(((cams[:, 0] ** 2 + cams[:, 1] ** 2) + 10.0 * (cams[:, 2] - float(cams[:, 2].median())).abs()).argmin())
    plan_j = int(((cams - plan.cameras[0]).abs().sum(-1)).argmin())
    out = {"scene": sc.name, "base": _held_mse(cap, case)}
    for name, k in (("planned", plan_j), ("random", j), ("fixed", top)):
        noise_rng = np.random.default_rng([SEED0, i, 2])  # the same noise draw for each choice
        out[name] = _held_mse(_with_shot(cap, case, lights[k].float(), inten[k].float(), cams[k].float(), noise_rng), case)
    return out


def run_section(n: int = 20, say=print) -> dict:
    rows = []
    for i in range(n):
        with tempfile.TemporaryDirectory(prefix="tm-plan-") as d:
            try:
                rows.append(score_scene(i, d))
            except Exception as e:  # noqa: BLE001 - a bench row records any failure and goes on
                rows.append({"scene": f"plan{i}", "error": f"{type(e).__name__}: {e}".splitlines()[0]})
        r = rows[-1]
        if say is not None and "error" not in r:
            say(f"  {r['scene']}: base {r['base']:.3g}, planned {r['planned']:.3g}, random {r['random']:.3g}, fixed {r['fixed']:.3g}")
    ok = [r for r in rows if "error" not in r]
    med = {k: float(np.median([r[k] for r in ok])) if ok else math.nan for k in ("base", "planned", "random", "fixed")}
    return {"rows": rows, "median": med, "errors": len(rows) - len(ok),
            "beats_random": float(np.mean([r["planned"] < r["random"] for r in ok])) if ok else math.nan,
            "beats_fixed": float(np.mean([r["planned"] < r["fixed"] for r in ok])) if ok else math.nan}


def markdown(res: dict) -> str:
    m = res["median"]
    lines = [f"{len(res['rows'])} random scenes (4 shots + 1; seeds {SEED0}+i), {res['errors']} failed. Held-out MSE against "
             f"the clean truth (linear). Planned beats random on {res['beats_random']:.0%} of scenes, fixed (overhead) on "
             f"{res['beats_fixed']:.0%}.", "",
             "| | 4 shots | + planned | + random | + fixed |", "|---|---:|---:|---:|---:|",
             f"| median held-out MSE | {m['base']:.3g} | {m['planned']:.3g} | {m['random']:.3g} | {m['fixed']:.3g} |"]
    return "\n".join(lines)


if __name__ == "__main__":
    res = run_section(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
    print(markdown(res))
