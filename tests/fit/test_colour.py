import torch

from torchmetal.fit import fit_phong
from torchmetal.fit.colour import fit_white, white_s
from torchmetal.fit.problem import build_observations
from torchmetal.fit.refine import evaluate_specular, fit_specular, spec_sums
from torchmetal.synth import synth_capture


def _colour_decision(fit):
    found = [d for d in fit.decisions if d["name"] == "specular colour"]
    assert len(found) == 1, [d["name"] for d in fit.decisions]
    return found[0]


def test_a_coloured_specular_keeps_per_channel_s():
    cap = synth_capture(size=64, shots=8, s=(0.6, 0.3, 0.1), alpha=(50.0, 50.0, 50.0), texture="procedural", seed=2,
                        noise=0.01).capture
    fit = fit_phong(cap, specular="auto", lobe="phong")
    d = _colour_decision(fit)
    assert d["chosen"] == "free" and d["z"]["white"] < 0
    assert float(fit.s[0]) > 2 * float(fit.s[2])


def test_white_fit_has_one_s_and_no_higher_cost_than_its_start():
    cap = synth_capture(size=48, shots=8, s=(0.5, 0.5, 0.5), alpha=(30.0, 60.0, 90.0), texture="procedural", seed=4,
                        noise=0.01).capture
    obs = build_observations(cap)
    free = fit_specular(obs, torch.log(torch.full((1, 3), 40.0, dtype=torch.float64)))
    white = fit_white(obs, free, tol=1e-6, max_iters=100)
    assert torch.allclose(white.s[0], white.s[0, :1].expand(3))
    start = evaluate_specular(obs, white_s(spec_sums(obs, free.alpha)[0]), free.alpha)  # white s at the free α
    assert float(white.cost.sum()) <= float(start.cost.sum()) * (1 + 1e-9)
    assert abs(float(white.s[0, 0]) - 0.5) < 0.05 and float(white.alpha.min()) > 20


def test_a_white_decision_gives_the_full_fit_one_s(monkeypatch):
    from torchmetal.fit import decisions
    from torchmetal.select.rule import Decision

    cap = synth_capture(size=48, shots=6, s=(0.5, 0.5, 0.5), alpha=(40.0, 40.0, 40.0), texture="procedural", seed=1,
                        noise=0.01).capture
    monkeypatch.setattr(decisions, "choose_colour", lambda *a, **k: Decision("specular colour", ("free", "white"), "white"))
    fit = fit_phong(cap, specular="auto", lobe="phong")
    assert _colour_decision(fit)["chosen"] == "white"
    assert float(fit.s.max() - fit.s.min()) == 0.0 and abs(float(fit.s[0]) - 0.5) < 0.05
    free = fit_phong(cap, specular="global", lobe="phong")  # no colour decision: per-channel s
    assert not [d for d in free.decisions if d["name"] == "specular colour"]
