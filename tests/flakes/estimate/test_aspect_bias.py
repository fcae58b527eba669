"""The flake statistics' aspect (minor/major) against flakes of known shape: the zoo's elliptical discs
(integrated over each pixel's box) in white noise, detected, associated, measured and fitted as the stage does."""

import math

import numpy as np
import pytest
import torch

from torchmetal.flakes.estimate import shot_geometry
from torchmetal.flakes.estimate.association import associate, observe
from torchmetal.flakes.estimate.detect import detect_flakes
from torchmetal.flakes.estimate.shape_colour import fit_shapes
from torchmetal.synth.zoo_flakes import flake_cover

N, SIGMA = 384, 0.01  # 300–1500 flakes: the fitted mean's own scatter over draws ≈ 0.02 (130 flakes: 0.03)


def _observed(area_median: float, aspect: tuple[float, float], density: float, seed: int = 0):
    """One shot of flakes glinting at Poisson positions, ``density`` per px (log-normal areas, σ 0.3; aspect
    uniform in ``aspect``; peak SNR log-uniform in 8–40): their observations, detections per px, the drawn
    aspects."""
    rng = np.random.default_rng(seed)
    m = rng.poisson(density * N * N)
    centre = rng.uniform(0, N, (m, 2))
    area = area_median * np.exp(0.3 * rng.normal(size=m))
    asp = rng.uniform(*aspect, m)
    major = np.sqrt(area / (math.pi * asp))
    fl = {"centre": centre, "axes": np.stack([major, major * asp], -1), "angle": rng.uniform(0, math.pi, m)}
    snr = np.exp(rng.uniform(math.log(8.0), math.log(40.0), m))
    img = np.zeros((N, N))
    for f, (rr, cc, cov) in enumerate(flake_cover(fl, N)):
        img[rr, cc] += snr[f] * SIGMA * cov
    img = 0.5 + img + SIGMA * rng.normal(size=(N, N))
    photos = torch.tensor(np.repeat(img[None, None], 3, 1))
    det = detect_flakes(photos, torch.full_like(photos, 0.5), torch.ones(1, 3, 1, 1, dtype=photos.dtype),
                        headroom=False)
    fid, count = associate(det.particles, N, N)
    flat = torch.zeros(3, N, N, dtype=torch.float64)
    flat[2] = 1.0
    above = torch.tensor([[0.0, 0.0, 10.0, 1.0]], dtype=torch.float64)
    geo = shot_geometry.Geometry(flat, above, torch.ones(1, 3, dtype=torch.float64), above, (1.0, 1.0))
    return observe(det, fid, count, geo), len(det.particles) / N**2, asp


OPEN_ASPECT_BIAS = pytest.mark.xfail(strict=True, reason=(
    "open: fit_shapes' aspect mean is the measured ellipses' mean, 0.10-0.19 low here (0.576, 0.574, 0.377 against "
    "0.744, 0.750, 0.451): noise and the pixel grid push a 2-5 px² blob's moment eigenvalues apart, the faint edge "
    "pixels fall below the hysteresis, neighbours' glints merge. A simulated inversion through the same detection "
    "fixes these cases but moves the fine flakes' colour (test_peak_weight: x0.90 -> x0.86-0.89), whose peak-weight "
    "correction leans on the low aspect and a flux/peak area biased high: 2026-12-07, the helper's measurement text"))


@OPEN_ASPECT_BIAS
@pytest.mark.parametrize(("area_median", "aspect", "density"),
                         [(2.5, (0.5, 1.0), 0.002), (4.0, (0.5, 1.0), 0.01), (3.0, (0.3, 0.6), 0.005)])
def test_fitted_aspect_mean_matches_the_drawn_flakes(area_median, aspect, density):
    """The fitted aspect mean is within 0.05 of the drawn flakes' mean (the fitted mean's own scatter over draws
    ≈ 0.02 at these 300-1500 flakes); the measured ellipses' mean is 0.07-0.18 below it."""
    obs, _, asp = _observed(area_median, aspect, density)
    truth = float(asp.mean())
    naive = float(obs.aspect[obs.snr >= 8].double().mean())
    assert naive < truth - 0.04, (naive, truth)  # the measurement's bias: there with or without a correction
    shapes = fit_shapes(obs)
    assert abs(shapes["aspect_mean"] - truth) <= 0.05, (shapes["aspect_mean"], naive, truth)
