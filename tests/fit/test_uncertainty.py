"""torchmetal.fit.uncertainty: the fit's intervals are finite, shrink with more shots, cover the truth."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchmetal.errors import InputError
from torchmetal.fit import fit_phong
from torchmetal.fit.uncertainty import UncertaintyOptions, _sandwich, estimate_uncertainty, fit_uncertainty
from torchmetal.io.capture import load_capture
from torchmetal.synth.zoo import Scene, make_case


def _scene(shots: int, seed: int = 43901) -> Scene:
    return Scene("unc", size=48, shots=shots, held=1, layout="hemisphere", encoding="linear16", noise=0.01, s=0.5,
                 alpha=60.0, seed=seed)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """(case, capture, fit, uncertainty) for 4 and for 10 shots of the same scene (the first 4 shared)."""
    out = {}
    case = make_case(_scene(10), tmp_path_factory.mktemp("unc"))
    cap = load_capture(case.capture_dir)
    for n in (4, 10):
        sub = cap.subset(list(range(n)))
        fit = fit_phong(sub, specular="global", lobe="phong")
        out[n] = (case, sub, fit, estimate_uncertainty(fit, sub))
    return out


def test_intervals_finite_and_ordered(fitted):
    _, _, fit, u = fitted[10]
    assert u.method == [["curvature"] * 3]
    for t in (u.s_std, u.beta_std, u.s_lo, u.s_hi, u.alpha_lo, u.alpha_hi):
        assert bool(torch.isfinite(t).all())
    assert bool((u.s_lo < u.s).all() and (u.s < u.s_hi).all())
    assert bool((u.alpha_lo < u.alpha).all() and (u.alpha < u.alpha_hi).all())
    assert u.texture_std.shape == fit.texture.shape
    assert bool(torch.isfinite(u.texture_std).all() and (u.texture_std > 0).all())


def test_intervals_shrink_with_more_shots(fitted):
    u4, u10 = fitted[4][3], fitted[10][3]
    assert bool((u10.s_std < u4.s_std).all())
    assert bool((u10.beta_std < u4.beta_std).all())
    assert float(u10.texture_std.median()) < float(u4.texture_std.median())


def test_intervals_cover_the_truth(fitted):
    for n in (4, 10):
        case, _, fit, u = fitted[n]
        sc = case.scene
        # 90 % intervals: all six of s and α inside would fail by chance 1 - 0.9^6 = 47 % of the time; 4 of 6 is the bar
        inside = int(((u.s_lo <= sc.s) & (sc.s <= u.s_hi)).sum() + ((u.alpha_lo <= sc.alpha) & (sc.alpha <= u.alpha_hi)).sum())
        assert inside >= 4, (n, u.s, u.s_lo, u.s_hi, u.alpha, u.alpha_lo, u.alpha_hi)
        lo, hi = u.texture_interval(fit.texture.double())
        truth = torch.as_tensor(case.truth.texture)
        cover = float(((truth >= lo) & (truth <= hi)).double().mean())
        assert 0.82 <= cover <= 0.97, (n, cover)


def test_dict_is_json_and_unseen_specular(tmp_path):
    case = make_case(_scene(4), tmp_path)
    cap = load_capture(case.capture_dir)
    fit = fit_phong(cap, specular="none", lobe="phong")
    d = fit_uncertainty(fit, cap)
    json.dumps(d)
    assert d["globals"]["method"] == [["unseen"] * 3]
    assert d["globals"]["s"]["hi"] == [[None] * 3]  # s in [0, ∞): no highlight, no upper bound
    assert d["texture"]["r"]["std_median"] > 0


def test_bound_uses_jackknife(fitted):
    case, cap, fit, _ = fitted[10]
    pinned = fit_phong(cap, specular="global", lobe="phong")
    pinned.alpha = torch.full_like(pinned.alpha, 1.0)  # α at its lower bound: curvature is not valid there
    u = estimate_uncertainty(pinned, cap, UncertaintyOptions(jackknife_pixels=1 << 10))
    assert u.method == [["jackknife"] * 3]
    assert bool(torch.isfinite(u.jack_s_std).all())
    assert bool((u.alpha_lo == 1.0).all())  # the bound stays that side of the interval
    off = estimate_uncertainty(pinned, cap, UncertaintyOptions(jackknife="off"))
    assert off.method == [["bound"] * 3]


def test_sandwich_is_inverse_when_weights_match():
    H = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=torch.float64)
    cov = _sandwich(H, H)
    assert torch.allclose(cov, torch.linalg.inv(H))
    singular = _sandwich(torch.ones(2, 2, dtype=torch.float64), H)
    assert bool(torch.isnan(singular).all())


def test_bad_options(fitted):
    _, cap, fit, _ = fitted[4]
    with pytest.raises(InputError, match="level"):
        estimate_uncertainty(fit, cap, UncertaintyOptions(level=1.5))
    with pytest.raises(InputError, match="jackknife"):
        estimate_uncertainty(fit, cap, UncertaintyOptions(jackknife="sometimes"))
    with pytest.raises(InputError, match="size"):
        estimate_uncertainty(fit, cap.downsampled(2))
    assert math.isclose(UncertaintyOptions().level, 0.9)


def test_pixel_budget_scales_to_the_full_capture(fitted):
    """A strided pass (48² → stride 3 under 2^8 pixels) scales H, M to every pixel: s and α's std within 15 % of
    the full pass's; the texture's summary and its spread map keep the full map's scale and shape."""
    _, cap, fit, full = fitted[10]
    assert full.stride == 1
    grid = estimate_uncertainty(fit, cap, UncertaintyOptions(max_pixels=1 << 8))
    assert grid.stride == 3 and grid.texture_grid.shape == (3, 16, 16)
    assert torch.allclose(grid.s_std, full.s_std, rtol=0.15) and torch.allclose(grid.beta_std, full.beta_std, rtol=0.15)
    assert grid.texture_std.shape == fit.texture.shape
    med = lambda u: u.to_dict()["texture"]["g"]["std_median"]  # noqa: E731
    assert math.isclose(med(grid), med(full), rel_tol=0.1)
    exact = estimate_uncertainty(fit, cap, UncertaintyOptions(max_pixels=1 << 8, texture_map=True))
    assert exact.stride == 1 and torch.equal(exact.texture_std, full.texture_std)
