"""The whole pipeline (Phong fit → flake stage → material) on extreme, flake-free captures:
a finite material and a report that says what was skipped — or a clear one-line error."""

from __future__ import annotations

import math

import pytest
import torch

from tests.stress.helpers import with_
from torchmetal.errors import TorchmetalError
from torchmetal.fit.result import skip_stages
from torchmetal.io.capture import Capture
from torchmetal.phong import phong_render
from torchmetal.pipeline import fit_material
from torchmetal.synth import synth_capture


@pytest.fixture(scope="module")
def base() -> Capture:
    return synth_capture(size=16, shots=8, seed=6, texture="procedural").capture


def one_pixel(base: Capture) -> Capture:
    n = torch.zeros(3, 1, 1)
    n[2] = 1.0
    img = phong_render(torch.full((3, 1, 1), 0.4), torch.full((3,), 0.5), torch.tensor([20.0, 50.0, 80.0]), n,
                       base.lights, base.intensities, base.cameras, base.size)
    return Capture(images=img, normals=n, lights=base.lights, intensities=base.intensities, cameras=base.cameras, size=base.size)


def down(base: Capture) -> Capture:
    n = torch.zeros_like(base.normals)
    n[2] = -1.0
    return with_(base, normals=n, images=torch.zeros_like(base.images))


CASES = {
    "plain": lambda b: b,
    "all-black": lambda b: with_(b, images=torch.zeros_like(b.images)),
    "all-saturated": lambda b: with_(b, images=torch.ones_like(b.images), saturated=torch.ones_like(b.saturated)),
    "one-shot": lambda b: b.subset([0]),
    "one-pixel": one_pixel,
    "normals-down": down,
    "float64": lambda b: b.to(dtype=torch.float64),
    "intensity-1e-6": lambda b: with_(b, images=b.images * 1e-6, intensities=b.intensities * 1e-6),
    "intensity-1e6": lambda b: with_(b, images=b.images * 1e6, intensities=b.intensities * 1e6),
}


@pytest.mark.parametrize("case", list(CASES))
def test_pipeline_gives_a_finite_material_and_a_report(base, case):
    cap = CASES[case](base)
    try:
        res = fit_material(cap)
    except TorchmetalError as e:
        assert str(e) and "\n" not in str(e)
        return
    m = res.material
    for name in ("texture", "s", "alpha"):
        x = getattr(m, name)
        assert torch.isfinite(x).all() and (x >= 0).all(), (name, x)
    assert m.texture.shape == cap.images.shape[1:]
    rep = res.report
    assert all(math.isfinite(v) and v >= 0 for v in rep["stage_times"].values())
    assert math.isfinite(rep["rmse"])
    # no flakes in any of these captures: the stage must not invent any, and must say why it stopped
    assert m.flakes is None
    assert "flakes" in skip_stages(rep["skipped"]), rep["skipped"]


def test_pipeline_scale_invariance(base):
    """Intensities and images scaled together by 1e6: the same material."""
    ref = fit_material(base, flakes="off").material
    big = fit_material(with_(base, images=base.images * 1e6, intensities=base.intensities * 1e6), flakes="off").material
    torch.testing.assert_close(big.texture, ref.texture, rtol=1e-3, atol=1e-6)
    torch.testing.assert_close(big.s, ref.s, rtol=1e-3, atol=0)
    torch.testing.assert_close(big.alpha, ref.alpha, rtol=1e-3, atol=0)


def test_pipeline_rejects_non_finite_pixels_in_one_line(base):
    cap = with_(base)
    cap.images[0, 0, 0, 0] = float("nan")
    with pytest.raises(TorchmetalError) as e:
        fit_material(cap)
    assert "\n" not in str(e.value) and "finite" in str(e.value)
