"""The accuracy rules on the CI-sized scene zoo, scored against the noise-free truth.

1. The default ``fit_material`` is never worse than the paper's scheme (−0.2 dB) on the coating.
2. Where Phong is the truth (global, or two materials; the shots sample the lobe), it is within
   1 dB of the oracle (the truth's own specular, texture solved from the same shots); so it is where the
   truth is Blinn or the renderer's GGX, and the default picks that lobe.
3. No flake model on a flake-free scene; a model on every flake scene, with its statistics near the truth's
   and its sparkles (as rendered) as good as the truth's own flakes drawn again at other places.
4. Where the shots never sample the lobe's peak, no highlight is invented.
"""

import math

import numpy as np
import pytest

from torchmetal.bench.zoo import METHODS, run_scene
from torchmetal.fit.result import skip_stages
from torchmetal.synth.zoo import ci_scenes

SCENES = {s.name: s for s in ci_scenes()}
UNIDENTIFIED = {"blind_peak", "grazing_only"}  # fit shots never near the mirror direction: s, α not identifiable
PSNR_CEILING = 100.0  # float32 rounding: above this, dB differences say nothing


@pytest.fixture(scope="module")
def zoo(tmp_path_factory):
    root = tmp_path_factory.mktemp("zoo")
    return {name: run_scene(sc, METHODS, workdir=root) for name, sc in SCENES.items()}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCENES))
def test_default_never_loses_to_the_paper(zoo, name):
    r = zoo[name]
    d, p = r["default"], r["paper"]
    assert math.isfinite(d["psnr_coat"]) and d["psnr_coat"] >= p["psnr_coat"] - 0.2, (d["psnr_coat"], p["psnr_coat"])


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n, s in SCENES.items()
                                  if s.lobe == "phong" and s.second is not None and s.flakes is None])
def test_default_reaches_the_oracle_on_two_phong_materials(zoo, name):
    """Two Phong materials (a foil disc on paper): clusters, their edge pixels relabelled per pixel."""
    r = zoo[name]
    assert r["default"]["psnr"] >= min(r["oracle"], PSNR_CEILING) - 1.0, (r["default"]["psnr"], r["oracle"])


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n, s in SCENES.items() if s.phong_truth and n not in UNIDENTIFIED])
def test_default_reaches_the_oracle_where_phong_is_the_truth(zoo, name):
    r = zoo[name]
    assert r["default"]["psnr"] >= min(r["oracle"], PSNR_CEILING) - 1.0, (r["default"]["psnr"], r["oracle"])
    assert r["default"]["s_err"] < 0.02 and r["default"]["alpha_err"] < 0.02


TRUE_LOBE = {"blinn": "blinn", "ggx_full": "ggx"}  # zoo truth lobes that are in the default's candidate set


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n, s in SCENES.items()
                                  if s.lobe in TRUE_LOBE and s.second is None and s.flakes is None])
def test_default_picks_the_true_lobe_and_reaches_the_oracle(zoo, name):
    """Where the truth is another lobe of the candidate set (Blinn, the renderer's GGX with Fresnel and
    shadowing), the default chooses it on left-out shots and lands within 1 dB of the oracle. (ggx_truth's
    lobe is the distribution D alone, outside the set: there the default's GGX stays 1.7 dB short.)"""
    r = zoo[name]
    assert r["default"]["lobe"] == TRUE_LOBE[SCENES[name].lobe], r["default"]["lobe"]
    assert r["default"]["psnr"] >= min(r["oracle"], PSNR_CEILING) - 1.0, (r["default"]["psnr"], r["oracle"])


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCENES))
def test_flake_models_only_where_there_are_flakes(zoo, name):
    has = SCENES[name].flakes is not None
    assert zoo[name]["default"]["flake_model"] == has, zoo[name]["default"]["skipped"]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(UNIDENTIFIED))
def test_no_highlight_where_the_data_never_showed_one(zoo, name):
    d = zoo[name]["default"]
    assert d["s"] == 0.0 and "specular" in skip_stages(d["skipped"])


PHOTO_TEXTURE_BIAS = pytest.mark.xfail(strict=True, reason=(
    "open: on a photo texture (zoo flakes_orange: the coffee photo, tinted) the density comes out 17 % low and the "
    "tilt 26 % high (before the statistics detected above null_test.glint_snr: ~6x and ~2.7x); the same flakes on "
    "the procedural texture are within tolerance"))


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param(n, marks=PHOTO_TEXTURE_BIAS) if s.texture.startswith("photo:") else n
                                  for n, s in SCENES.items() if s.flakes is not None])
def test_flake_statistics_within_tolerance(zoo, name):
    """Density within 10 %, tilt within 20 % on every flake scene; median area within 15 % where the
    flakes are not smaller than ~3 px² (flakes_b's 2.5 px² flakes measure 12-18 % large across seeds:
    an open bias of the smallest flakes' areas)."""
    d = zoo[name]["default"]
    assert d["density_err"] <= 0.10 and d["tilt_err"] <= 0.20, d
    if SCENES[name].flakes["area_median"] >= 3.0:
        assert d["area_err"] <= 0.15, d


MIN_SPARKLES = 30  # truth sparkles in the held-out shots below which one glint more or less decides a comparison


def _enough_sparkles(row: dict) -> None:
    if row["truth_sparkles"] < MIN_SPARKLES:
        pytest.skip(f"{row['truth_sparkles']} truth sparkles in the held-out shots (< {MIN_SPARKLES}): one glint more "
                    "or less decides the comparison, not the flake statistics")


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n, s in SCENES.items() if s.flakes is not None])
def test_sparkles_as_good_as_the_truths_redrawn(zoo, name):
    """Sparkles at random places cost PSNR against any render without them, the truth's own included, so the
    yardstick of a render with sparkles is the truth with its flakes redrawn (bench.zoo.SPARKLE_DRAWS), not the
    paper scheme's flake-free render: the default's as-rendered PSNR is within 1 dB of it or above, where the truth
    shows enough sparkles in the held-out shots for that to be about their statistics (as below)."""
    r = zoo[name]
    _enough_sparkles(r["default"])
    assert r["default"]["psnr"] >= r["oracle_sparkles"] - 1.0, (r["default"]["psnr"], r["oracle_sparkles"])


SPARKLE_RATIO_CI = (0.5, 2.0)  # CI size: a tilt σ 8 % low already gives ×0.67 on a ring (glints from the tilt's tail)


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n, s in SCENES.items() if s.flakes is not None])
def test_left_out_sparkle_count_near_the_truths(zoo, name):
    """The left-out sparkle count over the truth's, where the truth shows at least 30: no gross drift at CI size
    (the bench's full-size zoo reports the ratio against its 0.8–1.25 target)."""
    d = zoo[name]["default"]
    _enough_sparkles(d)
    lo, hi = SPARKLE_RATIO_CI
    assert lo <= d["sparkle_ratio"] <= hi, (d["sparkle_ratio"], d["truth_sparkles"])


@pytest.mark.slow
def test_scores_are_against_the_clean_truth(zoo):
    """A perfect fit scores the oracle's reach, not the noisy photo's floor: a noise-free capture gives > 100 dB
    (float_clean's fit in the module's zoo, not a fit of its own)."""
    r = zoo["float_clean"]
    assert SCENES["float_clean"].noise == 0.0 and SCENES["float_clean"].encoding == "float"
    assert r["default"]["psnr"] > 100.0 and np.isfinite(r["oracle"])
