"""A refit started from a chosen model (torchmetal.fit.start): the same solution as a refit that finds it again,
without the work of finding it."""

import torch

from torchmetal.fit import fit_phong
from torchmetal.fit.start import Start, refit_options
from torchmetal.synth import synth_capture


def _names(fit) -> list[str]:
    return [d["name"] for d in fit.decisions]


def test_start_reads_the_fits_values_and_choices():
    cap = synth_capture(size=48, shots=8, s=(0.5, 0.5, 0.5), alpha=(40.0, 40.0, 40.0), texture="procedural", seed=3,
                        noise=0.01).capture
    fit = fit_phong(cap, specular="auto", weights="noise")
    st = Start.of(fit)
    assert st.lobe == fit.lobe and st.s.shape == (1, 3) and st.alpha.shape == (1, 3)
    assert torch.allclose(st.alpha[0], fit.alpha.double())
    assert st.variance is not None and torch.allclose(st.variance[0], torch.tensor(fit.noise["a"], dtype=torch.float64))
    assert st.white == any(d["name"] == "specular colour" and d["chosen"] == "white" for d in fit.decisions)
    assert Start.of(fit_phong(cap, specular="none")) is None


def test_a_started_refit_finds_the_same_lobe_without_choosing_it_again():
    syn = synth_capture(size=64, shots=8, s=(0.5, 0.4, 0.3), alpha=(40.0, 60.0, 80.0), texture="procedural", seed=5,
                        noise=0.01)
    ref = fit_phong(syn.capture, specular="auto", weights="noise")
    train = syn.capture.subset([0, 1, 2, 4, 5, 6, 7])  # a candidate's shots
    model = {k: v for k, v in refit_options(ref).items() if k != "start"}
    plain = fit_phong(train, **model)
    started = fit_phong(train, **model, start=Start.of(ref))
    assert "paper" in plain.stage_times and "paper" not in started.stage_times  # no paper scheme, no α grid
    assert "specular evidence" in _names(plain) and "specular evidence" not in _names(started)
    assert torch.allclose(started.alpha, plain.alpha, rtol=0.02) and torch.allclose(started.s, plain.s, rtol=0.02)
    assert abs(started.rmse - plain.rmse) <= 0.02 * plain.rmse  # weighted: each by its own noise model
    assert torch.allclose(started.alpha, torch.tensor([40.0, 60.0, 80.0]), rtol=0.1)


def test_a_start_of_another_lobe_or_with_weights_to_choose_is_not_used():
    cap = synth_capture(size=48, shots=8, texture="procedural", seed=1, noise=0.01).capture
    ref = fit_phong(cap, specular="global", lobe="blinn")
    st = Start.of(ref)
    assert "paper" in fit_phong(cap, specular="global", lobe="phong", start=st).stage_times
    assert "choice.weights" in fit_phong(cap, specular="global", lobe="blinn", weights="auto", start=st).stage_times
    other = fit_phong(cap, specular="clustered", clusters=(2,), lobe="blinn", start=st)  # another structure
    assert "specular evidence" in _names(other)


def test_a_started_clustered_refit_keeps_the_cluster_count_and_splits_its_own_pixels():
    syn = synth_capture(size=64, shots=8, s=(0.6, 0.6, 0.6), alpha=(20.0, 20.0, 20.0), texture="procedural", seed=2,
                        noise=0.005, spec_clusters=2)
    ref = fit_phong(syn.capture, specular="clustered", clusters=(2,), relabel=False)
    started = fit_phong(syn.capture, **refit_options(ref))
    assert started.specular == "clustered" and started.cluster_s.shape == (2, 3)
    assert "specular evidence" not in _names(started) and "specular clusters" in _names(started)
    assert "paper" not in started.stage_times
    assert abs(started.rmse - ref.rmse) <= 0.02 * ref.rmse


def test_a_started_refit_of_a_maps_model_keeps_its_maps_untried():
    """The forced maps trial (a held-out fit of maps on the selection grid) is not made again for a refit of a model
    that kept gloss maps: the maps are fitted at full resolution, as the model says."""
    cap = synth_capture(size=48, shots=8, texture="procedural", seed=6, noise=0.01).capture
    ref = fit_phong(cap, specular="maps")
    assert ref.specular == "maps"
    started = fit_phong(cap.subset([0, 1, 2, 3, 4, 5]), **refit_options(ref))
    assert started.specular == "maps" and started.gloss_alpha is not None
    assert started.maps_selection["reason"].startswith("the model's gloss maps")
    assert "gloss maps" not in _names(started)


def test_noise_weights_from_a_start_without_a_noise_model_are_estimated():
    """A start from a uniform-weights fit, asked for noise weights: the noise model is estimated from the refit's
    residuals (as without a start), not silently left out."""
    cap = synth_capture(size=48, shots=8, texture="procedural", seed=4, noise=0.01).capture
    ref = fit_phong(cap, specular="global", weights="uniform")
    st = Start.of(ref)
    assert st.variance is None
    refit = fit_phong(cap, specular="global", weights="noise", start=st)
    assert refit.noise is not None and "paper" not in refit.stage_times
