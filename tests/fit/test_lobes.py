"""The lobes in the batched fit (torchmetal.fit.lobes): per-observation terms, Jacobian, recovery."""

from __future__ import annotations

import pytest
import torch

from tests.fit.helpers import replace, synth
from torchmetal.errors import InputError
from torchmetal.fit import fit_phong
from torchmetal.fit.lobes import lobe_factor
from torchmetal.fit.problem import build_observations
from torchmetal.fit.refine import model_terms
from torchmetal.lobes import LOBES, lobe_render


def lobe_capture(lobe: str, s=(0.5, 0.45, 0.4), alpha=(150.0, 200.0, 250.0), *, size=40, shots=12, bumpy=False,
                 layout="hemisphere", dtype=torch.float64, seed=0):
    """A synthetic capture (lights, cameras, texture of :func:`synth`) re-rendered with ``lobe`` as truth."""
    res = synth(size=size, shots=shots, seed=seed, layout=layout, bumpy=bumpy, dtype=dtype)
    cap = res.capture
    s_t, a_t = torch.tensor(s, dtype=dtype), torch.tensor(alpha, dtype=dtype)
    imgs = lobe_render(res.truth["texture"].to(dtype), s_t, a_t, cap.normals.to(dtype), cap.lights.to(dtype),
                       cap.intensities.to(dtype), cap.cameras.to(dtype), cap.size, lobe)
    return replace(cap, images=imgs, saturated=None), res.truth["texture"].to(dtype), s_t, a_t


