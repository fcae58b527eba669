"""Intervals by refits with one shot left out: estimated normals and flake statistics."""

from __future__ import annotations

import math

import pytest
import torch

from torchmetal.errors import InputError
from torchmetal.flakes.model import FlakeModel
from torchmetal.plan.leave_out import angle_deg, f2_quantile, flake_intervals, normals_intervals
from torchmetal.synth import synth_capture


@pytest.fixture(scope="module")
def capture():
    return synth_capture(size=12, shots=5, seed=3, layout="hemisphere", bumpy=True, noise=0.01, texture="procedural").capture


def test_f2_quantile():
    assert f2_quantile(0.9, 1) == pytest.approx(49.5)  # F(2, 1): 1/2·(0.1^-2 − 1)
    assert f2_quantile(0.9, 10**6) == pytest.approx(math.log(10), rel=1e-5)
    assert f2_quantile(0.9, 4) > f2_quantile(0.9, 40)


def _left_out_index(full, sub) -> int:
    """Which shot ``sub`` lacks (its cameras are a subset of ``full``'s)."""
    kept = {tuple(c) for c in sub.cameras.tolist()}
    return next(i for i, c in enumerate(full.cameras.tolist()) if tuple(c) not in kept)


def test_normals_jackknife_math(capture):
    n = capture.num_shots
    tilt = {i: 0.01 * (i - (n - 1) / 2) for i in range(n)}  # symmetric: the refits' mean stays (0, 0, 1)

    def estimate(c):
        a = 0.0 if c.num_shots == n else tilt[_left_out_index(capture, c)]
        out = torch.zeros(3, c.height, c.width, dtype=torch.float64)
        out[0], out[2] = math.sin(a), math.cos(a)
        return out

    got = normals_intervals(capture, estimate=estimate)
    std = math.sqrt((n - 1) / n * sum(a * a for a in tilt.values()))
    assert float(got["std_deg"][0, 0]) == pytest.approx(math.degrees(std), rel=1e-6)
    assert float(got["radius_deg"][3, 4]) == pytest.approx(math.degrees(std) * math.sqrt(f2_quantile(0.9, n - 1)), rel=1e-6)
    assert got["refits"].shape == (n, 3, capture.height, capture.width)
    assert got["median_radius_deg"] == pytest.approx(float(got["radius_deg"][0, 0]), rel=1e-6)


def test_normals_intervals_of_the_estimate(capture):
    got = normals_intervals(capture)
    assert got["radius_deg"].shape == (capture.height, capture.width)
    assert bool(torch.isfinite(got["radius_deg"]).all()) and float(got["radius_deg"].max()) > 0
    assert bool((angle_deg(got["normals"], got["normals"]) < 1e-3).all())


def test_normals_need_four_shots(capture):
    with pytest.raises(InputError, match="at least 4 shots"):
        normals_intervals(capture.subset([0, 1, 2]))


def test_flake_jackknife_log_scale_and_failed_refits(capture):
    n = capture.num_shots
    dens = {i: 0.004 * math.exp(0.1 * (i - 2)) for i in range(n)}

    def fit(c):
        if c.num_shots == n:
            return FlakeModel(density=0.004)
        i = _left_out_index(capture, c)
        return None if i == n - 1 else FlakeModel(density=dens[i], tilt_sigma=0.1 + 0.01 * i)

    got = flake_intervals(capture, fit=fit)
    assert got["failed_refits"] == 1
    logs = torch.tensor([math.log(dens[i]) for i in range(n - 1)], dtype=torch.float64)
    m = n - 1
    std = float(((m - 1) / m * ((logs - logs.mean()) ** 2).sum()).sqrt())
    d = got["density"]
    assert d["scale"] == "log" and d["std"] == pytest.approx(std, rel=1e-9)
    assert d["low"] < 0.004 < d["high"] and d["low"] * d["high"] == pytest.approx(0.004**2, rel=1e-9)  # symmetric in log
    assert got["aspect_mean"]["std"] == pytest.approx(0.0, abs=1e-12)  # every refit the same
    with pytest.raises(InputError, match="no flake model"):
        flake_intervals(capture, fit=lambda c: None)


def test_flake_intervals_stay_in_the_statistics_range():
    """A symmetric interval around a small aspect or colour would leave its range: it is cut at 0 (aspect also at 1),
    and a statistic every refit agrees on has the value at both ends exactly (log scale included)."""
    from torchmetal.plan.leave_out import flake_jackknife

    full = FlakeModel(density=0.004, aspect_mean=0.1, color_mean=(0.05, 0.5, 0.5))
    reps = [FlakeModel(density=0.004, aspect_mean=a, color_mean=(c, 0.5, 0.5))
            for a, c in ((0.05, 0.01), (0.4, 0.2), (0.1, 0.05), (0.95, 0.3))]
    got = flake_jackknife(full, reps)
    assert got["aspect_mean"]["low"] == 0.0 and got["aspect_mean"]["high"] <= 1.0
    assert got["color_r"]["low"] == 0.0 < got["color_r"]["high"]
    for name in ("density", "glint_sigma", "color_g"):
        assert got[name]["low"] == got[name]["value"] == got[name]["high"], (name, got[name])
