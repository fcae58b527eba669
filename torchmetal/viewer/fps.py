"""Frame rate of the viewer page in Chromium, per material size (static: onnxruntime-web wasm).

    python -m torchmetal.viewer.fps --sizes 512 1024 -o bench-results/viewer-fps

For each size: a synthetic material with flakes, its web site, then the page's ``bench(n)`` (n
back-to-back frames with the light sweeping; each frame = ORT run + sRGB encode + canvas draw),
flakes on and off, and the same in served mode (Python onnxruntime behind ``torchmetal view``).
Prints one JSON line per run and writes ``fps.json`` plus a screenshot per size.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path

from torchmetal.formats.web import write
from torchmetal.viewer.browser import launch_chromium, open_viewer, serve_folder
from torchmetal.viewer.server import make_server


def measure(size: int, out: Path, frames: int, modes: tuple[str, ...]) -> list[dict]:
    from playwright.sync_api import sync_playwright

    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.material import save_material
    from torchmetal.synth import synth_capture

    root = out / f"{size}"
    t0 = time.perf_counter()
    material = synth_capture(size=size, shots=1, seed=0, texture="procedural", flakes=FlakeModel(density=0.003, seed=0)).material()
    save_material(material, root / "material")
    site = write(material, root / "site")
    export_s = time.perf_counter() - t0
    rows = []
    httpd, static_url = serve_folder(site)
    server = None
    if "served" in modes:
        server = make_server(root / "material", port=0, reuse=(site / "renderer.onnx", site / "renderer-noflakes.onnx"))
        threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            for mode in modes:
                url = static_url if mode == "static" else server.url
                page = open_viewer(browser, url + "#lt=point&laz=30&lel=50&ld=1.5&ct=ortho&cel=90", timeout_ms=300_000)
                label = page.locator("#mode").inner_text()
                for fl in (1, 0):
                    page.evaluate("f => window.tmviewer.setState({fl: f})", fl)
                    page.evaluate("window.tmviewer.bench(3)")  # warm-up
                    r = page.evaluate("n => window.tmviewer.bench(n)", frames)
                    row = {"size": size, "mode": mode, "backend": label, "flakes": bool(fl), **r,
                           "site_export_s": round(export_s, 1), "cpus": os.cpu_count()}
                    print(json.dumps(row), flush=True)
                    rows.append(row)
                page.screenshot(path=str(out / f"{mode}-{size}.png"))
                page.close()
            browser.close()
    finally:
        httpd.shutdown()
        if server is not None:
            server.shutdown()
            server.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--modes", nargs="+", choices=["static", "served"], default=["static", "served"])
    ap.add_argument("-o", "--output", default="bench-results/viewer-fps")
    args = ap.parse_args(argv)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    rows = [row for size in args.sizes for row in measure(size, out, args.frames, tuple(args.modes))]
    (out / "fps.json").write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
