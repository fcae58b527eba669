"""The command line end to end, and its one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from torchmetal.cli import main


def run_cli(*args, cwd=None):
    """Run ``python -m torchmetal ARGS`` in a subprocess; returns the CompletedProcess."""
    return subprocess.run([sys.executable, "-m", "torchmetal", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600)


def assert_one_line_error(proc, expected):
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert expected in lines[0]


@pytest.mark.parametrize("verb", ["demo", "fit", "render", "export", "synth", "bench"])
def test_help_everywhere(verb):
    proc = run_cli(verb, "--help")
    assert proc.returncode == 0
    assert "usage" in proc.stdout.lower()


def test_synth_fit_render_export(tmp_path):
    cap, mat = tmp_path / "cap", tmp_path / "mat"
    assert main(["synth", "-o", str(cap), "--size", "48", "--shots", "6", "--flakes", "--noise", "0.005"]) == 0
    assert (cap / "capture.json").is_file() and (cap / "truth" / "truth.json").is_file()
    assert main(["fit", str(cap), "-o", str(mat), "-q"]) == 0
    meta = json.loads((mat / "material.json").read_text())
    assert meta["format"] == "torchmetal-material" and "stage_times" in meta["fit"]
    assert all(np.isfinite(meta["phong"]["alpha"]))
    # the report's registration and disagreement map (a synthetic capture: registered, the model its truth)
    reg, dis = meta["fit"]["registration"], meta["fit"]["disagreement"]
    assert len(reg["shifts"]) == 6 and reg["max"] < 1.0, reg  # 48² px with highlights: within a pixel
    assert dis["file"] == "disagreement.png" and 0.0 <= dis["share"] < 0.02, dis
    assert (mat / "disagreement.png").read_bytes()[:4] == b"\x89PNG"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "mat"]  # no temporary file left beside it
    assert main(["render", str(mat), "--light", "0 0.05 0.3 1", "--camera", "0 0 0.3 1", "-o", str(tmp_path / "r.npy")]) == 0
    img = np.load(tmp_path / "r.npy")
    assert img.shape == (48, 48, 3) and np.isfinite(img).all() and img.max() > 0
    assert main(["render", str(mat), "--light", "0 0.05 0.3 1", "--camera", "0 0 0.3 1", "-o", str(tmp_path / "r.png")]) == 0
    assert (tmp_path / "r.png").stat().st_size > 0
    assert main(["export", str(mat)]) == 0
    assert (mat / "renderer.onnx").is_file()


@pytest.mark.parametrize(
    "args, expected",
    [
        (["fit", "{missing}", "-o", "{tmp}/m"], "capture.json"),
        (["render", "{missing}", "--light", "0 0 1 0", "--camera", "0 0 1 0", "-o", "{tmp}/x.png"], "material.json"),
        (["render", "{mat}", "--light", "0 0 -1 1", "--camera", "0 0 1 0", "-o", "{tmp}/x.png"], "light"),
        (["render", "{mat}", "--light", "0 0 1 0.5", "--camera", "0 0 1 0", "-o", "{tmp}/x.png"], "w"),
        (["export", "{missing}"], "material.json"),
    ],
)
def test_bad_input_one_line(tmp_path, args, expected):
    import torch

    from torchmetal.material import Material, save_material

    save_material(Material(torch.rand(3, 4, 4), torch.zeros(3), torch.ones(3), (1.0, 1.0)), tmp_path / "mat")
    fmt = {"missing": tmp_path / "nope", "tmp": tmp_path, "mat": tmp_path / "mat"}
    proc = run_cli(*[a.format(**fmt) for a in args])
    assert_one_line_error(proc, expected)


def test_bad_vector_argument_is_usage_error():
    proc = run_cli("render", "m", "--light", "0 0 1", "--camera", "0 0 1 0", "-o", "x.png")
    assert proc.returncode == 2 and "expected 4 numbers" in proc.stderr and "Traceback" not in proc.stderr


def test_malformed_capture_json(tmp_path):
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "capture.json").write_text("{\"format\": ")
    assert_one_line_error(run_cli("fit", tmp_path / "cap", "-o", tmp_path / "m"), "JSON")


def test_fit_summary_says_when_density_is_at_capacity():
    from torchmetal.cli import _density_text
    from torchmetal.flakes.model import MAX_DENSITY, FlakeModel

    assert _density_text(FlakeModel(density=0.01)) == "density 0.01/px"
    capped = FlakeModel(density=MAX_DENSITY, extra={"density_fitted": 0.17})
    assert _density_text(capped) == "density 0.111/px (fitted 0.17, drawn at the field's capacity)"


def test_observed_flakes_option_defaults_to_auto_and_bare_flag_is_on():
    from torchmetal.cli import build_parser

    p = build_parser()
    assert p.parse_args(["fit", "C", "-o", "M"]).observed_flakes == "auto"
    assert p.parse_args(["fit", "C", "-o", "M", "--observed-flakes"]).observed_flakes == "on"
    assert p.parse_args(["fit", "C", "-o", "M", "--observed-flakes", "off"]).observed_flakes == "off"


def test_console_entry_exits_fast_with_complete_outputs(tmp_path):
    """``python -m torchmetal`` (and the ``torchmetal`` script) end with ``os._exit``: the exit code,
    the flushed summary line and a complete material with its ONNX file must survive it, and no
    temporary file may be left beside the output."""
    from torchmetal.material import load_material

    cap, mat = tmp_path / "cap", tmp_path / "out" / "mat"
    assert main(["synth", "-o", str(cap), "--size", "24", "--shots", "4"]) == 0
    proc = run_cli("fit", cap, "-o", mat, "-q", "--export")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("fitted 4 shots 24x24") and proc.stdout.endswith("\n")
    assert load_material(mat).texture.shape == (3, 24, 24) and (mat / "renderer.onnx").stat().st_size > 0
    assert sorted(p.name for p in mat.parent.iterdir()) == ["mat"]
    tiled = run_cli("fit", cap, "-o", tmp_path / "out" / "bad", "--tile", "8", "--normals", "estimate")
    assert_one_line_error(tiled, "--normals estimate")
    assert sorted(p.name for p in mat.parent.iterdir()) == ["mat"]


def test_fit_light_option(tmp_path):
    cap, mat = tmp_path / "cap", tmp_path / "mat"
    assert main(["synth", "-o", str(cap), "--size", "32", "--shots", "5"]) == 0
    assert main(["fit", str(cap), "-o", str(mat), "-q", "--flakes", "off"]) == 0  # --light auto: the default
    light = json.loads((mat / "material.json").read_text())["fit"]["light"]
    assert light["mode"] == "auto" and light["chosen"] == "off" and light["decision"]["name"] == "light"
    assert light["falloff"] == 0.0 and light["offsets"] is None and light["flash"] is None  # the synth's exact lights
    near = tmp_path / "near"
    assert main(["synth", "-o", str(near), "--size", "32", "--shots", "5", "--layout", "near"]) == 0
    proc = run_cli("fit", near, "-o", tmp_path / "pos", "-q", "--flakes", "off", "--light", "positions")
    assert proc.returncode == 0 and "5 lights moved to their photos (--light positions)" in proc.stdout, proc.stdout
    light = json.loads((tmp_path / "pos" / "material.json").read_text())["fit"]["light"]
    assert light["mode"] == "positions" and len(light["offsets"]) == 5 and all(len(o) == 3 for o in light["offsets"])
    assert_one_line_error(run_cli("fit", cap, "-o", tmp_path / "m2", "--light", "falloff", "--tile", "16"), "--light")
    assert_one_line_error(run_cli("fit", cap, "-o", tmp_path / "m4", "--light", "positions", "--tile", "16"), "--light")
    proc = run_cli("fit", cap, "-o", tmp_path / "m3", "--light", "lamp")
    assert proc.returncode == 2 and "--light" in proc.stderr and "Traceback" not in proc.stderr


def test_fit_weights_option(tmp_path):
    """--weights auto (the default) records its held-out choice; noise with --tile is a one-line refusal."""
    cap, mat = tmp_path / "cap", tmp_path / "mat"
    assert main(["synth", "-o", str(cap), "--size", "32", "--shots", "5"]) == 0
    assert main(["fit", str(cap), "-o", str(mat), "-q", "--flakes", "off"]) == 0
    names = [d["name"] for d in json.loads((mat / "material.json").read_text())["fit"]["decisions"]]
    assert "weights" in names
    assert main(["fit", str(cap), "-o", str(tmp_path / "u"), "-q", "--flakes", "off", "--weights", "uniform"]) == 0
    assert "weights" not in [d["name"] for d in json.loads((tmp_path / "u" / "material.json").read_text())["fit"]["decisions"]]
    assert_one_line_error(run_cli("fit", cap, "-o", tmp_path / "m2", "--weights", "noise", "--tile", "16"), "--weights")


def test_fit_clipping_option(tmp_path):
    """--clipping auto (the default) records how the clipped channels were read; pixel with --tile is refused."""
    cap, mat = tmp_path / "cap", tmp_path / "mat"
    assert main(["synth", "-o", str(cap), "--size", "32", "--shots", "5"]) == 0
    assert main(["fit", str(cap), "-o", str(mat), "-q", "--flakes", "off"]) == 0
    fit = json.loads((mat / "material.json").read_text())["fit"]
    assert fit["clipping"]["mode"] == "auto" and fit["clipping"]["chosen"] in ("channel", "pixel")
    assert [d["name"] for d in fit["decisions"][:2]] == ["registration", "clipping"]
    assert main(["fit", str(cap), "-o", str(tmp_path / "p"), "-q", "--flakes", "off", "--clipping", "pixel"]) == 0
    fit = json.loads((tmp_path / "p" / "material.json").read_text())["fit"]
    assert fit["clipping"] == {"mode": "pixel", "chosen": "pixel"}
    assert "clipping" not in [d["name"] for d in fit["decisions"]]
    assert_one_line_error(run_cli("fit", cap, "-o", tmp_path / "m2", "--clipping", "pixel", "--tile", "16"), "--clipping")
