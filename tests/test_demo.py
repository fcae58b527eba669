"""``torchmetal demo``: the report folder, sane numbers, and the command line."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchmetal.demo import run_demo, summary

# Intra-op threads for the demo runs. On a shared 2-core machine, one thread per process is both
# faster and far steadier than OpenMP threads fighting other jobs for the cores.
THREADS = os.environ.get("TORCHMETAL_TEST_THREADS", "1")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    old = torch.get_num_threads()
    torch.set_num_threads(int(THREADS))
    try:
        metrics = run_demo(out, quick=True, verbose=False)
    finally:
        torch.set_num_threads(old)
    return out, metrics


def _finite_numbers(x, path="metrics"):
    """Every number in a JSON tree is finite (non-finite ones would have become strings)."""
    if isinstance(x, dict):
        for k, v in x.items():
            _finite_numbers(v, f"{path}.{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            _finite_numbers(v, f"{path}[{i}]")
    elif isinstance(x, float):
        assert math.isfinite(x), path
    elif isinstance(x, str):
        assert x not in ("nan", "inf", "-inf"), f"{path} = {x}"


def test_files(demo):
    out, _ = demo
    assert (out / "report.png").stat().st_size > 50_000
    assert (out / "material" / "material.json").is_file()
    assert (out / "material" / "texture.npy").is_file()
    assert (out / "material" / "renderer.onnx").stat().st_size > 10_000
    assert not list(out.glob(".*tmp*")), "temporary files left behind"
    meta = json.loads((out / "material" / "material.json").read_text())
    assert meta["format"] == "torchmetal-material" and meta["flakes"] is not None


def test_metrics_json_matches_return_value(demo):
    out, metrics = demo
    on_disk = json.loads((out / "metrics.json").read_text())
    _finite_numbers(on_disk)
    assert on_disk["phong_psnr_db"] == pytest.approx(metrics["phong_psnr_db"])
    assert set(on_disk["stage_times"]) == set(metrics["stage_times"])
    assert isinstance(on_disk["skipped"], list)


def test_metric_bounds(demo):
    _, m = demo
    assert m["phong_psnr_db"] > 35
    assert m["heldout_psnr_db"] > 35
    # held-out error close to the ceiling set by noise and quantisation
    assert m["heldout_psnr_db"] > m["heldout_truth_psnr_db"] - 1.5
    assert m["texture_psnr_db"] > 30
    assert max(m["s_rel_err"]) < 0.1 and max(m["alpha_rel_err"]) < 0.1
    f = m["flakes"]
    assert f["detected"] > 10 and f["fitted"]
    assert f["density_rel_err"] < 0.5 and f["median_area_rel_err"] < 0.5 and f["color_mean_abs_err"] < 0.2
    assert 0 <= m["md_heldout"] <= 100 and 0 <= m["md_heldout_no_flakes"] <= 100
    # the sparkle term makes the render closer in MD, even though PSNR prefers no sparkle
    assert m["md_heldout"] < m["md_heldout_no_flakes"]
    assert all(v >= 0 for v in m["stage_times"].values())
    assert m["demo_times"]["total"] > 0


def test_figure_is_a_real_image(demo):
    import matplotlib.pyplot as plt

    out, _ = demo
    img = plt.imread(out / "report.png")
    assert img.ndim == 3 and img.shape[0] > 600 and img.shape[1] > 1000
    assert float(np.std(img[..., :3])) > 0.05  # not blank


def test_summary_mentions_the_numbers(demo):
    out, m = demo
    text = summary(m, out)
    assert f"{m['phong_psnr_db']:.1f} dB" in text and "MD" in text and "report.png" in text


def test_cli_demo(tmp_path):
    out = tmp_path / "cli"
    proc = subprocess.run(
        [sys.executable, "-m", "torchmetal", "demo", "--quick", "--size", "64", "-o", str(out)],
        capture_output=True, text=True, timeout=300, cwd=Path(__file__).resolve().parents[1],
        env={**os.environ, "OMP_NUM_THREADS": THREADS, "MKL_NUM_THREADS": THREADS},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "torchmetal demo" in proc.stdout and "PSNR" in proc.stdout
    assert (out / "report.png").is_file() and (out / "metrics.json").is_file()


def test_demo_fails_loudly(tmp_path, monkeypatch):
    """A stage that raises makes the demo (and the CLI) fail, never a silent partial report."""
    import torchmetal.pipeline as pipeline

    def broken(*args, **kwargs):
        raise RuntimeError("stage exploded")

    monkeypatch.setattr(pipeline, "fit_material", broken)
    with pytest.raises(RuntimeError, match="stage exploded"):
        run_demo(tmp_path / "x", size=32, quick=True, verbose=False)
    assert not (tmp_path / "x" / "metrics.json").exists()
