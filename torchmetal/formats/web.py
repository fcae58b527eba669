"""``export --format web -o SITE/``: a static folder that relights the material in the browser.

```
SITE/
  index.html viewer.js state.js display.js style.css preview.js   the page (shared with ``torchmetal view``)
  material.glb, three/…                                the 3D preview: the glTF export, three.js 0.187 from npm
                                                       (absent without three.js: the page then has no preview)
  config.json                                          size, surface, graphs, shots (torchmetal.viewer.site)
  renderer.onnx, renderer-noflakes.onnx                flakes on / off (one renderer.onnx without flakes)
  ort/ort.wasm.min.mjs, ort-wasm-simd-threaded.{mjs,wasm}   onnxruntime-web 1.30 (wasm, single-threaded)
  ort/ort.webgpu.min.mjs, ort-wasm-simd-threaded.asyncify.{mjs,wasm}   only with webgpu=True
  photos/NNN.png                                       with a capture: its shots as 8-bit sRGB
  README.txt                                           how to serve it
```
onnxruntime-web comes from npm (the repository's package.json + package-lock.json, ``npm ci``):
the writer copies it from ``ort_dir``, else ``$TORCHMETAL_ORT_WEB``, else the copy a wheel carries
(``torchmetal/_npm/onnxruntime-web``, put there by setup.py's build hook, so ``pip install torchmetal``
exports sites without npm), else ``node_modules`` of the repository or of the working directory.
The page loads ORT only from the site folder. Browsers refuse wasm from ``file://``, so the folder
is served (any static server, e.g. ``python3 -m http.server``); single-threaded wasm needs no cross-origin isolation headers.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from torchmetal.errors import ExportError
from torchmetal.viewer import site
from torchmetal.viewer.three import copy_three

if TYPE_CHECKING:
    from torchmetal.material import Material


ORT_ENV = "TORCHMETAL_ORT_WEB"
ORT_VERSION = "1.30."
WASM_FILES = ("ort.wasm.min.mjs", "ort-wasm-simd-threaded.mjs", "ort-wasm-simd-threaded.wasm")
WEBGPU_FILES = ("ort.webgpu.min.mjs", "ort-wasm-simd-threaded.asyncify.mjs", "ort-wasm-simd-threaded.asyncify.wasm")

README = """torchmetal web viewer: {title} ({height}x{width})

Serve this folder over http and open it, e.g.
    python3 -m http.server 8000 --bind 127.0.0.1     (in this folder)
    then http://127.0.0.1:8000/
