"""The ``uncertainty`` section of ``torchmetal bench``: are the fit's 90 % intervals calibrated?

Randomised synthetic scenes (:mod:`torchmetal.synth.zoo`'s generator, seeds 43000 + i, apart from the
zoo's): size, shot count, noise, layout, encoding, s and α drawn per scene, the truth the fit's own
model (global Phong, no flakes). Each is fitted (``fit_phong``, global specular, Phong lobe) and
:func:`torchmetal.fit.uncertainty.estimate_uncertainty` gives its intervals; the table counts how often
the clean truth falls inside, per parameter kind: s and α (one per channel and scene) and the texture
(every pixel). Target: 85–95 % each.

``python -m torchmetal.bench.uncertainty [N [MAX_PIXELS]]`` runs it alone (MAX_PIXELS 1024: the strided pass).

**Leave-out intervals** (:func:`run_leave_out`): the flake statistics and estimated normals, whose 90 % intervals
come from refits with one shot left out (``torchmetal intervals``, :mod:`torchmetal.plan.intervals`), on the
randomised captures of :mod:`torchmetal.synth.random_scenes` (their truth not the fit's model: lobes, clipping,
wrong lights), the draws that have something to refit (:func:`leave_out_seeds`): flake scenes (7–9 shots, at 64²)
and bumpy or embossed ones whose normals are not given (32²–40², 6–8 shots), alternately. Each is fitted by
``fit_material`` with that kind forced on (``flakes="on"`` / ``normals="estimate"``: the intervals exist only
where the material has them) and every other choice the default's, saved, and given its intervals by
:func:`~torchmetal.plan.intervals.leave_out_intervals` as the verb does. Truth: the drawn flakes' own statistics
(:func:`flake_truth`: what these shots can tell, not the generator's parameters), the true normal per pixel.
``python -m torchmetal.bench.uncertainty leave_out [N [KIND]]`` runs it alone (KIND: flakes or normals only).
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


# ---------------------------------------------------------------------------- leave-out intervals

LEAVE_OUT_KINDS = ("flakes", "normals")
# flake draws at 64² instead of their 48² (the same density per pixel: ×1.8 the flakes): at 48² 13 of 15 draws kept
# no flake model even with flakes="on" and a 14th found flakes in 1 of 7 refits (2026-12-07): nothing to count
FLAKE_SIZE = 64
FLAKE_STATS = ("density", "area_log_mean", "area_log_std", "aspect_mean", "tilt_sigma", "glint_sigma", "color_r",
               "color_g", "color_b")  # plan.leave_out.flake_stats' names


def leave_out_kind(rs) -> str | None:
    """What a :class:`~torchmetal.synth.random_scenes.RandomScene` has to refit: "flakes", "normals" (bumpy or
    embossed, its normals not given, no flakes) or None."""
    d = rs.describe()
    if d["flakes"] != "none":
        return "flakes"
    return "normals" if d["surface"] != "flat" and not d["given_normals"] else None


def leave_out_seeds(n: int, start: int = 0, kinds: tuple[str, ...] = LEAVE_OUT_KINDS) -> list[tuple[int, str]]:
    """The first ``n`` (seed, kind) of random_scenes draws from ``start`` with something to refit, the ``kinds`` taken
    in turn (flakes, normals, flakes, …) so that each is counted whatever ``n``."""
    from torchmetal.synth.random_scenes import random_scene

    queues: dict[str, list[int]] = {k: [] for k in LEAVE_OUT_KINDS}
    seed, out = start, []
    while len(out) < n:
        want = kinds[len(out) % len(kinds)]
        while not queues[want]:
            kind = leave_out_kind(random_scene(seed))
            if kind is not None:
                queues[kind].append(seed)
            seed += 1
        out.append((queues[want].pop(0), want))
    return out


def flake_truth(flakes: dict, size: int) -> dict:
    """The drawn flakes' statistics in :func:`torchmetal.plan.leave_out.flake_stats`' names: density per pixel over
    the whole sample (a "left" scene's too: the model's density is the sample's mean), the log areas' mean and std,
    the minor/major mean, the tilt σ per tangent axis (√(mean θ²/2): the draw's Rayleigh scale), the generator's glint
    σ (no per-flake draw), the colours' mean. ``flakes``: the zoo's truth dict (centre, axes, normal, color, area)."""
    area = np.asarray(flakes["area"], dtype=np.float64)
    axes = np.asarray(flakes["axes"], dtype=np.float64)
    theta = np.arccos(np.clip(np.asarray(flakes["normal"], dtype=np.float64)[:, 2], -1.0, 1.0))
    colour = np.asarray(flakes["color"], dtype=np.float64).mean(0)
    return {"density": len(area) / size**2, "area_log_mean": float(np.log(area).mean()),
            "area_log_std": float(np.log(area).std()), "aspect_mean": float((axes[:, 1] / axes[:, 0]).mean()),
            "tilt_sigma": float(np.sqrt((theta**2).mean() / 2)), "glint_sigma": float(flakes["spec"]["glint_sigma"]),
            **{f"color_{c}": float(v) for c, v in zip("rgb", colour)}}


def score_leave_out(seed: int, kind: str, work: str, *, level: float = 0.9, size: int | None = None) -> dict:
    """Fit random scene ``seed`` with ``kind`` forced on, run ``torchmetal intervals``' refits on it and count the
    truths inside. Flakes: per statistic {"value", "low", "high", "truth", "inside"} (None where the material kept no
    flake model or the refits gave no interval); normals: the mask's pixels whose true normal lies within the 90 %
    radius of the material's (``normals_in`` of ``normals_n``), the median radius and error in degrees."""
    from pathlib import Path

    import torch

    from torchmetal.io.capture import load_capture
    from torchmetal.material import load_material, save_material
    from torchmetal.pipeline import fit_material
    from torchmetal.plan.intervals import leave_out_intervals
    from torchmetal.plan.leave_out import angle_deg
    from torchmetal.synth.random_scenes import make_random_case, random_scene, with_size

    rs = random_scene(seed) if size is None else with_size(random_scene(seed), size)
    work = Path(work)
    case = make_random_case(rs, work / "capture")
    cap = load_capture(case.capture_dir)
    forced = {"flakes": "on"} if kind == "flakes" else {"normals": "estimate", "flakes": "off"}
    t0 = time.perf_counter()
    result = fit_material(cap, **forced)
    save_material(result.material, work / "material")
    t1 = time.perf_counter()
    row = {"seed": seed, "kind": kind, **{k: rs.describe()[k] for k in ("size", "shots", "lobe", "surface", "lighting",
                                                                       "light_error", "clip", "encoding", "flakes")},
           "fit_s": t1 - t0}
    if kind == "flakes" and result.material.flakes is None:
        return row | {"stats": None, "note": "no flake model kept"}
    if kind == "normals" and result.material.normals is None:
        return row | {"normals_in": 0, "normals_n": 0, "note": "the estimate was flat"}
    entry = leave_out_intervals(work / "material", case.capture_dir, level=level)
    row["intervals_s"] = time.perf_counter() - t1
    if kind == "flakes":
        truth = flake_truth(case.truth.flakes, rs.scene.size)
        fl = entry["flakes"]
        row["failed_refits"] = fl["failed_refits"]
        row["stats"] = {k: {"value": fl[k]["value"], "low": fl[k]["low"], "high": fl[k]["high"], "truth": truth[k],
                            "inside": bool(fl[k]["low"] <= truth[k] <= fl[k]["high"])
                            if math.isfinite(fl[k]["low"]) and math.isfinite(fl[k]["high"]) else None}
                        for k in FLAKE_STATS}
        return row
    m = load_material(work / "material")
    err = angle_deg(m.normals.double(), torch.as_tensor(case.truth.normals, dtype=torch.float64))
    radius = m.normals_interval.double()  # the map the report names (normals_interval_deg.npy)
    inside = cap.mask.bool().reshape(cap.height, cap.width).cpu()
    hit = (err <= radius)[inside]
    return row | {"normals_in": int(hit.sum()), "normals_n": int(hit.numel()), "normals_scene": float(hit.double().mean()),
                  "median_radius_deg": float(radius[inside].median()), "median_error_deg": float(err[inside].median()),
                  "p90_error_deg": float(err[inside].quantile(0.9))}


def run_leave_out(n: int = 24, *, start: int = 0, kinds: tuple[str, ...] = LEAVE_OUT_KINDS, level: float = 0.9,
                  size: int | None = None, say=print) -> dict:
    """Score the ``n`` scenes of :func:`leave_out_seeds` (``kinds`` in turn; ``size``: every scene's side, else the
    draw's, flake scenes :data:`FLAKE_SIZE`); returns {"rows", "coverage": {kind: fraction}, "n": {kind:
    count}, "scenes": {kind: scenes counted}, "level", "errors"}: a flake statistic's kind counts one interval per
    scene, the normals one per pixel."""
    rows = []
    for seed, kind in leave_out_seeds(n, start, kinds):
        with tempfile.TemporaryDirectory(prefix="tm-leave-out-") as d:
            try:
                side = size or (FLAKE_SIZE if kind == "flakes" else None)
                rows.append(score_leave_out(seed, kind, d, level=level, size=side))
            except Exception as e:  # noqa: BLE001 - a bench row records any failure and goes on
                rows.append({"seed": seed, "kind": kind, "error": f"{type(e).__name__}: {e}".splitlines()[0]})
        if say is not None:
            say(f"  random_{seed:04d} ({kind}): {_leave_out_line(rows[-1])}")
    cov, counts, scenes = {}, {}, {}
    for k in FLAKE_STATS:
        v = [r["stats"][k]["inside"] for r in rows if r.get("stats") and r["stats"][k]["inside"] is not None]
        cov[k], counts[k], scenes[k] = _frac(v), len(v), len(v)
    nr = [r for r in rows if r.get("normals_n")]
    counts["normals"] = sum(r["normals_n"] for r in nr)
    cov["normals"] = sum(r["normals_in"] for r in nr) / max(1, counts["normals"])
    cov["normals_scene_median"] = float(np.median([r["normals_scene"] for r in nr])) if nr else math.nan
    scenes["normals"] = len(nr)
    return {"rows": rows, "coverage": cov, "n": counts, "scenes": scenes, "level": level,
            "errors": sum("error" in r for r in rows)}


def _leave_out_line(r: dict) -> str:
    if "error" in r:
        return f"error: {r['error']}"
    if "note" in r:
        return r["note"]
    if r["kind"] == "normals":
        return (f"{r['normals_scene']:.1%} of {r['normals_n']} px inside, median radius {r['median_radius_deg']:.2f}°, "
                f"median error {r['median_error_deg']:.2f}° ({r['fit_s']:.0f} + {r['intervals_s']:.0f} s)")
    got = [k for k, v in r["stats"].items() if v["inside"] is not None]
    inside = [k for k in got if r["stats"][k]["inside"]]
    what = (f"{len(inside)}/{len(got)} inside, out: {', '.join(k for k in got if k not in inside) or 'none'}" if got
            else "no interval (under 3 refits found flakes)")
    return f"{what} ({r['failed_refits']} refits without flakes; {r['fit_s']:.0f} + {r['intervals_s']:.0f} s)"


def leave_out_markdown(res: dict) -> str:
    """The coverage table of the leave-out intervals (per flake statistic and for the normals' pixels) and the
    flake rows' estimate / interval / truth."""
    lvl = res["level"]
    rows = res["rows"]
    notes = [f"random_{r['seed']:04d}: {r.get('note') or r.get('error')}" for r in rows if "note" in r or "error" in r]
    lines = [f"Coverage of the truth by the leave-out {lvl:.0%} intervals (target {lvl - 0.05:.0%}–{lvl + 0.05:.0%}); "
             f"{len(rows)} random_scenes draws, {res['errors']} failed" + (f"; not counted: {'; '.join(notes)}" if notes else "") + ".",
             "", "| parameter | scenes | intervals | truth inside |", "|---|---:|---:|---:|"]
    for k in FLAKE_STATS:
        if res["n"][k]:  # a kind no scene gave an interval of: no row (its draws are in the notes)
            lines.append(f"| flake {k} | {res['scenes'][k]} | {res['n'][k]} | {res['coverage'][k]:.1%} |")
    if res["n"]["normals"]:
        lines.append(f"| normals (per pixel) | {res['scenes']['normals']} | {res['n']['normals']} | "
                     f"{res['coverage']['normals']:.1%} (median scene {res['coverage']['normals_scene_median']:.1%}) |")
    fr = [r for r in rows if r.get("stats")]
    if fr:
        lines += ["", "| scene | shots | lobe | " + " | ".join(FLAKE_STATS) + " |", "|---|---:|---|" + "---|" * len(FLAKE_STATS)]
        for r in fr:
            mark = {True: "", False: " ✗", None: " (no interval)"}
            cells = [f"{v['value']:.3g} [{v['low']:.3g}, {v['high']:.3g}] {v['truth']:.3g}{mark[v['inside']]}"
                     for v in (r["stats"][k] for k in FLAKE_STATS)]
            lines.append(f"| random_{r['seed']:04d} | {r['shots']} | {r['lobe']} | " + " | ".join(cells) + " |")
    nr = [r for r in rows if r.get("normals_n")]
    if nr:
        lines += ["", "| scene | shots | size | surface | lobe | inside | median radius | median error | p90 error |",
                  "|---|---:|---:|---|---|---:|---:|---:|---:|"]
        for r in nr:
            lines.append(f"| random_{r['seed']:04d} | {r['shots']} | {r['size']} | {r['surface']} | {r['lobe']} | "
                         f"{r['normals_scene']:.1%} | {r['median_radius_deg']:.2f}° | {r['median_error_deg']:.2f}° | "
                         f"{r['p90_error_deg']:.2f}° |")
    return "\n".join(lines)


if __name__ == "__main__" and sys.argv[1:2] == ["leave_out"]:  # leave_out [N [KIND]]
    print(leave_out_markdown(run_leave_out(int(sys.argv[2]) if len(sys.argv) > 2 else 24,
                                           kinds=(sys.argv[3],) if len(sys.argv) > 3 else LEAVE_OUT_KINDS)))
elif __name__ == "__main__":
    res = run_section(int(sys.argv[1]) if len(sys.argv) > 1 else 100, max_pixels=int(sys.argv[2]) if len(sys.argv) > 2 else None)
    print(markdown(res))
