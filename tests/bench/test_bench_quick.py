"""The benchmark harness: its pieces, and one ``--quick`` run end to end (what CI runs)."""

from __future__ import annotations

import csv
import importlib.util
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from torchmetal.bench.children import run_jobs
from torchmetal.bench.memory import PeakMemory
from torchmetal.bench.plans import full_plan, quick_plan, sweep_configs
from torchmetal.bench.runner import SECTIONS
from torchmetal.bench.scoring import holdout_indices, psnr_or_nan, rel_err
from torchmetal.bench.tables import EQUAL_DB, speed_ratio
from torchmetal.bench.worker import run_task


def _importable(mod: str) -> bool:
    try:
        return importlib.util.find_spec(mod) is not None
    except ModuleNotFoundError:
        return False


# ----------------------------------------------------------------------------- pieces


def test_full_plan_sweeps_the_issue_ranges():
    plan = full_plan()
    cfgs = sweep_configs(plan)
    sizes = {c["size"] for c in cfgs}
    shots = {c["shots"] for c in cfgs}
    assert min(sizes) == 256 and max(sizes) == 2048
    assert min(shots) == 4 and max(shots) == 32
    assert len({c["noise"] for c in cfgs}) >= 3 and len({c["tol"] for c in cfgs}) >= 3
    keys = [(c["size"], c["shots"], c["noise"], c["bits"], c["tol"]) for c in cfgs]
    assert len(keys) == len(set(keys)), "identical configurations must run once"
    base = [c for c in cfgs if len(c["axes"]) > 1]
    assert len(base) == 1 and set(base[0]["axes"]) == {"resolution", "shots", "noise", "tol"}


def test_holdout_indices_are_spread_and_distinct():
    for n, k in [(14, 2), (6, 2), (34, 2), (5, 5), (8, 3)]:
        idx = holdout_indices(n, k)
        assert len(idx) == k == len(set(idx))
        assert all(0 <= i < n for i in idx)
    assert holdout_indices(10, 0) == []
    assert holdout_indices(14, 2) == [3, 10]


def test_psnr_and_relative_error():
    ref = torch.full((2, 3, 4, 4), 0.5, dtype=torch.float64)
    ref[0, 0, 0, 0] = 0.9  # below 1: the +0.01 stays inside the clipped [0, 1] range
    pred = ref + 0.01
    assert psnr_or_nan(pred, ref) == pytest.approx(40.0, abs=1e-9)  # metrics.psnr: peak 1, rmse 0.01
    valid = torch.ones_like(ref, dtype=torch.bool)
    pred2 = pred.clone()
    pred2[1, 2, 3, 3] = 100.0
    valid[1, 2, 3, 3] = False
    assert psnr_or_nan(pred2, ref, valid) == pytest.approx(40.0, abs=1e-9)  # the masked outlier is ignored
    assert psnr_or_nan(ref, ref) == math.inf
    # a failed method is recorded, not raised: NaN for non-finite renders or an empty valid mask
    pred2[0, 0, 1, 1] = float("nan")
    assert math.isnan(psnr_or_nan(pred2, ref, valid))
    assert math.isnan(psnr_or_nan(pred, ref, torch.zeros_like(valid)))
    assert rel_err([1.1, 2.0, 0.0], [1.0, 2.0, 0.0]) == pytest.approx(0.1)
    assert math.isnan(rel_err(np.ones((3, 4)), [1.0, 1.0, 1.0]))


def test_speed_ratio_only_at_equal_or_better_error():
    tm = {"wall_s": 2.0, "psnr_holdout": 50.0}
    ratio, txt = speed_ratio(tm, {"wall_s": 20.0, "psnr_holdout": 49.0})
    assert ratio == pytest.approx(10.0) and txt == "10.0×"
    ratio, _ = speed_ratio(tm, {"wall_s": 20.0, "psnr_holdout": 50.0 + EQUAL_DB / 2})
    assert ratio == pytest.approx(10.0)
    ratio, txt = speed_ratio(tm, {"wall_s": 20.0, "psnr_holdout": 51.0})
    assert ratio is None and "worse" in txt
    # the error against the clean truth decides when both results have it, not the noisy-photo one
    tm2 = {"wall_s": 2.0, "psnr_holdout": 40.0, "psnr_truth": 55.0}
    ratio, _ = speed_ratio(tm2, {"wall_s": 20.0, "psnr_holdout": 41.0, "psnr_truth": 54.0})
    assert ratio == pytest.approx(10.0)
    ratio, txt = speed_ratio(tm2, {"wall_s": 20.0, "psnr_holdout": 39.0, "psnr_truth": 56.0})
    assert ratio is None and "worse" in txt
    assert speed_ratio({"error": "x"}, {"wall_s": 1.0, "psnr_holdout": 1.0})[0] is None


