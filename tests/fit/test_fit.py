"""fit_phong end to end on tiny synthetic captures: accuracy, edge cases, skips, the result API."""

import math

import pytest
import torch

from tests.fit.helpers import rel_err, render_all, replace, synth
from torchmetal.errors import FitError, InputError
from torchmetal.fit import FitResult, fit_phong, leave_one_out
from torchmetal.material import Material
from torchmetal.metrics import psnr
from torchmetal.phong import phong_render


@pytest.fixture(scope="module")
def clean():
    return synth(size=64, shots=12, seed=0)


@pytest.fixture(scope="module")
def clean_fit(clean):
    return fit_phong(clean.capture, specular="global")


def test_noise_free_refine_is_exact(clean, clean_fit):
    f = clean_fit
    assert isinstance(f, FitResult) and f.status == "converged" and f.scheme == "refine"
    assert psnr(render_all(f, clean.capture), clean.capture.images) >= 70.0
    assert rel_err(f.s, clean.truth["s"]) <= 1e-3 and rel_err(f.alpha, clean.truth["alpha"]) <= 1e-3
    assert psnr(f.texture, clean.truth["texture"]) >= 70.0
    assert f.texture.shape == (3, 64, 64) and f.s.shape == (3,) and f.alpha.shape == (3,)
    assert f.spec_labels is None and f.cluster_s is None and f.cluster_alpha is None


def test_history_times_iterations(clean_fit):
    f = clean_fit
    assert {h["stage"] for h in f.history} >= {"init", "paper", "refine"}
    for h in f.history:
        assert set(h) >= {"stage", "iter", "rmse", "active"} and math.isfinite(h["rmse"]) and 0 <= h["active"] <= 1
    assert set(f.stage_times) >= {"init", "paper", "refine", "geometry", "texture"}
    assert all(v >= 0 for v in f.stage_times.values())
    assert int(f.iterations) == sum(f.iterations.values()) and f.iterations["refine"] <= 5
    assert math.isfinite(f.rmse) and f.rmse < 1e-4


def test_paper_scheme(clean):
    f = fit_phong(clean.capture, scheme="paper", tol=1e-5)
    assert f.scheme == "paper" and f.status == "converged"
    assert rel_err(f.s, clean.truth["s"]) < 5e-3 and rel_err(f.alpha, clean.truth["alpha"]) < 5e-3
    assert psnr(render_all(f, clean.capture), clean.capture.images) > 60.0
    assert "specular clusters" in f.skips and f.selection is None  # the paper's scheme fits global specular only
    with pytest.raises(InputError, match="clustered"):
        fit_phong(clean.capture, scheme="paper", specular="clustered")


def test_noisy_8bit_texture_and_heldout():
    r = synth(size=64, shots=14, seed=1, noise=0.01, bits=8)
    cap = r.capture
    fit_idx, hold = list(range(12)), [12, 13]
    f = fit_phong(cap.subset(fit_idx), specular="global")
    assert psnr(f.texture, r.truth["texture"]) >= 40.0
    hc = cap.subset(hold)
    v = ~hc.saturated
    truth = phong_render(r.truth["texture"], r.truth["s"], r.truth["alpha"], hc.normals, hc.lights, hc.intensities,
                         hc.cameras, hc.size)
    assert psnr(render_all(f, hc), hc.images, mask=v) >= psnr(truth, hc.images, mask=v) - 0.5


def test_one_shot_no_specular_no_nan():
    r = synth(size=24, shots=1, seed=2)
    f = fit_phong(r.capture)
    assert torch.isfinite(f.texture).all() and bool((f.s == 0).all())
    assert f.specular == "none" and "specular" in f.skips and not f.decisions  # one shot: no held-out test either
    assert psnr(render_all(f, r.capture), r.capture.images) > 60.0  # one shot: texture explains it


def test_no_highlight_evidence_is_skipped():
    r = synth(size=32, shots=8, seed=3, s=(0.0, 0.0, 0.0))
    f = fit_phong(r.capture)
    assert f.specular == "none" and bool((f.s == 0).all())
    assert "specular" in f.skips
    assert "select" not in f.stage_times  # no clusters tried either
    assert psnr(f.texture, r.truth["texture"]) > 70.0


