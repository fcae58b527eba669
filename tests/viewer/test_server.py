"""The served viewer's HTTP API (no browser): config, frames, photos, bad requests, host check."""

from __future__ import annotations

import http.client
import json
import urllib.error
import urllib.request

import numpy as np
import pytest

from tests.viewer.conftest import SIZE, ort_render


def post(server, body: bytes, host: str | None = None, path: str = "/render"):
    port = server.server_address[1]
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    headers = {"Content-Type": "application/json"}
    if host:
        headers["Host"] = host
    c.request("POST", path, body=body, headers=headers)
    r = c.getresponse()
    data = r.read()
    c.close()
    return r.status, data, r


def get(server, path: str):
    with urllib.request.urlopen(server.url + path.lstrip("/")) as r:
        return r.status, r.read(), r.headers


SHOT = {"light": [0.02, -0.01, 0.05, 1.0], "light_intensity": [0.004, 0.004, 0.004], "camera": [0.0, 0.0, 1.0, 0.0]}


class TestServer:
    def test_bound_to_loopback(self, served):
        assert served.server_address[0] == "127.0.0.1"

    def test_page_assets(self, served):
        status, body, headers = get(served, "/")
        assert status == 200 and b'<script type="module" src="viewer.js">' in body
        assert headers["Content-Type"].startswith("text/html")
        status, body, headers = get(served, "/viewer.js")
        assert headers["Content-Type"].startswith("text/javascript") and b"ServedBackend" in body

    def test_config(self, served, scene):
        _, body, _ = get(served, "/config.json")
        cfg = json.loads(body)
        assert (cfg["format"], cfg["mode"], cfg["width"], cfg["height"]) == ("torchmetal-viewer", "served", SIZE, SIZE)
        assert set(cfg["graphs"]) == {"plain", "flakes"}
        assert len(cfg["shots"]) == scene.capture.num_shots
        np.testing.assert_allclose(cfg["shots"][2]["light"], scene.capture.lights[2].tolist())

    @pytest.mark.parametrize("flakes", [True, False])
    def test_render_is_onnxruntime(self, served, scene, flakes):
        status, body, r = post(served, json.dumps({**SHOT, "flakes": flakes}).encode())
        assert status == 200 and r.headers["X-Image-Shape"] == f"3,{SIZE},{SIZE}"
        got = np.frombuffer(body, "<f4").reshape(3, SIZE, SIZE)
        ref = ort_render(scene.site / ("renderer.onnx" if flakes else "renderer-noflakes.onnx"), *SHOT.values())
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7)

    def test_flakes_graph_differs(self, served):
        on = np.frombuffer(post(served, json.dumps({**SHOT, "flakes": True}).encode())[1], "<f4")
        off = np.frombuffer(post(served, json.dumps({**SHOT, "flakes": False}).encode())[1], "<f4")
        assert np.abs(on - off).max() > 1e-3

    def test_photo(self, served, scene):
        from torchmetal.viewer.site import photo_png

        status, body, headers = get(served, "/photos/003.png")
        assert status == 200 and headers["Content-Type"] == "image/png" and body == photo_png(scene.capture, 3)

    @pytest.mark.parametrize("body, match", [
        (b"{not json", "expected JSON"),
        (b"[1, 2]", "expected a JSON object"),
        (json.dumps({**SHOT, "light": [0, 0, 1]}).encode(), "light: expected 4 finite numbers"),
        (json.dumps({**SHOT, "camera": [0, 0, "x", 0]}).encode(), "camera: expected 4 finite numbers"),
        (json.dumps({**SHOT, "light": [0.1, 0.1, -1, 1]}).encode(), "light"),
        (json.dumps({**SHOT, "light": [0.1, 0.1, 1, 0.5]}).encode(), "light"),
        (json.dumps({**SHOT, "light_intensity": [-1, 1, 1]}).encode(), "light_intensity"),
    ])
    def test_bad_render_request_is_one_line_400(self, served, body, match):
        status, data, _ = post(served, body)
        text = data.decode()
        assert status == 400 and match in text and text.count("\n") == 1, text

    def test_wrong_host_refused(self, served):
        status, data, _ = post(served, json.dumps(SHOT).encode(), host="evil.example:80")
        assert status == 403 and b"host" in data

    @pytest.mark.parametrize("path", ["/../material.json", "/photos/099.png", "/nope.js", "/config.json/x", "/photos/../x.png"])
    def test_unknown_paths_404(self, served, path):
        with pytest.raises(urllib.error.HTTPError) as e:
            get(served, path)
        assert e.value.code == 404


def test_busy_port_is_one_line_error(scene, served):
    from torchmetal.errors import InputError
    from torchmetal.viewer.server import make_server

    with pytest.raises(InputError, match=r"port: expected a free port on 127.0.0.1, found \d+ unavailable"):
        make_server(scene.material_dir, port=served.server_address[1])


def test_stale_renderer_is_not_reused(scene, tmp_path):
    """A renderer.onnx of the right size but another material is re-exported, not served."""
    import shutil

    from torchmetal.viewer.site import GRAPH_PLAIN, export_graphs

    other = scene.material.__class__(scene.material.texture * 0.5, scene.material.s, scene.material.alpha, scene.material.size,
                                     flakes=None)
    shutil.copyfile(scene.site / GRAPH_PLAIN, tmp_path / "stale.onnx")
    graphs = export_graphs(other, tmp_path / "out", reuse=[tmp_path / "stale.onnx"])
    assert graphs == {"plain": "renderer.onnx"}
    import torch

    from torchmetal.renderer import MaterialRenderer

    with torch.inference_mode():
        want = MaterialRenderer(other)(*(torch.tensor([v], dtype=torch.float32) for v in SHOT.values()))[0].numpy()
    stale = ort_render(tmp_path / "stale.onnx", *SHOT.values())
    fresh = ort_render(tmp_path / "out" / "renderer.onnx", *SHOT.values())
    np.testing.assert_allclose(fresh, want, atol=1e-4)  # the new file renders the new material
    assert np.abs(stale - want).max() > 1e-2
