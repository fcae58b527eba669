"""The selection harness (torchmetal.select.harness) on a declared toy choice: untested cases, the screen, the
folds, pairing, futility, the record."""

import math

import torch

from torchmetal.select.harness import Choice, Context, Screen, decide, observation_errors, pixel_errors
from torchmetal.synth import synth_capture

CAP = synth_capture(size=16, shots=7, seed=0, noise=0.0).capture


def _toy(scale: dict, **kw) -> Choice:
    """Candidate c renders the held-out photos times (1 + scale[c]): its errors grow with scale."""
    def fit(train, c, ctx):
        assert train.num_shots >= 4 and c in scale
        fits.append((train.num_shots, c))
        return lambda hold: hold.images * (1.0 + scale[c] * (1.0 + 0.1 * torch.rand(hold.images.shape, generator=torch.Generator().manual_seed(1))))

    fits: list = []
    choice = Choice("toy", tuple(scale), fit=fit, errors=observation_errors, grid=lambda c: c, **kw)
    return choice, fits


def test_the_better_extension_wins_on_every_fold():
    choice, fits = _toy({"ref": 0.1, "ext": 0.01})
    d = decide(choice, CAP, Context.fixed({}))
    assert d.chosen == "ext" and d.reference == "ref" and d.z["ext"] > 4 and d.seconds > 0
    assert len(d.holds) == 3 and sorted(k for g in d.holds for k in g) == list(range(7))
    assert len(fits) == 6 and all(n == 7 - len(g) for (n, _), g in zip(fits[::2], d.holds))
    trail = d.scores["folds"]  # the rule's outcome after each group, the last one the decision's
    assert len(trail) == 3 and trail[-1]["chosen"] == d.chosen and trail[-1]["z"] == d.z
    assert trail[0]["z"]["ext"] < trail[-1]["z"]["ext"]  # more groups, more evidence


def test_a_worse_extension_stops_after_one_fold():
    choice, fits = _toy({"ref": 0.01, "ext": 0.1})
    d = decide(choice, CAP, Context.fixed({}))
    assert d.chosen == "ref" and len(d.holds) == 1 and "stopped after 1 of 3" in d.reason and len(fits) == 2
    assert [f["chosen"] for f in d.scores["folds"]] == ["ref"]


def test_the_typical_rule_stops_once_its_gain_is_out_of_reach():
    """Under the typical pairing an extension lower on every pixel but short of the gain (squared errors × 0.64:
    36 % against 50 %) is not fitted on the other folds; one that quarters them wins on all three."""
    rule = {"typical": True, "min_gain": 0.5}
    choice, fits = _toy({"ref": 0.1, "ext": 0.08}, rule=rule)
    d = decide(choice, CAP, Context.fixed({}))
    assert d.chosen == "ref" and d.z["ext"] > 4 and len(d.holds) == 1 and "stopped after 1 of 3" in d.reason
    assert 0.3 < d.scores["log_ratio"]["ext"]["gain"] < 0.4 and len(fits) == 2
    choice, fits = _toy({"ref": 0.1, "ext": 0.05}, rule=rule)
    d = decide(choice, CAP, Context.fixed({}))
    assert d.chosen == "ext" and len(d.holds) == 3 and len(fits) == 6


def test_untested_and_screened_cases_fit_nothing():
    choice, fits = _toy({"ref": 0.1, "ext": 0.01}, untested=lambda c, ctx: "not today")
    d = decide(choice, CAP, Context.fixed({}))
    assert d.chosen == "ref" and d.reason == "not today" and not fits
    choice, fits = _toy({"ref": 0.1, "ext": 0.01}, screen=lambda g, ctx: Screen(False, "nothing to gain", {"x": 1.0}))
    d = decide(choice, CAP, Context.fixed({}))
    assert d.chosen == "ref" and "nothing to gain" in d.reason and d.scores["screen"]["x"] == 1.0 and not fits
    choice, fits = _toy({"ref": 0.1, "ext": 0.01}, min_shots=8)
    assert decide(choice, CAP, Context.fixed({})).reason.endswith("found 7") and not fits


def test_an_abstaining_candidate_keeps_the_reference():
    choice = Choice("toy", ("ref", "ext"), fit=lambda t, c, ctx: None if c == "ext" else (lambda h: h.images),
                    errors=observation_errors, grid=lambda c: c)
    d = decide(choice, CAP, Context.fixed({}))
    assert d.chosen == "ref" and "could not be tested" in d.reason


def test_the_prefit_choices_are_declared_in_order():
    from torchmetal.select.choices import PREFIT

    assert [c.name for c in PREFIT] == ["registration", "clipping", "normals", "relief", "light"]
    for c in PREFIT:  # the reference first; every choice follows only choices made before it
        assert len(c.candidates) >= 2 and c.reference == c.candidates[0]
        assert set(c.follows) <= {p.name for p in PREFIT[: PREFIT.index(c)]}, c.name


def test_error_measures():
    hold = CAP.subset([0, 1])
    pred = hold.images + 0.1
    e = observation_errors(pred, hold)  # 16² pixels: blocks of one pixel (a side of 1/64 of the grid, at least 1)
    assert e.shape == (16 * 16,) and torch.allclose(e, torch.full_like(e, 0.01))
    big = synth_capture(size=128, shots=2, seed=0, noise=0.0).capture
    e = observation_errors(big.images + 0.1, big)
    assert e.shape == (64 * 64,) and torch.allclose(e, torch.full_like(e, 0.01))  # 2 × 2 pixel blocks
    p = pixel_errors(pred, hold)  # per mask pixel
    assert p.shape == (256,) and torch.allclose(p, torch.full_like(p, 0.01))
    assert pixel_errors(big.images + 0.1, big).shape == (128 * 128,)
    sat = hold.saturated.clone()
    sat[:, :, 0, 0] = True
    from dataclasses import replace

    assert math.isnan(float(pixel_errors(pred, replace(hold, saturated=sat))[0]))


def test_the_context_fits_the_same_data_once():
    """Grids and shot subsets made apart (copies) share one fit where their data are equal; other data, or other
    options, get their own (the registration's, normals', relief's and light's folds on a small capture)."""
    from dataclasses import replace

    from torchmetal.io.grid import strided_capture
    from torchmetal.select.harness import capture_key, content_key

    big = synth_capture(size=24, shots=5, seed=1, noise=0.0).capture
    ctx = Context.fixed({"lobe": "phong", "specular": "global", "weights": "uniform"})
    a, b = strided_capture(big, 100).subset([0, 1, 2]), strided_capture(big, 100).subset([0, 1, 2])
    assert capture_key(a) != capture_key(b) and content_key(a) == content_key(b)
    assert ctx.fit(a) is ctx.fit(b)
    assert ctx.fit(a, scheme="paper") is not ctx.fit(a)
    other = replace(a, images=a.images * 1.01)
    assert content_key(other) != content_key(a) and ctx.fit(other) is not ctx.fit(a)
    assert len(ctx.fits) == 3
