"""The density-map evidence script (torchmetal.bench.sparkle_map) on a small flakes_half scene, without the card."""

import json

import cv2
import pytest

from torchmetal.bench.sparkle_map import run


@pytest.fixture(scope="module")
def half(tmp_path_factory):
    out = tmp_path_factory.mktemp("sparkle_map")
    return out, run(out, card_path=None, size=128)


def test_it_writes_the_json_it_returns_and_the_side_by_side_png(half):
    out, result = half
    assert set(result) == {"flakes_half"}  # no card asked for: no card entry
    assert json.loads((out / "sparkle_map.json").read_text()) == json.loads(json.dumps(result, default=float))
    png = cv2.imread(str(out / "flakes_half.png"))
    assert png is not None and png.shape == (128, 3 * 128, 3)  # photo, uniform render, map render


def test_the_sparkles_are_counted_inside_and_outside_the_glitter(half):
    _, result = half
    rep = result["flakes_half"]
    assert rep["flakes"] is True  # the glitter half is found
    assert rep["decision"]["candidates"][0] == "uniform" and rep["decision"]["winner"] in rep["decision"]["candidates"]
    per = rep["sparkles"]
    assert set(per) == {"truth", "uniform", "map"}
    assert all(v >= 0 and float(v).is_integer() for c in per.values() for v in (c["inside"], c["outside"]))
    assert per["truth"]["inside"] > per["truth"]["outside"]  # the scene's glitter is on the left half
