"""The flake2d port and the FlakeModel → flake2d mapping, checked by glint statistics."""

import math

import numpy as np
import pytest

from torchmetal.errors import ExportError
from torchmetal.flakes.model import FlakeModel
from torchmetal.formats.flake2d import (
    density_to_probability,
    fit_flake_roughness,
    flake2d_inputs,
    flake2d_pattern,
    glint_statistics,
    slope_density_ggx,
)


def test_probability_curve():
    p = density_to_probability(np.linspace(0, 1, 101))
    assert p[0] == 0 and bool((np.diff(p) > 0).all())


def test_pattern_normals_are_ggx_samples():
    """Per flake, tan θ of flake2d's normal is a GGX sample: median tan θ = roughness²."""
    t = (np.arange(400) + 0.5) / 400
    yy, xx = np.meshgrid(t, t, indexing="ij")
    key, n = flake2d_pattern(np.stack([xx.ravel(), yy.ravel()], 1), size=0.01, roughness=0.5, coverage=0.3)
    _, first = np.unique(key[key >= 0], return_index=True)
    m = n[key >= 0][first]
    assert len(m) > 500
    tan = np.sqrt(m[:, 0] ** 2 + m[:, 1] ** 2) / m[:, 2]
    assert np.median(tan) == pytest.approx(0.25, rel=0.1)
    assert bool((n[key < 0] == (0, 0, 1)).all())


def test_roughness_fit_is_better_than_median_match():
    r, err = fit_flake_roughness(0.15)
    s = np.linspace(0, 0.45, 200)
    ref = np.exp(-s * s / (2 * 0.15**2)) / (2 * math.pi * 0.15**2)
    a0 = 0.15 * math.sqrt(2 * math.log(2))
    e0 = math.sqrt(((s * (slope_density_ggx(s, a0) - ref) ** 2).sum()) / (s * ref * ref).sum())
    assert err < e0 and err < 0.25


@pytest.mark.parametrize("model", [FlakeModel(0.02, area_log_mean=1.5, tilt_sigma=0.12, glint_sigma=0.05, seed=3),
                                   FlakeModel(0.01, area_log_mean=math.log(6.0), tilt_sigma=0.15, glint_sigma=0.05, seed=1)])
def test_glint_statistics_match(model):
    inp = flake2d_inputs(model, 256)
    st = glint_statistics(model, inp, 256, height_px=160)
    for key in ("covered_fraction", "flakes_per_texel", "mean_area_texels"):
        ours, theirs = st[key]
        assert theirs == pytest.approx(ours, rel=0.3), (key, st)
    for tilt, (ours, theirs) in st["glinting"].items():
        if ours > 0.05:
            assert theirs == pytest.approx(ours, rel=0.4), (tilt, st)


def test_a_dense_layer_takes_the_coverage_the_field_draws():
    """Density × mean area ≥ 0.95 (the real card at capacity: 0.111/px, ~10 px² flakes): the field clamps
    each flake to its 3-px cell, and flake2d matches what it draws instead of refusing the material."""
    model = FlakeModel(0.1, area_log_mean=math.log(20.0), seed=2)
    inp = flake2d_inputs(model, 256)
    assert inp.drawn and 0.0 < inp.covered_fraction < 0.95
    st = glint_statistics(model, inp, 256, height_px=160)
    for key in ("covered_fraction", "flakes_per_texel"):
        ours, theirs = st[key]
        assert theirs == pytest.approx(ours, rel=0.3), (key, st)


def test_too_dense_is_one_line(monkeypatch):
    from torchmetal.formats import flake2d

    monkeypatch.setattr(flake2d, "drawn_coverage", lambda model: (0.97, model.density))
    with pytest.raises(ExportError, match="covered fraction"):
        flake2d_inputs(FlakeModel(0.1, area_log_mean=math.log(20.0)), 256)