def test_peak_memory_sees_numpy_allocations():
    from torchmetal.memory import release_free_memory

    # glibc serves even a 160 MiB request from a free heap chunk that earlier tests left resident
    # (then RSS does not move): hand those pages back first, so the allocation must fault in new ones
    release_free_memory()
    with PeakMemory() as small:
        x = np.ones(1000)
    with PeakMemory() as big:
        y = np.ones(160 * 2**20 // 8)  # 160 MiB, touched
        y[::512] = 2.0
        del y
    assert big.peak >= 140 * 2**20
    assert small.peak < 40 * 2**20
    assert big.peak_abs >= big.peak
    del x


def test_children_isolate_memory_and_report_failures():
    res = run_jobs(
        [("selftest", {"mib": 120}), ("selftest", {}), ("selftest", {"fail": "boom"}),
         ("selftest", {"missing": "torchmetal.no_such_stage"})],
        isolate=True, timeout=60,
    )
    assert res[0]["peak_bytes"] >= 100 * 2**20
    assert res[1]["peak_bytes"] < 40 * 2**20  # a fresh process: the first child's peak does not leak in
    assert res[0]["pid"] != res[1]["pid"]
    assert res[2]["error"].startswith("RuntimeError: boom")
    assert "torchmetal.no_such_stage" in res[3]["not_available"]


def test_thread_count_reaches_the_children():
    one = run_jobs([("selftest", {})], isolate=True, timeout=60, threads=1)[0]
    shared = run_jobs([("selftest", {})], isolate=False, timeout=60, threads=1)[0]
    assert one["torch_threads"] == 1 and shared["torch_threads"] == 1
    assert quick_plan().threads == 1


def test_a_hanging_child_is_stopped():
    t0 = time.perf_counter()
    res = run_jobs([("selftest", {"sleep": 30})], isolate=True, timeout=3)
    assert time.perf_counter() - t0 < 20
    assert "timed out" in res[0]["error"]


def test_sweep_scores_held_out_shots_against_the_clean_truth(tmp_path):
    """task_prepare keeps noise-free held-out renders; task_method scores against them (psnr_truth)."""
    for noise in (0.0, 0.03):
        path = str(tmp_path / f"c{noise}.pt")
        prep = run_task("prepare", {"path": path, "size": 16, "shots": 4, "noise": noise, "holdout": 2})
        assert "error" not in prep, prep
        d = torch.load(path, weights_only=False)
        assert d["clean_hold"].shape == d["capture"].images[d["hold_idx"]].shape
        r = run_task("method", {"path": path, "method": "paper-numpy", "tol": 1e-6, "max_iters": 50})
        assert "error" not in r, r
        assert math.isfinite(r["psnr_truth"]) and math.isfinite(r["psnr_holdout"])
        if noise == 0.0:  # float images without noise are the clean renders
            assert torch.equal(d["clean_hold"], d["capture"].images[d["hold_idx"]])
            assert r["psnr_truth"] == pytest.approx(r["psnr_holdout"])
        else:  # the noise is no longer charged to the fit
            assert r["psnr_truth"] > r["psnr_holdout"] + 3.0


def test_zoo_markdown_rows_and_verdict():
    from torchmetal.bench.zoo_section import verdict, zoo_markdown

    row = {"psnr": 50.0, "psnr_coat": 50.0, "s_err": 0.01, "alpha_err": 0.02, "time": 1.0, "flake_model": False,
           "stage_times": {"phong.init": 0.1, "phong.refine": 0.2, "flakes": 0.3, "lm_evaluations": 7}}
    good = {"oracle": 51.0, "truth": {}, "default": row, "paper": {**row, "psnr_coat": 50.15, "psnr": 49.0}}
    bad = {"oracle": 51.0, "truth": {"density": 0.01}, "default": row, "paper": {**row, "psnr_coat": 50.3}}
    assert verdict(good) is True and verdict(bad) is False
    md = zoo_markdown(["a", "b", "c"], [good, bad, {"error": "RuntimeError: x"}], {"a": "8² × 3"})
    lines = [ln for ln in md.splitlines() if ln.startswith("| ") and not ln.startswith("| scene")]
    assert [ln.split(" | ")[0] for ln in lines] == ["| a", "| b", "| c"]
    a, b = lines[0].split(" | "), lines[1].split(" | ")
    assert a[1] == "8² × 3" and a[2] == "50.00" and a[3] == "50.15 (as rendered 49.00)" and a[4] == "51.00"
    assert a[-1] == "yes |" and b[-1] == "no |" and "no (MISSED)" in b
    assert "init 0.10, refine 0.20, flakes 0.30" in a and "lm_evaluations" not in md
    assert "100.0%" in a  # the flake stage over the Phong stages (0.3 s / 0.1 + 0.2 s)
    assert "error: RuntimeError: x" in lines[2]
    assert "on 1 of 2 scenes" in md


def test_unknown_task_config_is_an_error_entry_not_a_crash():
    r = run_task("method", {"path": "/nonexistent/capture.pt", "method": "paper-numpy"})
    assert "error" in r and "FileNotFoundError" in r["error"]


def test_real_task_scores_paper_and_default_leave_one_out(tmp_path):
    """The real section's variants on a capture directory (a zoo scene standing in for shared/data):
    each left-out shot scored once per variant, the default pipeline and the paper scheme beside
    fit_phong, and an unknown variant is an error entry."""
    from torchmetal.synth.zoo import SCENES, make_case

    case = make_case(SCENES["three_shots"].with_(size=32, shots=4), tmp_path / "cap")
    r = run_task("real", {"dir": str(case.capture_dir), "speculars": ["global", "paper", "default"],
                          "gallery": str(tmp_path / "gallery"), "gallery_shots": 1})
    assert "error" not in r, r
    assert r["shots"] == 4 and r["size"] == [32, 32]
    # the three score kinds side by side at three scales (sRGB), own shots first; own-shot gallery beside the left out
    sc = r["default"]["scores"]
    assert set(sc) == {"in_sample", "light_fitted", "left_out"} and set(r["global"]["scores"]) == {"in_sample", "left_out"}
    assert sc["in_sample"]["extrapolation"] is None and 0.0 <= sc["left_out"]["extrapolation"] <= 1.0
    assert all(25 < sc[k]["psnr"][f] < 120 for k in sc for f in ("1", "4", "16")), sc
    assert sc["in_sample"]["psnr"]["1"] > sc["left_out"]["psnr"]["1"]
    assert [Path(g).name for g in r["default"]["gallery_own"]] == ["cap_own_shot0.png"]
    assert Path(r["default"]["gallery_own"][0]).read_bytes()[:4] == b"\x89PNG"
    for v in ("global", "paper", "default"):
        assert len(r[v]["psnr"]) == 4 and all(30 < x < 100 for x in r[v]["psnr"]), (v, r[v])
        assert r[v]["mean"] == pytest.approx(sum(r[v]["psnr"]) / 4)
        # in sample (fitted on the shots it is scored on): the model's reach, above the left-out mean
        assert 30 < r[v]["in_sample"] < 100 and r[v]["in_sample"] > r[v]["mean"], (v, r[v])
    assert "coat" not in r["global"]  # fit_phong renders have no sparkles to leave out
    for v in ("paper", "default"):  # no flakes on this scene: the coat is the render
        assert r[v]["coat"] == pytest.approx(r[v]["psnr"]) and r[v]["coat_in_sample"] == pytest.approx(r[v]["in_sample"])
    bad = run_task("real", {"dir": str(case.capture_dir), "speculars": ["nonsense"]})
    assert "error" in bad and "nonsense" in bad["error"]


def test_real_task_coat_is_the_render_without_sparkles(monkeypatch, tmp_path):
    """A pipeline variant's coat column renders its material without the flake model: the sparkled
    render is brighter where the flakes glint, the coat is the flake-free render exactly."""
    from dataclasses import replace
    from types import SimpleNamespace

    import torch

    import torchmetal.pipeline
    from torchmetal.bench.real_tasks import _material_fit_render
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.io.capture import load_capture
    from torchmetal.lightcal import LightCalibration
    from torchmetal.renderer import MaterialRenderer
    from torchmetal.synth.zoo import SCENES, make_case

    case = make_case(SCENES["three_shots"].with_(size=32, shots=4), tmp_path / "cap")
    cap = load_capture(case.capture_dir)
    coat_only = torchmetal.pipeline.fit_material(cap, flakes="off").material
    sparkly = replace(coat_only, flakes=FlakeModel(density=0.1, tilt_sigma=0.3, glint_sigma=0.4, color_mean=(5.0, 5.0, 5.0)))
    monkeypatch.setattr(torchmetal.pipeline, "fit_material",
                        lambda *a, **k: SimpleNamespace(material=sparkly, light=LightCalibration()))
    coats: list = []
    one = cap.subset([1])
    pred = _material_fit_render("default", coats)(cap.subset([0, 2, 3]), one)
    with torch.no_grad():
        want = MaterialRenderer(coat_only)(one.lights, one.intensities, one.cameras)
    assert len(coats) == 1 and torch.allclose(coats[0], want)
    assert float((pred - want).abs().max()) > 1e-3  # the sparkles are in the scored render, not in the coat


def test_real_task_light_fitted_renders_under_the_shots_own_light(monkeypatch, tmp_path):
    """A left-out shot photographed with its light moved: the light-fitted render (the material held fixed,
    the light fitted to the photo) is closer to it than the render under capture.json's light; a fitted shot
    gets its calibration's lights and no light-fitted render."""
    from types import SimpleNamespace

    import torchmetal.pipeline
    from tests.lightcal.helpers import misplaced_capture
    from torchmetal.bench.real_tasks import _material_fit_render
    from torchmetal.lightcal import LightCalibration
    from torchmetal.material import Material

    cap, true, t = misplaced_capture(size=32, shots=4, noise=0.0)
    m = Material(t["texture"], t["s"], t["alpha"], cap.size)
    cal = LightCalibration(offsets=tuple(tuple(o) for o in true.tolist()))
    monkeypatch.setattr(torchmetal.pipeline, "fit_material", lambda *a, **k: SimpleNamespace(material=m, light=cal))
    fitted: list = []
    fr = _material_fit_render("default", None, fitted)
    one = cap.subset([1])
    as_given = fr(cap.subset([0, 2, 3]), one)
    assert len(fitted) == 1
    err = lambda x: float(((x - one.images) ** 2).mean())  # noqa: E731
    assert err(fitted[0]) < 0.01 * err(as_given)
    in_sample = fr(cap, cap)  # the calibration's own shots: its moved lights
    assert len(fitted) == 1 and err(in_sample[1:2]) < 0.01 * err(as_given)


def test_cli_rejects_unknown_sections(capsys):
    from torchmetal.bench.__main__ import main

    assert main(["--quick", "--sections", "sweep,nonsense"]) == 2
    assert "nonsense" in capsys.readouterr().err


# ----------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    from torchmetal.bench.__main__ import main

    out = tmp_path_factory.mktemp("bench")
    t0 = time.perf_counter()
    rc = main(["--quick", "--quiet", "--out", str(out)])
    return rc, out, time.perf_counter() - t0


def test_quick_run_writes_every_output(quick_run):
    rc, out, wall = quick_run
    assert rc == 0
    md = (out / "results.md").read_text()
    titles = ("Sweep", "Capture load", "Phong fit", "Skip evidence", "Flake detection", "ONNX renderer",
              "Real captures: leave-one-out", "Real captures: flake statistics", "Scene zoo", "Whole command",
              "ONNX renderer per material kind", "GPU", "Robustness", "Uncertainty", "Selection", "Capture plan")
    for title in titles:
        assert f"## {title}" in md
    assert len(SECTIONS) == len(titles)
    png = (out / "time_vs_error.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    assert "traceback" not in md.lower()


def test_quick_run_baselines_have_numbers(quick_run):
    _, out, _ = quick_run
    rows = list(csv.DictReader(open(out / "results.csv")))
    by_method = {}
    for r in rows:
        by_method.setdefault(r["method"], []).append(r)
    for m in ("paper-numpy", "adam"):
        assert by_method.get(m), f"no {m} rows"
        for r in by_method[m]:
            p = float(r["psnr_holdout"])
            assert math.isfinite(p) and p > 30.0, (m, p)
            assert float(r["wall_s"]) > 0 and float(r["peak_bytes"]) >= 0
            assert abs(p - float(r["psnr_holdout_truth"])) < 6.0  # near the noise ceiling (quick: few Adam steps)
            t = float(r["psnr_truth"])  # the primary error: against the noise-free render of the truth
            assert math.isfinite(t) and t > 30.0, (m, t)
    if _importable("torchmetal.fit"):
        assert by_method.get("torchmetal"), "torchmetal.fit exists but the sweep has no torchmetal rows"
        for r in by_method["torchmetal"]:
            assert math.isfinite(float(r["psnr_holdout"]))


def test_quick_run_sections_report_numbers_or_a_reason(quick_run):
    """Each section prints its numbers, or 'not available: <reason>' — never an unexplained error."""
    _, out, _ = quick_run
    md = (out / "results.md").read_text()
    assert "error:" not in md, [ln for ln in md.splitlines() if "error:" in ln][:5]
    load = md.split("## Capture load")[1].split("\n## ")[0]
    if _importable("torchmetal.io.capture"):
        assert "load_capture s" in load and "not available" not in load


def test_quick_run_zoo_has_a_row_per_scene_with_numbers(quick_run):
    import json

    from torchmetal.bench.plans import quick_plan

    _, out, _ = quick_run
    names = list(quick_plan().zoo_scenes)
    rows = json.loads((out / "zoo.json").read_text())
    assert [r["scene"] for r in rows] == names
    for r in rows:
        assert "error" not in r and "not_available" not in r, r
        for m in ("default", "paper"):
            for k in ("psnr", "psnr_coat", "time"):
                assert math.isfinite(float(r[m][k])), (r["scene"], m, k, r[m][k])
            assert float(r[m]["psnr_coat"]) > 30.0, (r["scene"], m)
        assert math.isfinite(float(r["oracle"]))
        assert any(k.startswith("phong.") for k in r["default"]["stage_times"])
    md = (out / "results.md").read_text().split("## Scene zoo")[1].split("\n## ")[0]
    table = [ln for ln in md.splitlines() if ln.startswith("| ") and not ln.startswith("| scene")]
    assert [ln.split(" | ")[0][2:] for ln in table] == names
    for ln in table:
        cells = ln.strip("| ").split(" | ")
        for c in cells[2:5]:  # default, paper, oracle dB: a number (∞ for the clean float oracle)
            v = c.split(" ")[0]
            assert v == "∞" or math.isfinite(float(v)), (cells[0], c)
        assert cells[-1] in ("yes", "no"), cells
    assert "default ≥ paper − 0.2 dB on" in md


def test_shared_server_survives_a_timeout():
    """--quick runs every job on one worker: a hung job is stopped and the next one still runs."""
    res = run_jobs([("selftest", {}), ("selftest", {"sleep": 60}), ("selftest", {}), ("selftest", {})],
                   isolate=False, timeout=15)  # 15 s: a worker's start (torch import) on a loaded 2-core machine
    assert "peak_bytes" in res[0] and "timed out" in res[1]["error"]
    assert "peak_bytes" in res[2] and "peak_bytes" in res[3]
    assert res[2]["pid"] == res[3]["pid"] != res[0]["pid"]  # restarted once, then reused


def test_torchmetal_bench_verb_forwards_options(capsys):
    from torchmetal.cli import main

    assert main(["bench", "--quick", "--sections", "bogus"]) == 2
    assert "bogus" in capsys.readouterr().err
