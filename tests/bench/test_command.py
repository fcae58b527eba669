"""The command section: fresh processes timed, both fits scored against the clean truth."""

from __future__ import annotations

import math
import sys

import pytest

from torchmetal.bench import command
from torchmetal.bench.children import _env


@pytest.fixture(scope="module")
def row(tmp_path_factory):
    return command.run_case(command.fit_scene(24, 4), tmp_path_factory.mktemp("cmd"), _env(1), 300.0)


def test_case_row_times_and_errors(row):
    tm, ip, pp = row["torchmetal"], row["inproc"], row["paper_numpy"]
    assert "error" not in tm and "error" not in ip and "error" not in pp, (tm, ip, pp)
    assert tm["wall_s"] > 0 and pp["wall_s"] > 0 and ip["wall_s"] > 0
    assert ip["wall_s"] < tm["wall_s"]  # the whole command includes the interpreter start
    assert 0 < pp["fit_s"] < pp["wall_s"]
    assert math.isfinite(tm["psnr_truth"]) and math.isfinite(pp["psnr_truth"])
    assert tm["psnr_truth"] > 30 and pp["psnr_truth"] > 30  # both fits actually fit the clean truth
    assert tm["peak_rss_bytes"] > 0 and ip["peak_bytes"] >= 0
    assert ip["capture_f32_bytes"] == 4 * 3 * 24 * 24 * 4


def test_markdown_has_every_table(row):
    su = {"torchmetal --help": {"runs": [0.2, 0.3], "median_s": 0.25}}
    md = command.markdown({"fits": [row], "dome": None, "startup": su, "memory": [24, 4]})
    assert "| 24² × 4 |" in md and "torchmetal --help" in md and "peak / capture" in md


def test_speedup_needs_equal_error():
    fast_worse = {"torchmetal": {"wall_s": 1.0, "psnr_truth": 40.0}, "paper_numpy": {"wall_s": 10.0, "psnr_truth": 41.0}}
    assert command.speedup(fast_worse)[0] is None and "worse" in command.speedup(fast_worse)[1]
    fast_equal = {"torchmetal": {"wall_s": 1.0, "psnr_truth": 40.95}, "paper_numpy": {"wall_s": 10.0, "psnr_truth": 41.0}}
    assert command.speedup(fast_equal)[0] == pytest.approx(10.0)


def test_startup_medians_are_positive():
    su = command.startup(_env(1), 1)
    for name in ("torchmetal --help", 'python -c "import torchmetal"'):
        assert su[name]["median_s"] > 0, su


def test_timed_process_failures_are_rows():
    assert "exit 3" in command.timed_process([sys.executable, "-c", "import sys; sys.exit(3)"], _env(), 30)["error"]
    assert "timed out" in command.timed_process([sys.executable, "-c", "import time; time.sleep(5)"], _env(), 0.3)["error"]


def test_plans():
    assert (2048, 8) not in command.command_plan("full")["fits"]
    assert (2048, 16) in command.command_plan("full", full=True)["fits"]
    assert command.command_plan("quick", full=True)["fits"] == [(24, 4)]


def test_torch_import_floor_is_reported_only_where_it_binds():
    rows = {"fits": [{"scene": "fit1024x8", "size": 1024, "shots": 8, "paper_numpy": {"wall_s": 7.2}}],
            "dome": {"scene": "dome72", "size": 150, "shots": 66, "paper_numpy": {"wall_s": 40.0}}}
    line = command._torch_floor(rows, 1.9)
    assert "fit1024x8: ≥ 10× needs the whole command in ≤ 0.72 s" in line and "1.90 s" in line
    assert "dome72" not in line  # 40 s / 2 = 20 s is above the import
    assert command._torch_floor(rows, None) == ""
