"""The ``uncertainty`` section of ``torchmetal bench``: are the fit's 90 % intervals calibrated?

Randomised synthetic scenes (:mod:`torchmetal.synth.zoo`'s generator, seeds 43000 + i, apart from the
zoo's): size, shot count, noise, layout, encoding, s and α drawn per scene, the truth the fit's own
model (global Phong, no flakes). Each is fitted (``fit_phong``, global specular, Phong lobe) and
:func:`torchmetal.fit.uncertainty.estimate_uncertainty` gives its intervals; the table counts how often
the clean truth falls inside, per parameter kind: s and α (one per channel and scene) and the texture
(every pixel). Target: 85–95 % each.

``python -m torchmetal.bench.uncertainty [N [MAX_PIXELS]]`` runs it alone (MAX_PIXELS 1024: the strided pass).
"""

from __future__ import annotations

import math
import sys
import tempfile
import time

import numpy as np

SEED0 = 43000  # the zoo's seeds run 0–18; issue 43's scenes start here
LAYOUTS = ("hemisphere", "ring")
ENCODINGS = ("srgb8", "linear16")


def random_scene(i: int, size: int | None = None):
    """Scene i of the calibration set (a :class:`~torchmetal.synth.zoo.Scene`, global Phong truth)."""
    from torchmetal.synth.zoo import Scene

    rng = np.random.default_rng([SEED0, i])
    return Scene(f"calib{i}", size=int(size or rng.choice([64, 96])), shots=int(rng.integers(4, 11)), held=1,
                 layout=str(rng.choice(LAYOUTS)), encoding=str(rng.choice(ENCODINGS)),
                 noise=float(rng.choice([0.005, 0.01, 0.02])), s=float(rng.uniform(0.2, 0.8)),
                 alpha=float(math.exp(rng.uniform(math.log(20.0), math.log(300.0)))), seed=SEED0 + i)


def score_scene(scene, work: str, level: float = 0.9, max_pixels: int | None = None) -> dict:
    """Fit one scene and count its truths inside the intervals. ``max_pixels``: the curvature pass's pixel
    budget (None: the default, 2^16, above every scene here; 2^10 forces stride 2–3 on them, the case of a
    1 MP capture under the default: the grid's sums scaled to the full pixel count)."""
    import torch

    from torchmetal.fit import fit_phong
    from torchmetal.fit.uncertainty import UncertaintyOptions, estimate_uncertainty
    from torchmetal.io.capture import load_capture
    from torchmetal.synth.zoo import make_case

    case = make_case(scene, work)
    cap = load_capture(case.capture_dir)
    t0 = time.perf_counter()
    fit = fit_phong(cap, specular="global", lobe="phong")
    t1 = time.perf_counter()
    o = UncertaintyOptions(level=level) if max_pixels is None else UncertaintyOptions(level=level, max_pixels=max_pixels)
    u = estimate_uncertainty(fit, cap, o)
    t2 = time.perf_counter()
    s_in = ((u.s_lo[0] <= scene.s) & (scene.s <= u.s_hi[0])).tolist()
    a_in = ((u.alpha_lo[0] <= scene.alpha) & (scene.alpha <= u.alpha_hi[0])).tolist()
    truth = torch.as_tensor(case.truth.texture)
    lo, hi = u.texture_interval(fit.texture.double())
    fin = torch.isfinite(u.texture_std)
    inside = (truth >= lo) & (truth <= hi) & fin
    return {"scene": scene.name, "size": scene.size, "shots": scene.shots, "noise": scene.noise,
            "encoding": scene.encoding, "layout": scene.layout, "s": scene.s, "alpha": scene.alpha,
            "s_fit": u.s[0].tolist(), "alpha_fit": u.alpha[0].tolist(), "s_pm": ((u.s_hi - u.s_lo)[0] / 2).tolist(),
            "alpha_pm": ((u.alpha_hi - u.alpha_lo)[0] / 2).tolist(), "method": u.method[0],
            "s_in": s_in, "alpha_in": a_in, "texture_in": int(inside.sum()), "texture_n": int(fin.sum()),
            "stride": u.stride, "fit_s": t1 - t0, "uncertainty_s": t2 - t1}


