"""Coverage of the leave-one-shot-out intervals (:mod:`torchmetal.plan.leave_out`) on synthetic captures.

Normals: seeded bumpy captures (``synth_capture``, hemisphere lights, 8-bit, noise 0.01–0.02, seeds 43800 + i);
per scene the share of pixels whose true normal lies within the 90 % radius of the estimate, the median radius
and the median error. Flakes: one capture with a known flake model; whether each statistic's 90 % interval
holds the truth.

``python -m torchmetal.bench.leave_out [N_NORMALS [FLAKE_SIZE]]`` (FLAKE_SIZE 0: no flake capture).
"""

from __future__ import annotations

import math
import sys

import numpy as np

SEED0 = 43800


def normals_scene(i: int, size: int = 32, shots: int = 8) -> dict:
    from torchmetal.plan.leave_out import angle_deg, normals_intervals
    from torchmetal.synth import synth_capture

    rng = np.random.default_rng([SEED0, i])
    noise = float(rng.choice([0.01, 0.02]))
    r = synth_capture(size=size, shots=shots, seed=SEED0 + i, layout="hemisphere", bumpy=True, noise=noise, bits=8,
                      texture="procedural")
    got = normals_intervals(r.capture)
    err = angle_deg(got["normals"], r.truth["normals"])
    return {"scene": i, "noise": noise, "coverage": float((err <= got["radius_deg"]).double().mean()),
            "median_radius_deg": got["median_radius_deg"], "p90_radius_deg": got["p90_radius_deg"],
            "median_error_deg": float(err.median()), "p90_error_deg": float(err.quantile(0.9))}


def flake_scene(size: int = 256, shots: int = 12, seed: int = 7) -> dict:
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.plan.leave_out import flake_intervals, flake_stats
    from torchmetal.synth import synth_capture

    truth = FlakeModel(density=0.004, area_log_mean=math.log(4.0), area_log_std=0.35, tilt_sigma=0.12, glint_sigma=0.03,
                       color_mean=(0.9, 0.8, 0.6))
    r = synth_capture(size=size, shots=shots, seed=seed, layout="hemisphere", noise=0.01, bits=8, texture="procedural",
                      flakes=truth)
    got = flake_intervals(r.capture)
    ts = flake_stats(r.truth["flakes"])
    return {"failed_refits": got["failed_refits"],
            "stats": {k: {**{f: v[f] for f in ("value", "low", "high", "scale")}, "truth": ts[k],
                          "inside": bool(v["low"] <= ts[k] <= v["high"])}
                      for k, v in got.items() if isinstance(v, dict)}}


def markdown(normals: list[dict], flakes: dict | None) -> str:
    lines = ["| scene | noise | truth within the 90 % radius | median radius | p90 radius | median error | p90 error |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in normals:
        lines.append(f"| {r['scene']} | {r['noise']:g} | {r['coverage']:.1%} | {r['median_radius_deg']:.2f}° | "
                     f"{r['p90_radius_deg']:.2f}° | {r['median_error_deg']:.2f}° | {r['p90_error_deg']:.2f}° |")
    if normals:
        lines.append(f"| median | | {np.median([r['coverage'] for r in normals]):.1%} | | | | |")
    if flakes:
        lines += ["", f"Flake statistics (failed refits {flakes['failed_refits']}):", "",
                  "| statistic | estimate | 90 % interval | truth | inside |", "|---|---:|---|---:|---|"]
        for k, v in flakes["stats"].items():
            lines.append(f"| {k} ({v['scale']}) | {v['value']:.4g} | [{v['low']:.4g}, {v['high']:.4g}] | {v['truth']:.4g} | "
                         f"{'yes' if v['inside'] else 'no'} |")
    return "\n".join(lines)


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 8
    fsize = int(sys.argv[2]) if len(sys.argv) > 2 else 256
    rows = []
    for i in range(n):
        rows.append(normals_scene(i))
        print(f"  normals {i}: {rows[-1]}", flush=True)
    print(markdown(rows, flake_scene(fsize) if fsize else None))