Browsers block WebAssembly from file://. The page renders with onnxruntime-web {version}
(wasm, {threads} thread(s)){webgpu}; the view state is in the URL fragment, so a link reproduces
the view.
"""


def _candidates(ort_dir: str | os.PathLike | None) -> list[Path]:
    if ort_dir is not None:
        return [Path(ort_dir)]
    if os.environ.get(ORT_ENV):
        return [Path(os.environ[ORT_ENV])]
    here = Path(__file__).resolve()
    wheel = here.parents[1] / "_npm" / "onnxruntime-web"  # copied into the wheel by setup.py's build hook
    repo = here.parents[2] / "node_modules" / "onnxruntime-web"
    return list(dict.fromkeys([wheel, repo, Path.cwd() / "node_modules" / "onnxruntime-web"]))


def find_ort_web(ort_dir: str | os.PathLike | None = None, *, webgpu: bool = False) -> tuple[Path, str]:
    """The ``dist`` folder of onnxruntime-web 1.30.x and its version.

    ``ort_dir`` (or ``$TORCHMETAL_ORT_WEB``) may name the package folder or its ``dist``.
    Raises :class:`ExportError` (one line, saying to run ``npm ci``) when none is found.
    """
    need = WASM_FILES + (WEBGPU_FILES if webgpu else ())
    tried = []
    for c in _candidates(ort_dir):
        dist = c / "dist" if (c / "dist").is_dir() else c
        tried.append(str(dist))
        missing = [f for f in need if not (dist / f).is_file()]
        if missing:
            continue
        version = "unknown"
        pkg = dist.parent / "package.json"
        if pkg.is_file():
            try:
                version = str(json.loads(pkg.read_text()).get("version", "unknown"))
            except (OSError, ValueError):
                pass
        if not version.startswith(ORT_VERSION):
            raise ExportError(f"onnxruntime-web: expected version {ORT_VERSION}x in {dist.parent}, found {version}; run `npm ci` in the torchmetal repository")
        return dist, version
    raise ExportError(f"onnxruntime-web: expected {', '.join(need)} in {' or '.join(tried)}, found them missing; "
                      f"run `npm ci` in the torchmetal repository (or set {ORT_ENV} to an onnxruntime-web 1.30 folder)")


def _check_target(path: Path) -> None:
    if path.exists():
        if not path.is_dir():
            raise ExportError(f"{path}: expected a folder (or nothing) to write the web viewer to, found a file")
        cfg = path / "config.json"
        previous = False
        if cfg.is_file():
            try:
                previous = json.loads(cfg.read_text()).get("format") == "torchmetal-viewer"
            except (OSError, ValueError, AttributeError):
                previous = False
        if any(path.iterdir()) and not previous:
            raise ExportError(f"{path}: expected an empty folder or an earlier web export, found other files (not overwritten)")


def write(material: Material, path: str | os.PathLike, *, capture: str | os.PathLike | None = None, webgpu: bool = False,
          ort_dir: str | os.PathLike | None = None, threads: int = 1, opset: int = 20, title: str | None = None) -> Path:
    """Write the static viewer of ``material`` to the folder ``path`` (atomically); returns it.

    Args:
        material: a :class:`~torchmetal.material.Material`.
        path: the site folder (new, empty, or an earlier web export, which is replaced).
        capture: optional capture directory (or :class:`Capture`) whose shots the page shows as
            photos beside the render; its surface must be the material's.
        webgpu: also copy ORT's WebGPU build (the page's ``?ep=webgpu`` switch; +26 MiB).
        ort_dir: onnxruntime-web folder (default: see :func:`find_ort_web`).
        threads: wasm threads the page asks for. 1 (default) needs no cross-origin isolation;
            more need a server sending COOP/COEP headers, else onnxruntime-web runs one thread.
        opset: ONNX opset of the exported graphs.
        title: page title (default: "torchmetal").
    """
    import tempfile

    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.io.capture import Capture, load_capture
    from torchmetal.io.capture_save import replace_dir
    from torchmetal.io.images import atomic_write_bytes

    if not isinstance(threads, int) or threads < 1:
        raise ExportError(f"threads: expected an integer >= 1, found {threads!r}")
    dist, version = find_ort_web(ort_dir, webgpu=webgpu)
    path = Path(path)
    _check_target(path)
    cap = capture if isinstance(capture, Capture) or capture is None else load_capture(capture)
    shots = site.shots_of(cap, material) if cap is not None else []
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp.", dir=path.parent))
    try:
        graphs = site.export_graphs(material, tmp, opset=opset)
        preview, preview_note = site.write_preview(material, tmp)
        if preview is not None:
            copy_three(tmp)
        for name in site.PAGE_FILES:
            shutil.copyfile(site.static_dir() / name, tmp / name)
        (tmp / "ort").mkdir()
        for name in WASM_FILES + (WEBGPU_FILES if webgpu else ()):
            shutil.copyfile(dist / name, tmp / "ort" / name)
        if shots:
            (tmp / "photos").mkdir()
            for k, shot in enumerate(shots):
                atomic_write_bytes(tmp / shot["photo"], site.photo_png(cap, k))
        title = title or "torchmetal"
        ort = {"wasm": f"ort/{WASM_FILES[0]}", "webgpu": f"ort/{WEBGPU_FILES[0]}" if webgpu else None, "version": version}
        cfg = site.make_config(material, graphs, shots, mode="static", title=title, ort=ort, threads=threads,
                               preview=preview, preview_note=preview_note)
        (tmp / "config.json").write_text(json.dumps(cfg, indent=1, allow_nan=False) + "\n")
        (tmp / "README.txt").write_text(README.format(
            title=title, height=material.height, width=material.width, version=version, threads=threads,
            webgpu=", WebGPU with ?ep=webgpu" if webgpu else ""))
        os.chmod(tmp, 0o755)
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path
