"""The scene zoo's generator: deterministic, its own geometry agrees with docs/design.md §2.1/2.2, noise as stated."""

import json

import numpy as np
import pytest
import torch

from torchmetal.fit import fit_phong
from torchmetal.io.capture import load_capture
from torchmetal.synth.zoo import SCENES, Scene, ci_scenes, decode, make_case, oracle_render


def test_same_seed_same_files(tmp_path):
    sc = SCENES["photo_srgb8"].with_(size=48, shots=4, held=1)
    a, b = make_case(sc, tmp_path / "a"), make_case(sc, tmp_path / "b")
    for f in sorted((tmp_path / "a" / "images").iterdir()):
        assert f.read_bytes() == (tmp_path / "b" / "images" / f.name).read_bytes()
    assert np.array_equal(a.clean, b.clean)
    c = make_case(sc.with_(seed=sc.seed + 1), tmp_path / "c")
    assert not np.array_equal(a.clean, c.clean)


@pytest.mark.parametrize("name", ["float_clean", "directional_sharp"])
def test_independent_geometry_agrees_with_the_fit(tmp_path, name):
    """On a noise-free float capture the project's fit recovers the zoo's Phong truth exactly
    (point and directional lights, perspective and orthographic cameras, flat and bumpy normals)."""
    sc = SCENES[name].with_(size=64, encoding="float", noise=0.0, exposure=0.8)
    case = make_case(sc, tmp_path / "c")
    f = fit_phong(load_capture(case.capture_dir), specular="global")
    assert torch.allclose(f.s.double(), torch.full((3,), sc.s, dtype=torch.float64), rtol=2e-3)
    assert torch.allclose(f.alpha.double(), torch.full((3,), sc.alpha, dtype=torch.float64), rtol=2e-3)


def test_encodings_and_clipping(tmp_path):
    for enc, space, suffix in (("srgb8", "srgb", ".png"), ("linear16", "linear", ".png"), ("float", "linear", ".npy")):
        case = make_case(SCENES["bumpy_lin16"].with_(size=48, shots=3, held=1, encoding=enc), tmp_path / enc)
        meta = json.loads((case.capture_dir / "capture.json").read_text())
        assert meta["color_space"] == space and meta["shots"][0]["image"].endswith(suffix)
        assert meta["normals"] == "normals.npy"
    cap = load_capture(tmp_path / "linear16")
    assert 0.0 < float(cap.saturated.float().mean()) < 0.2  # exposure 2.2: some highlights clip, as the scene is exposed to


def test_noise_is_signal_dependent(tmp_path):
    sc = Scene("n", size=96, shots=2, held=1, encoding="float", noise=0.02, s=0.0)
    case = make_case(sc, tmp_path / "c")
    clean = make_case(sc.with_(noise=0.0), tmp_path / "d")
    y, _ = decode(np.load(case.capture_dir / "images/000.npy"), "float")
    x, _ = decode(np.load(clean.capture_dir / "images/000.npy"), "float")
    r = (y - x).ravel()
    bright, dark = x.ravel() > np.quantile(x, 0.8), x.ravel() < np.quantile(x, 0.2)
    ratio = r[bright].std() / r[dark].std()
    expect = np.mean(np.sqrt(x.ravel()[bright]) + 0.1) / np.mean(np.sqrt(x.ravel()[dark]) + 0.1)
    assert ratio == pytest.approx(expect, rel=0.1) and ratio > 1.3


def test_flakes_follow_their_spec(tmp_path):
    sc = SCENES["flakes_b"].with_(size=160)
    case = make_case(sc, tmp_path / "c")
    assert case.truth_stats["density"] == pytest.approx(sc.flakes["density"], rel=0.15)
    assert case.truth_stats["median_area"] == pytest.approx(sc.flakes["area_median"], rel=0.15)
    assert 0.0 < case.flake_pixels.mean() < 0.2


def test_oracle_is_exact_without_noise(tmp_path):
    case = make_case(SCENES["two_materials"].with_(size=48, encoding="float", noise=0.0), tmp_path / "c")
    assert np.allclose(oracle_render(case), case.clean, atol=1e-5)


def test_ci_scenes_are_the_zoo_smaller():
    ci = ci_scenes()
    assert [s.name for s in ci] == list(SCENES) and all(s.size <= SCENES[s.name].size for s in ci)
    with pytest.raises(ValueError, match="layout"):
        Scene("bad", layout="nowhere")


def test_full_ggx_truth_is_the_renderers_lobe():
    """The zoo's ggx_full lobe (numpy, written apart from the fit) equals torchmetal.lobes.ggx_lobe, Fresnel
    and shadowing included, on random normals, lights and views; the plain ggx lobe is its distribution alone."""
    from torchmetal.lobes import ggx_lobe
    from torchmetal.synth.zoo_shading import lobe_value

    rng = np.random.default_rng(0)

    def unit(x):
        return x / np.linalg.norm(x, axis=0, keepdims=True)

    n = unit(np.concatenate([0.3 * rng.normal(size=(2, 8, 8)), np.ones((1, 8, 8))]))
    l, v = (unit(np.concatenate([rng.normal(size=(2, 8, 8)), 1 + rng.random((1, 8, 8))])) for _ in range(2))
    s, alpha = np.full(3, 0.3), np.array([150.0, 40.0, 7.0])
    h = unit(l + v)
    t = lambda x: torch.from_numpy(x.sum(0))[None, None]  # noqa: E731
    want = 0.3 * ggx_lobe(1.0 - t(n * h), t(n * l), t(n * v), t(v * h), torch.from_numpy(alpha))[0].numpy()
    want = np.where((n * l).sum(0)[None] > 0, want, 0.0)
    np.testing.assert_allclose(lobe_value("ggx_full", n, l, v, s, alpha), want, rtol=1e-12, atol=1e-15)
    assert not np.allclose(lobe_value("ggx", n, l, v, s, alpha), want)
