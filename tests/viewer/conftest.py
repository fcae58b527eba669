"""Viewer tests: one small synthetic scene (64², flakes, 4 shots), its web site, and Chromium.

Screenshots and snapshots go to ``$TORCHMETAL_ARTEFACTS`` (e.g. bench-results/viewer) or else a
pytest temporary folder (printed in the session summary via ``artefacts``).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

SIZE = 64


@pytest.fixture(scope="session")
def scene(tmp_path_factory):
    """capture dir, material dir, the Material, the Capture and its static site (both graphs)."""
    import torch

    from torchmetal.flakes.model import FlakeModel
    from torchmetal.formats.web import write
    from torchmetal.io.capture import load_capture
    from torchmetal.material import save_material
    from torchmetal.synth import synth_capture, write_synth

    root = tmp_path_factory.mktemp("viewer_scene")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        r = synth_capture(size=SIZE, shots=4, seed=0, texture="procedural", flakes=FlakeModel(density=0.01, seed=0))
        write_synth(r, root / "capture")
        material = r.material()
        save_material(material, root / "material")
        site = write(material, root / "site", capture=root / "capture")
    finally:
        torch.set_num_threads(threads)
    return SimpleNamespace(root=root, capture_dir=root / "capture", material_dir=root / "material", material=material,
                           capture=load_capture(root / "capture"), site=site)


@pytest.fixture(scope="session")
def artefacts(tmp_path_factory) -> Path:
    out = Path(os.environ["TORCHMETAL_ARTEFACTS"]) if os.environ.get("TORCHMETAL_ARTEFACTS") else tmp_path_factory.mktemp("viewer_artefacts")
    out.mkdir(parents=True, exist_ok=True)
    return out


@pytest.fixture(scope="session")
def browser():
    from torchmetal.viewer.browser import CHROMIUM, close_shared_chromium, shared_chromium

    if not Path(CHROMIUM).exists():
        pytest.skip(f"browser tests need Debian's chromium at {CHROMIUM} (CI installs it)")
    yield shared_chromium()  # one per process: tests/formats/test_engine_parity.py uses it too
    close_shared_chromium()


@pytest.fixture(scope="session")
def static_url(scene):
    from torchmetal.viewer.browser import serve_folder

    httpd, url = serve_folder(scene.site)
    yield url
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture(scope="session")
def served(scene):
    """A running ``torchmetal view`` server of the scene (graphs reused from the site: no export)."""
    from torchmetal.viewer.server import make_server

    server = make_server(scene.material_dir, capture=scene.capture_dir, port=0, threads=1,
                         reuse=(scene.site / "renderer.onnx", scene.site / "renderer-noflakes.onnx"))
    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    yield server
    server.shutdown()
    server.close()


def session_of(path: Path):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def ort_render(path: Path, light, intensity, camera) -> np.ndarray:
    """onnxruntime (Python) render of one light: (3, H, W) float32 linear."""
    feeds = {"light": np.asarray([light], np.float32), "light_intensity": np.asarray([intensity], np.float32),
             "camera": np.asarray([camera], np.float32)}
    return session_of(path).run(["image"], feeds)[0][0]


def srgb8(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(3, H, W) linear → (H, W, 3) uint8 sRGB, with the library's curve and rounding."""
    import torch

    from torchmetal.io.images import linear_to_srgb, quantize

    x = torch.from_numpy(np.ascontiguousarray(linear, dtype=np.float32) * np.float32(exposure)).clamp(0, 1)
    return quantize(linear_to_srgb(x).permute(1, 2, 0).numpy(), 8)


def state_inputs(s: dict, extent: float) -> tuple[list, list, list]:
    """The renderer inputs of a page state (the semantics documented in static/state.js)."""
    import math

    def d(az, el):
        a, e = math.radians(az), math.radians(el)
        return [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]

    l, c = d(s["laz"], s["lel"]), d(s["caz"], s["cel"])
    r = s["ld"] * extent
    point = s["lt"] == "point"
    light = [x * r for x in l] + [1.0] if point else l + [0.0]
    lc = s.get("lc", [1.0, 1.0, 1.0])
    intensity = [v * s["li"] * (r * r if point else 1.0) for v in lc]
    cr = s["cd"] * extent
    camera = [x * cr for x in c] + [1.0] if s["ct"] == "point" else c + [0.0]
    return light, intensity, camera


def parse_hash(h: str) -> dict:
    from urllib.parse import parse_qsl

    s = dict(parse_qsl(h.lstrip("#")))
    out = {k: (v if k in ("lt", "ct", "ab") else [float(x) for x in v.split(",")] if k == "lc" else float(v)) for k, v in s.items()}
    return out
