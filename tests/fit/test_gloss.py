"""Gloss maps: the per-pixel fit, the held-out choice, the material files, renderer and ONNX."""

import json

import numpy as np
import pytest
import torch

from tests.fit.helpers import render_all, synth
from torchmetal.errors import InputError, MaterialError
from torchmetal.fit import fit_phong
from torchmetal.fit.gloss import bilateral_weights, fit_gloss_maps, pool
from torchmetal.fit.problem import build_observations
from torchmetal.fit.refine import fit_specular, grid_beta
from torchmetal.lobes import lobe_render
from torchmetal.material import Material, load_material, save_material
from torchmetal.renderer import MaterialRenderer


@pytest.fixture(scope="module")
def two():
    """Two specular materials (K = 2 regions), noise-free, 40²."""
    return synth(size=40, shots=12, seed=3, spec_clusters=2)


def test_a_maps_model_refitted_without_maps_starts_from_its_values(two, monkeypatch):
    """The selection's candidate fits refit a gloss-maps reference as the structure its maps grew from
    (refit_options(maps=False)); they start from the maps' α instead of searching for the lobe again (the
    paper scheme and the α grid: 0.28 s a refit against 0.05 s on the random scenes)."""
    import torchmetal.fit.decisions as decisions
    from torchmetal.fit.start import refit_options

    cap = two.capture.subset(list(range(8)))
    maps = fit_phong(cap, specular="maps")
    assert maps.specular == "maps"
    model = refit_options(maps, maps=False)

    def searched(*a, **kw):
        raise AssertionError("the refit searched for the lobe again")

    monkeypatch.setattr(decisions, "paper_scheme", searched)
    refit = fit_phong(cap, **model)
    assert refit.specular == model["specular"] and bool(torch.isfinite(refit.alpha).all())


def test_pool_box_sums_neighbours():
    g = torch.zeros(3, 5, 6, dtype=torch.float64)
    wts = bilateral_weights(g, 1, sigma=1.0)
    x = torch.ones(1, 5, 6, dtype=torch.float64)
    out = pool(x, wts, 1)
    # interior pixel: 1 + 4·e^{-1/2} + 4·e^{-1}; r_s = 1 → spatial weight exp(−|o|²/2)
    want = 1 + 4 * np.exp(-0.5) + 4 * np.exp(-1.0)
    assert out[0, 2, 2].item() == pytest.approx(want, rel=1e-12)
    assert out[0, 0, 0].item() == pytest.approx(1 + 2 * np.exp(-0.5) + np.exp(-1.0), rel=1e-12)  # corner: zero padding


def test_bilateral_weights_stop_at_colour_edges():
    g = torch.zeros(3, 4, 6, dtype=torch.float64)
    g[0, :, 3:] = 5.0
    wts = {(dy, dx): w for dy, dx, w in bilateral_weights(g, 1, sigma=0.5)}
    assert float(wts[(0, 1)][1, 2]) < 1e-20  # pixel (1,2) does not pool its right neighbour across the edge
    assert float(wts[(0, -1)][1, 2]) > 0.5


def test_maps_recover_two_materials_better_than_global(two):
    cap = two.capture
    obs = build_observations(cap, dtype=torch.float64, want_tmin=True)
    g = fit_specular(obs, grid_beta(obs, 1), tol=1e-6, max_iters=50)
    maps = fit_gloss_maps(obs, g.s[0].view(3, 1), g.alpha[0].view(3, 1), tol=1e-6, max_iters=30)
    s_true, a_true = two.specular_maps()
    s_true, a_true = s_true.reshape(3, -1).double(), a_true.reshape(3, -1).double()
    err_map = (torch.log(maps.alpha) - torch.log(a_true)).abs().median()
    err_glob = (torch.log(g.alpha[0]).view(3, 1) - torch.log(a_true)).abs().median()
    assert float(err_map) < 0.25 * float(err_glob), (float(err_map), float(err_glob))
    assert float((maps.s - s_true).abs().median()) < 0.25 * float((g.s[0].view(3, 1) - s_true).abs().median())
    assert maps.s.shape == (3, 40 * 40) and bool((maps.s >= 0).all()) and bool(torch.isfinite(maps.alpha).all())


