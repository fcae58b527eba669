"""torchmetal intervals: leave-out intervals of a fitted material's flake statistics and estimated normals, written
into its report (material.json's fit.uncertainty.leave_out), the verb's line, one-line errors."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import torchmetal.plan.intervals as intervals
from torchmetal.cli import main
from torchmetal.config import FitConfig
from torchmetal.errors import InputError
from torchmetal.flakes.model import FlakeModel
from torchmetal.material import load_material, save_material
from torchmetal.pipeline import fit_material
from torchmetal.plan.intervals import NORMALS_FILE, leave_out_intervals, refit_options
from torchmetal.synth import synth_capture, write_synth

SHOTS = 5


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A tiny bumpy capture on disk and its material, normals estimated, no flakes."""
    root = tmp_path_factory.mktemp("intervals")
    write_synth(synth_capture(size=12, shots=SHOTS, seed=3, layout="hemisphere", bumpy=True, noise=0.01,
                              texture="procedural"), root / "cap")
    from torchmetal.io.capture import load_capture

    result = fit_material(load_capture(root / "cap"), normals="estimate", flakes="off")
    save_material(result.material, root / "mat")
    return root


@pytest.fixture()
def with_flakes(fitted, tmp_path):
    """The fitted material with a flake model put in: a copy in tmp_path."""
    m = load_material(fitted / "mat")
    m.flakes = FlakeModel(density=0.004, tilt_sigma=0.1, seed=5)
    save_material(m, tmp_path / "mat")
    return tmp_path / "mat"


def fake_refit(capture_root):
    """capture → a stand-in for the refit's Material: its flake density moved by which shot was left out, no model
    when shot 4 was (a failed refit), the normals the full material's."""
    from torchmetal.io.capture import load_capture

    full = load_capture(capture_root)

    def refit(c):
        kept = {tuple(x) for x in c.cameras.tolist()}
        i = next(k for k, x in enumerate(full.cameras.tolist()) if tuple(x) not in kept)
        flakes = None if i == 4 else FlakeModel(density=0.004 * math.exp(0.1 * (i - 1.5)), tilt_sigma=0.1 + 0.01 * i)
        return SimpleNamespace(flakes=flakes, flat_normals=lambda: torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 12, 12))

    return refit


def test_flake_intervals_contain_the_material_and_reach_its_report(fitted, with_flakes):
    before = (with_flakes / "material.json").read_text()
    entry = leave_out_intervals(with_flakes, fitted / "cap", refit=fake_refit(fitted / "cap"))
    fl = entry["flakes"]
    assert entry["refits"] == SHOTS and entry["level"] == 0.9 and fl["failed_refits"] == 1
    for name in ("density", "tilt_sigma", "glint_sigma", "area_log_mean", "aspect_mean", "color_r"):
        s = fl[name]
        assert s["low"] <= s["value"] <= s["high"], (name, s)
    d = fl["density"]
    assert d["value"] == pytest.approx(0.004) and d["low"] < 0.004 < d["high"]  # the refits spread: a real width
    assert len(d["refits"]) == SHOTS - 1
    assert fl["aspect_mean"]["low"] == pytest.approx(fl["aspect_mean"]["high"])  # every refit the same aspect
    # the report: the entry under fit.uncertainty.leave_out, everything else exactly as the fit wrote it
    doc = json.loads((with_flakes / "material.json").read_text())
    written = doc["fit"]["uncertainty"].pop("leave_out")
    assert written["flakes"]["density"]["high"] == pytest.approx(d["high"])
    assert written["normals"]["file"] == NORMALS_FILE and (with_flakes / NORMALS_FILE).is_file()  # estimated: both
    assert json.dumps(doc, indent=2, allow_nan=False) == before
    assert load_material(with_flakes).flakes.density == pytest.approx(0.004)  # still a material


