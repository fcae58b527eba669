"""The ``selection`` bench section (issue 41, item 3): its counting of false positives and misses, and the
section end to end on two tiny random scenes."""

import json
import math

from torchmetal.bench import selection
from torchmetal.bench.runner import SECTIONS


def _scene(seed, truth, chosen, base, fixed, default=30.0, paper=29.0):
    return {"seed": seed, "truth": truth, "chosen": chosen, "base": base, "fixed": fixed,
            "default": {"psnr_coat": default, "time": 1.0}, "paper": {"psnr_coat": paper}}


def test_false_positives_and_misses_are_counted():
    base = {"normals": "flat", "light": "off", "lobe": "phong", "flakes": "off"}
    scenes = [
        # truth flat, relief not taken, light's flash move gains 2 dB but kept off: a miss
        _scene(0, {"normals": "reference", "light": "reference"},
               {"normals": {"chosen": "flat", "reference": "flat"}, "light": {"chosen": "off", "reference": "off"}},
               base, {"base": {"psnr_coat": 30.0}, "light=flash": {"psnr_coat": 32.0},
                      "normals=estimate": {"psnr_coat": 30.5}}),
        # truth flat, estimate taken: a false positive (its fit worse: no miss)
        _scene(1, {"normals": "reference", "light": "extension"},
               {"normals": {"chosen": "estimate", "reference": "flat"}, "light": {"chosen": "flash", "reference": "off"}},
               {**base, "normals": "estimate", "light": "flash"},
               {"base": {"psnr_coat": 28.0}, "normals=flat": {"psnr_coat": 29.0}, "light=off": {"psnr_coat": 25.0}},
               default=28.0, paper=31.0),
        {"seed": 2, "error": "RuntimeError: boom"},
    ]
    st = selection.choice_stats(scenes)
    assert (st["normals"]["n_ref"], st["normals"]["fp"], st["normals"]["fp_scenes"]) == (2, 1, [1])
    assert st["normals"]["n_gain"] == 0 and math.isnan(st["normals"]["miss_rate"])
    assert (st["light"]["n_ref"], st["light"]["n_ext"], st["light"]["taken_ext"]) == (1, 1, 1)
    assert (st["light"]["n_gain"], st["light"]["miss"], st["light"]["miss_scenes"]) == (2, 1, [0])  # scene 1's +3 dB was taken
    assert st["flakes"]["n_ref"] == 0  # no "flakes" entry in these hand-made scenes: not counted
    ov = selection.overall_stats(scenes)
    assert ov["fitted"] == 2 and ov["errors"] == [2]
    assert ov["within_best"] == 0.0  # scene 0: 30 vs 32 fixed; scene 1: 28 vs 29
    assert ov["below_paper"] == 1 and ov["below_paper_scenes"] == [1]
    md = selection.markdown(selection.summarise(scenes))
    assert "| light | 1 | 1 | 0.0% (0/1) | 100.0% (1/1) | 2 | 50.0% (1/2) **over** | – |" in md  # no times: no share


def test_cost_shares_are_the_choices_seconds_over_the_default_fits():
    times = [{"normals": 0.5, "light": 1.0, "reference": 0.5}, {"normals": 1.0}]
    scenes = [{"seed": k, "truth": {}, "chosen": {}, "base": {}, "fixed": {}, "paper": {"psnr_coat": 1.0},
               "default": {"psnr_coat": 1.0, "time": 4.0, "choice_s": t}} for k, t in enumerate(times)]
    st = selection.choice_stats(scenes)
    assert st["normals"]["cost_share"] == (0.125 + 0.25) / 2 and st["light"]["cost_share"] == 0.125  # 0 where not run
    ov = selection.overall_stats(scenes)
    assert (ov["choices_share_median"], ov["choices_share_max"], ov["reference_share"]) == (0.375, 0.5, 0.0625)
    md = selection.markdown(selection.summarise(scenes))
    assert "| normals | 0 | 0 | – | – | 0 | – | 18.8% |" in md
    assert "median 37.5%, at most 50.0% of a default fit's time (target ≤ 25%)" in md
    assert "False positives by scene: none.\nMisses by scene: none." in md


def test_section_end_to_end_on_two_tiny_scenes(tmp_path):
    """Two random scenes at 24²: every fit scored, the default's own choices reproduced by the forced base set."""
    assert "selection" in SECTIONS
    lines = []
    res = selection.run_section([7, 21], size=24, say=lines.append, jsonl=tmp_path / "s.jsonl")
    assert len(lines) == 2 and len((tmp_path / "s.jsonl").read_text().splitlines()) == 2
    for r in res["scenes"]:
        assert "error" not in r, r.get("error")
        assert math.isfinite(r["default"]["psnr_coat"]) and math.isfinite(r["paper"]["psnr_coat"])
        assert abs(r["fixed"]["base"]["psnr_coat"] - r["default"]["psnr_coat"]) < 0.05
        groups = {k.split("=")[0] for k in r["fixed"] if k != "base"}
        assert {"lobe", "specular", "weights", "flakes"} <= groups
        assert all("error" not in v for v in r["fixed"].values())
    assert res["scenes"][1]["base"]["normals"] == "given" and not any(
        k.startswith("normals=") for k in res["scenes"][1]["fixed"])  # scene 21 brings its normals.npy
    assert res["choices"]["flakes"]["n_ref"] == 2
    assert all(r["default"]["choice_s"] and all(v >= 0 for v in r["default"]["choice_s"].values())
               for r in res["scenes"])  # the default's choices timed (stage_times' choice.NAME)
    assert 0.0 < res["overall"]["choices_share_median"] <= res["overall"]["choices_share_max"] <= 1.0
    again = selection.run_section([7, 21], size=24, say=lines.append, jsonl=tmp_path / "s.jsonl")  # resumed: no refit
    assert len(lines) == 2 and json.dumps(again["overall"]) == json.dumps(res["overall"])
