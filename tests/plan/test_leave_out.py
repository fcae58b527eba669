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


def test_a_pixel_every_refit_snapped_flat_gets_the_flat_tests_floor_not_zero():
    """Refits that all give exactly (0, 0, 1) agree, so the jackknife alone says radius 0; where the material's own
    normal is the flat test's (0, 0, 1), the radius is at least the tilt that test could not reject (the floor map),
    and elsewhere the jackknife's own (2026-12-07: 15 % of the pixels of random scenes had radius 0, 26 % covered)."""
    from torchmetal.plan.leave_out import normals_jackknife

    h, w, n = 2, 3, 6
    full = torch.zeros(3, h, w, dtype=torch.float64)
    full[2] = 1.0
    full[:, 1, 2] = torch.tensor([math.sin(0.1), 0.0, math.cos(0.1)], dtype=torch.float64)  # a kept tilt
    reps = full.expand(n, 3, h, w).clone()  # every refit the same: no spread anywhere
    floor = torch.full((h, w), 1.5, dtype=torch.float64)
    floor[0, 1] = 0.25
    inside = torch.ones(h, w, dtype=torch.bool)
    got = normals_jackknife(full, reps, inside, flat_floor_deg=floor)
    want = floor.clone()
    want[1, 2] = 0.0  # not set flat: the refits' agreement is all there is
    assert torch.allclose(got["radius_deg"], want, rtol=0, atol=1e-9)  # the tilted pixel: 0 up to rounding
    assert got["median_radius_deg"] == pytest.approx(float(want.median()))
    assert float(normals_jackknife(full, reps, inside)["radius_deg"].max()) < 1e-9  # without the floor: all 0
    with pytest.raises(InputError, match="flat_floor_deg"):
        normals_jackknife(full, reps, inside, flat_floor_deg=floor[:1])


def test_the_estimates_flat_pixels_get_the_tilt_the_test_could_not_reject():
    """normals_intervals of the estimate on a flat, noisy sample: the flat test sets (nearly) every pixel flat in the
    full fit and in the refits; their radius is the floor of :func:`unrejected_tilt_deg` (positive, at most the
    test's 5° cut), which bounds every estimate the test set flat (the ellipse of its threshold: the estimate
    before the test, flat_test=False, is within the floor wherever the test snapped it)."""
    from torchmetal.normals.estimate import estimate_normals
    from torchmetal.normals.flat import FLAT_TILT_MAX, flat_where_unresolved, unrejected_tilt_deg

    cap = synth_capture(size=10, shots=6, seed=3, layout="hemisphere", bumpy=False, noise=0.01,
                        texture="procedural").capture
    got = normals_intervals(cap)
    f = got["normals"]
    snapped = (f[0] == 0) & (f[1] == 0) & (f[2] == 1) & cap.mask[0]
    assert int(snapped.sum()) > 0.9 * int(cap.mask[0].sum())
    agreed = snapped & (got["std_deg"] == 0)  # every refit exactly flat too
    assert int(agreed.sum()) > 0.5 * int(cap.mask[0].sum())
    r = got["radius_deg"][agreed]
    assert bool((r > 0).all()) and float(r.max()) <= math.degrees(math.atan(FLAT_TILT_MAX)) + 1e-9
    pre = estimate_normals(cap, flat_test=False)
    out, _ = flat_where_unresolved(cap, pre.normals, pre.s, pre.alpha)
    assert torch.equal(out, f.to(out.dtype))  # the same test as the estimate's last step
    floor = unrejected_tilt_deg(cap, out, pre.s, pre.alpha)
    assert torch.allclose(got["radius_deg"][agreed], floor[agreed])
    tilt = torch.rad2deg(torch.acos(pre.normals.double()[2].clamp(-1, 1)))
    ratio = tilt[snapped] / floor[snapped]  # the test snapped nothing steeper than the floor (up to its linearisation:
    assert float(ratio.max()) < 1.1 and float(ratio.median()) < 0.6  # the 10x10 image's few pixels per robust scale)
    assert not bool(floor[~snapped].any())  # a floor only where the test set a normal flat


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
