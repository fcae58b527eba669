"""Fine bright flakes: the colour is the peak amplitude over the field's brightest footprint weight.

A detection's amplitude is the flake's colour times the weight of its brightest pixel (below 1 for a fine
flake), and the field renders c·w again: without the correction the colour came out ×0.8 on area-2 px²
flakes and their left-out sparkles fewer than the truth's."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.flakes.scenes import capture_of, layout, make_scene
from torchmetal.errors import InputError
from torchmetal.flakes.estimate.shape_colour import fit_colour
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.field import flake_field, mean_peak_weight, sparkle_render
from torchmetal.flakes.stage import flake_stage
from torchmetal.metrics import sparkle_count

SIZE, SHOTS, SEED = 256, 10, 3
TRUE = dict(density=0.012, area_log_mean=math.log(2.5), area_log_std=0.3, tilt_sigma=0.15, glint_sigma=0.03,
            color_mean=(0.8, 0.8, 0.8))


def test_peak_weight_is_below_one_for_fine_flakes_and_grows_with_area():
    w = [mean_peak_weight(math.log(a), 0.3, 0.8, 0.1) for a in (1.5, 2.0, 4.0, 16.0)]
    assert w[0] < w[1] < w[2] <= w[3] <= 1.0
    assert w[0] < 0.85 and w[3] > 0.99
    assert mean_peak_weight(math.log(2.0), 0.3, 0.8, 0.1) == w[1]  # deterministic draws


def test_a_peak_weight_outside_0_1_is_an_input_error():
    with pytest.raises(InputError, match="peak_weight"):
        fit_colour(None, None, peak_weight=0.0)


@pytest.fixture(scope="module")
def fitted():
    truth = FlakeModel(seed=SEED, **TRUE)
    sc = make_scene(SIZE, SIZE, truth, texture="noise", kind="pairs", shots=SHOTS, seed=SEED)
    return sc, truth, flake_stage(capture_of(sc), sc.phong, seed=SEED + 1)


def test_fine_bright_flakes_colour_within_10_percent(fitted):
    sc, truth, res = fitted
    assert res.model is not None, res.report.get("skipped")
    realised = float(sc.field.color[:, sc.field.weight[0] > 0].mean())  # the colour of the flakes drawn
    assert abs(float(np.mean(res.model.color_mean)) / realised - 1) < 0.10


def test_fine_bright_flakes_left_out_sparkles_within_0_8_to_1_25(fitted):
    sc, truth, res = fitted
    lights, inten, cams = layout("pairs", SHOTS + 4)  # shots the fit did not see
    held = slice(SHOTS, SHOTS + 4)
    gen = torch.Generator().manual_seed(0)
    counts = []
    for model in (truth, res.model):
        img = sparkle_render(flake_field(model, SIZE, SIZE, sc.normals), sc.normals, lights[held], inten[held],
                             cams[held], sc.size)
        img = img + 0.005 * torch.randn(img.shape, generator=gen)  # a photo's noise: the count's σ
        counts.append(sum(sparkle_count(im) for im in img))
    assert counts[0] >= 30, counts  # enough sparkles for a ratio
    assert 0.8 <= counts[1] / counts[0] <= 1.25, counts
