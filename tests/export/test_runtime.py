"""export/torchmetal_runtime.py: torch-free relighting, image writers, CLI, bad input."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.test_renderer import light_camera_cases, make_material
from torchmetal.onnx_export import PARITY_TOL, export_onnx, scaled_error
from torchmetal.renderer import MaterialRenderer

ROOT = Path(__file__).resolve().parents[2]
RUNTIME = ROOT / "export" / "torchmetal_runtime.py"


def load_runtime():
    spec = importlib.util.spec_from_file_location("torchmetal_runtime", RUNTIME)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["torchmetal_runtime"] = mod
    spec.loader.exec_module(mod)
    return mod


rt = load_runtime()


@pytest.fixture(scope="module")
def renderer_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("runtime")
    r = MaterialRenderer(make_material("clustered_flakes", h=36, w=44)).eval()
    return r, export_onnx(r, d / "renderer.onnx")


@pytest.fixture(scope="module")
def no_torch_env(tmp_path_factory):
    """Environment whose Python cannot import torch (nor torchmetal)."""
    shim = tmp_path_factory.mktemp("no_torch")
    for name in ("torch", "torchmetal"):
        (shim / f"{name}.py").write_text(f"raise ImportError('{name} is blocked in this test')\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = str(shim)
    env.pop("PYTHONSTARTUP", None)
    return env


def run_cli(args, env=None, cwd=None):
    return subprocess.run([sys.executable, str(RUNTIME), *map(str, args)], capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


class TestRender:
    def test_matches_torch(self, renderer_file):
        r, path = renderer_file
        ren = rt.Renderer(path, threads=1)
        assert (ren.height, ren.width) == (r.height, r.width)
        for batch in (1, 9):
            light, inten, camera = light_camera_cases(r.size, "mixed", batch=batch, seed=batch)
            got = ren.render(light.numpy(), inten.numpy(), camera.numpy())
            with torch.no_grad():
                ref = r(light, inten, camera).numpy()
            assert got.dtype == np.float32 and got.shape == (batch, 3, r.height, r.width)
            assert scaled_error(got, ref) <= PARITY_TOL

    def test_single_rows_broadcast_and_lists(self, renderer_file):
        _, path = renderer_file
        ren = rt.Renderer(path)
        lights = np.array([[0.02, 0.01, 0.1, 1.0], [0.3, 0.1, 1.0, 0.0]], np.float32)
        both = ren.render(lights, [0.01, 0.01, 0.01], [0, 0, 1, 0])
        one = ren.render([0.02, 0.01, 0.1, 1.0], np.full((1, 3), 0.01), (0, 0, 1, 0))
        assert both.shape[0] == 2 and np.array_equal(both[:1], one)

    @pytest.mark.parametrize(
        "light, inten, camera, match",
        [
            ([1, 2, 3], [1, 1, 1], [0, 0, 1, 0], r"light: expected shape \(4,\) or \(B, 4\)"),
            ([0, 0, 1, 0], [1, 1], [0, 0, 1, 0], "light_intensity: expected shape"),
            ([0, 0, 1, 0], [1, 1, 1], np.zeros((2, 2, 4)), "camera: expected shape"),
            ([0, 0, float("nan"), 0], [1, 1, 1], [0, 0, 1, 0], "light: expected finite values"),
            ([0, 0, 1, 0], [1, float("inf"), 1], [0, 0, 1, 0], "light_intensity: expected finite"),
            (np.zeros((2, 4)), np.ones((3, 3)), [0, 0, 1, 0], "batch: expected equal batch sizes"),
            ("up", [1, 1, 1], [0, 0, 1, 0], "light: expected numbers"),
            ([0, 0, 1e39, 0], [1, 1, 1], [0, 0, 1, 0], "float32 range"),
        ],
    )
    def test_bad_input_one_line(self, renderer_file, light, inten, camera, match):
        ren = rt.Renderer(renderer_file[1])
        with pytest.raises(rt.RuntimeInputError, match=match) as e:
            ren.render(light, inten, camera)
        assert "\n" not in str(e.value) and isinstance(e.value, ValueError)

    def test_bad_files(self, tmp_path):
        with pytest.raises(rt.RuntimeInputError, match="found nothing"):
            rt.Renderer(tmp_path / "missing.onnx")
        junk = tmp_path / "junk.onnx"
        junk.write_bytes(b"not an onnx file")
        with pytest.raises(rt.RuntimeInputError, match="expected a loadable ONNX renderer") as e:
            rt.Renderer(junk)
        assert "\n" not in str(e.value)

    def test_orbit_and_time(self, renderer_file):
        ren = rt.Renderer(renderer_file[1])
        frames = ren.orbit(5, elevation=30, batch=2)
        assert frames.shape == (5, 3, ren.height, ren.width) and np.isfinite(frames).all()
        point = ren.orbit(3, elevation=60, distance=0.5)
        assert point.shape[0] == 3
        lights = rt.orbit_lights(4, elevation=30)
        np.testing.assert_allclose(np.linalg.norm(lights[:, :3], axis=1), 1.0, rtol=1e-6)
        assert np.all(lights[:, 3] == 0)
        t = ren.time(repeats=2, warmup=0, batch=2)
        assert t["ms_min"] > 0 and t["batch"] == 2 and t["height"] == ren.height
        with pytest.raises(rt.RuntimeInputError):
            rt.orbit_lights(0)
        with pytest.raises(rt.RuntimeInputError):
            rt.orbit_lights(3, elevation=120)


class TestWriters:
    def test_png_roundtrip(self, tmp_path):
        g = np.random.default_rng(0)
        rgb = g.integers(0, 256, size=(17, 23, 3), dtype=np.uint8)
        p = rt.write_png(tmp_path / "a.png", rgb)
        import cv2

        back = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[:, :, ::-1]
        assert np.array_equal(back, rgb)

    def test_apng_frames(self, tmp_path):
        pil = pytest.importorskip("PIL.Image")
        g = np.random.default_rng(1)
        frames = [g.integers(0, 256, size=(9, 11, 3), dtype=np.uint8) for _ in range(4)]
        p = rt.write_apng(tmp_path / "a.png", frames, fps=10)
        im = pil.open(p)
        assert im.is_animated and im.n_frames == 4
        for k in range(4):
            im.seek(k)
            assert np.array_equal(np.asarray(im.convert("RGB")), frames[k])

    def test_srgb_and_bad_frames(self, tmp_path):
        img = np.stack([np.zeros((2, 2)), np.full((2, 2), 0.5), np.full((2, 2), 2.0)]).astype(np.float32)
        out = rt.to_srgb8(img)
        assert out.shape == (2, 2, 3) and out[0, 0].tolist() == [0, 188, 255]
        with pytest.raises(rt.RuntimeInputError, match="expected shape"):
            rt.to_srgb8(np.zeros((2, 2)))
        with pytest.raises(rt.RuntimeInputError, match="uint8"):
            rt.write_png(tmp_path / "b.png", np.zeros((2, 2, 3), np.float32))
        with pytest.raises(rt.RuntimeInputError, match="expected an animation file"):
            rt.write_animation(tmp_path / "b.mp4", [np.zeros((2, 2, 3), np.uint8)])


class TestWithoutTorch:
    """The runtime works in a Python where ``import torch`` fails."""

    def test_torch_really_blocked(self, no_torch_env):
        p = subprocess.run([sys.executable, "-c", "import torch"], capture_output=True, text=True, env=no_torch_env)
        assert p.returncode != 0 and "blocked" in p.stderr

    def test_module_api_without_torch(self, renderer_file, no_torch_env, tmp_path):
        r, path = renderer_file
        light, inten, camera = light_camera_cases(r.size, "mixed", batch=4, seed=7)
        np.savez(tmp_path / "in.npz", light=light.numpy(), inten=inten.numpy(), camera=camera.numpy())
        code = textwrap.dedent(f"""
            import sys, json
            sys.path.insert(0, {str(RUNTIME.parent)!r})
            import numpy as np
            import torchmetal_runtime as rt
            d = np.load({str(tmp_path / 'in.npz')!r})
            img = rt.Renderer({str(path)!r}).render(d['light'], d['inten'], d['camera'])
            np.save({str(tmp_path / 'out.npy')!r}, img)
            print(json.dumps({{'torch': 'torch' in sys.modules, 'torchmetal': 'torchmetal' in sys.modules}}))
        """)
        p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=no_torch_env, timeout=300)
        assert p.returncode == 0, p.stderr
        assert json.loads(p.stdout.strip().splitlines()[-1]) == {"torch": False, "torchmetal": False}
        with torch.no_grad():
            ref = r(light, inten, camera).numpy()
        assert scaled_error(np.load(tmp_path / "out.npy"), ref) <= PARITY_TOL

    def test_cli_without_torch(self, renderer_file, no_torch_env, tmp_path):
        r, path = renderer_file
        p = run_cli([path, "--light", 0.01, 0.02, 0.1, 1, "--intensity", 0.01, 0.01, 0.01, "--camera", 0, 0, 1, 0, "-o", tmp_path / "f.png"], env=no_torch_env)
        assert p.returncode == 0, p.stderr
        assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        p = run_cli([path, "--light", 0.01, 0.02, 0.1, 1, "--intensity", 0.01, 0.01, 0.01, "-o", tmp_path / "f.npy"], env=no_torch_env)
        assert p.returncode == 0, p.stderr
        with torch.no_grad():
            ref = r(torch.tensor([[0.01, 0.02, 0.1, 1.0]]), torch.full((1, 3), 0.01), torch.tensor([[0.0, 0.0, 1.0, 0.0]])).numpy()
        assert scaled_error(np.load(tmp_path / "f.npy")[None], ref) <= PARITY_TOL
        p = run_cli([path, "--orbit", 6, "--elevation", 35, "-o", tmp_path / "orbit.png"], env=no_torch_env)
        assert p.returncode == 0, p.stderr
        data = (tmp_path / "orbit.png").read_bytes()
        assert b"acTL" in data and data.count(b"fcTL") == 6
        p = run_cli([path, "--time", "--repeats", 2], env=no_torch_env)
        assert p.returncode == 0 and "ms median" in p.stdout

    @pytest.mark.parametrize(
        "args, match",
        [
            (["--light", 1, 2, "nan", 1, "-o", "x.png"], "light: expected finite values"),
            (["--exposure", -1, "-o", "x.png"], "--exposure: expected a positive number"),
            (["-o", "x.jpg"], "expected an output ending in .png or .npy"),
            (["--orbit", 0, "-o", "x.png"], "frames: expected >= 1"),
            ([], "expected -o OUTPUT or --time"),
        ],
    )
    def test_cli_bad_input(self, renderer_file, no_torch_env, tmp_path, args, match):
        p = run_cli([renderer_file[1], *args], env=no_torch_env, cwd=tmp_path)
        assert p.returncode == 2
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and match in lines[0]
        assert not list(tmp_path.glob("x.*"))

    def test_cli_missing_file(self, no_torch_env, tmp_path):
        p = run_cli([tmp_path / "nope.onnx", "--time"], env=no_torch_env)
        assert p.returncode == 2 and p.stderr.strip().count("\n") == 0 and "found nothing" in p.stderr
