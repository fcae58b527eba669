"""Report helpers: the PSNR re-export, display encoding, ellipses, and the one-page figure.

The figure test uses a hand-made result (the true material and a Phong render function), so it
checks the drawing code alone, fast, without running a fit.
"""

import math
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from torchmetal.flakes.estimate.results import Particles  # noqa: E402
from torchmetal.flakes.model import FlakeModel  # noqa: E402
from torchmetal.phong import phong_render  # noqa: E402
from torchmetal.report import (  # noqa: E402
    exposure_for,
    lobe_samples,
    particle_ellipses,
    plot_error,
    plot_flakes,
    plot_lobe,
    psnr,
    report_figure,
    to_display,
)
from torchmetal.synth import synth_capture  # noqa: E402


class TestPSNR:
    """report.psnr is torchmetal.metrics.psnr (its own tests: tests/test_metrics.py)."""

    def test_is_the_metrics_psnr(self):
        from torchmetal import metrics

        assert psnr is metrics.psnr
        ref = torch.zeros(1, 3, 4, 4, dtype=torch.float64)
        ref[0, 0, 0, 0] = 0.5
        pred = ref + 0.1  # MSE 0.01, peak 1 (not ref.max())
        assert psnr(pred, ref) == pytest.approx(20.0, abs=1e-9)
        assert psnr(pred, ref, peak=10.0) == pytest.approx(40.0, abs=1e-9)
        assert psnr(pred, pred) == math.inf


class TestDisplay:
    @pytest.mark.parametrize("shape", [(3, 6, 7), (1, 3, 6, 7), (6, 7, 3), (6, 7)])
    def test_layouts(self, shape):
        out = to_display(torch.rand(shape))
        assert out.shape == (6, 7, 3)
        assert out.min() >= 0 and out.max() <= 1

    def test_exposure_maps_percentile_to_white(self):
        x = torch.linspace(0, 2, 3 * 100 * 100).reshape(3, 100, 100)
        k = exposure_for(x, 100.0)
        assert k == pytest.approx(0.5, rel=1e-3)
        assert to_display(x, k).max() == pytest.approx(1.0, abs=1e-6)

    def test_srgb_midpoint(self):
        # linear 0.2140 encodes to sRGB 0.5 (IEC 61966-2-1)
        out = to_display(torch.full((3, 2, 2), 0.214041), exposure=1.0)
        assert np.allclose(out, 0.5, atol=1e-4)


def _particles(rows):
    """Particles table from (shot, cy, cx, major, minor, angle) rows, other fields zero."""
    t = torch.tensor(rows, dtype=torch.float64)
    p = len(rows)
    z = torch.zeros(p)
    return Particles(shot=t[:, 0].long(), area=torch.ones(p), cy=t[:, 1], cx=t[:, 2], major=t[:, 3], minor=t[:, 4],
                     angle=t[:, 5], rgb=torch.zeros(p, 3), lab=torch.zeros(p, 3), peak=torch.zeros(p, 3), amp=z,
                     snr=z, flux=z, sigma=z)


def test_particle_ellipses_convention():
    parts = _particles([(0, 10.0, 20.0, 6.0, 2.0, math.pi / 2), (1, 3.0, 4.0, 2.0, 2.0, 0.0)])
    e0 = particle_ellipses(parts, shot=0)
    assert e0 == [pytest.approx((20.0, 10.0, 6.0, 2.0, 90.0))]  # x = column, y = row, degrees
    assert len(particle_ellipses(parts)) == 2
    assert particle_ellipses(None) == [] and particle_ellipses(parts, shot=5) == []


def test_plot_flakes_draws_ellipses_where_the_flakes_are():
    img = torch.zeros(3, 32, 32)
    img[:, 10, 20] = 1.0
    parts = _particles([(0, 10.0, 20.0, 4.0, 2.0, 0.3)])
    fig, ax = plt.subplots()
    n = plot_flakes(ax, img, parts, shot=0)
    assert n == 1 and len(ax.patches) == 1
    assert ax.patches[0].center == pytest.approx((20.0, 10.0))
    plt.close(fig)


def test_plot_lobe_and_error_smoke():
    fig, (a, b) = plt.subplots(1, 2)
    s, al = torch.tensor([0.5, 0.4, 0.3]), torch.tensor([40.0, 60.0, 80.0])
    samples = (np.array([0.0, 5.0, 10.0]), np.array([[0.5, 0.4, 0.3]] * 3))
    plot_lobe(a, s, al, truth=(s, al), samples=samples)
    assert len(a.lines) == 6  # 3 fitted + 3 truth
    # the fitted red curve starts at s_R
    assert a.lines[0].get_ydata()[0] == pytest.approx(0.5)
    ref = torch.rand(3, 8, 8)
    plot_error(b, ref + 0.01, ref, fig=fig)
    assert "PSNR" in b.get_title()
    plt.close(fig)


@pytest.fixture(scope="module")
def scene():
    flakes = FlakeModel(density=0.004, area_log_mean=math.log(8.0), color_mean=(0.9, 0.85, 0.7), seed=1)
    return synth_capture(size=48, shots=5, seed=0, texture="procedural", flakes=flakes)


def test_lobe_samples_follow_the_true_lobe(scene):
    cap, t = scene.capture, scene.truth
    ang, val = lobe_samples(cap, t["texture"], max_samples=2000)
    assert ang.shape[0] == val.shape[0] > 100 and val.shape[1] == 3
    assert np.all((ang >= 0) & (ang <= 180))
    # with the true texture the residual is the lobe plus sparkles: the median sits on the lobe
    lobe = t["s"].numpy()[None] * np.cos(np.radians(ang))[:, None].clip(0) ** t["alpha"].numpy()[None]
    assert np.median(np.abs(val - lobe)) < 1e-3


def test_report_figure_from_a_hand_made_result(scene, tmp_path):
    cap, t = scene.capture, scene.truth
    material = scene.material()
    fit = SimpleNamespace(render=lambda l, e, c: phong_render(t["texture"], t["s"], t["alpha"], cap.normals, l, e, c, cap.size))
    w = t["flake_field"].weight[0]
    ii, jj = torch.nonzero(w > 0.5, as_tuple=True)
    parts = _particles([(2, float(i), float(j), 3.0, 2.0, 0.0) for i, j in zip(ii[:20].tolist(), jj[:20].tolist())])
    result = SimpleNamespace(material=material, fit=fit, flakes=SimpleNamespace(particles=parts, model=material.flakes))
    out = tmp_path / "r" / "report.png"
    fig = report_figure(cap.subset([0, 1, 2, 3]), result, out, truth=t, heldout=cap.subset([4]), title="test")
    assert out.is_file() and out.stat().st_size > 20_000
    titles = [a.get_title() for a in fig.axes]
    assert any("fitted texture" in x for x in titles)
    assert any("specular lobe" in x for x in titles)
    assert any("20 detections in this shot" in x for x in titles)  # the busiest shot is shot 2
    assert any(x.startswith("photo (held-out") for x in titles)
    assert any("|render − photo|" in x for x in titles)
    img = plt.imread(out)
    assert img.shape[0] > 500 and img.shape[1] > 1000
