"""Tiled vs in-memory fit of the same capture: s, α and texture equal to 1e-6 relative."""

import json

import numpy as np
import pytest
import torch

from torchmetal.cli import main
from torchmetal.errors import InputError
from torchmetal.fit import fit_phong
from torchmetal.fit.result import skip_stages
from torchmetal.io.capture import load_capture
from torchmetal.scale.tiled import fit_tiled
from torchmetal.scale.tiles import convert_capture

REL = 1e-6


def rel_err(x, y):
    x, y = x.double(), y.double()
    return float(((x - y).abs() / y.abs().clamp_min(1e-12)).max())


@pytest.fixture(scope="module")
def tiled256(tmp_path_factory):
    from torchmetal.synth import synth_capture, write_synth

    root = tmp_path_factory.mktemp("t256")
    write_synth(synth_capture(size=256, shots=8, seed=5, noise=0.003, bumpy=True, bits=16), root / "png")
    return convert_capture(root / "png", root / "tiled")


@pytest.fixture(scope="module")
def tiled128(tmp_path_factory):
    from torchmetal.synth import synth_capture, write_synth

    root = tmp_path_factory.mktemp("t128")
    write_synth(synth_capture(size=128, shots=8, seed=6, noise=0.003, bits=16), root / "png")
    return convert_capture(root / "png", root / "tiled")


def assert_same_fit(a, b):
    assert rel_err(b.s, a.s) <= REL and rel_err(b.alpha, a.alpha) <= REL, (a.s, b.s, a.alpha, b.alpha)
    # the texture in float32, its sums in tile order: equal to 1e-6 of its range (a texel of 0.05 may differ by one
    # float32 step of 1.0, 2e-6 of itself)
    assert float((b.texture.double() - a.texture.double()).abs().max()) <= REL * float(a.texture.abs().max())
    assert b.specular == a.specular and b.skipped == a.skipped and b.flat == a.flat


def test_tiled_equals_in_memory_256(tiled256, tmp_path):
    """256² × 8 shots, bumpy normals, texels saturated in every shot (inpainted), 64² tiles; a subsample of
    512 pixels, so that the LM over the tiles has a step to take (from a subsample of 4096 the fit is already at
    the whole image's optimum and the tile LM stops at its first evaluation)."""
    a = fit_phong(load_capture(tiled256), sub_pixels=512)
    b = fit_tiled(tiled256, tile=64, scratch=tmp_path, sub_pixels=512)
    assert b.tiled["tiles"] == 16 and b.tiled["passes"] >= 3
    assert_same_fit(a, b)
    assert "texture" in b.skips and not b.flat  # the texels saturated in every shot: inpainted, and reported
    assert torch.equal(b.normals, load_capture(tiled256).normals)


def test_tiled_strided_subsample_and_clusters(tiled128, tmp_path):
    """128² × 8: subsample decisions on a strided grid read from the files, clustered specular per
    tile, and a tile size that does not divide the image."""
    kw = dict(sub_pixels=2048, select_pixels=512, specular="clustered", max_iters=20)
    a = fit_phong(load_capture(tiled128), **kw)
    b = fit_tiled(tiled128, tile=50, scratch=tmp_path, **kw)
    assert a.specular == "clustered"
    assert_same_fit(a, b)
    assert torch.equal(b.spec_labels, a.spec_labels)
    assert rel_err(b.cluster_alpha, a.cluster_alpha) <= REL