def test_noisy_capture_without_highlights_skips_specular():
    """With 1% noise and no highlight, the specular term is rejected (in sample or on a held-out shot)."""
    r = synth(size=128, shots=12, seed=0, s=(0.0, 0.0, 0.0), noise=0.01)
    f = fit_phong(r.capture, specular="global")
    assert f.specular == "none" and bool((f.s == 0).all())
    assert "specular" in f.skips, f.skipped


def test_noisy_capture_with_highlights_keeps_specular():
    r = synth(size=64, shots=12, seed=0, noise=0.01)
    f = fit_phong(r.capture, specular="global")
    assert f.specular == "global" and "specular" not in f.skips, f.skipped
    assert rel_err(f.s, r.truth["s"]) < 0.05


def test_specular_none():
    r = synth(size=24, shots=6, seed=4)
    f = fit_phong(r.capture, specular="none")
    assert bool((f.s == 0).all()) and f.specular == "none" and "specular" in f.skips and not f.decisions


def test_black_pixels():
    r = synth(size=32, shots=8, seed=5)
    img = r.capture.images.clone()
    img[:, :, 10:14, 10:14] = 0.0  # black: no light at all there
    f = fit_phong(replace(r.capture, images=img), specular="global")
    assert torch.isfinite(f.texture).all() and float(f.texture[:, 10:14, 10:14].abs().max()) < 0.05
    assert rel_err(f.s, r.truth["s"]) < 0.05


def test_saturated_pixels_are_left_out():
    r = synth(size=48, shots=12, seed=6, bits=16, exposure=1.6)
    cap = r.capture
    assert 0.001 < float(cap.saturated.float().mean()) < 0.5
    f = fit_phong(cap, specular="global")
    assert rel_err(f.s, r.truth["s"]) < 1e-3 and rel_err(f.alpha, r.truth["alpha"]) < 1e-3
    assert torch.isfinite(f.texture).all()


def test_shadowed_pixels_and_normal_maps():
    r = synth(size=48, shots=12, seed=7, bumpy=True)
    cap = r.capture
    normals = cap.normals.clone()
    normals[:, 5:8, 5:8] = torch.tensor([0.0, 0.0, -1.0]).view(3, 1, 1)  # facing away: n·l ≤ 0 everywhere
    f = fit_phong(replace(cap, normals=normals), specular="global")
    assert not f.flat and torch.isfinite(f.texture).all()
    assert rel_err(f.s, r.truth["s"]) < 1e-3 and rel_err(f.alpha, r.truth["alpha"]) < 1e-3
    ok = torch.ones(48, 48, dtype=torch.bool)
    ok[5:8, 5:8] = False
    assert float((f.texture - r.truth["texture"])[:, ok].abs().max()) < 1e-3


def test_only_mask_pixels_count():
    r = synth(size=32, shots=8, seed=8)
    cap = r.capture
    mask = torch.ones_like(cap.mask)
    mask[:, :, :10] = False
    img = cap.images.clone()
    img[:, :, :, :10] = torch.rand(img[:, :, :, :10].shape, generator=torch.Generator().manual_seed(0)) * 5
    f = fit_phong(replace(cap, images=img, mask=mask), specular="global")
    assert rel_err(f.s, r.truth["s"]) < 1e-3 and rel_err(f.alpha, r.truth["alpha"]) < 1e-3
    assert float((f.texture - r.truth["texture"])[:, :, 10:].abs().max()) < 1e-3


@pytest.mark.parametrize("dtype", [torch.float16, torch.float64])
def test_half_and_double_captures(dtype):
    r = synth(size=32, shots=8, seed=9, dtype=torch.float64)
    cap = r.capture.to(dtype=dtype)
    f = fit_phong(cap, specular="global", tol=1e-10)
    assert f.texture.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
    tol = 1e-7 if dtype == torch.float64 else 2e-2
    assert rel_err(f.s, r.truth["s"]) < tol and rel_err(f.alpha, r.truth["alpha"]) < tol


def test_chunking_gives_the_same_result():
    r = synth(size=40, shots=8, seed=10, noise=0.01)
    a = fit_phong(r.capture, specular="global")
    b = fit_phong(r.capture, specular="global", max_pixels_per_chunk=97)
    torch.testing.assert_close(a.s, b.s, rtol=1e-5, atol=0)
    torch.testing.assert_close(a.alpha, b.alpha, rtol=1e-5, atol=0)
    torch.testing.assert_close(a.texture, b.texture, rtol=0, atol=1e-5)


