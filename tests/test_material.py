"""Material directory: round trip, atomic writes, one-line errors."""

import json
import math

import numpy as np
import pytest
import torch

from torchmetal.errors import MaterialError
from torchmetal.flakes.model import FlakeModel
from torchmetal.material import Material, load_material, save_material


def make_material(clustered=False, flakes=True, normals=False):
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(3, 6, 5, generator=g)
    kw = {}
    if clustered:
        kw = dict(spec_labels=torch.randint(0, 2, (6, 5), generator=g), cluster_s=torch.rand(2, 3, generator=g),
                  cluster_alpha=torch.rand(2, 3, generator=g) * 100 + 1)
    n = None
    if normals:
        n = torch.nn.functional.normalize(torch.rand(3, 6, 5, generator=g) + torch.tensor([0, 0, 2.0]).view(3, 1, 1), dim=0)
    return Material(tex, torch.tensor([0.1, 0.2, 0.3]), torch.tensor([10.0, 20.0, 30.0]), (0.1, 0.2), normals=n,
                    flakes=FlakeModel(0.01, seed=3) if flakes else None, report={"status": "converged"}, **kw)


@pytest.mark.parametrize("clustered", [False, True])
@pytest.mark.parametrize("normals", [False, True])
def test_round_trip_exact(tmp_path, clustered, normals):
    m = make_material(clustered=clustered, normals=normals)
    save_material(m, tmp_path / "mat")
    m2 = load_material(tmp_path / "mat")
    assert torch.equal(m2.texture, m.texture)
    assert torch.equal(m2.s, m.s) and torch.equal(m2.alpha, m.alpha)
    assert m2.size == m.size and m2.flakes == m.flakes and m2.report == m.report
    if clustered:
        assert torch.equal(m2.spec_labels, m.spec_labels)
        s_map, a_map = m2.specular_maps()
        assert s_map.shape == (3, 6, 5) and torch.equal(s_map[:, 0, 0], m.cluster_s[m.spec_labels[0, 0]])
    if normals:
        assert torch.equal(m2.normals, m.normals)
    texture = np.load(tmp_path / "mat" / "texture.npy")  # numpy alone reads the texture
    assert texture.shape == (6, 5, 3)


def test_flakes_null_in_json(tmp_path):
    save_material(make_material(flakes=False), tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "material.json").read_text())
    assert meta["format"] == "torchmetal-material" and meta["version"] == 1 and meta["flakes"] is None


def test_interrupted_save_keeps_old_material(tmp_path, monkeypatch):
    path = tmp_path / "m"
    save_material(make_material(), path)
    before = (path / "material.json").read_text()

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr("torchmetal.material.material_to_json", boom)
    with pytest.raises(KeyboardInterrupt):
        save_material(make_material(flakes=False), path)
    assert (path / "material.json").read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no temp leftovers


@pytest.mark.parametrize(
    "mutate, expected",
    [
        (lambda d, p: (p / "material.json").write_text("{bad json"), "line 1"),
        (lambda d, p: (p / "material.json").write_text(json.dumps({**d, "format": "x"})), "expected format"),
        (lambda d, p: (p / "material.json").write_text(json.dumps({**d, "version": 9})), "expected version 1"),
        (lambda d, p: (p / "texture.npy").unlink(), "texture"),
        (lambda d, p: (p / "material.json").unlink(), "material.json"),
        (lambda d, p: (p / "material.json").write_text(json.dumps({k: v for k, v in d.items() if k != "phong"})), "'phong'"),
    ],
)
def test_bad_material_dir(tmp_path, mutate, expected):
    path = tmp_path / "m"
    save_material(make_material(), path)
    mutate(json.loads((path / "material.json").read_text()), path)
    with pytest.raises(MaterialError) as e:
        load_material(path)
    assert expected in str(e.value) and "\n" not in str(e.value)