def run_section(n: int = 100, *, size: int | None = None, level: float = 0.9, max_pixels: int | None = None,
                say=print) -> dict:
    """Score ``n`` random scenes; returns {"rows": [...], "coverage": {kind: fraction}, "n": {kind: count}}."""
    rows = []
    for i in range(n):
        with tempfile.TemporaryDirectory(prefix="tm-calib-") as d:
            try:
                rows.append(score_scene(random_scene(i, size), d, level, max_pixels))
            except Exception as e:  # noqa: BLE001 - a bench row records any failure and goes on
                rows.append({"scene": f"calib{i}", "error": f"{type(e).__name__}: {e}".splitlines()[0]})
        if say is not None and "error" not in rows[-1]:
            r = rows[-1]
            say(f"  {r['scene']}: {r['shots']} shots {r['size']}² {r['encoding']} noise {r['noise']}: s in {sum(r['s_in'])}/3, "
                f"α in {sum(r['alpha_in'])}/3, texture {r['texture_in'] / max(1, r['texture_n']):.1%}")
    ok = [r for r in rows if "error" not in r]
    seen = [r for r in ok if "unseen" not in r["method"]]  # a fit that saw no highlight reports s in [0, ∞): counted apart
    cov = {"s": _frac([v for r in seen for v in r["s_in"]]), "alpha": _frac([v for r in seen for v in r["alpha_in"]]),
           "texture": sum(r["texture_in"] for r in ok) / max(1, sum(r["texture_n"] for r in ok)),
           "texture_scene_median": float(np.median([r["texture_in"] / max(1, r["texture_n"]) for r in ok])) if ok else math.nan}
    counts = {"s": 3 * len(seen), "alpha": 3 * len(seen), "texture": sum(r["texture_n"] for r in ok)}
    strides = sorted({r["stride"] for r in ok})
    return {"rows": rows, "coverage": cov, "n": counts, "level": level, "errors": len(rows) - len(ok),
            "unseen": len(ok) - len(seen), "strides": strides, "max_pixels": max_pixels}


def _frac(v: list) -> float:
    return float(np.mean(v)) if v else math.nan


def markdown(res: dict) -> str:
    """The coverage table (per parameter kind) and the per-scene rows."""
    lvl = res["level"]
    lines = [f"Coverage of the clean truth by the {lvl:.0%} intervals (target {lvl - 0.05:.0%}–{lvl + 0.05:.0%}); "
             f"{len(res['rows'])} random scenes (seeds {SEED0}+i), {res['errors']} failed; s and α over the scenes whose "
             f"fit saw a highlight ({res['unseen']} did not: their s in [0, ∞), α anywhere, not counted). Curvature pass "
             f"stride {', '.join(map(str, res.get('strides', [])))} (pixel budget {res.get('max_pixels') or 'default'}).", "",
             "| parameter | intervals | truth inside |", "|---|---:|---:|"]
    for k, name in (("s", "s (per channel)"), ("alpha", "α (per channel)"), ("texture", "texture (per pixel)")):
        lines.append(f"| {name} | {res['n'][k]} | {res['coverage'][k]:.1%} |")
    lines.append(f"\nTexture coverage, median over scenes: {res['coverage']['texture_scene_median']:.1%}.\n")
    lines += ["| scene | shots | size | encoding | noise | s | ± s (median ch.) | α | ± α | s in | α in | texture in |",
              "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        if "error" in r:
            lines.append(f"| {r['scene']} | error: {r['error']} |")
            continue
        lines.append(f"| {r['scene']} | {r['shots']} | {r['size']} | {r['encoding']} | {r['noise']} | {r['s']:.3f} | "
                     f"{np.median(r['s_pm']):.4f} | {r['alpha']:.1f} | {np.median(r['alpha_pm']):.2f} | {sum(r['s_in'])}/3 | "
                     f"{sum(r['alpha_in'])}/3 | {r['texture_in'] / max(1, r['texture_n']):.1%} |")
    return "\n".join(lines)


if __name__ == "__main__":
    res = run_section(int(sys.argv[1]) if len(sys.argv) > 1 else 100, max_pixels=int(sys.argv[2]) if len(sys.argv) > 2 else None)
    print(markdown(res))
