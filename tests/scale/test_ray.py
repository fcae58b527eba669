"""fit-many on a local Ray cluster (ray.init(num_cpus=2)): the same materials as single fits, a
killed worker's task retried, a resumed run redoes nothing. One test: Ray start-up is slow."""

import os
from pathlib import Path

import pytest
import torch

from torchmetal.cli import main
from torchmetal.scale.fit_many import fit_many

from .helpers import kill_once_task, make_captures, material_fingerprint, never_task

ray = pytest.importorskip("ray", reason="ray is not installed (pip install torchmetal[ray])")

FIT_ARGS = ["--flakes", "off", "--max-iters", "30"]


@pytest.fixture(scope="module")
def cluster():
    root = str(Path(__file__).resolve().parents[2])  # workers import tests.scale.helpers
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_ray_fit_many_retry_resume(cluster, tmp_path):
    caps = make_captures(tmp_path / "caps")
    for cap in caps:
        assert main(["fit", str(cap), "-o", str(tmp_path / "single" / cap.name), *FIT_ARGS, "-q"]) == 0
    out = tmp_path / "out"
    recs = fit_many(caps, out, fit_args=FIT_ARGS, engine="ray", workers=2, progress=False, task=kill_once_task)
    by = {r.name: r for r in recs}
    assert all(r.status == "ok" for r in recs), [r.errors for r in recs]
    assert by["cap1"].attempts == 2 and "Worker" in by["cap1"].errors[0]  # the crash is recorded, then retried
    for cap in caps:
        assert material_fingerprint(out / cap.name) == material_fingerprint(tmp_path / "single" / cap.name)
    again = fit_many(caps, out, fit_args=FIT_ARGS, engine="ray", workers=2, progress=False, task=never_task)
    assert [r.status for r in again] == ["resumed"] * 3


def test_ray_tiled_fit_equals_in_process(cluster, tmp_path):
    """The tiled fit's tile tasks on Ray workers: the same fit as in this process, bit for bit."""
    from torchmetal.scale.tiled import fit_tiled
    from torchmetal.scale.tiles import convert_capture
    from torchmetal.synth import synth_capture, write_synth

    write_synth(synth_capture(size=64, shots=6, seed=4, noise=0.003), tmp_path / "cap")
    cap = convert_capture(tmp_path / "cap", tmp_path / "tiled")
    kw = dict(tile=32, sub_pixels=1024, select_pixels=256, max_iters=20)
    here = fit_tiled(cap, scratch=tmp_path / "here", **kw)
    on_ray = fit_tiled(cap, scratch=tmp_path / "ray", engine="ray", workers=2, threads=1, **kw)
    assert on_ray.tiled["engine"] == "ray"
    assert torch.equal(on_ray.s, here.s) and torch.equal(on_ray.alpha, here.alpha)
    assert torch.equal(on_ray.texture, here.texture)
