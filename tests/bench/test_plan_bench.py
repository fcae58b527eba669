"""The plan bench's pieces: the paper's fixed rig, the K vs 2K summary, the real captures' leave-shot-in."""

from __future__ import annotations

import math

import pytest
import torch

from torchmetal.bench import plan as plan_bench
from torchmetal.bench import plan_real
from torchmetal.plan.core import Scene


def _scene() -> Scene:
    cams = torch.tensor([[0.01, 0.0, 0.3, 1.0], [-0.01, 0.01, 0.3, 1.0], [0.0, -0.01, 0.3, 1.0]], dtype=torch.float64)
    return Scene(texture=torch.full((3, 16, 16), 0.3, dtype=torch.float64), s=torch.full((1, 3), 0.5, dtype=torch.float64),
                 alpha=torch.full((1, 3), 60.0, dtype=torch.float64), labels=None, normals=None, size=(0.1, 0.1),
                 lobe="phong", lights=cams.clone(), cameras=cams, intensities=torch.ones(3, 3, dtype=torch.float64))


@pytest.mark.parametrize("n", [1, 2, 4])
def test_paper_positions_ring_of_glares(n):
    sc = _scene()
    lights, cams, inten = plan_bench.paper_positions(sc, n)
    assert lights.shape == (n, 4) and cams.shape == (n, 4) and inten.shape == (n, 3)
    dist = float(sc.cameras[:, :3].norm(dim=-1).median())
    assert torch.allclose(cams[:, :3].norm(dim=-1), torch.full((n,), dist, dtype=torch.float64))
    # co-located flash (the scene's lights are its cameras): the glare is under the camera, on the ring
    assert torch.allclose(cams[:, :2].norm(dim=-1), torch.full((n,), plan_bench.PAPER_RADIUS * 0.1, dtype=torch.float64))
    assert torch.allclose(lights, cams, atol=1e-12)
    az = torch.atan2(cams[:, 1], cams[:, 0])
    if n > 1:
        gaps = torch.remainder(az.roll(-1) - az, 2 * math.pi)
        assert torch.allclose(gaps, torch.full((n,), 2 * math.pi / n, dtype=torch.float64))
    assert bool((inten > 0).all())


def test_multi_summary_medians_and_target():
    rows = [{"base": 1.0, "multi": {1: {"planned": 0.8, "random2k": [0.6, 0.7, 0.9], "paper": 0.9, "paper2k": 0.7}},
             "multi_dropped": {"random2@1": 2}},
            {"base": 2.0, "multi": {1: {"planned": 1.0, "random2k": [1.6, 1.8, 2.0], "paper": 1.8, "paper2k": 1.4}},
             "multi_dropped": {}}]
    s = plan_bench.multi_summary(rows)[1]
    assert s["planned"] == pytest.approx(0.65)  # median of 0.8, 0.5
    assert s["random2k"] == pytest.approx((0.7 + 0.9) / 2)  # scene medians 0.7, 1.8 over bases 1, 2
    assert s["planned_le_random2k"] == pytest.approx(0.5)
    assert s["dropped"]["random2"] == 2 and s["dropped"]["planned1"] == 0
    md = plan_bench.markdown({"rows": rows, "errors": 0, "median": {"base": 1, "planned": 1, "random": 1, "fixed": 1},
                              "dropped": {"planned": 0, "random": 0, "fixed": 0}, "refits": {"planned": 6, "random": 18, "fixed": 6},
                              "base_none": 0, "beats_random": 0.5, "beats_random_scenes": 0.5, "beats_fixed": 0.5,
                              "multi": {1: s}})
    assert "| 1 | 0.650 | 0.800 |" in md and "| yes |" in md


def test_spearman():
    assert plan_real.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert plan_real.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert math.isnan(plan_real.spearman([1, 2, 3], [5, 5, 5]))


def test_splits_all_or_drawn():
    assert len(plan_real.splits(7, 3, 35, 0)) == 35
    drawn = plan_real.splits(12, 3, 10, 0)
    assert len(drawn) == 10 and len(set(drawn)) == 10 and drawn == plan_real.splits(12, 3, 10, 0)


def test_real_section_skips_without_data(tmp_path):
    res = plan_real.run_section(tmp_path, 2, say=None)
    assert set(res) == set(plan_real.CAPTURES)
    assert all("skipped" in r for r in res.values())
    assert "not available" in plan_real.markdown(res)


def test_leave_shot_in_on_a_synthetic_capture(tmp_path):
    from torchmetal.io.capture import load_capture
    from torchmetal.synth.zoo import Scene as ZooScene
    from torchmetal.synth.zoo import make_case

    case = make_case(ZooScene("lsi", size=24, shots=6, held=1, layout="hemisphere", s=0.5, alpha=60.0, seed=43911), tmp_path)
    cap = load_capture(case.capture_dir)
    row = plan_real.score_split(cap, (0, 1, 2))
    assert row["candidates"] == [3, 4, 5]
    assert len(row["score"]) == 3 and len(row["gain"]) == 3
    assert all(math.isfinite(g) for g in row["gain"]) and all(math.isfinite(v) for v in row["score"])
    assert -1.0 <= row["rho"] <= 1.0 or math.isnan(row["rho"])
    assert row["best_gain"] <= row["pick_gain"]


def test_leave_out_normals_scene_and_table():
    from torchmetal.bench import leave_out

    row = leave_out.normals_scene(0, size=12, shots=5)
    assert 0.0 <= row["coverage"] <= 1.0 and row["median_radius_deg"] >= 0 and row["p90_error_deg"] >= row["median_error_deg"]
    md = leave_out.markdown([row], {"failed_refits": 0, "stats": {"density": {"value": 0.005, "low": 0.004, "high": 0.006,
                                                                              "scale": "log", "truth": 0.004, "inside": True}}})
    assert "| median |" in md and "| density (log) | 0.005 | [0.004, 0.006] | 0.004 | yes |" in md
