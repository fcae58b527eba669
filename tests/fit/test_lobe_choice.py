"""lobe="auto" (torchmetal.fit.lobe_choice): the held-out comparison picks the truth's lobe, Phong otherwise."""

from __future__ import annotations

import math

import pytest
import torch

from tests.fit.helpers import replace
from tests.fit.test_lobes import lobe_capture
from torchmetal.fit import fit_phong
from torchmetal.fit.clusters import heldout_mse
from torchmetal.fit.lobe_choice import choose_lobe, fit_lobe, heldout_errors
from torchmetal.fit.problem import build_observations
from torchmetal.fit.refine import texture_map
from torchmetal.select.rule import paired_z


def noisy(lobe: str, sigma: float = 0.004, seed: int = 1, **kw):
    cap, *_ = lobe_capture(lobe, dtype=torch.float32, **kw)
    g = torch.Generator().manual_seed(seed)
    return replace(cap, images=(cap.images + sigma * torch.randn(cap.images.shape, generator=g)).clamp_min(0.0))


@pytest.mark.parametrize("truth", ["phong", "blinn", "ggx"])
def test_auto_picks_the_truth(truth):
    alpha = {"phong": (40.0, 50.0, 60.0), "blinn": (160.0, 200.0, 240.0), "ggx": (60.0, 80.0, 100.0)}[truth]
    cap = noisy(truth, alpha=alpha)
    fit = fit_phong(cap, lobe="auto")
    sel = fit.lobe_selection
    assert fit.lobe == truth == sel["lobe"], sel["reason"]
    assert set(sel["mse"]) == {"phong", "blinn", "ggx"} and set(sel["z"]) == {"blinn", "ggx"}
    assert len(sel["holds"]) == 12 and sel["reason"]
    assert min(sel["mse"], key=sel["mse"].get) == truth
    rep = fit.report()
    assert rep["lobe"] == truth and rep["lobe_selection"]["lobe"] == truth
    assert fit.to_material().report["lobe_selection"]["lobe"] == truth


def test_few_shots_or_no_highlight_keep_phong():
    cap = noisy("blinn", size=16, shots=2)
    fit = fit_phong(cap, lobe="auto")
    sel = fit.lobe_selection  # 2 shots: no held-out comparison, no record
    assert fit.lobe == "phong" == sel["lobe"] and not sel["holds"] and not sel["mse"]
    assert "lobe" not in {d["name"] for d in fit.decisions}
    matte = noisy("phong", s=(0.0, 0.0, 0.0), size=16, shots=6)  # Lambertian: no lobe to see
    sel = choose_lobe(matte, stride=1, tol=1e-4, max_iters=20, dtype=torch.float32, chunk=4096)
    assert sel.lobe == "phong" and not sel.holds and not sel.mse and sel.decision is None  # nothing to compare


def test_heldout_errors_and_paired_z():
    cap = noisy("ggx", size=24, shots=6)
    obs = build_observations(cap, shots=[0, 1, 2, 3, 4], lobe="ggx")
    ho = build_observations(cap, shots=[5], lobe="ggx")
    fit = fit_lobe(obs, tol=1e-4, max_iters=50)
    tex = texture_map(obs, fit.s, fit.eb)
    e = heldout_errors(ho, tex, fit.s, fit.alpha)
    assert e.numel() == int(ho.valid.sum())
    assert math.isclose(float(e.mean()), heldout_mse(ho, tex, fit.s, fit.alpha, None), rel_tol=1e-5)
    assert paired_z(e, e) == 0.0
    assert paired_z(0.5 * e, e) > 10 and paired_z(2 * e, e) < -10
