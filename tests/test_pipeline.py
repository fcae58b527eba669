"""End to end (torchmetal.pipeline.fit_material → MaterialRenderer) on synthetic flake captures:
the render of a left-out shot against its photo, by the paper's MD, over several seeds,
textures and light layouts.

MD's own sampling noise is measured alongside (reported on failure): two photos of the same
truth whose flake fields differ only in their seed (the best any statistical model can do)
score 1–6 at 256².
"""

import math
from dataclasses import replace

import pytest
import torch

import torchmetal.flakes.run as flake_run
from torchmetal.demo import DEMO_FLAKES
from torchmetal.errors import InputError
from torchmetal.fit.result import skip_stages
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.md import metallic_difference
from torchmetal.pipeline import fit_material, render_shots
from torchmetal.renderer import MaterialRenderer
from torchmetal.synth import synth_capture

SIZE, SHOTS, HOLD = 256, 13, 6
CASES = [  # seed, texture, bumpy, layout
    (0, "procedural", False, "ring"),
    (1, "photo", False, "ring"),
    (2, "procedural", True, "ring"),
    (3, "photo", False, "hemisphere"),
    (4, "procedural", False, "hemisphere"),
]


def _capture(seed, texture, bumpy, layout, flake_seed):
    flakes = FlakeModel(**DEMO_FLAKES, seed=flake_seed)
    return synth_capture(size=SIZE, shots=SHOTS, seed=seed, texture=texture, bumpy=bumpy, noise=0.005, bits=16,
                         exposure=0.8, flakes=flakes, layout=layout)


@pytest.fixture(scope="module")
def left_out():
    """Per case: MD of the render with and without flakes, MD between photos of two flake seeds,
    and the fitted density over the realised one."""
    out = {}
    for seed, texture, bumpy, layout in CASES:
        syn = _capture(seed, texture, bumpy, layout, flake_seed=20 + seed)
        cap = syn.capture
        fit = fit_material(cap.subset([k for k in range(SHOTS) if k != HOLD]), flakes="auto", seed=0)
        one = cap.subset([HOLD])
        md = {}
        with torch.inference_mode():
            for flakes in (True, False):
                img = MaterialRenderer(fit.material, flakes=flakes)(one.lights, one.intensities, one.cameras)
                md[flakes] = float(metallic_difference(img, one.images))
        other = _capture(seed, texture, bumpy, layout, flake_seed=50 + seed).capture.images[HOLD : HOLD + 1]
        model = fit.material.flakes
        out[(seed, texture, layout)] = {
            "md": md[True], "md_no_flakes": md[False], "md_floor": float(metallic_difference(other, one.images)),
            "density": None if model is None else model.density / (syn.truth["flake_field"].count / SIZE**2),
        }
    return out


def test_md_of_left_out_photo(left_out):
    # target: an MD of at most 4 on a left-out photo (the paper reports 4.05 and 5.40); measured 3.54, 2.23, 3.68, 0.48, 3.53
    # against a seed-to-seed floor of 3.26, 1.09, 3.21, 1.37, 3.56
    for case, r in left_out.items():
        assert r["md"] <= 4.0, (case, r)


def test_sparkles_are_needed(left_out):
    for case, r in left_out.items():
        # ~200 flakes, ~120 detected: the estimator's own noise is ~10 % here (the 10 % accuracy
        # target is tested at 384² on the flake stage, tests/flakes/estimate/test_stats.py)
        assert r["density"] is not None and abs(r["density"] - 1) < 0.25, (case, r)
        if r["md_no_flakes"] > 5.0:  # photo textures hide most sparkle in their own detail
            assert r["md"] < 0.5 * r["md_no_flakes"], (case, r)


def test_same_capture_same_material():
    syn = _capture(0, "procedural", False, "ring", flake_seed=20)
    cap = syn.capture.subset(list(range(8)))
    a, b = fit_material(cap, flakes="auto", seed=3), fit_material(cap, flakes="auto", seed=3)
    assert a.material.flakes is not None
    assert a.material.flakes.to_dict() == b.material.flakes.to_dict()
    assert torch.equal(a.material.texture, b.material.texture)
    assert math.isfinite(a.material.report["total_time"])