def test_normals_intervals_by_real_refits_and_the_line(fitted, tmp_path, capsys):
    import shutil

    mat = tmp_path / "mat"
    shutil.copytree(fitted / "mat", mat)
    assert main(["intervals", str(mat), str(fitted / "cap"), "-q"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert re.fullmatch(r"normals 90 % radius median [\d.e-]+ deg, p90 [\d.e-]+ deg \(5 leave-one-out refits; per "
                        rf"pixel: {NORMALS_FILE}\)", out[0]), out
    assert out[1].startswith(f"-> {mat}/material.json (uncertainty.leave_out) in ")
    entry = json.loads((mat / "material.json").read_text())["fit"]["uncertainty"]["leave_out"]
    nr = entry["normals"]
    assert 0 < nr["median_radius_deg"] <= nr["p90_radius_deg"] < 180  # 4-shot refits of 12²: a wide tail
    assert entry["options"]["normals"] == "estimate" and entry["options"]["flakes"] == "off"
    radius = np.load(mat / NORMALS_FILE)
    assert radius.shape == (12, 12) and radius.dtype == np.float32 and bool(np.isfinite(radius).all())
    assert float(np.quantile(radius, 0.5, method="lower")) == pytest.approx(nr["median_radius_deg"], rel=1e-5)  # torch: lower


def test_the_flake_line(fitted, with_flakes, monkeypatch, capsys):
    monkeypatch.setattr(intervals, "default_refit", lambda options: fake_refit(fitted / "cap"))
    assert main(["intervals", str(with_flakes), str(fitted / "cap"), "-q"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    m = re.fullmatch(r"flake density ([\d.e-]+) \[([\d.e-]+), ([\d.e-]+)\] \(90 %, 5 leave-one-out refits, 1 without "
                     r"flakes\)", line)
    assert m, line
    value, lo, hi = map(float, m.groups())
    assert lo < value < hi and value == pytest.approx(0.004)


def _named(material_dir):
    """The normals file material.json's leave-out entry names (None: none)."""
    entry = json.loads((material_dir / "material.json").read_text())["fit"]["uncertainty"].get("leave_out") or {}
    return (entry.get("normals") or {}).get("file")


def test_the_normals_map_survives_a_reload_and_resave_and_the_report_names_only_what_is_there(fitted, with_flakes,
                                                                                             tmp_path):
    # estimated normals: the map is written and named; a reload and re-save (in place or elsewhere) keeps both
    leave_out_intervals(with_flakes, fitted / "cap", refit=fake_refit(fitted / "cap"))
    radius = np.load(with_flakes / NORMALS_FILE)
    m = load_material(with_flakes)
    for target in (with_flakes, tmp_path / "copy"):
        save_material(m, target)
        assert _named(target) == NORMALS_FILE and (target / NORMALS_FILE).is_file(), target
        assert np.array_equal(np.load(target / NORMALS_FILE), radius)
    assert np.array_equal(m.normals_interval.numpy(), radius)  # carried by the Material
    # a directory that lost the map (a re-save before this fix): it loads, and its next save stops naming it
    (tmp_path / "copy" / NORMALS_FILE).unlink()
    lost = load_material(tmp_path / "copy")
    assert lost.normals_interval is None
    save_material(lost, tmp_path / "copy")
    assert _named(tmp_path / "copy") is None and not (tmp_path / "copy" / NORMALS_FILE).exists()
    assert "median_radius_deg" in load_material(tmp_path / "copy").report["uncertainty"]["leave_out"]["normals"]  # the rest kept
    # flat normals: no map and no name, and an earlier run's map does not stay behind unnamed
    flat = load_material(with_flakes)
    flat.normals, flat.report["normals"]["chosen"] = None, "flat"
    save_material(flat, tmp_path / "flat")
    assert _named(tmp_path / "flat") == NORMALS_FILE  # still the estimated run's report and map
    entry = leave_out_intervals(tmp_path / "flat", fitted / "cap", refit=fake_refit(fitted / "cap"))
    assert "normals" not in entry and _named(tmp_path / "flat") is None
    assert not (tmp_path / "flat" / NORMALS_FILE).exists()
    assert load_material(tmp_path / "flat").normals_interval is None


def test_refit_options_fix_the_fits_choices(fitted):
    m = load_material(fitted / "mat")
    opts = refit_options(m.report, m)
    assert opts["normals"] == "estimate" and opts["lobe"] == m.lobe and opts["observed_flakes"] == "off"
    assert opts["flakes"] == "off" and "seed" not in opts
    assert opts["registration"] == m.report["registered"]["chosen"] and opts["light"] == m.report["light"]["chosen"]
    FitConfig.of(None, **opts)
    m.flakes = FlakeModel(density=0.004, seed=9)
    assert refit_options(m.report, m)["flakes"] == "on" and refit_options(m.report, m)["seed"] == 9


def test_errors_are_one_line(fitted, tmp_path, capsys):
    write_synth(synth_capture(size=16, shots=SHOTS, seed=4, layout="hemisphere"), tmp_path / "other")
    assert main(["intervals", str(fitted / "mat"), str(tmp_path / "other")]) == 2
    err = capsys.readouterr().err
    assert err == ("torchmetal intervals: error: intervals: the capture is 16x16 pixels and the material 12x12: not the "
                   "capture it was fitted to\n")
    assert main(["intervals", str(tmp_path / "other"), str(fitted / "cap")]) == 2
    assert "expected a material directory (material.json)" in capsys.readouterr().err
    # a flat, flake-free material: nothing the curvature intervals do not cover already
    m = load_material(fitted / "mat")
    m.normals, m.report["normals"]["chosen"] = None, "flat"
    save_material(m, tmp_path / "flat")
    with pytest.raises(InputError, match="no flake model and no estimated normals"):
        leave_out_intervals(tmp_path / "flat", fitted / "cap")
    write_synth(synth_capture(size=12, shots=3, seed=3, layout="hemisphere"), tmp_path / "three")
    with pytest.raises(InputError, match="at least 4 shots"):
        leave_out_intervals(fitted / "mat", tmp_path / "three")


def test_help_loads_nothing_heavy():
    code = ("import sys, torchmetal.cli as cli\ntry:\n    cli.main(['intervals', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('torch', 'matplotlib', 'scipy') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "usage: torchmetal intervals" in proc.stdout and proc.stdout.strip().splitlines()[-1] == "[]"