def test_fit_maps_beats_global_on_clean_renders(two):
    cap = two.capture
    glob = fit_phong(cap, specular="global")
    mp = fit_phong(cap, specular="maps")
    assert mp.specular == "maps" and mp.gloss_s.shape == (3, 40, 40)
    clean = two.render_clean()
    e_g = float(((render_all(glob, cap) - clean) ** 2).mean())
    e_m = float(((render_all(mp, cap) - clean) ** 2).mean())
    assert e_m < 0.5 * e_g, (e_m, e_g)
    rep = mp.report()
    assert rep["specular"] == "maps" and rep["maps_selection"]["mse"]["maps"] < rep["maps_selection"]["mse"]["base"]


def test_auto_keeps_global_on_a_uniform_sample():
    cap = synth(size=32, shots=10, seed=1, noise=0.01).capture
    res = fit_phong(cap)
    assert res.specular == "global" and res.gloss_s is None
    records = {d["name"]: d for d in res.decisions}
    assert res.maps_selection["kept"] is False and records["gloss maps"]["chosen"] == "base", res.skipped
    assert "gloss maps" in res.skips


def _choose(cap, force=False, more_holds=None):
    from torchmetal.fit.gloss import choose_maps
    from torchmetal.fit.problem import Reference

    glob = fit_phong(cap, specular="global")
    base = Reference(glob.s.double().view(1, 3), glob.alpha.double().view(1, 3))
    return choose_maps(cap, base, stride=1, hold=0, force=force, tol=1e-4, max_iters=100, dtype=torch.float64,
                       chunk=1 << 20, weighting=None, more_holds=more_holds)


def test_choose_maps_stops_early_when_the_maps_lose():
    """Uniform gloss: the maps fit noise, the held-out shot says so after EARLY_ITERS iterations."""
    sel = _choose(synth(size=32, shots=10, seed=1, noise=0.01).capture)
    assert not sel.kept and sel.stopped_early and sel.decision.chosen == "base", sel.reason
    assert sel.mse["maps"] >= sel.mse["base"]
    forced = _choose(synth(size=32, shots=10, seed=1, noise=0.01).capture, force=True)
    assert forced.kept and not forced.stopped_early and forced.iterations > sel.iterations


def test_the_maps_test_leaves_out_each_held_shot_in_turn():
    """Three shots left out in turn pair three shots' errors: the same gain reaches a higher z than on one (a single
    shot's highlight covers too few pixels); a trial that loses on the first shot is not fitted without the others."""
    cap = synth(size=40, shots=12, seed=3, spec_clusters=2, noise=0.01).capture
    one, three = _choose(cap), _choose(cap, more_holds=[0, 5, 9])
    assert three.decision.holds == [0, 5, 9] and one.decision.holds == [0]
    assert three.kept and three.decision.z["maps"] > 1.3 * one.decision.z["maps"], (one.reason, three.reason)
    uniform = _choose(synth(size=32, shots=10, seed=1, noise=0.01).capture, more_holds=[4, 7])
    assert uniform.stopped_early and uniform.decision.holds == [0] and not uniform.kept


def test_the_fit_leaves_out_the_plans_first_shots_for_the_maps():
    from torchmetal.fit.gloss import HOLDS

    res = fit_phong(synth(size=40, shots=12, seed=3, spec_clusters=2, noise=0.01).capture, specular="maps")
    d = next(d for d in res.decisions if d["name"] == "gloss maps")  # forced: fitted without each held shot
    assert d["chosen"] == "maps" and d["holds"] == res.shot_plan.holds(HOLDS) and len(d["holds"]) == HOLDS == 3


def test_choose_maps_keeps_maps_where_the_gloss_varies():
    """Two materials, noisy: the trial is not stopped early and the maps win on the held-out shot."""
    sel = _choose(synth(size=40, shots=12, seed=3, spec_clusters=2, noise=0.01).capture)
    assert sel.kept and sel.mse["maps"] < 0.5 * sel.mse["base"], sel.reason


def test_paper_scheme_rejects_maps():
    cap = synth(size=16, shots=4).capture
    with pytest.raises(InputError, match="maps"):
        fit_phong(cap, scheme="paper", specular="maps")