def test_bad_material_values():
    with pytest.raises(MaterialError, match=r"expected shape \(3, H, W\)"):
        Material(torch.rand(4, 2, 2), torch.zeros(3), torch.ones(3), (1.0, 1.0))
    with pytest.raises(MaterialError, match="size"):
        Material(torch.rand(3, 2, 2), torch.zeros(3), torch.ones(3), (0.0, 1.0))
    with pytest.raises(MaterialError, match="together"):
        Material(torch.rand(3, 2, 2), torch.zeros(3), torch.ones(3), (1.0, 1.0), spec_labels=torch.zeros(2, 2))
    with pytest.raises(MaterialError, match="density"):
        FlakeModel(density=float("nan"))


def test_report_with_non_finite_numbers_saves_as_strings(tmp_path):
    """A decision's held-out PSNR is inf for a perfect prediction: material.json stays strict JSON."""
    m = Material(torch.full((3, 4, 4), 0.5), torch.tensor([0.1, 0.1, 0.1]), torch.tensor([10.0, 10.0, 10.0]), (1.0, 1.0))
    m.report = {"decisions": [{"psnr_heldout": {"uniform": math.inf}, "z": {"noise": float("nan")}}], "t": (1.0, -math.inf)}
    save_material(m, tmp_path / "m")
    fit = json.loads((tmp_path / "m" / "material.json").read_text())["fit"]
    assert fit == {"decisions": [{"psnr_heldout": {"uniform": "inf"}, "z": {"noise": "nan"}}], "t": [1.0, "-inf"]}
    m.flakes = FlakeModel(density=0.01, extra={"std_err": {"log_glint_sigma": math.nan}})  # not computed: NaN
    save_material(m, tmp_path / "f")
    assert load_material(tmp_path / "f").flakes.extra == {"std_err": {"log_glint_sigma": "nan"}}


def _disagreement_named(material_dir):
    """The file material.json's disagreement entry names (None: none)."""
    return (json.loads((material_dir / "material.json").read_text())["fit"].get("disagreement") or {}).get("file")


def test_the_disagreement_map_survives_a_reload_and_resave_and_the_report_names_only_what_is_there(tmp_path):
    # as torchmetal fit writes it: the report names disagreement.png and the file comes in as an extra file
    from torchmetal.report.disagreement import disagreement_png

    png = disagreement_png(tmp_path / "d.png", torch.zeros(6, 5, dtype=torch.bool), torch.full((3, 6, 5), 0.2))
    m = make_material()
    m.report["disagreement"] = {"share": 0.01, "file": "disagreement.png"}
    save_material(m, tmp_path / "fit", extra_files={"disagreement.png": png})
    data = (tmp_path / "fit" / "disagreement.png").read_bytes()
    loaded = load_material(tmp_path / "fit")
    for target in (tmp_path / "fit", tmp_path / "copy"):  # a re-save in place or elsewhere keeps the file and the name
        save_material(loaded, target)
        assert _disagreement_named(target) == "disagreement.png", target
        assert (target / "disagreement.png").is_file() and (target / "disagreement.png").read_bytes() == data, target
    assert loaded.disagreement_png == data  # carried by the Material
    # a directory that lost the map (a re-save before this fix): it loads, and its next save stops naming it
    (tmp_path / "copy" / "disagreement.png").unlink()
    lost = load_material(tmp_path / "copy")
    assert lost.disagreement_png is None
    save_material(lost, tmp_path / "copy")
    assert _disagreement_named(tmp_path / "copy") is None and not (tmp_path / "copy" / "disagreement.png").exists()
    assert load_material(tmp_path / "copy").report["disagreement"] == {"share": 0.01}  # the rest of the entry kept
    assert lost.report["disagreement"]["file"] == "disagreement.png"  # the caller's report is not changed
    with pytest.raises(MaterialError, match="disagreement_png: expected the bytes of a PNG file"):
        Material(m.texture, m.s, m.alpha, m.size, disagreement_png=b"GIF89a")
