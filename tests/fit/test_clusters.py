"""Spatially varying specular: k-means, labelers, feature maps, the held-out choice."""

import torch

from tests.fit.helpers import synth
from torchmetal.fit import fit_phong
from torchmetal.fit.cluster_features import SpecFeatureMap, colour_features, grid_coords, kmeans, make_labeler


def test_kmeans_separates_blobs():
    g = torch.Generator().manual_seed(0)
    x = torch.cat([torch.randn(200, 2, generator=g) * 0.1, torch.randn(300, 2, generator=g) * 0.1 + 3.0]).double()
    cent, lab = kmeans(x, 2, seed=1)
    assert lab[:200].unique().numel() == 1 and lab[200:].unique().numel() == 1 and lab[0] != lab[-1]
    assert sorted(torch.bincount(lab).tolist()) == [200, 300]


def test_colour_labeler_splits_two_materials():
    tex = torch.zeros(3, 8, 8)
    tex[:, :, :4] = torch.tensor([0.6, 0.5, 0.1]).view(3, 1, 1)  # gold-ish
    tex[:, :, 4:] = torch.tensor([0.1, 0.4, 0.5]).view(3, 1, 1)  # teal-ish
    tex = tex + 0.01 * torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0))
    t = tex.reshape(3, -1)
    ij = grid_coords(8, 8, 1, t.device).to(t.dtype)
    lab = make_labeler(t, ij, torch.ones(64, dtype=torch.bool), 2, spec=None, features="colour")
    out = lab(t, ij).view(8, 8)
    assert out[:, :4].unique().numel() == 1 and out[:, 4:].unique().numel() == 1 and out[0, 0] != out[0, -1]
    f = colour_features(t, 1e-3)
    assert f.shape == (64, 3) and torch.isfinite(f).all()


def test_spec_feature_map_samples_its_grid_exactly():
    maps = torch.arange(2 * 4 * 5, dtype=torch.float32).view(2, 4, 5)
    fm = SpecFeatureMap(maps, stride=3, off=1)
    ij = grid_coords(4, 5, 3, torch.device("cpu")).float()
    torch.testing.assert_close(fm.sample(ij), maps.reshape(2, -1).T)
    mid = fm.sample(torch.tensor([[2.5], [1.0]]))  # halfway between rows 0 and 1 of the grid
    torch.testing.assert_close(mid[0], 0.5 * (maps[:, 0, 0] + maps[:, 1, 0]))


def test_clustered_with_two_shots_has_no_holdout_but_still_clusters():
    r = synth(size=32, shots=2, seed=3, spec_clusters=2)
    f = fit_phong(r.capture, specular="clustered", clusters=(2,))
    assert f.specular in ("clustered", "none")
    if f.specular == "clustered":
        assert f.selection["hold"] == -1
        m = f.to_material()
        assert m.clustered and m.spec_labels.shape == (32, 32)
    a = fit_phong(r.capture, specular="auto")
    assert a.spec_labels is None
    assert a.selection is None and {"specular clusters", "specular"} & set(a.skips)  # 2 shots: not tried, or no highlight


def test_heldout_scores_score_the_texture_the_material_stores():
    """A free variable-projection texture below 0 is scored as the material renders it (clamped)."""
    from torchmetal.fit.clusters import heldout_mse
    from torchmetal.fit.lobe_choice import heldout_errors
    from torchmetal.fit.problem import build_observations

    r = synth(size=16, shots=4, seed=3)
    obs = build_observations(r.capture, shots=[1])
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(3, 256, generator=g) - 0.5
    s, a = torch.full((1, 3), 0.3), torch.full((1, 3), 20.0)
    clamped = heldout_mse(obs, tex.clamp_min(0.0), s, a, None)
    assert heldout_mse(obs, tex, s, a, None) == clamped
    assert heldout_mse(obs, tex.abs(), s, a, None) != clamped  # the negatives did count as 0
    assert torch.equal(heldout_errors(obs, tex, s, a), heldout_errors(obs, tex.clamp_min(0.0), s, a))


def _mislabelled(fit, truth_labels) -> int:
    """Pixels whose cluster's majority truth label is not their own truth label."""
    lab, true = fit.spec_labels.reshape(-1), truth_labels.reshape(-1)
    major = torch.stack([torch.bincount(true[lab == k], minlength=2).argmax() if bool((lab == k).any())
                         else torch.tensor(0) for k in range(int(lab.max()) + 1)])
    return int((major[lab] != true).sum())


def test_relabel_moves_edge_pixels_to_their_material(monkeypatch):
    """Clusters drawn on a subsample miss pixels at the edge of two specular materials; the
    per-pixel relabelling moves them, and leaves the rest alone."""
    import torchmetal.fit.clusters as clusters

    syn = synth(size=64, shots=10, seed=3, noise=0.005, spec_clusters=2)
    truth = syn.truth["spec_labels"]
    after = fit_phong(syn.capture, specular="clustered")
    moved = [h["pixels"] for h in after.history if h["stage"] == "relabel"]
    monkeypatch.setattr(clusters, "RELABEL_ROUNDS", 0)
    before = fit_phong(syn.capture, specular="clustered")
    assert moved and moved[0] > 0
    assert _mislabelled(after, truth) < _mislabelled(before, truth)
    assert _mislabelled(after, truth) <= 0.005 * truth.numel()
    assert int((after.spec_labels != before.spec_labels).sum()) <= 2 * moved[0]  # only the moved pixels changed