def test_cli_fit_tile_equals_fit(tmp_path, capsys):
    from torchmetal.synth import synth_capture, write_synth

    write_synth(synth_capture(size=48, shots=6, seed=1, noise=0.003, bits=16), tmp_path / "cap")  # PNG: converted first
    assert main(["fit", str(tmp_path / "cap"), "-o", str(tmp_path / "tiled"), "--tile", "20", "-q"]) == 0
    assert main(["fit", str(tmp_path / "cap"), "-o", str(tmp_path / "mem"), "--flakes", "off", "-q"]) == 0
    a, b = np.load(tmp_path / "mem" / "texture.npy"), np.load(tmp_path / "tiled" / "texture.npy")
    assert np.abs(b - a).max() <= REL * np.abs(a).max()
    ja, jb = (json.loads((tmp_path / m / "material.json").read_text()) for m in ("mem", "tiled"))
    assert np.allclose(jb["phong"]["alpha"], ja["phong"]["alpha"], rtol=REL, atol=0)
    assert jb["fit"]["tiled"] == {"tile": 20, "tiles": 9, "passes": jb["fit"]["tiled"]["passes"]}
    assert jb["fit"]["flakes"] is None and "flakes" in skip_stages(jb["fit"]["skipped"])  # not run by the tiled fit
    assert main(["fit", str(tmp_path / "cap"), "-o", str(tmp_path / "pool"), "--tile", "20", "--tile-workers", "2",
                 "-q"]) == 0  # tile tasks on a process pool: the same material
    assert np.array_equal(np.load(tmp_path / "pool" / "texture.npy"), b)
    assert json.loads((tmp_path / "pool" / "material.json").read_text())["phong"] == jb["phong"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # scratch files removed
    assert main(["fit", str(tmp_path / "cap"), "-o", str(tmp_path / "x"), "--tile", "20", "--scheme", "paper"]) == 2
    assert main(["fit", str(tmp_path / "cap"), "-o", str(tmp_path / "x"), "--tile", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--scheme paper: expected one of ['refine'] with --tile" in err[0] and "tile: expected an int >= 1" in err[1]


def test_bad_arguments(tiled256):
    with pytest.raises(InputError, match="specular"):
        fit_tiled(tiled256, specular="shiny")


def test_tiles_on_a_process_pool_are_bit_identical(tiled128, tmp_path):
    """The same tile tasks on 2 pool workers (results reduced in tile order) = in this process."""
    kw = dict(tile=48, sub_pixels=2048, select_pixels=512, max_iters=20)
    here = fit_tiled(tiled128, scratch=tmp_path / "here", **kw)
    pool = fit_tiled(tiled128, scratch=tmp_path / "pool", engine="local", workers=2, threads=1, **kw)
    assert pool.tiled["engine"] == "local" and pool.tiled["passes"] == here.tiled["passes"]
    assert torch.equal(pool.s, here.s) and torch.equal(pool.alpha, here.alpha)
    assert torch.equal(pool.texture, here.texture)


def test_gloss_maps_that_win_are_refused_in_one_line(tmp_path, monkeypatch):
    """The tiled fit runs fit_phong's own subsample decisions; when they pick gloss maps it stops."""
    import dataclasses

    import torchmetal.scale.tiled as tiled
    from torchmetal.errors import FitError
    from torchmetal.synth import synth_capture, write_synth

    write_synth(synth_capture(size=32, shots=6, seed=7, noise=0.003), tmp_path / "png")
    cap = convert_capture(tmp_path / "png", tmp_path / "tiled")
    real = tiled.subsample_decisions
    calls = []

    def maps_win(*args, **kw):
        calls.append(kw)
        return dataclasses.replace(real(*args, **kw), use_maps=True)

    monkeypatch.setattr(tiled, "subsample_decisions", maps_win)
    with pytest.raises(FitError, match="gloss maps win") as err:
        fit_tiled(cap, tile=16, scratch=tmp_path / "scratch")
    assert "\n" not in str(err.value)
    assert len(calls) == 1 and calls[0]["robust"] is None and calls[0]["outliers"] is None  # least squares


def test_tiled_relabels_pixels_as_in_memory(tmp_path):
    """Two specular materials whose subsample clusters miss pixels at their edge: the tiled fit moves
    the same pixels (fit.clusters.relabel, one pass over the tiles per round) and ends at the same fit."""
    from torchmetal.synth import synth_capture, write_synth

    write_synth(synth_capture(size=96, shots=10, seed=3, noise=0.005, spec_clusters=2, bits=16), tmp_path / "png")
    tiled = convert_capture(tmp_path / "png", tmp_path / "tiled")
    kw = dict(specular="clustered", max_iters=30)
    a = fit_phong(load_capture(tiled), **kw)
    b = fit_tiled(tiled, tile=40, scratch=tmp_path / "scratch", **kw)
    moved = [h["pixels"] for h in a.history if h["stage"] == "relabel"]
    assert moved and moved[0] > 0, a.history[-3:]
    assert [h["pixels"] for h in b.history if h["stage"] == "relabel"] == moved
    assert torch.equal(b.spec_labels, a.spec_labels)
    assert_same_fit(a, b)
