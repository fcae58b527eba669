"""Drive the viewer page in a real Chromium (tests and the frame-rate script).

Debian's ``chromium`` through Playwright's ``executable_path`` (no browser download), started with
the flags CI uses. :func:`serve_folder` serves a static site (``export --format web``) on
127.0.0.1 with the MIME types the page needs (``.mjs``, ``.wasm``).
"""

from __future__ import annotations

import functools
import os
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

CHROMIUM = os.environ.get("TORCHMETAL_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]


def launch_chromium(playwright, **kwargs):
    """``playwright.chromium.launch`` of :data:`CHROMIUM` with :data:`CHROMIUM_ARGS`."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, **kwargs)


_SHARED: dict = {}


def shared_chromium():
    """One Chromium per process (Playwright's sync API allows one running instance per thread):
    the viewer tests and the engine-parity client share it. :func:`close_shared_chromium` ends it."""
    if "browser" not in _SHARED:
        from playwright.sync_api import sync_playwright

        pw = sync_playwright().start()
        try:
            _SHARED["browser"] = launch_chromium(pw)
        except BaseException:
            pw.stop()
            raise
        _SHARED["playwright"] = pw
    return _SHARED["browser"]


def close_shared_chromium() -> None:
    """Close the browser of :func:`shared_chromium` (if started); idempotent."""
    browser, pw = _SHARED.pop("browser", None), _SHARED.pop("playwright", None)
    for f in (getattr(browser, "close", None), getattr(pw, "stop", None)):
        if f is not None:
            try:
                f()
            except Exception:
                pass


class _Quiet(SimpleHTTPRequestHandler):
    extensions_map = {**SimpleHTTPRequestHandler.extensions_map, ".mjs": "text/javascript", ".js": "text/javascript",
                      ".wasm": "application/wasm", ".onnx": "application/octet-stream", ".json": "application/json",
                      ".glb": "model/gltf-binary"}

    def log_message(self, format: str, *args) -> None:
        pass


def serve_folder(folder: str | os.PathLike, port: int = 0) -> tuple[ThreadingHTTPServer, str]:
    """Serve ``folder`` on 127.0.0.1 from a daemon thread; returns (server, url). ``server.shutdown()`` stops it."""
    httpd = ThreadingHTTPServer(("127.0.0.1", port), functools.partial(_Quiet, directory=str(Path(folder))))
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd, f"http://127.0.0.1:{httpd.server_address[1]}/"


def open_viewer(browser, url: str, *, timeout_ms: float = 60_000, viewport=None, requests: list | None = None):
    """A new page at ``url`` whose first frame has been drawn; raises RuntimeError with the page's error.

    ``requests``, when given, collects the URL of every request the page makes.
    """
    page = browser.new_page(viewport=viewport or {"width": 1280, "height": 900}, accept_downloads=True)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    if requests is not None:
        page.on("request", lambda r: requests.append(r.url))
    page.goto(url)
    page.wait_for_function("window.tmviewer && (window.tmviewer.frames > 0 || window.tmviewer.error)", timeout=timeout_ms)
    err = page.evaluate("window.tmviewer.error")
    if err or errors:
        raise RuntimeError(f"viewer at {url}: {err or errors[0]}")
    return page