def test_non_finite_input_raises_one_line_fit_error():
    r = synth(size=16, shots=4, seed=11)
    cap = r.capture
    bad = cap.images.clone()
    bad[1, 0, 3, 3] = float("nan")
    cap.images = bad  # bypass Capture's own checks: fit_phong must still refuse
    with pytest.raises(FitError) as e:
        fit_phong(cap)
    assert "\n" not in str(e.value) and "non-finite" in str(e.value)


@pytest.mark.parametrize("kw", [dict(scheme="x"), dict(specular="x"), dict(tol=0.0), dict(max_iters=0),
                                dict(robust="l1"), dict(outliers=-1.0), dict(clusters=(1,))])
def test_bad_arguments(kw):
    r = synth(size=8, shots=2, seed=12)
    with pytest.raises(InputError):
        fit_phong(r.capture, **kw)


def test_robust_losses_and_outlier_masks_resist_glints():
    r = synth(size=40, shots=10, seed=13, noise=0.005)
    g = torch.Generator().manual_seed(1)
    img = r.capture.images.clone()
    spots = torch.rand(img.shape[0], 1, 40, 40, generator=g) < 0.01  # glints: 1 % of observations
    img = torch.where(spots, img + 2.0, img)
    cap = replace(r.capture, images=img)
    plain = fit_phong(cap, specular="global", outliers=None)
    errs = {}
    for name, kw in {"mad": dict(outliers=5.0), "huber": dict(robust="huber", outliers=None),
                     "cauchy": dict(robust="cauchy", outliers=None)}.items():
        f = fit_phong(cap, specular="global", **kw)
        errs[name] = psnr(f.texture, r.truth["texture"])
        assert torch.isfinite(f.texture).all()
    base = psnr(plain.texture, r.truth["texture"])
    assert errs["mad"] > base + 10 and errs["cauchy"] > base + 10 and errs["huber"] > base + 3


def test_clustered_specular_found_and_kept():
    r = synth(size=64, shots=12, seed=14, spec_clusters=2)
    f = fit_phong(r.capture, specular="auto")
    assert f.specular == "clustered" and f.spec_labels.shape == (64, 64) and f.spec_labels.dtype == torch.int64
    assert f.cluster_s.shape[1] == 3 and f.cluster_alpha.shape == f.cluster_s.shape
    assert f.selection is not None and f.selection["k"] >= 2
    truth_s = r.truth["cluster_s"][r.truth["spec_labels"]]
    got_s = f.cluster_s[f.spec_labels]
    agree = ((got_s - truth_s).abs().amax(-1) < 0.01).float().mean()
    assert float(agree) > 0.9
    assert psnr(render_all(f, r.capture), r.capture.images) > 45.0
    g = fit_phong(r.capture, specular="global")
    assert f.rmse < 0.5 * g.rmse


def test_auto_keeps_global_when_clusters_do_not_help(clean):
    f = fit_phong(clean.capture, specular="auto")
    assert f.specular == "global" and f.spec_labels is None
    records = {d["name"]: d for d in f.decisions}
    assert "specular clusters" in f.skips and f.selection["k"] == 1 and records["specular clusters"]["chosen"] == "global"
    c = fit_phong(clean.capture, specular="clustered")
    assert c.specular == "clustered"


def test_to_material_and_render(clean_fit, clean):
    m = clean_fit.to_material({"extra": 1})
    assert isinstance(m, Material) and m.report["extra"] == 1
    assert set(m.report) >= {"stage_times", "iterations", "history", "status", "skipped"}
    assert m.normals is None  # flat capture
    img = clean_fit.render(clean.capture.lights[:2], clean.capture.intensities[:2], clean.capture.cameras[:2])
    assert img.shape == (2, 3, 64, 64)


