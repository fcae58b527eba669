"""The tinted specular s(p) = s_m·d(p): recovered from a capture rendered with it; black and unseen pixels."""

from dataclasses import replace

import torch

from torchmetal.fit import fit_phong
from torchmetal.fit.tint import fit_tint, tint_factor, tinted_fit, tinted_texture
from torchmetal.lobes import lobe_render
from torchmetal.synth import synth_capture

S_M = (1.3, 1.3, 1.3)  # one s_m: the highlight in the texture's hue
ALPHA = (40.0, 40.0, 40.0)


def _scene(tinted: bool, size=40, shots=8, seed=3, noise=0.01):
    """(capture, truth dict) of a glossy "near" scene, its specular s_m ⊙ texture where ``tinted``."""
    r = synth_capture(size=size, shots=shots, layout="near", texture="procedural", seed=seed, alpha=ALPHA,
                      s=(0.5, 0.5, 0.5))
    cap, t = r.capture, dict(r.truth)
    if tinted:
        t["s"] = torch.tensor(S_M).view(3, 1, 1) * t["texture"]
    photo = lobe_render(t["texture"], t["s"], t["alpha"], t["normals"], cap.lights, cap.intensities, cap.cameras,
                        cap.size)
    g = torch.Generator().manual_seed(seed)
    photo = photo * (1 + noise * torch.randn(photo.shape, generator=g))
    return replace(cap, images=photo.clamp_min(0.0)), t


def test_fit_tint_recovers_alpha_and_tint():
    cap, t = _scene(True, noise=0.0)
    alpha, s_m = fit_tint(cap)
    assert torch.allclose(alpha, torch.tensor(ALPHA, dtype=torch.float64), rtol=0.02)
    assert torch.allclose(s_m, torch.tensor(S_M, dtype=torch.float64), rtol=0.02)
    d = tinted_texture(cap, alpha, s_m, rows=7)  # bands that do not divide the height
    assert d.shape == t["texture"].shape and float((d - t["texture"]).abs().max()) < 0.01


def test_tinted_fit_is_a_gloss_map_fit_that_renders():
    cap, t = _scene(True)
    base = fit_phong(cap)
    fit = tinted_fit(cap, base)
    assert fit.specular == "tinted" and fit.lobe == "phong" and fit.spec_labels is None
    assert fit.gloss_s.shape == fit.texture.shape == fit.gloss_alpha.shape
    assert torch.allclose(torch.tensor(tint_factor(fit)), torch.tensor(S_M), rtol=0.05)
    assert tint_factor(base) is None
    pred = fit.render(cap.lights, cap.intensities, cap.cameras)
    truth = lobe_render(t["texture"], t["s"], t["alpha"], t["normals"], cap.lights, cap.intensities, cap.cameras, cap.size)
    err_tint = float(((pred - truth) ** 2).mean())
    err_base = float(((base.render(cap.lights, cap.intensities, cap.cameras) - truth) ** 2).mean())
    assert err_tint < 0.2 * err_base  # the model the truth has explains it; one s per channel cannot
    mat = fit.to_material()
    assert mat.gloss_s is not None and torch.isfinite(mat.gloss_s).all()


def test_black_and_unseen_pixels_stay_finite():
    cap, _ = _scene(True, noise=0.0)
    mask = cap.mask.clone()
    mask[..., :5, :] = False  # rows no shot sees: the seen pixels' median
    images = cap.images.clone()
    images[:, :, 10:14, 10:14] = 0.0  # black pixels: texture 0
    cap = replace(cap, mask=mask, images=images)
    fit = tinted_fit(cap, fit_phong(cap))
    assert torch.isfinite(fit.texture).all() and torch.isfinite(fit.gloss_s).all()
    assert float(fit.texture[:, 11, 11].abs().max()) < 1e-6
    med = fit.texture[:, 5:].reshape(3, -1)
    assert torch.allclose(fit.texture[:, 0, 0], med[:, mask[..., 5:, :].reshape(-1)].median(1).values, atol=1e-6)


def test_fit_material_tint_on_and_its_report():
    from torchmetal.pipeline import fit_material

    cap, _ = _scene(True, size=32, shots=6)
    r = fit_material(cap, flakes="off", light="off", normals="given", tint="on")
    assert r.material.gloss_s is not None and r.fit.specular == "tinted"
    rep = r.material.report["tint"]
    assert rep["mode"] == "on" and abs(rep["s_m"][0] - S_M[0]) < 0.1 and rep["time"] > 0
    off = fit_material(cap, flakes="off", light="off", normals="given")
    assert off.material.report["tint"] is None and off.fit.specular != "tinted"