def test_glint_observations_leave_the_coat_fit_shot_by_shot():
    """The coating's refit leaves out each detection (grown by 1 px) in the shot that saw it, as a saturated
    observation; the pixel stays in the mask for its other shots."""
    from torchmetal.flakes.run import without_glints

    cap = _capture(0, "procedural", False, "ring", flake_seed=20).capture.subset([0, 1, 2])
    labels = torch.zeros(3, SIZE, SIZE, dtype=torch.int64)
    labels[1, 10, 20] = 7
    out = without_glints(cap, labels)
    assert torch.equal(out.mask, cap.mask)
    added = out.saturated & ~cap.saturated
    assert added[1, :, 9:12, 19:22].all() and int(added.sum()) == 3 * 9  # shot 1 only, 3×3, every channel
    assert torch.equal(out.saturated | cap.saturated, out.saturated)  # what was clipped stays clipped


def test_flakes_not_kept_give_the_flake_free_material(monkeypatch):
    """When the left-out shots' MD says no (torchmetal.flakes.choice.keep_flakes), the material is the one
    flakes="off" gives — the first fit, no refit away from the detections, no sparkles — and the report
    says why; when it says yes, the flakes stay with its numbers in the report."""

    flakes = FlakeModel(**DEMO_FLAKES, seed=20)
    cap = synth_capture(size=128, shots=8, seed=0, noise=0.005, bits=16, exposure=0.8, flakes=flakes).capture
    kept = fit_material(cap, seed=0)
    ch = kept.report["flakes"]["flakes_choice"]
    assert kept.material.flakes is not None and ch["kept"]
    mean = lambda rows: sum(r["md"] for r in rows) / len(rows)  # noqa: E731
    assert mean(ch["flakes"]) <= mean(ch["none"])
    records = {d["name"]: d for d in kept.report["decisions"]}  # one record per choice, in one list
    assert records["flakes"]["chosen"] == "flakes" and records["flakes"]["scores"]["flakes"]["md"] == mean(ch["flakes"])
    assert records["lobe"]["chosen"] == kept.material.lobe and "specular evidence" in records
    assert "weights" in records  # the first fit's choice, kept by the flake stage's refits, is on record
    assert records["observed flakes"]["chosen"] == ("observed" if kept.material.observed_flakes is not None
                                                    else "statistical")
    assert set(records) <= {"registration", "clipping", "normals", "relief", "light", "weights", "lobe", "specular evidence", "specular clusters", "relabel",
                            "gloss maps", "specular colour", "observed flakes", "flakes", "density map"}
    times = kept.report["stage_times"]  # the total counts the flake choices too
    assert kept.report["total_time"] >= times["flakes"] + times["choice.observed flakes"] + times["choice.flakes"]
    # every choice's seconds under its own name, the Phong fit's and the flake stage's own ones too (not as
    # "phong.choice.…" or "flakes.…")
    assert {"choice.weights", "choice.specular evidence", "choice.density map"} <= set(times)
    # (the relabelling is tried inside the clusters' choice: its seconds are theirs)
    assert {f"choice.{name}" for name in records if name != "relabel"} <= set(times)
    assert not any(k.startswith("phong.choice") for k in times)
    # applying a choice made before the fit is a stage of its own (the registration resamples every shot)
    assert {"registration", "clipping", "normals", "light"} <= set(times)
    monkeypatch.setattr(flake_run, "keep_flakes", lambda *a, **k: (False, {"kept": False, "reason": "MD says no"}))
    dropped, off = fit_material(cap, seed=0), fit_material(cap, seed=0, flakes="off")
    m = dropped.material
    assert m.flakes is None and m.observed_flakes is None and dropped.flakes.model is None
    assert torch.equal(m.texture, off.material.texture) and torch.equal(m.s, off.material.s)
    assert dropped.report["flakes"]["flakes_choice"]["kept"] is False and "flakes" in skip_stages(m.report["skipped"])
    assert dropped.report["flakes"]["flakes_choice"]["reason"] == "MD says no"


