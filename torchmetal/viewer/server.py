"""The served viewer: a stdlib HTTP server on 127.0.0.1 that renders frames with onnxruntime.

```python
from torchmetal.viewer.server import make_server
server = make_server("material/", capture="capture/", port=0)   # 0: any free port
print(server.url); server.serve_forever()                        # Ctrl-C, then server.close()
```
Routes: ``GET /`` and the page assets (``static/``), ``GET /config.json`` (see
:mod:`torchmetal.viewer.site`), ``GET /photos/NNN.png`` (shot NNN as 8-bit sRGB), and
``GET /material.glb`` and ``GET /three/…`` (the 3D preview: the glTF export and three.js from npm), and
``POST /render`` with JSON ``{"light": [4], "light_intensity": [3], "camera": [4], "flakes": bool}``
answered with the renderer's image (3, H, W) as little-endian float32 bytes (the page encodes it).
Bad requests get HTTP 400 with a one-line reason. Requests whose ``Host`` is not this server's
loopback address are refused (no DNS rebinding from other sites).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from torchmetal.errors import InputError, TorchmetalError
from torchmetal.viewer import site
from torchmetal.viewer.three import three_files

MAX_BODY = 1 << 16
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".json": "application/json", ".png": "image/png",
                 ".glb": "model/gltf-binary", "": "text/plain; charset=utf-8"}


class Viewer:
    """One material ready to serve: its config, onnxruntime sessions and the capture's photos.

    Args:
        material_dir: a material directory (docs/design.md §2.3); its ``renderer.onnx`` is used when it
            matches the material, the other graph is exported into a temporary folder.
        capture: optional capture directory whose shots are offered as photos (A/B).
        reuse: further ONNX files that may hold the graphs (checked like ``renderer.onnx``).
        threads: onnxruntime intra-op threads (None: its default).
        log: optional ``log(text)`` told before each (slow) ONNX export.
    """

    def __init__(self, material_dir: str | os.PathLike, *, capture: str | os.PathLike | None = None,
                 reuse: tuple[str | os.PathLike, ...] = (), threads: int | None = None, log=None) -> None:
        import onnxruntime as ort

        # on use: loads torch (this module imports nothing heavy)
        from torchmetal.material import load_material
        from torchmetal.onnx_export import session_options

        root = Path(material_dir)
        self.material = load_material(root)
        self.capture = None
        shots = []
        if capture is not None:
            # on use: loads torch (this module imports nothing heavy)
            from torchmetal.io.capture import load_capture

            self.capture = load_capture(capture)
            shots = site.shots_of(self.capture, self.material)
        self.graph_dir = Path(tempfile.mkdtemp(prefix="torchmetal-view-"))
        try:
            graphs = site.export_graphs(self.material, self.graph_dir, reuse=(root / site.GRAPH_FLAKES, *reuse), log=log)
            so = session_options(threads)
            self.sessions = {k: ort.InferenceSession(str(self.graph_dir / name), so, providers=["CPUExecutionProvider"])
                             for k, name in graphs.items()}
            if log is not None:
                log("exporting the 3D preview (glTF)…")
            preview, note = site.write_preview(self.material, self.graph_dir)
        except BaseException:
            shutil.rmtree(self.graph_dir, ignore_errors=True)
            raise
        self.config = site.make_config(self.material, graphs, shots, mode="served", title=f"torchmetal · {root.resolve().name}",
                                       preview=preview, preview_note=note)

        self.assets = {}  # the 3D preview's files: served name -> path
        if preview is not None:
            self.assets = {site.PREVIEW_GLB: self.graph_dir / site.PREVIEW_GLB, **(three_files() or {})}
        self._photos: dict[int, bytes] = {}
        self._lock = threading.Lock()

    def close(self) -> None:
        """Release the onnxruntime sessions (here, not at interpreter teardown) and remove the exported graphs."""
        self.sessions = {}
        shutil.rmtree(self.graph_dir, ignore_errors=True)

    def photo(self, k: int) -> bytes:
        if self.capture is None or not 0 <= k < self.capture.num_shots:
            raise KeyError(k)
        with self._lock:
            if k not in self._photos:
                self._photos[k] = site.photo_png(self.capture, k)
            return self._photos[k]

    def render(self, request: dict) -> bytes:
        """The image for one request (see the module docstring) as float32 (3, H, W) bytes."""
        import numpy as np

        if not isinstance(request, dict):
            raise InputError(f"render: expected a JSON object, found {type(request).__name__}")
        feeds = {}
        for name, width in (("light", 4), ("light_intensity", 3), ("camera", 4)):
            v = request.get(name)
            if not isinstance(v, list) or len(v) != width or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
                raise InputError(f"{name}: expected {width} finite numbers, found {json.dumps(v)[:80]}")
            feeds[name] = np.asarray([v], dtype=np.float32)
        _check_inputs(feeds)
        key = "flakes" if request.get("flakes", True) and "flakes" in self.sessions else "plain"
        image = self.sessions[key].run(["image"], feeds)[0]
        return np.ascontiguousarray(image[0], dtype="<f4").tobytes()


def _check_inputs(feeds: dict) -> None:
    import torch

    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.io.capture import check_light_camera

    check_light_camera(*(torch.from_numpy(feeds[k]) for k in ("light", "light_intensity", "camera")),
                       labels=["render"], error=InputError)


class _Handler(BaseHTTPRequestHandler):
    server: ViewerServer
    protocol_version = "HTTP/1.1"
    disable_nagle_algorithm = True  # frames follow headers at once (no Nagle / delayed-ACK stalls)

    def log_message(self, format: str, *args) -> None:  # quiet: the CLI prints one line at start
        pass

    def _send(self, code: int, body: bytes, ctype: str, extra: dict | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _error(self, code: int, text: str) -> None:
        self._send(code, (text.splitlines()[0] if text else "error").encode() + b"\n", "text/plain; charset=utf-8")

    def _host_ok(self) -> bool:
        port = self.server.server_address[1]
        if self.headers.get("Host") in {f"127.0.0.1:{port}", f"localhost:{port}"}:
            return True
        self._error(403, f"host: expected 127.0.0.1:{port}, found {self.headers.get('Host')!r}")
        return False

    def do_GET(self) -> None:  # noqa: N802 (http.server's names)
        if not self._host_ok():
            return
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        name = "index.html" if path == "/" else path.lstrip("/")
        viewer = self.server.viewer
        if name == "config.json":
            return self._send(200, json.dumps(viewer.config).encode(), CONTENT_TYPES[".json"])
        if name in site.PAGE_FILES:
            return self._send(200, site.page_bytes(name), CONTENT_TYPES[Path(name).suffix])
        if name in viewer.assets:
            return self._send(200, viewer.assets[name].read_bytes(), CONTENT_TYPES[Path(name).suffix])
        if name.startswith("photos/") and name.endswith(".png") and name[7:-4].isdigit():
            try:
                return self._send(200, viewer.photo(int(name[7:-4])), CONTENT_TYPES[".png"])
            except KeyError:
                pass
        self._error(404, f"{path}: not found")

    do_HEAD = do_GET

    def do_POST(self) -> None:  # noqa: N802
        if not self._host_ok():
            return
        if self.path.split("?", 1)[0] != "/render":
            return self._error(404, f"{self.path}: not found")
        try:
            n = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            n = -1
        if not 0 < n <= MAX_BODY:
            return self._error(400, f"body: expected 1 to {MAX_BODY} bytes of JSON, found Content-Length {self.headers.get('Content-Length')!r}")
        try:
            request = json.loads(self.rfile.read(n))
            body = self.server.viewer.render(request)
        except json.JSONDecodeError as e:
            return self._error(400, f"body: expected JSON, found a syntax error ({e.msg})")
        except TorchmetalError as e:
            return self._error(400, str(e))
        h, w = self.server.viewer.config["height"], self.server.viewer.config["width"]
        self._send(200, body, "application/octet-stream", {"X-Image-Shape": f"3,{h},{w}"})


class ViewerServer(ThreadingHTTPServer):
    """A :class:`ThreadingHTTPServer` on 127.0.0.1 serving one :class:`Viewer`."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, viewer: Viewer | None, port: int = 8765) -> None:
        self.viewer = viewer
        try:
            super().__init__(("127.0.0.1", int(port)), _Handler)
        except OSError as e:
            raise InputError(f"port: expected a free port on 127.0.0.1, found {port} unavailable ({e.strerror or e}); try --port 0") from None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/"

    def close(self) -> None:
        self.server_close()
        if self.viewer is not None:
            self.viewer.close()


def make_server(material_dir: str | os.PathLike, *, capture: str | os.PathLike | None = None, port: int = 8765,
                reuse: tuple[str | os.PathLike, ...] = (), threads: int | None = None, log=None) -> ViewerServer:
    """A ready :class:`ViewerServer` (not yet serving: call ``serve_forever``)."""
    if not isinstance(port, int) or not 0 <= port <= 65535:
        raise InputError(f"port: expected an integer in 0..65535, found {port!r}")
    server = ViewerServer(None, port)  # bind first: a busy port fails before any export
    try:
        server.viewer = Viewer(material_dir, capture=capture, reuse=reuse, threads=threads, log=log)
    except BaseException:
        server.close()
        raise
    return server
