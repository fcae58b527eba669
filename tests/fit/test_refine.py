"""Variable-projection sums (:mod:`torchmetal.fit.refine`): exactness when shots are skipped."""

import torch

from torchmetal.fit.problem import build_observations
from torchmetal.fit.projected_sums import chunk_stats
from torchmetal.fit.refine import evaluate_specular, lobe_terms, spec_sums
from torchmetal.io.capture import load_capture
from torchmetal.synth.zoo import SCENES, make_case


def _capture(tmp_path):
    # 8 shots, 5 of them far from the mirror direction: their lobe is below e^-40 in many chunks
    scene = SCENES["few_highlight"].with_(size=96, encoding="float", noise=0.0)
    return load_capture(make_case(scene, tmp_path / "c").capture_dir), scene


def test_skipped_shots_keep_the_texture_coupling(tmp_path):
    """s(α) at the true α is exact on noise-free data whether or not chunks skip shots (it was 24 % high)."""
    cap, scene = _capture(tmp_path)
    alpha = torch.full((1, 3), scene.alpha, dtype=torch.float64)
    small = build_observations(cap, dtype=torch.float32, chunk=256)
    whole = build_observations(cap, dtype=torch.float32, chunk=1 << 20)
    f_small, f_whole = evaluate_specular(small, None, alpha), evaluate_specular(whole, None, alpha)
    assert f_small.active < 0.95  # the case under test: some chunk × shot pairs were skipped
    assert torch.allclose(f_small.s, torch.full_like(f_small.s, scene.s), rtol=1e-5)
    assert torch.allclose(f_whole.s, f_small.s, rtol=1e-5)


def test_skipped_stats_equal_dense_stats(tmp_path):
    cap, scene = _capture(tmp_path)
    alpha = torch.full((1, 3), 120.0, dtype=torch.float64)
    obs = build_observations(cap, dtype=torch.float64, chunk=256)
    st, eb, frac = spec_sums(obs, alpha)
    assert frac < 0.95
    # dense reference: every shot of every pixel, no skipping
    y, g, u, L, w, inten = obs.y.double(), obs.g, obs.u, obs.L, obs.w(slice(None)), obs.inten
    a, b, t = lobe_terms(g, u, L, inten, alpha[0].view(1, 3, 1))
    eb_ref, _, st_ref = chunk_stats(y, a, b, t, w, obs.isaa())
    ref = st_ref.double().sum(-1).unsqueeze(1)  # (6, 1, 3)
    assert torch.allclose(st, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    assert torch.allclose(eb, eb_ref, rtol=1e-9, atol=1e-15)


def _shot_noise(cap, a: float, b: float, seed: int = 0):
    """``cap`` with Gaussian noise of variance a + b·value added to every observation (read + shot noise)."""
    import dataclasses

    g = torch.Generator().manual_seed(seed)
    clean = cap.images.double()
    noisy = clean + (a + b * clean.clamp_min(0.0)).sqrt() * torch.randn(clean.shape, generator=g, dtype=torch.float64)
    return dataclasses.replace(cap, images=noisy.clamp_min(0.0).to(cap.images.dtype))


def test_noise_model_recovers_read_and_shot_noise(tmp_path):
    """noise_model: var = a + b·ŷ per channel from the residuals of a fit at the true terms."""
    from torchmetal.fit.refine import noise_model

    scene = SCENES["flakes_a"].with_(size=96, encoding="float", noise=0.0, flakes=None)
    cap = load_capture(make_case(scene, tmp_path / "c").capture_dir)
    a, b = 2e-6, 4e-4
    obs = build_observations(_shot_noise(cap, a, b), dtype=torch.float64, chunk=1024)
    alpha = torch.full((1, 3), scene.alpha, dtype=torch.float64)
    fit = evaluate_specular(obs, torch.full((1, 3), scene.s, dtype=torch.float64), alpha)
    got = noise_model(obs, fit.s, fit.alpha, fit.eb)
    assert got.shape == (2, 3)
    assert torch.allclose(got[1], torch.full((3,), b, dtype=torch.float64), rtol=0.25), got
    assert bool((got[0] > 0).all()) and bool((got[0] < 10 * a + 0.05 * b).all()), got  # small beside b·ŷ
    # without shot noise the slope vanishes
    obs = build_observations(_shot_noise(cap, 1e-4, 0.0), dtype=torch.float64, chunk=1024)
    fit = evaluate_specular(obs, fit.s, alpha)
    flat = noise_model(obs, fit.s, fit.alpha, fit.eb)
    assert bool((flat[1] * 0.5 < 0.25 * flat[0]).all()), flat  # b·ŷ (ŷ ≲ 0.5) well below a
