"""gpu: skips in one line without CUDA; the same code runs device-agnostically (here on the CPU)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchmetal.bench import gpu


def test_skip_reason_matches_the_machine():
    reason = gpu.skip_reason()
    if torch.cuda.is_available():
        assert reason is None
    else:
        assert reason and "\n" not in reason and "CUDA" in reason
        assert gpu.markdown({"skipped": reason}) == f"skipped: {reason}"


@pytest.mark.skipif(torch.cuda.is_available(), reason="the skip path only exists without CUDA")
def test_main_writes_the_skip(tmp_path):
    out = tmp_path / "gpu.json"
    assert gpu.main(["cuda", "64", "4", str(out)]) == 0
    assert json.loads(out.read_text()) == {"skipped": gpu.skip_reason()}


def test_same_code_on_the_cpu():
    r = gpu.run_gpu("cpu", size=24, shots=6, flake_size=48, render_size=16, repeats=1, pipeline_size=24)
    f = r["fit"]
    assert f["device"] == "cpu" and f["seconds"] > 0
    assert f["s_err"] < 0.05 and f["alpha_err"] < 0.05 and math.isfinite(f["texture_psnr"]) and f["texture_psnr"] > 30
    assert r["flakes"]["seconds"] > 0
    assert r["renderer"]["ms_per_frame"] > 0 and r["renderer"]["finite"]
    assert "not_available" in r["onnx"] or r["onnx"]["ms_median"] > 0
    p = r["pipeline"]
    assert p["seconds"] > 0 and p["cpu_seconds"] > 0 and p["max_texture_diff_vs_cpu"] == 0.0 and p["texture_psnr"] > 25
    md = gpu.markdown(r)
    assert "fit_phong 24² × 6" in md and "flake stage 48² × 8" in md and "MaterialRenderer 16²" in md
    assert "fit_material default 24² × 8" in md and "| error |" not in md


def test_a_failing_part_is_reported_and_the_others_run(monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("q tensor must be on the same device\nsecond line")

    monkeypatch.setattr(gpu, "_flake_part", broken)
    r = gpu.run_gpu("cpu", size=16, shots=4, flake_size=32, render_size=16, repeats=1, pipeline_size=16)
    assert r["flakes"]["error"] == "RuntimeError: q tensor must be on the same device"
    assert r["flakes"]["at"].startswith("gpu.py:")  # the innermost torchmetal frame
    assert r["fit"]["seconds"] > 0 and r["renderer"]["finite"] and r["pipeline"]["seconds"] > 0
    md = gpu.markdown(r)
    assert "| flake stage ?² × ? | error | RuntimeError: q tensor must be on the same device (at gpu.py:" in md
