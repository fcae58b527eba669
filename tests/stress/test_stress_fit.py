"""Numerical stress of the Phong fit: every extreme capture gives a finite, sane fit or a clear
one-line TorchmetalError — never NaN, never a hang (the conftest stops a test after 60 s).

"Sane": texture ≥ 0, s ≥ 0, α ≥ 1, all finite, and on noise-free data the fitted model re-renders
the fitted shots closely.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.stress.helpers import with_
from torchmetal.errors import TorchmetalError
from torchmetal.fit import fit_phong
from torchmetal.io.capture import Capture
from torchmetal.phong import phong_render
from torchmetal.synth import synth_capture

SIZE = (0.1, 0.1)
FIT_STRESS = settings(max_examples=12, deadline=None, derandomize=True,
                      suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def assert_sane(fit) -> None:
    for name in ("texture", "s", "alpha"):
        x = getattr(fit, name)
        assert torch.isfinite(x).all(), f"{name} not finite: {x}"
    assert (fit.texture >= 0).all() and (fit.s >= 0).all() and (fit.alpha >= 1 - 1e-6).all()
    assert math.isfinite(fit.rmse) and fit.rmse >= 0
    assert fit.status in ("converged", "max_iters", "skipped")


def render_fit(fit, cap: Capture) -> torch.Tensor:
    with torch.no_grad():
        return fit.render(cap.lights, cap.intensities, cap.cameras)


def rel_rmse(fit, cap: Capture) -> float:
    """Re-render RMSE on the fitted shots over valid pixels, relative to the largest valid value."""
    pred = render_fit(fit, cap).double()
    valid = cap.mask.expand_as(cap.images) & ~cap.saturated
    ref = cap.images.double()
    if not bool(valid.any()):
        return 0.0
    err = (pred - ref)[valid]
    return float(err.square().mean().sqrt()) / max(float(ref[valid].abs().max()), 1e-30)


def fit_or_clear_error(cap: Capture, **kw):
    """The fit, or None after checking the TorchmetalError is one clear line."""
    try:
        return fit_phong(cap, **kw)
    except TorchmetalError as e:
        msg = str(e)
        assert msg and "\n" not in msg and len(msg) < 400, msg
        return None


def flat(h: int, w: int, z: float = 1.0, dtype=torch.float32) -> torch.Tensor:
    n = torch.zeros(3, h, w, dtype=dtype)
    n[2] = z
    return n


def phong_capture(texture, s, alpha, normals, lights, intensities, cameras, **kw) -> Capture:
    img = phong_render(texture, s, alpha, normals, lights, intensities, cameras, SIZE)
    return Capture(images=img, normals=normals, lights=lights, intensities=intensities, cameras=cameras, size=SIZE, **kw)


def ring(n: int, elev_deg: float, *, point: bool = False, dist: float = 0.3) -> torch.Tensor:
    az = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n + 0.3
    e = math.radians(elev_deg)
    d = torch.stack([math.cos(e) * torch.cos(az), math.cos(e) * torch.sin(az), torch.full((n,), math.sin(e), dtype=torch.float64)], 1)
    if point:
        return torch.cat([dist * d, torch.ones(n, 1, dtype=torch.float64)], 1).float()
    return torch.cat([d, torch.zeros(n, 1, dtype=torch.float64)], 1).float()


@pytest.fixture(scope="module")
def base() -> Capture:
    return synth_capture(size=16, shots=8, seed=2, texture="procedural").capture


# ----------------------------------------------------------------------------- α and s ranges


@FIT_STRESS
@given(
    alpha=st.floats(math.log(1.0), math.log(5000.0)).map(math.exp),
    s=st.one_of(st.just(0.0), st.floats(0.0, 10.0)),
    seed=st.integers(0, 50),
)
def test_fit_alpha_1_to_5000_and_s_0_to_10(alpha, s, seed):
    res = synth_capture(size=16, shots=8, seed=seed, s=(s, s, s), alpha=(alpha, alpha, alpha), texture="procedural")
    fit = fit_or_clear_error(res.capture, specular="global")
    assert fit is not None, "noise-free synthetic data must fit"
    assert_sane(fit)
    assert rel_rmse(fit, res.capture) < 1e-3
    if s == 0.0:
        assert float(fit.s.max()) < 1e-3
        assert any("specular" in k for k in fit.skipped), fit.skipped


@pytest.mark.parametrize("scheme,alpha,s", [
    *[(sch, a, sv) for sch in ("paper", "refine") for a, sv in [(1.0, 10.0), (5000.0, 0.01), (1.0, 0.0)]],
    *[(sch, a, 10.0) for sch in ("paper", "refine") for a in (300.0, 5000.0)],
])
def test_fit_extreme_corners_both_schemes(scheme, alpha, s):
    res = synth_capture(size=16, shots=8, seed=4, s=(s, s, s), alpha=(alpha, alpha, alpha), texture="procedural")
    fit = fit_or_clear_error(res.capture, scheme=scheme, specular="global")
    assert fit is not None
    assert_sane(fit)
    assert rel_rmse(fit, res.capture) < 2e-3


# ----------------------------------------------------------------------------- geometry extremes


def test_fit_lights_at_half_degree_elevation():
    h = w = 12
    tex = 0.1 + 0.6 * torch.rand(3, h, w, generator=torch.Generator().manual_seed(0))
    n = 8
    cap = phong_capture(tex, torch.full((3,), 0.5), torch.full((3,), 50.0), flat(h, w), ring(n, 0.5), torch.ones(n, 3),
                        torch.tensor([[0.0, 0.0, 0.3, 1.0]]).repeat(n, 1))
    fit = fit_or_clear_error(cap)
    assert fit is not None
    assert_sane(fit)
    # n·l = sin 0.5° ≈ 0.0087: images are dim, yet the texture is fully determined
    torch.testing.assert_close(fit.texture, tex, rtol=1e-3, atol=1e-4)


def test_fit_point_lights_grazing_at_half_degree():
    h = w = 12
    tex = torch.full((3, h, w), 0.4)
    n = 6
    cap = phong_capture(tex, torch.full((3,), 2.0), torch.full((3,), 300.0), flat(h, w), ring(n, 0.5, point=True, dist=0.5),
                        torch.full((n, 3), 0.25), torch.tensor([[0.0, 0.0, 0.3, 1.0]]).repeat(n, 1))
    fit = fit_or_clear_error(cap)
    if fit is not None:
        assert_sane(fit)
        assert rel_rmse(fit, cap) < 1e-3


@pytest.mark.parametrize("alpha", [10.0, 1000.0])
def test_fit_light_at_the_camera(alpha):
    """Collocated flash (light = camera position), the MaterialGAN-style capture."""
    h = w = 16
    tex = 0.1 + 0.6 * torch.rand(3, h, w, generator=torch.Generator().manual_seed(1))
    n = 8
    az = torch.arange(n) * 2 * math.pi / n
    pos = torch.stack([0.02 * torch.cos(az), 0.02 * torch.sin(az), torch.full((n,), 0.3), torch.ones(n)], 1)
    cap = phong_capture(tex, torch.full((3,), 0.5), torch.full((3,), alpha), flat(h, w), pos.clone(), torch.full((n, 3), 0.05), pos)
    fit = fit_or_clear_error(cap)
    assert fit is not None
    assert_sane(fit)
    assert rel_rmse(fit, cap) < 1e-3


def test_fit_normals_pointing_down(base):
    """Every pixel faces away from every light: nothing is observable → a defined fit or a clear error."""
    cap = with_(base, normals=flat(16, 16, z=-1.0), images=torch.zeros_like(base.images))
    fit = fit_or_clear_error(cap)
    if fit is not None:
        assert_sane(fit)
        assert float(fit.s.max()) == 0.0


def test_fit_one_pixel_image(base):
    tex = torch.full((3, 1, 1), 0.4)
    cap = phong_capture(tex, torch.full((3,), 0.5), torch.tensor([20.0, 50.0, 80.0]), flat(1, 1), base.lights,
                        base.intensities, base.cameras)
    fit = fit_or_clear_error(cap)
    assert fit is not None
    assert fit.texture.shape == (3, 1, 1)
    assert_sane(fit)
    assert rel_rmse(fit, cap) < 1e-3


def test_fit_one_shot(base):
    fit = fit_or_clear_error(base.subset([0]))
    assert fit is not None
    assert_sane(fit)
    assert rel_rmse(fit, base.subset([0])) < 1e-3  # one shot: the texture alone explains it
    assert float(fit.s.max()) == 0.0 and "specular" in fit.skips


# ----------------------------------------------------------------------------- degenerate pixels


def test_fit_all_black_shots(base):
    fit = fit_or_clear_error(with_(base, images=torch.zeros_like(base.images)))
    assert fit is not None
    assert_sane(fit)
    assert float(fit.texture.abs().max()) == 0.0 and float(fit.s.max()) == 0.0


def test_fit_one_black_shot_among_good_ones(base):
    imgs = base.images.clone()
    imgs[3] = 0.0
    fit = fit_or_clear_error(with_(base, images=imgs))
    assert fit is not None
    assert_sane(fit)


def test_fit_all_saturated_shots(base):
    cap = with_(base, images=torch.ones_like(base.images), saturated=torch.ones_like(base.saturated))
    fit = fit_or_clear_error(cap)
    if fit is not None:
        assert_sane(fit)


def test_fit_some_saturated_observations_are_ignored(base):
    """Clipped highlights flagged saturated must not bias the fit (they are left out)."""
    imgs = base.images.clone()
    top = float(imgs.quantile(0.95))
    sat = imgs > top
    imgs[sat] = top
    fit = fit_or_clear_error(with_(base, images=imgs, saturated=sat), specular="global")
    ref = fit_phong(base, specular="global")
    assert fit is not None
    assert_sane(fit)
    torch.testing.assert_close(fit.s, ref.s, rtol=1e-3, atol=0)
    torch.testing.assert_close(fit.alpha, ref.alpha, rtol=1e-3, atol=0)
    seen = (~sat).sum(0) >= 2  # a texel needs two unclipped observations to be determined
    assert bool(seen.float().mean() > 0.9)
    torch.testing.assert_close(fit.texture[seen], ref.texture[seen], rtol=1e-3, atol=1e-5)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_pixels_are_a_clear_error(base, value):
    imgs = base.images.clone()
    imgs[2, 1, 3, 4] = value
    with pytest.raises(TorchmetalError) as e:
        with_(base, images=imgs)
    assert "\n" not in str(e.value) and "finite" in str(e.value)
    # a capture mutated after it was checked is caught again at the fit boundary
    cap = with_(base)
    cap.images[2, 1, 3, 4] = value
    with pytest.raises(TorchmetalError) as e:
        fit_phong(cap)
    assert "\n" not in str(e.value) and "finite" in str(e.value)


# ----------------------------------------------------------------------------- dtypes and scales


@pytest.mark.parametrize("dtype", [torch.float16, torch.float64])
def test_fit_float16_and_float64_captures(base, dtype):
    ref = fit_phong(base, specular="global")
    fit = fit_or_clear_error(base.to(dtype=dtype), specular="global")
    assert fit is not None
    assert_sane(fit)
    tol = 5e-3 if dtype == torch.float16 else 1e-4  # float16 images carry ~5e-4 relative rounding
    torch.testing.assert_close(fit.s.double(), ref.s.double(), rtol=tol, atol=0)
    torch.testing.assert_close(fit.alpha.double(), ref.alpha.double(), rtol=tol, atol=0)
    torch.testing.assert_close(fit.texture.double(), ref.texture.double(), rtol=tol * 4, atol=tol * 1e-2)


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1e3, 1e6])
def test_fit_is_invariant_to_light_intensity_scale(base, scale):
    """Intensities from 1e-6 to 1e6 with images to match: same texture, s and α."""
    ref = fit_phong(base, specular="global")
    cap = with_(base, images=base.images * scale, intensities=base.intensities * scale)
    fit = fit_or_clear_error(cap, specular="global")
    assert fit is not None
    assert_sane(fit)
    torch.testing.assert_close(fit.s, ref.s, rtol=1e-3, atol=0)
    torch.testing.assert_close(fit.alpha, ref.alpha, rtol=1e-3, atol=0)
    torch.testing.assert_close(fit.texture, ref.texture, rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_fit_with_mismatched_intensity_stays_finite(base, scale):
    """Intensities off by 1e±6 from the images (a calibration blunder): finite, never NaN."""
    fit = fit_or_clear_error(with_(base, intensities=base.intensities * scale))
    if fit is not None:
        assert_sane(fit)