def test_default_chooses_lobe_and_normals_on_left_out_shots():
    """fit_material's defaults (normals="auto", lobe="auto") record their decisions: a bumpy GGX sample
    without its normal map gets estimated normals and the GGX lobe; with the map given, the map is kept."""
    from dataclasses import replace

    from tests.fit.test_lobes import lobe_capture

    cap, *_ = lobe_capture("ggx", alpha=(300.0, 300.0, 300.0), size=48, shots=12, bumpy=True, dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    cap = replace(cap, images=(cap.images + 0.003 * torch.randn(cap.images.shape, generator=g)).clamp_min(0.0))
    res = fit_material(replace(cap, normals=None), flakes="off")
    rep = res.report
    assert rep["normals"]["mode"] == "auto" and rep["normals"]["chosen"] == "estimate", rep["normals"]["decision"]
    assert rep["normals"]["decision"]["z"]["estimate"] > 4 and res.material.normals is not None
    given = fit_material(cap, flakes="off")
    assert given.report["normals"]["chosen"] == "given" and given.material.normals is not None
    assert given.report["lobe"] == "ggx" == given.report["lobe_selection"]["lobe"], given.report["lobe_selection"]
    names = [d["name"] for d in rep["decisions"]]
    assert names[:5] == ["registration", "clipping", "normals", "light", "lobe"] and rep["decisions"][2]["chosen"] == "estimate"
    assert rep["clipping"]["chosen"] == rep["decisions"][1]["chosen"]  # the stage's report holds its record
    assert rep["registered"]["chosen"] == rep["decisions"][0]["chosen"] == "off"  # a synthetic capture: untested
    assert [d["chosen"] for d in given.report["decisions"] if d["name"] == "lobe"] == ["ggx"]


def test_light_calibration_stage_records_its_decision():
    from tests.lightcal.helpers import flash_capture

    cap, *_ = flash_capture()
    res = fit_material(cap, flakes="off", normals="given", lobe="phong")  # light="auto", the default
    names = [d["name"] for d in res.report["decisions"]]
    assert names[:3] == ["registration", "clipping", "light"]
    assert res.report["decisions"][2]["chosen"] == res.report["light"]["chosen"]
    assert res.report["light"]["chosen"] == "flash" and len(res.report["light"]["flash"]) == 3
    assert res.report["stage_times"]["light"] > 0
    off = fit_material(cap, flakes="off", normals="given", lobe="phong", light="off")
    assert off.light.identity and "light" not in [d["name"] for d in off.report["decisions"]]
    # the calibrated material predicts the photos better once the renders use the moved lights
    err = lambda r: float(((render_shots(r.fit, replace(cap, lights=r.light.lights(cap))) - cap.images) ** 2).mean())  # noqa: E731
    assert err(res) < 0.5 * err(off)
    with pytest.raises(InputError, match="light: expected one of"):
        fit_material(cap, light="lamp")


def test_the_statistics_refit_keeps_the_first_fits_clusters():
    """The flake statistics' Huber refit tries only the first fit's cluster count, and relabels only where
    the first fit did (the relabelling trial was 10 s of the real card's 18 s refit)."""
    from types import SimpleNamespace

    from torchmetal.fit.start import refit_options

    def fit(specular, selection):
        return SimpleNamespace(specular=specular, selection=selection, lobe="phong", noise=None, decisions=[],
                               s=torch.ones(3), alpha=torch.full((3,), 10.0), cluster_alpha=None)

    assert "clusters" not in refit_options(fit("global", {"k": 1}))
    assert "clusters" not in refit_options(fit("maps", None))
    kept = refit_options(fit("clustered", {"k": 4, "relabel": False}))
    assert kept["clusters"] == (4,) and kept["relabel"] is False and kept["weights"] == "uniform"
    assert refit_options(fit("clustered", {"k": 2, "relabel": True}))["relabel"]
    assert refit_options(fit("none", None))["start"] is None
    # a maps model refitted as the structure its maps grew from starts as that structure: fit_phong drops a start of
    # another structure, and each refit searched for the lobe again
    for k, structure in ((1, "global"), (3, "clustered")):
        base = refit_options(fit("maps", {"k": k}), maps=False)
        assert base["specular"] == base["start"].specular == structure
    assert refit_options(fit("maps", {"k": 3}))["start"].specular == "maps"


def test_glints_with_a_small_share_of_the_residual_leave_the_coating_fit_alone(monkeypatch):
    """Detections holding under REFIT_ENERGY_SHARE of the first fit's squared residual cannot steer it: the
    coating is the first fit (its texture re-solved under them), as the report says; above it, refitted."""
    import torchmetal.flakes.run as P

    cap = _capture(0, "procedural", False, "ring", flake_seed=20).capture.subset(list(range(8)))
    refitted = fit_material(cap, flakes="on", seed=0)
    share = refitted.flakes.report["glint_energy_share"]
    assert share >= P.REFIT_ENERGY_SHARE  # synthetic glitter: a large share of the misfit
    assert any("refitted away from the detected glints" in s for s in refitted.material.report["skipped"])
    monkeypatch.setattr(P, "REFIT_ENERGY_SHARE", 1.01)
    kept = fit_material(cap, flakes="on", seed=0)
    assert kept.flakes.report["glint_energy_share"] == share
    assert any("not refitted away" in s for s in kept.material.report["skipped"])
    first = fit_material(cap, flakes="off", seed=0).fit
    assert torch.equal(kept.fit.s, first.s) and torch.equal(kept.fit.alpha, first.alpha)
    assert not torch.equal(kept.fit.texture, first.texture)  # re-solved under the detections
    assert kept.flakes.model.to_dict() == refitted.flakes.model.to_dict()  # the statistics' fit is the same


def test_one_shot_plan_for_every_choice_on_left_out_shots(monkeypatch):
    """The capture's shots are planned once: the flake stage's refits hold out the first fit's shots, and
    every flake choice holds the plan's flake shots (the report's "shot_plan")."""
    import torchmetal.pipeline as P

    plans = []
    real = P.fit_phong

    def spy(*a, **kw):
        plans.append(kw.get("plan"))
        return real(*a, **kw)

    monkeypatch.setattr(P, "fit_phong", spy)
    monkeypatch.setattr(flake_run, "fit_phong", spy)
    cap = _capture(0, "procedural", False, "ring", flake_seed=20).capture.subset(list(range(8)))
    res = fit_material(cap, flakes="auto", seed=0)
    first_plan = res.material.report["shot_plan"]
    assert plans[0] is None and len(plans) >= 2  # the first fit plans; the refits are given its plan
    assert all(p is not None and list(p.order) == first_plan["order"] for p in plans[1:])
    assert sorted(first_plan["order"]) == list(range(8)) and first_plan["flakes"]
    rep = res.flakes.report
    assert rep["observed_choice"]["held"] == rep["flakes_choice"]["held"] == first_plan["flakes"]
    assert [f["shot"] for f in rep["density_map_choice"]["folds"]] == first_plan["flakes"]  # tried, kept or not


def test_the_density_choice_reuses_the_observed_choices_renders(monkeypatch, tmp_path):
    """The statistical flake material's renders of the plan's flake shots, made by the observed-flakes choice,
    are the density-map choice's uniform candidate: the same scores, without rendering them again."""
    import torchmetal.flakes.density_choice as dc
    from torchmetal.io.capture import load_capture
    from torchmetal.synth.zoo import SCENES, make_case

    cap = load_capture(make_case(SCENES["flakes_half"], tmp_path / "half").capture_dir)  # glitter on one half
    calls = []
    real_render = dc.render_held
    monkeypatch.setattr(dc, "render_held", lambda m, c, shots: calls.append(list(shots)) or real_render(m, c, shots))
    shared = fit_material(cap, flakes="auto", seed=0)
    n_shared, calls[:] = len(calls), []
    real_choice = flake_run.choose_density_map
    monkeypatch.setattr(flake_run, "choose_density_map", lambda *a, **kw: real_choice(*a, **{**kw, "renders": None}))
    alone = fit_material(cap, flakes="auto", seed=0)
    a, b = shared.flakes.report["density_map_choice"], alone.flakes.report["density_map_choice"]
    assert a["held"] and shared.material.observed_flakes is None  # the uniform candidate was scored
    assert a["per_shot"] == b["per_shot"] and a["winner"] == b["winner"]
    assert n_shared < len(calls)  # the left-out shots' uniform renders came from the observed choice