def _analytic_grads(fit, cap):
    """Gradients of Σ (y − render)² w.r.t. texture, s and log α from the analytic Jacobian."""
    from torchmetal.fit.problem import build_observations
    from torchmetal.fit.refine import model_terms

    obs = build_observations(cap)
    labels = None if fit.spec_labels is None else fit.spec_labels.reshape(-1)
    s = fit.s.view(1, 3) if labels is None else fit.cluster_s
    alpha = fit.alpha.view(1, 3) if labels is None else fit.cluster_alpha
    a, b, db = model_terms(obs, alpha.double(), labels)
    s_pix = s.double()[labels].T if labels is not None else s.double().view(3, 1)
    d = fit.texture.double().reshape(3, -1)
    r = obs.y.double() - a * d - s_pix * b
    lit = obs.g > 0
    r = torch.where(lit.expand_as(r), r, torch.zeros_like(r))
    g_d = (-2 * r * a).sum(0)
    g_s_pix = (-2 * r * b).sum(0)
    g_b_pix = (-2 * r * s_pix * db).sum(0)
    if labels is None:
        return g_d, g_s_pix.sum(-1), g_b_pix.sum(-1)
    k = s.shape[0]
    return (g_d, torch.zeros(k, 3, dtype=torch.float64).index_add_(0, labels, g_s_pix.T),
            torch.zeros(k, 3, dtype=torch.float64).index_add_(0, labels, g_b_pix.T))


@pytest.mark.parametrize("clustered", [False, True])
def test_module_gradients_equal_the_analytic_ones(clustered):
    r = synth(size=12, shots=5, seed=15, noise=0.02, bumpy=True, spec_clusters=2 if clustered else 1)
    f = fit_phong(r.capture, specular="clustered" if clustered else "global", clusters=(2,))
    cap = r.capture.to(dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(f.to_module()(r.capture.lights, r.capture.intensities, r.capture.cameras),
                                   render_all(f, r.capture), rtol=1e-5, atol=1e-6)
    # move away from the optimum (gradients O(1)), in float64
    f.texture = (f.texture.double() * 1.1).contiguous()
    f.normals = f.normals.double()
    if clustered:
        f.cluster_s, f.cluster_alpha = f.cluster_s.double() * 0.9, f.cluster_alpha.double() * 1.2
    else:
        f.s, f.alpha = f.s.double() * 0.9, f.alpha.double() * 1.2
    mod = f.to_module()
    assert mod.texture.requires_grad
    loss = (mod(cap.lights, cap.intensities, cap.cameras) - cap.images).square().sum()
    loss.backward()
    g_d, g_s, g_b = _analytic_grads(f, cap)
    close = lambda a, b: torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()))  # noqa: E731
    close(mod.texture.grad.reshape(3, -1), g_d)
    if clustered:
        close(mod.cluster_s.grad, g_s)
        close(mod.cluster_log_alpha.grad, g_b)
    else:
        close(mod.s.grad, g_s)
        close(mod.log_alpha.grad, g_b)
    opt = torch.optim.Adam(mod.parameters(), lr=1e-3)  # and a user can keep training it
    opt.step()


def test_progress_bar_and_leave_one_out():
    r = synth(size=16, shots=4, seed=16)
    f = fit_phong(r.capture, progress=True)
    assert f.status == "converged"
    vals = leave_one_out(r.capture, specular="global")
    assert len(vals) == 4 and all(v > 50 for v in vals)


def test_leave_one_out_with_any_fit_scores_each_left_out_shot():
    from torchmetal.errors import InputError
    from torchmetal.fit.holdout import leave_one_out_with

    r = synth(size=16, shots=4, seed=16)
    seen = []

    def fit_render(train, one):
        seen.append((train.num_shots, one.num_shots, torch.is_grad_enabled()))  # fits may use autograd
        return fit_phong(train, specular="global").render(one.lights, one.intensities, one.cameras)

    assert leave_one_out_with(r.capture, fit_render) == leave_one_out(r.capture, specular="global")
    assert seen == [(3, 1, True)] * 4
    # a render that misses the photo scores lower: the PSNR is of the left-out shot, not of the fit
    bad = leave_one_out_with(r.capture, lambda train, one: 0.5 * fit_render(train, one))
    assert all(b < 30 for b in bad)
    with pytest.raises(InputError, match="at least 2 shots"):
        leave_one_out_with(r.capture.subset([0]), fit_render)


