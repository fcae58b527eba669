"""``torchmetal view``: help, bad input as one line, and a real served session in a subprocess."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import urllib.request

import numpy as np

from tests.viewer.conftest import SIZE


def test_help_lists_options(capsys):
    import pytest

    from torchmetal.cli import main

    with pytest.raises(SystemExit):
        main(["view", "--help"])
    out = capsys.readouterr().out
    for opt in ("--port", "--no-open", "--capture", "MATERIAL".lower()):
        assert opt in out


def test_missing_material_is_one_line(tmp_path, capsys):
    from torchmetal.cli import main

    assert main(["view", str(tmp_path / "nope"), "--no-open", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("torchmetal view: error:") and "material.json" in err and err.count("\n") == 1


def test_bad_port_is_one_line(scene, capsys):
    from torchmetal.cli import main

    assert main(["view", str(scene.material_dir), "--no-open", "--port", "70000"]) == 2
    err = capsys.readouterr().err
    assert "port: expected an integer in 0..65535, found 70000" in err and err.count("\n") == 1


def test_serves_until_interrupted(scene, tmp_path):
    """The verb reuses MATERIAL/renderer.onnx, exports the flake-free graph, serves, stops on Ctrl-C."""
    material = tmp_path / "material"
    shutil.copytree(scene.material_dir, material)
    shutil.copyfile(scene.site / "renderer.onnx", material / "renderer.onnx")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "TMPDIR": str(tmp)}
    proc = subprocess.Popen([sys.executable, "-m", "torchmetal", "view", str(material), "--no-open", "--port", "0",
                             "--capture", str(scene.capture_dir), "--threads", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        m = re.search(r"at (http://127\.0\.0\.1:\d+/)", line)
        assert m, (line, proc.stderr.read() if proc.poll() is not None else "")
        assert f"({SIZE}x{SIZE}, flakes on/off, 4 shots)" in line
        with urllib.request.urlopen(m.group(1) + "config.json", timeout=30) as r:
            cfg = json.loads(r.read())
        assert cfg["mode"] == "served" and set(cfg["graphs"]) == {"plain", "flakes"}
        body = json.dumps({"light": [0.0, 0.0, 1.0, 0.0], "light_intensity": [1, 1, 1], "camera": [0, 0, 1, 0], "flakes": False})
        req = urllib.request.Request(m.group(1) + "render", data=body.encode(), headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=30) as r:
            img = np.frombuffer(r.read(), "<f4")
        assert img.shape == (3 * SIZE * SIZE,) and np.isfinite(img).all() and img.max() > 0
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            raise AssertionError(f"still serving 60 s after Ctrl-C; stderr: {err[-2000:]!r}") from None
        assert proc.returncode == 0 and "stopped" in err
        assert "exporting renderer-noflakes.onnx (64x64, flakes off)" in err and "exporting renderer.onnx" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    # nothing written into the material; the exported graph's temporary folder is gone
    assert sorted(p.name for p in material.iterdir()) == sorted([p.name for p in scene.material_dir.iterdir()] + ["renderer.onnx"])
    assert not list(tmp.glob("torchmetal-view-*"))