@pytest.mark.parametrize("lobe", LOBES)
@pytest.mark.parametrize("bumpy", [False, True])
def test_observation_terms_are_the_renderer(lobe, bumpy):
    """i·u·exp(λ) of the observations == the specular part of :func:`lobe_render` (texture 0, s = 1)."""
    cap, _, _, _ = lobe_capture(lobe, size=16, shots=5, bumpy=bumpy)
    alpha = torch.tensor([3.0, 30.0, 300.0], dtype=torch.float64)
    obs = build_observations(cap, lobe=lobe, chunk=100)
    assert obs.lobe == lobe and (obs.geo is not None) == (lobe == "ggx")
    b = torch.cat([(inten * u) * lobe_factor(L, alpha.view(1, 3, 1), obs.geo_chunk(j), obs.lobe)
                   for j, (y, g, u, L, w, inten) in enumerate(obs.chunk(j) for j in range(len(obs.chunks)))], -1)
    ref = lobe_render(torch.zeros(3, 16, 16, dtype=torch.float64), torch.ones(3, dtype=torch.float64), alpha, cap.normals,
                      cap.lights, cap.intensities, cap.cameras, cap.size, lobe)
    torch.testing.assert_close(b, ref.reshape(5, 3, -1), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("lobe", ["blinn", "ggx"])
def test_model_terms_jacobian(lobe):
    """∂b/∂β of :func:`model_terms` against central differences in β (float64)."""
    cap, _, _, _ = lobe_capture(lobe, size=12, shots=4, bumpy=True)
    obs = build_observations(cap, lobe=lobe)
    beta = torch.log(torch.tensor([[5.0, 50.0, 500.0]], dtype=torch.float64))
    _, b, db = model_terms(obs, torch.exp(beta))
    h = 1e-6
    _, bp, _ = model_terms(obs, torch.exp(beta + h))
    _, bm, _ = model_terms(obs, torch.exp(beta - h))
    torch.testing.assert_close(db, (bp - bm) / (2 * h), rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("lobe,alpha", [("blinn", (150.0, 200.0, 250.0)), ("ggx", (60.0, 100.0, 140.0))])
def test_fit_recovers_its_lobe(lobe, alpha):
    """Noise-free float capture with a Blinn / GGX truth: the same lobe's fit recovers s, α and the texture."""
    cap, tex, s_t, a_t = lobe_capture(lobe, alpha=alpha)
    fit = fit_phong(cap, lobe=lobe)
    assert fit.lobe == lobe and fit.report()["lobe"] == lobe
    assert float(((fit.s.double() - s_t) / s_t).abs().max()) < 1e-3
    assert float(((fit.alpha.double() - a_t) / a_t).abs().max()) < 1e-3
    assert float((fit.texture.double() - tex).abs().max()) < 1e-3
    phong = fit_phong(cap)  # the default model cannot reproduce another lobe as well
    assert phong.lobe == "phong" and phong.rmse > 3 * fit.rmse
    assert fit.to_material().lobe == lobe
    model = fit.to_module()
    with torch.no_grad():
        torch.testing.assert_close(model(cap.lights, cap.intensities, cap.cameras), fit.render(cap.lights, cap.intensities,
                                                                                              cap.cameras))


def test_ggx_shares_alpha_only_where_the_channels_agree():
    """One true GGX roughness (noisy photos): one α for the three channels, which the renderer draws
    as one fraction; three different α: kept per channel (the χ² test of share_alpha)."""
    from torchmetal.renderer import MaterialRenderer

    cap, _, _, _ = lobe_capture("ggx", alpha=(100.0, 100.0, 100.0))
    noisy = replace(cap, images=cap.images * (1 + 0.01 * torch.randn(cap.images.shape, generator=torch.Generator().manual_seed(2),
                                                                        dtype=cap.images.dtype)))
    fit = fit_phong(noisy, lobe="ggx", specular="global")
    assert bool((fit.alpha == fit.alpha[0]).all()) and abs(float(fit.alpha[0]) / 100.0 - 1.0) < 0.02, fit.alpha
    assert "specular" in fit.skips  # the report says the per-channel α were not kept
    assert MaterialRenderer(fit.to_material()).alpha_uniform
    cap3, _, _, a_t = lobe_capture("ggx", alpha=(60.0, 100.0, 140.0))
    fit3 = fit_phong(cap3, lobe="ggx", specular="global")
    assert float(((fit3.alpha.double() - a_t) / a_t).abs().max()) < 1e-3
    assert "specular" not in fit3.skips


def test_a_refit_keeps_per_channel_ggx_alpha_untested(monkeypatch):
    """A GGX fit that kept three α (the channels told apart) hands that to its refits (Start.per_channel): they do
    not run the sharing test again (four full-size passes); a fit that shared α does not, and its refits test."""
    import torchmetal.fit.api as api
    from torchmetal.fit.start import Start, refit_options

    cap3, _, _, _ = lobe_capture("ggx", alpha=(60.0, 100.0, 140.0))
    fit3 = fit_phong(cap3, lobe="ggx", specular="global")
    assert Start.of(fit3).per_channel
    maps = fit_phong(cap3, lobe="ggx", specular="maps")  # gloss maps never take the sharing test: nothing to keep
    assert maps.specular == "maps" and not Start.of(maps).per_channel
    assert not refit_options(maps, maps=False)["start"].per_channel
    cap1, _, _, _ = lobe_capture("ggx", alpha=(100.0, 100.0, 100.0))
    noisy = replace(cap1, images=cap1.images * (1 + 0.01 * torch.randn(cap1.images.shape, dtype=cap1.images.dtype,
                                                                         generator=torch.Generator().manual_seed(2))))
    shared = fit_phong(noisy, lobe="ggx", specular="global")
    assert not Start.of(shared).per_channel and not Start.of(fit_phong(cap1)).per_channel  # shared; Phong
    calls = []
    real = api.share_alpha
    monkeypatch.setattr(api, "share_alpha", lambda *a, **k: calls.append(1) or real(*a, **k))
    refit = fit_phong(cap3, **refit_options(fit3))
    assert not calls and float(((refit.alpha - fit3.alpha) / fit3.alpha).abs().max()) < 1e-3
    fit_phong(noisy, **refit_options(shared))
    assert calls  # tested again


def test_bad_lobe_arguments():
    cap, _, _, _ = lobe_capture("phong", size=8, shots=3)
    with pytest.raises(InputError, match="lobe: expected one of"):
        fit_phong(cap, lobe="beckmann")
    with pytest.raises(InputError, match="scheme='paper'"):
        fit_phong(cap, scheme="paper", lobe="ggx")
    with pytest.raises(InputError, match="lobe: expected one of"):
        build_observations(cap, lobe="cook")


def test_default_is_phong_unchanged():
    """lobe='phong' (the default) is the same fit, to the bit, as not passing a lobe."""
    cap = synth(size=24, shots=8).capture
    a, b = fit_phong(cap), fit_phong(cap, lobe="phong")
    assert a.lobe == "phong" and a.lobe_selection is None
    assert torch.equal(a.texture, b.texture) and torch.equal(a.s, b.s) and torch.equal(a.alpha, b.alpha)
