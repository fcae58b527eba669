"""The randomized scene generator (issue 41, item 3): deterministic per seed, every variation drawn across seeds,
its truth per choice consistent with what it rendered, and the capture's lights off where it says so."""

import json

import numpy as np
import pytest

from torchmetal.synth.random_scenes import (
    SEED_BASE,
    VARIATIONS,
    embossed_normals,
    make_random_case,
    random_scene,
    scene_truth,
    with_size,
)
from torchmetal.synth.zoo import SCENES

SEEDS = range(300)


@pytest.fixture(scope="module")
def drawn():
    return [random_scene(s) for s in SEEDS]


def test_same_seed_same_scene_and_files(tmp_path):
    assert random_scene(5) == random_scene(5) and random_scene(5) != random_scene(6)
    rs = with_size(random_scene(6), 24)  # flakes, float: every random stream used
    a, b = make_random_case(rs, tmp_path / "a"), make_random_case(rs, tmp_path / "b")
    for f in sorted((tmp_path / "a" / "images").iterdir()):
        assert f.read_bytes() == (tmp_path / "b" / "images" / f.name).read_bytes()
    assert (tmp_path / "a" / "capture.json").read_text() == (tmp_path / "b" / "capture.json").read_text()
    assert np.array_equal(a.clean, b.clean)


def test_every_variation_is_drawn(drawn):
    for key, values in VARIATIONS.items():
        seen = {rs.variation(key) for rs in drawn}
        assert set(values) <= seen, (key, set(values) - seen)


def test_seeds_apart_from_the_zoo(drawn):
    zoo = {sc.seed for sc in SCENES.values()}
    assert not zoo & {rs.scene.seed for rs in drawn} and min(rs.scene.seed for rs in drawn) == SEED_BASE


def test_truth_follows_the_scene(drawn):
    for rs in drawn:
        t = scene_truth(rs)
        d = rs.describe()
        if d["given_normals"]:
            assert t["normals"] == t["relief"] == "n/a"
        elif d["surface"] == "flat":
            assert t["normals"] == t["relief"] == "reference"
        else:
            assert t["normals"] == "extension"
            assert t["relief"] == ("extension" if d["surface"] == "embossed" else "n/a")
        assert t["registration"] == "reference"  # no drawn shot is moved
        assert t["clipping"] == ("extension" if d["clip"] == "processed" else "reference")
        assert t["lobe"] == ("reference" if d["lobe"] == "phong" else "extension")
        assert t["flakes"] == ("reference" if d["flakes"] == "none" else "extension")
        if d["lighting"] == "directional" or d["light_error"] == "none":
            assert t["light"] == "reference"
        if d["materials"] > 1:
            assert t["specular clusters"] == "extension"
        assert t["specular colour"] == ("extension" if d["spec_colour"] == "white" else "reference")


def _capture_lights(case) -> np.ndarray:
    meta = json.loads((case.capture_dir / "capture.json").read_text())
    return np.array([s["light"] for s in meta["shots"]])


@pytest.mark.parametrize("error", ["none", "flash", "jitter"])
def test_capture_lights_are_off_as_drawn(tmp_path, drawn, error):
    """capture.json states the rendering lights, the flash at the lens (a common move), or each shot's own error."""
    from torchmetal.synth.random_scenes import _flash_layout
    from torchmetal.synth.zoo_render import _rng

    rs = next(r for r in drawn if r.lighting == "flash" and r.light_error == error)
    rs = with_size(rs, 16)
    told = _capture_lights(make_random_case(rs, tmp_path / "c"))
    true, cams, _, offset = _flash_layout(rs, _rng(rs.scene.seed, 3))
    true = true[: rs.scene.shots]
    if error == "none":
        np.testing.assert_allclose(told, true)
    elif error == "flash":  # every light off by the same move: the flash beside the lens
        np.testing.assert_allclose(told[:, :3] - true[:, :3], np.broadcast_to(-offset, told[:, :3].shape), atol=1e-12)
        np.testing.assert_allclose(told, cams[: rs.scene.shots])
    else:
        d = told[:, :3] - true[:, :3]
        assert np.all(np.abs(d).max(1) > 1e-4) and np.std(d[:, 0]) > 1e-3  # each shot its own error


def test_processed_clip_whitens_the_pixel(tmp_path, drawn):
    """A processed clip raises a clipped pixel's other channels; the honest clip leaves them as they were."""
    from dataclasses import replace

    import cv2

    rs = with_size(next(r for r in drawn if r.clip == "processed" and r.scene.encoding == "linear16"), 32)
    honest = replace(rs, clip="channel")
    a = make_random_case(rs, tmp_path / "p").capture_dir
    b = make_random_case(honest, tmp_path / "h").capture_dir
    raised = 0
    for f in sorted((a / "images").iterdir()):
        p = cv2.imread(str(f), cv2.IMREAD_UNCHANGED).astype(np.int64)
        h = cv2.imread(str(b / "images" / f.name), cv2.IMREAD_UNCHANGED).astype(np.int64)
        clipped = (h == 65535).any(-1) & ~(h == 65535).all(-1)
        assert np.all(p >= h)
        raised += int((p[clipped] > h[clipped]).any(-1).sum())
    assert raised > 0


def test_embossed_surface_is_plateaus_with_edges():
    n = embossed_normals(64, np.random.default_rng(0))
    assert np.allclose((n * n).sum(0), 1.0)
    flat = n[2] > 1 - 1e-9
    assert 0.3 < flat.mean() < 0.97  # plateaus and the plane between them, tilted only at the edges
    assert n[2].min() < 0.97


def test_materials_and_gloss_in_the_truth(tmp_path, drawn):
    rs = with_size(next(r for r in drawn if len(r.materials) == 3 and not r.gloss and r.scene.flakes is None), 32)
    t = make_random_case(rs, tmp_path / "m").truth
    assert len(np.unique(t.alpha[0])) == 3
    metal = with_size(next(r for r in drawn if r.spec_colour != (1.0, 1.0, 1.0) and r.scene.flakes is None), 16)
    ts = make_random_case(metal, tmp_path / "g").truth.s
    assert ts[0].mean() > ts[2].mean()  # a gold-like specular
    gloss = with_size(next(r for r in drawn if r.gloss and len(r.materials) == 1), 32)
    ta = make_random_case(gloss, tmp_path / "s").truth.alpha
    assert ta.max() / ta.min() > 1.5


def test_flakes_under_directional_lights(tmp_path, drawn):
    """Directional lights and flakes together (the zoo has no such scene): their glints render."""
    rs = with_size(next(r for r in drawn if r.lighting == "directional" and r.scene.flakes is not None), 32)
    case = make_random_case(rs, tmp_path / "d")
    assert np.isfinite(case.clean).all() and case.flake_pixels.any()
