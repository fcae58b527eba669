"""The numpy paper process reads a capture as torchmetal does, fits it, and never imports torch."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from torchmetal.bench.children import _env
from torchmetal.bench.paper_process import main, read_capture
from torchmetal.synth.zoo import Scene, make_case


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    sc = Scene("pp", size=16, shots=5, held=2, layout="hemisphere", normals="bumpy", noise=0.01, seed=4)
    return make_case(sc, tmp_path_factory.mktemp("pp") / "cap")


def test_read_capture_decodes_like_load_capture(case):
    from torchmetal.io.capture import load_capture

    ref = load_capture(case.capture_dir)
    got = read_capture(case.capture_dir)
    assert got.images.shape == tuple(ref.images.shape)
    np.testing.assert_allclose(got.images, ref.images.numpy(), atol=2e-6)
    np.testing.assert_allclose(got.normals, ref.normals.numpy(), atol=1e-6)
    np.testing.assert_allclose(got.lights, ref.lights.numpy(), rtol=1e-6)
    np.testing.assert_allclose(got.cameras, ref.cameras.numpy(), rtol=1e-6)
    assert got.size == pytest.approx(tuple(ref.size))


def test_main_fits_without_torch(case, tmp_path):
    out = tmp_path / "fit.npz"
    code = ("import sys; from torchmetal.bench.paper_process import main; "
            f"rc = main([{str(case.capture_dir)!r}, {str(out)!r}]); print(rc, 'torch' in sys.modules)")
    p = subprocess.run([sys.executable, "-c", code], env=_env(1), capture_output=True, text=True, timeout=120)
    assert p.stdout.split() == ["0", "False"], p.stderr[-500:]
    r = np.load(out)
    assert r["texture"].shape == (3, 16, 16) and np.isfinite(r["texture"]).all()
    assert np.all(r["s"] > 0) and np.all(r["alpha"] > 1) and float(r["seconds"]) > 0


def test_main_usage_error():
    assert main([]) == 2
