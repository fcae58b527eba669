"""Memory: a capture whose unchunked fit would exceed a set memory budget is fitted in pixel chunks
(``fit_phong(max_pixels_per_chunk=…)``) within that budget, with the same result.

Each fit runs in its own child process (the benchmark's worker), and its peak resident memory
above the loaded capture is read from the kernel's high-water mark, so the two runs cannot
contaminate each other.
"""

from __future__ import annotations

import pytest

from torchmetal.bench.children import run_jobs
from torchmetal.bench.tasks import task_prepare

BUDGET = 80 * 2**20  # working memory a fit may use above the loaded capture
SIZE, SHOTS = 256, 6  # 4.5 MiB of float32 images; an unchunked fit needs ~170 MiB of temporaries


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("mem") / "capture.pt")
    task_prepare({"path": path, "size": SIZE, "shots": SHOTS, "noise": 0.01, "holdout": 0, "seed": 5})
    jobs = []
    for chunk in (SIZE * SIZE, 1024):
        jobs.append(("method", {"path": path, "method": "torchmetal", "specular": "global",
                                "fit_kwargs": {"max_pixels_per_chunk": chunk}}))
    res = run_jobs(jobs, isolate=True, timeout=50)
    for r in res:
        assert "error" not in r and "not_available" not in r, r
    return res[0], res[1]


def test_unchunked_fit_would_exceed_the_budget(runs):
    whole, _ = runs
    assert whole["peak_bytes"] > BUDGET, f"test is vacuous: unchunked peak {whole['peak_bytes'] / 2**20:.0f} MiB"


def test_chunked_fit_stays_within_the_budget(runs):
    _, chunked = runs
    assert chunked["peak_bytes"] <= BUDGET, f"chunked peak {chunked['peak_bytes'] / 2**20:.0f} MiB > {BUDGET / 2**20:.0f} MiB"


def test_chunked_fit_gives_the_same_result(runs):
    whole, chunked = runs
    for key in ("s", "alpha"):
        for a, b in zip(whole[key], chunked[key]):
            assert a == pytest.approx(b, rel=1e-5)
    assert chunked["texture_sum"] == pytest.approx(whole["texture_sum"], rel=1e-6)
    assert chunked["texture_abs_max"] == pytest.approx(whole["texture_abs_max"], rel=1e-5)
    assert chunked["psnr_texture"] == pytest.approx(whole["psnr_texture"], abs=0.01)
    assert chunked["psnr_texture"] > 40.0
