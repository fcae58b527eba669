"""The benchmark's baselines must be honest references: they recover the truth on easy data."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from torchmetal.bench.baselines import adam_fit, capture_arrays, np_render, paper_scheme_numpy
from torchmetal.phong import phong_render
from torchmetal.synth import synth_capture

S_TRUE = (0.6, 0.5, 0.4)
A_TRUE = (40.0, 120.0, 300.0)


@pytest.fixture(scope="module")
def tiny():
    """16² × 8 shots, noise-free float images (no quantisation, nothing saturated)."""
    return synth_capture(size=16, shots=8, seed=3, s=S_TRUE, alpha=A_TRUE, texture="procedural")


def _rel(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b) / np.abs(b)))


def _texture_err(texture, truth) -> float:
    t = truth.numpy().astype(np.float64)
    return float(np.max(np.abs(np.asarray(texture) - t)) / t.max())


def test_paper_scheme_numpy_recovers_truth(tiny):
    r = paper_scheme_numpy(tiny.capture)
    assert r.status == "converged"
    assert 2 <= r.iterations < 100
    assert _rel(r.s, S_TRUE) < 2e-3
    assert _rel(r.alpha, A_TRUE) < 2e-3
    assert _texture_err(r.texture, tiny.truth["texture"]) < 2e-3
    assert r.history[-1] <= r.history[0]
    for stage in ("geometry", "init", "specular", "texture", "error"):
        assert r.stage_times[stage] >= 0


def test_paper_scheme_numpy_initial_approximation_is_close(tiny):
    """4.1.6: T_min minus the fitted X(p) already lands near the truth after one iteration."""
    one = paper_scheme_numpy(tiny.capture, max_iters=1)
    assert one.status == "max_iters" and one.iterations == 1
    assert _rel(one.s, S_TRUE) < 0.1
    assert _rel(one.alpha, A_TRUE) < 0.1


def test_adam_fit_recovers_truth(tiny):
    r = adam_fit(tiny.capture, steps=800)
    assert r.iterations == 800
    assert _rel(r.s, S_TRUE) < 2e-2
    assert _rel(r.alpha, A_TRUE) < 2e-2
    assert _texture_err(r.texture, tiny.truth["texture"]) < 1e-2
    assert r.history[-1] < 1e-3 * r.history[0]


def test_adam_fit_respects_time_budget(tiny):
    r = adam_fit(tiny.capture, steps=10**6, time_budget=0.3)
    assert r.status == "time_budget"
    assert r.iterations < 10**6
    assert r.seconds < 5.0


def test_np_render_matches_torch_phong(tiny):
    cap = tiny.capture
    t = tiny.truth
    ref = phong_render(t["texture"].double(), t["s"].double(), t["alpha"].double(), cap.normals.double(),
                       cap.lights.double(), cap.intensities.double(), cap.cameras.double(), cap.size)
    out = np_render(t["texture"].numpy(), t["s"].numpy(), t["alpha"].numpy(), cap.normals.numpy(), cap.lights.numpy(),
                    cap.intensities.numpy(), cap.cameras.numpy(), cap.size)
    np.testing.assert_allclose(out, ref.numpy(), rtol=1e-9, atol=1e-12 * float(ref.max()))


def test_paper_scheme_numpy_ignores_saturated_and_masked_pixels(tiny):
    """Garbage in observations flagged saturated / outside the mask must not move the fit."""
    cap = tiny.capture
    images = cap.images.clone()
    sat = torch.zeros_like(cap.saturated)
    sat[0, :, :4] = True
    images[0, :, :4] = 50.0  # absurd values, flagged saturated
    mask = torch.ones_like(cap.mask)
    mask[:, -3:, :] = False
    images[:, :, -3:, :] = 0.0  # black outside the mask
    fake = types.SimpleNamespace(images=images, normals=cap.normals, mask=mask, saturated=sat, lights=cap.lights,
                                 intensities=cap.intensities, cameras=cap.cameras, size=cap.size)
    r = paper_scheme_numpy(fake)
    assert _rel(r.s, S_TRUE) < 5e-3
    assert _rel(r.alpha, A_TRUE) < 5e-3
    inside = tiny.truth["texture"][:, :-3].numpy()
    assert float(np.max(np.abs(r.texture[:, :-3] - inside))) < 5e-3 * inside.max()


def test_paper_scheme_numpy_specular_free_scene():
    res = synth_capture(size=12, shots=6, seed=1, s=(0.0, 0.0, 0.0), texture="procedural")
    r = paper_scheme_numpy(res.capture)
    assert np.all(np.isfinite(r.s)) and np.all(np.isfinite(r.alpha)) and np.all(np.isfinite(r.texture))
    assert float(np.max(r.s)) < 1e-3
    assert _texture_err(r.texture, res.truth["texture"]) < 1e-3


def test_capture_arrays_valid_mask(tiny):
    a = capture_arrays(tiny.capture)
    assert a["images"].shape == tuple(tiny.capture.images.shape)
    assert a["valid"].all()
    assert a["normals"].shape == (3, 16, 16)


def test_paper_scheme_numpy_runs_without_torch(tmp_path: Path, tiny):
    """Baseline (a) is numpy/scipy only: it runs in a process where importing torch fails."""
    cap = tiny.capture
    arrays = {k: getattr(cap, k).numpy() for k in ("images", "normals", "lights", "intensities", "cameras")}
    np.savez(tmp_path / "cap.npz", **arrays)
    script = textwrap.dedent(f"""
        import sys, types, json, importlib.util
        sys.modules["torch"] = None  # any "import torch" now raises ImportError
        import numpy as np
        spec = importlib.util.spec_from_file_location("bl", {str(Path(__file__).resolve().parents[2] / "torchmetal/bench/baselines.py")!r})
        bl = importlib.util.module_from_spec(spec); sys.modules["bl"] = bl; spec.loader.exec_module(bl)
        d = np.load({str(tmp_path / "cap.npz")!r})
        cap = types.SimpleNamespace(size={tuple(cap.size)!r}, **{{k: d[k] for k in d.files}})
        r = bl.paper_scheme_numpy(cap)
        print(json.dumps({{"s": r.s.tolist(), "alpha": r.alpha.tolist(), "torch": "torch" in sys.modules and sys.modules["torch"] is not None}}))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["torch"] is False
    assert _rel(got["s"], S_TRUE) < 2e-3 and _rel(got["alpha"], A_TRUE) < 2e-3