def _maps_material(h=12, w=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    tex = 0.2 + 0.5 * torch.rand(3, h, w, generator=g)
    gs = 0.1 + torch.rand(3, h, w, generator=g)
    ga = 5.0 + 200.0 * torch.rand(3, h, w, generator=g)
    return Material(tex, gs.mean((1, 2)), ga.mean((1, 2)), (1.0, 1.2), gloss_s=gs, gloss_alpha=ga)


def test_material_round_trip_files_readable_with_numpy(tmp_path):
    m = _maps_material()
    save_material(m, tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "material.json").read_text())
    assert meta["phong"]["maps"] == {"s": "gloss_s.npy", "alpha": "gloss_alpha.npy"}
    a = np.load(tmp_path / "m" / "gloss_alpha.npy", allow_pickle=False)
    assert a.shape == (12, 10, 3) and a.dtype == np.float32
    back = load_material(tmp_path / "m")
    torch.testing.assert_close(back.gloss_s, m.gloss_s)
    torch.testing.assert_close(back.specular_maps()[1], m.gloss_alpha)


def test_material_bad_maps():
    m = _maps_material()
    with pytest.raises(MaterialError, match="together"):
        Material(m.texture, m.s, m.alpha, m.size, gloss_s=m.gloss_s)
    with pytest.raises(MaterialError, match="gloss_alpha: expected shape"):
        Material(m.texture, m.s, m.alpha, m.size, gloss_s=m.gloss_s, gloss_alpha=m.gloss_alpha[:, :5])
    with pytest.raises(MaterialError, match="alpha > 0"):
        Material(m.texture, m.s, m.alpha, m.size, gloss_s=m.gloss_s, gloss_alpha=-m.gloss_alpha)


def _shots(b=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    light = torch.cat([torch.rand(b, 2, generator=g) - 0.5, 1.0 + torch.rand(b, 1, generator=g), torch.ones(b, 1)], 1)
    light[-1, 3] = 0.0  # one directional light
    cam = torch.cat([torch.rand(b, 2, generator=g) - 0.5, 1.5 + torch.rand(b, 1, generator=g), torch.ones(b, 1)], 1)
    return light, torch.rand(b, 3, generator=g) + 0.5, cam


def test_renderer_matches_the_reference_model():
    m = _maps_material()
    r = MaterialRenderer(m)
    assert r.mapped and "maps=True" in repr(r)
    light, inten, cam = _shots()
    with torch.no_grad():
        got = r(light, inten, cam)
    n = m.flat_normals()
    ref = lobe_render(m.texture.double(), m.gloss_s.double(), m.gloss_alpha.double(), n.double(), light.double(),
                      inten.double(), cam.double(), m.size, "phong")
    torch.testing.assert_close(got.double(), ref, atol=2e-5, rtol=1e-4)


def test_onnx_parity(tmp_path):
    pytest.importorskip("onnxruntime")
    from torchmetal.onnx_export import PARITY_TOL, export_onnx, verify_onnx

    m = _maps_material(16, 16)
    path = export_onnx(m, tmp_path / "r.onnx")
    err = verify_onnx(path, MaterialRenderer(m))
    assert err <= PARITY_TOL


def test_maps_are_tried_on_top_of_kept_clusters(tmp_path):
    """Two materials whose gloss also varies inside each (random scene 262: embossed, given normals, dome): the
    clusters win their test, and gloss maps started from them must still be tried, and win — before, a kept
    clustered result was never given maps (8 dB lost against the clean truth)."""
    from torchmetal.bench.selection import score
    from torchmetal.io.capture import load_capture
    from torchmetal.pipeline import fit_material
    from torchmetal.synth.random_scenes import make_random_case, random_scene

    rs = random_scene(262)
    assert rs.gloss and len(rs.materials) == 2
    case = make_random_case(rs, tmp_path / rs.name)
    cap = load_capture(case.capture_dir)
    res = fit_material(cap)
    records = {d["name"]: d for d in res.report["decisions"]}
    assert records["specular clusters"]["chosen"] != "global" and records["gloss maps"]["chosen"] == "maps"
    assert res.fit.specular == "maps"
    clustered = fit_material(cap, specular="clustered")
    assert score(case, res)["psnr_coat"] > score(case, clustered)["psnr_coat"] + 3.0
