"""The uncertainty bench's leave-out part: which draws it refits, the flakes' truth, one small scene end to end, the
coverage counts per parameter kind."""

from __future__ import annotations

import math

import numpy as np
import pytest

from torchmetal.bench import uncertainty as unc
from torchmetal.synth.random_scenes import random_scene


def test_leave_out_seeds_take_the_kinds_in_turn():
    got = unc.leave_out_seeds(6)
    assert [k for _, k in got] == ["flakes", "normals"] * 3
    assert len({s for s, _ in got}) == 6 and got == unc.leave_out_seeds(6)  # distinct, deterministic
    for seed, kind in got:
        d = random_scene(seed).describe()
        assert (d["flakes"] != "none") if kind == "flakes" else (d["surface"] != "flat" and not d["given_normals"])
    assert unc.leave_out_kind(random_scene(next(s for s in range(50) if random_scene(s).describe()["surface"] == "flat"
                                                and random_scene(s).describe()["flakes"] == "none"))) is None


def test_flake_truth_is_the_drawn_flakes_statistics():
    theta = np.array([0.1, 0.2])
    fl = {"area": np.array([2.0, 8.0]), "axes": np.array([[2.0, 1.0], [4.0, 3.0]]),
          "normal": np.stack([np.sin(theta), np.zeros(2), np.cos(theta)], -1), "color": np.array([[0.5, 0.6, 0.7], [0.7, 0.8, 0.9]]),
          "spec": {"glint_sigma": 0.04}}
    t = unc.flake_truth(fl, 10)
    assert t["density"] == pytest.approx(0.02) and t["area_log_mean"] == pytest.approx(math.log(4.0))
    assert t["area_log_std"] == pytest.approx(math.log(2.0)) and t["aspect_mean"] == pytest.approx(0.625)
    assert t["tilt_sigma"] == pytest.approx(math.sqrt((0.01 + 0.04) / 4)) and t["glint_sigma"] == 0.04
    assert (t["color_r"], t["color_g"], t["color_b"]) == pytest.approx((0.6, 0.7, 0.8))
    assert set(t) == set(unc.FLAKE_STATS)


def test_one_small_normals_scene_end_to_end(tmp_path):
    seed = next(s for s, k in unc.leave_out_seeds(4) if k == "normals")
    r = unc.score_leave_out(seed, "normals", str(tmp_path), size=16)
    assert r["kind"] == "normals" and r["size"] == 16
    assert r["normals_n"] == 256 and 0 <= r["normals_in"] <= 256, r  # every pixel of the full mask counted
    assert r["median_radius_deg"] >= 0 and math.isfinite(r["median_error_deg"])


def test_coverage_counts_per_kind(monkeypatch):
    def stats(inside):
        return {k: {"value": 1.0, "low": 0.5, "high": 2.0, "truth": 1.0, "inside": inside} for k in unc.FLAKE_STATS}

    rows = iter([
        {"kind": "flakes", "stats": stats(True), "failed_refits": 0, "fit_s": 1.0, "intervals_s": 1.0},
        {"kind": "normals", "normals_in": 90, "normals_n": 100, "normals_scene": 0.9, "median_radius_deg": 1.0,
         "median_error_deg": 0.5, "p90_error_deg": 2.0, "fit_s": 1.0, "intervals_s": 1.0},
        {"kind": "flakes", "stats": stats(False), "failed_refits": 2, "fit_s": 1.0, "intervals_s": 1.0},
        {"kind": "normals", "normals_in": 0, "normals_n": 0, "note": "the estimate was flat"},
        {"kind": "flakes", "stats": stats(None), "failed_refits": 5, "fit_s": 1.0, "intervals_s": 1.0},
        {"kind": "normals", "normals_in": 50, "normals_n": 300, "normals_scene": 1 / 6, "median_radius_deg": 1.0,
         "median_error_deg": 0.5, "p90_error_deg": 2.0, "fit_s": 1.0, "intervals_s": 1.0},
    ])
    scene = {"size": 32, "shots": 6, "lobe": "phong", "surface": "bumpy"}
    monkeypatch.setattr(unc, "score_leave_out", lambda seed, kind, work, **kw: {"seed": seed, **scene, **next(rows)})
    res = unc.run_leave_out(6, say=None)
    assert res["n"]["density"] == 2 and res["coverage"]["density"] == 0.5  # the no-interval scene not counted
    assert res["n"]["normals"] == 400 and res["coverage"]["normals"] == pytest.approx(140 / 400)  # pixels
    assert res["scenes"]["normals"] == 2 and res["errors"] == 0
    md = unc.leave_out_markdown(res)
    assert "| flake density | 2 | 2 | 50.0% |" in md and "| normals (per pixel) | 2 | 400 | 35.0%" in md
    assert "the estimate was flat" in md and "(no interval)" in md
    rows = iter([{"kind": "normals", "normals_in": 1, "normals_n": 2, "normals_scene": 0.5, "median_radius_deg": 1.0,
                  "median_error_deg": 0.5, "p90_error_deg": 2.0}])
    md = unc.leave_out_markdown(unc.run_leave_out(1, kinds=("normals",), say=None))
    assert "flake density" not in md and "nan" not in md  # no flake scene: no flake rows