@pytest.mark.parametrize("case", ["clustered", "maps", "ggx_bumpy", "robust"])
def test_streamed_full_resolution_pass_gives_the_same_fit(monkeypatch, case):
    """A large capture streams its full-resolution geometry (torchmetal.memory.streams_geometry): the fit is
    the one the stored geometry gives, bit for bit, through clusters and relabelling, gloss maps,
    GGX with normal maps, and robust weights."""
    import torchmetal.fit.api as api

    kw = {"clustered": dict(specular="auto"), "maps": dict(specular="maps"), "ggx_bumpy": dict(lobe="ggx"),
          "robust": dict(robust="huber")}[case]
    r = synth(size=40, shots=8, seed=21, spec_clusters=2 if case == "clustered" else 1, bumpy=case == "ggx_bumpy")
    stored = fit_phong(r.capture, **kw)
    monkeypatch.setattr(api, "streams_geometry", lambda capture: True)
    seen = []
    build = api.build_observations
    monkeypatch.setattr(api, "build_observations", lambda *a, **k: seen.append(k.get("stream")) or build(*a, **k))
    streamed = fit_phong(r.capture, **kw)
    assert seen == [True]  # the full-resolution pass (the subsamples are built elsewhere, stored)
    assert streamed.specular == stored.specular and streamed.lobe == stored.lobe
    for name in ("texture", "s", "alpha", "spec_labels", "cluster_s", "gloss_s", "gloss_alpha"):
        a, b = getattr(streamed, name), getattr(stored, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert torch.equal(a, b), name
    assert streamed.rmse == stored.rmse


def test_noise_weights_beat_plain_least_squares_under_shot_noise(tmp_path):
    """Shot noise (variance growing with the value): weighting each observation by its fitted noise variance
    brings the texture and held-out renders closer to the clean truth than plain least squares does."""
    import dataclasses

    from torchmetal.io.capture import load_capture
    from torchmetal.synth.zoo import SCENES, make_case

    scene = SCENES["photo_srgb8"].with_(size=192, encoding="float", noise=0.0, shots=14)  # 96²: auto's z only 1.5
    cap = load_capture(make_case(scene, tmp_path / "c").capture_dir)
    clean = cap.images.double()
    g = torch.Generator().manual_seed(3)
    noisy = clean + (1e-6 + 2e-3 * clean.clamp_min(0.0)).sqrt() * torch.randn(clean.shape, generator=g, dtype=torch.float64)
    fit_cap, held = dataclasses.replace(cap, images=noisy.clamp_min(0.0).float()).subset(list(range(10))), cap.subset(list(range(10, 14)))
    scores = {}
    for weights in (True, False):
        fit = fit_phong(fit_cap, weights="noise" if weights else "uniform", specular="global")
        assert (fit.noise is not None) == weights
        with torch.no_grad():
            pred = fit.render(held.lights, held.intensities, held.cameras)
        scores[weights] = float(psnr(pred, held.images))
    assert scores[True] > scores[False] + 0.1, scores
    auto = fit_phong(fit_cap, weights="auto", specular="global")  # the held-out shot sees the gain
    (d,) = [d for d in auto.decisions if d["name"] == "weights"]
    assert d["chosen"] == "noise" and d["reference"] == "uniform" and auto.noise is not None
    assert torch.equal(auto.texture, fit_phong(fit_cap, weights="noise", specular="global").texture)


def test_noise_weights_auto_keeps_least_squares_without_noise(tmp_path):
    """A noise-free float capture: the noise model's floor makes the weights uniform, nothing to gain on the
    held-out shot; auto keeps plain least squares (the same fit, bit for bit)."""
    from torchmetal.io.capture import load_capture
    from torchmetal.synth.zoo import SCENES, make_case

    cap = load_capture(make_case(SCENES["float_clean"].with_(size=64), tmp_path / "c").capture_dir)
    auto = fit_phong(cap, weights="auto", specular="global")
    (d,) = [d for d in auto.decisions if d["name"] == "weights"]
    assert d["chosen"] == "uniform" and auto.noise is None
    assert torch.equal(auto.texture, fit_phong(cap, specular="global").texture)
    with pytest.raises(InputError, match="weights: expected one of"):
        fit_phong(cap, weights="sometimes")


def test_skips_key_each_skipped_sentence_by_its_stage():
    from torchmetal.fit.result import skip_stages

    assert skip_stages(["specular: no highlight evidence; s = 0", "flakes: a: b", "flakes: c"]) == {
        "specular": "no highlight evidence; s = 0", "flakes": "a: b; c"}
    f = fit_phong(synth(size=16, shots=1, seed=2).capture)
    assert f.skipped and f.skips == skip_stages(f.skipped) and all(": " in s for s in f.skipped)