def test_relabel_false_keeps_the_subsample_labels():
    """relabel=False (a refit keeping an earlier fit's structure): no relabelling trial, no relabel stage,
    and the clusters of the same K; the default tries it and, on this edge case, relabels."""
    syn = synth(size=64, shots=10, seed=3, noise=0.005, spec_clusters=2)
    on = fit_phong(syn.capture, specular="clustered", clusters=(2,))
    off = fit_phong(syn.capture, specular="clustered", clusters=(2,), relabel=False)
    assert any(h["stage"] == "relabel" for h in on.history)
    assert not any(h["stage"] == "relabel" for h in off.history)
    assert "relabel" not in [d["name"] for d in off.decisions] and not off.selection["relabel"]
    assert off.selection["k"] == on.selection["k"] == 2
    assert _mislabelled(off, syn.truth["spec_labels"]) > _mislabelled(on, syn.truth["spec_labels"])


def test_relabel_keeps_labels_without_evidence():
    """Every pixel explained equally well by each cluster (no highlight difference): nobody moves."""
    from torchmetal.fit.clusters import relabel
    from torchmetal.fit.problem import build_observations

    cap = synth(size=24, shots=6, seed=1, noise=0.01).capture
    obs = build_observations(cap, dtype=torch.float64)
    obs.labels = torch.arange(obs.num_pixels) % 2
    s = torch.tensor([[0.3, 0.3, 0.3], [0.3, 0.3, 0.3]], dtype=torch.float64)
    alpha = torch.full((2, 3), 40.0, dtype=torch.float64)
    labels, n = relabel(obs, s, alpha, per_obs=1e-6)
    assert n == 0 and torch.equal(labels, obs.labels)


def test_a_cluster_whose_s_runs_away_keeps_the_global_terms(monkeypatch):
    """A cluster whose highlight its shots saw only in the lobe's tail has an s without bound (random scene 221's
    fold: s 1.5e6, renders of 1e6 on the left-out shots). Beyond S_RATIO_MAX times the global s it is held at the
    global terms, and so is any element the holding sends beyond it; here the bound is lowered so that the
    brighter cluster of a two-material sample crosses it."""
    import torchmetal.fit.clusters as clusters
    from torchmetal.fit.clusters import fit_clustered
    from torchmetal.fit.problem import build_observations
    from torchmetal.fit.refine import fit_specular, grid_beta

    syn = synth(size=48, shots=8, seed=2, noise=0.003, spec_clusters=2, s=(0.9, 0.9, 0.9))
    obs = build_observations(syn.capture, want_tmin=True)
    glob = fit_specular(obs, grid_beta(obs, 1))
    ij = grid_coords(obs.height, obs.width, 1, obs.device).to(obs.dtype)
    lab = make_labeler(obs.tmin, ij, obs.n.sum(0) > 0, 2, spec=None)
    obs.labels = lab(obs.tmin, ij)
    free = fit_clustered(obs, lab, glob, tol=1e-6, max_iters=100)
    ratio = float(free.s.max() / glob.s.max())
    assert free.pinned is None or not bool(free.pinned.any())
    monkeypatch.setattr(clusters, "S_RATIO_MAX", 0.5 * (1.0 + ratio))  # between the global s and the brighter cluster's
    held = fit_clustered(obs, lab, glob, tol=1e-6, max_iters=100)
    assert held.pinned is not None and bool(held.pinned.any())
    free_s = held.s[~held.pinned]
    assert bool((free_s <= clusters.S_RATIO_MAX * glob.s.max() * (1 + 1e-9)).all())
    assert torch.allclose(held.s[held.pinned], glob.s.expand_as(held.s)[held.pinned].to(held.s.dtype))


def test_the_full_resolution_fit_holds_a_runaway_cluster_too(monkeypatch):
    """The full-resolution LM (and the relabelling's refits) starts from the subsample's clusters; an element that
    runs beyond the bound there is held at the subsample fit's terms, and the report says so."""
    import torchmetal.fit.clusters as clusters

    syn = synth(size=48, shots=8, seed=2, noise=0.003, spec_clusters=2, s=(0.9, 0.9, 0.9))
    monkeypatch.setattr(clusters, "S_RATIO_MAX", 0.9)  # below 1: the brightest full-resolution element crosses it
    fit = fit_phong(syn.capture, specular="clustered", clusters=(2,))
    assert fit.specular == "clustered"
    assert any("ran beyond" in msg for msg in fit.skipped), fit.skipped
    assert bool(torch.isfinite(fit.cluster_s).all())
