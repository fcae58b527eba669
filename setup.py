"""Build hook: the wheel carries the browser files that `export --format web` (and the viewer) copy.

`pip install .` / `python -m build` copy onnxruntime-web's wasm build (and three.js, when the
checkout has it) from the checkout's ``node_modules`` (``npm ci``) into the wheel under
``torchmetal/_npm/<package>/`` — the npm package's own layout, its ``package.json`` and licence
included — so a site exported from a pip install is self-contained and works offline. Which files:
``WASM_FILES``/``WEBGPU_FILES`` of torchmetal/formats/web.py and ``FILES`` of
torchmetal/viewer/three.py, read from the source (nothing of torchmetal is imported here).
An editable install (``pip install -e``) copies nothing: it finds ``node_modules`` in the checkout.
Set TORCHMETAL_ORT_WEB to an onnxruntime-web folder to take it from elsewhere.
"""

import ast
import json
import os
import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
# onnxruntime-web's npm package ships no licence file; its package.json says MIT (Microsoft's).
ORT_LICENSE = """MIT License

Copyright (c) Microsoft Corporation.

Permission is hereby granted, free of charge, to any person obtaining a copy
of this software and associated documentation files (the "Software"), to deal
in the Software without restriction, including without limitation the rights
to use, copy, modify, merge, publish, distribute, sublicense, and/or sell
copies of the Software, and to permit persons to whom the Software is
furnished to do so, subject to the following conditions:

The above copyright notice and this permission notice shall be included in all
copies or substantial portions of the Software.

THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF ANY KIND, EXPRESS OR
IMPLIED, INCLUDING BUT NOT LIMITED TO THE WARRANTIES OF MERCHANTABILITY,
FITNESS FOR A PARTICULAR PURPOSE AND NONINFRINGEMENT. IN NO EVENT SHALL THE
AUTHORS OR COPYRIGHT HOLDERS BE LIABLE FOR ANY CLAIM, DAMAGES OR OTHER
LIABILITY, WHETHER IN AN ACTION OF CONTRACT, TORT OR OTHERWISE, ARISING FROM,
OUT OF OR IN CONNECTION WITH THE SOFTWARE OR THE USE OR OTHER DEALINGS IN THE
SOFTWARE.
"""


def _constants(path: Path) -> dict:
    """Module-level constants (literals) of a source file, without importing it."""
    if not path.is_file():
        return {}
    out = {}
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            try:
                out[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                pass
    return out


def npm_files() -> list[tuple[str, Path, dict[str, str], bool]]:
    """(package, source folder, {path in the wheel folder: path in the package}, required) per npm package."""
    web = _constants(ROOT / "torchmetal" / "formats" / "web.py")
    ort = Path(os.environ.get("TORCHMETAL_ORT_WEB") or ROOT / "node_modules" / "onnxruntime-web")
    if ort.name == "dist":
        ort = ort.parent
    files = {f"dist/{n}": f"dist/{n}" for n in web["WASM_FILES"] + web["WEBGPU_FILES"]}
    files["package.json"] = "package.json"
    out = [("onnxruntime-web", ort, files, True)]
    three = _constants(ROOT / "torchmetal" / "viewer" / "three.py").get("FILES")
    if three:
        rels = {rel: rel for rel in three.values()}
        rels["package.json"] = "package.json"
        out.append(("three", ROOT / "node_modules" / "three", rels, False))
    return out


class BuildPyWithNpm(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return
        for package, src, files, required in npm_files():
            missing = [rel for rel in files.values() if not (src / rel).is_file()]
            if missing:
                if required:
                    raise SystemExit(f"torchmetal build: expected {package} in {src} (run `npm ci` in the repository "
                                     f"first), found {', '.join(missing[:3])} missing")
                print(f"torchmetal build: {package} not in {src}, left out of the wheel")
                continue
            dest = Path(self.build_lib) / "torchmetal" / "_npm" / package
            shutil.rmtree(dest, ignore_errors=True)
            for out_rel, rel in files.items():
                (dest / out_rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src / rel, dest / out_rel)
            if package == "onnxruntime-web" and not (dest / "LICENSE").exists():
                (dest / "LICENSE").write_text(ORT_LICENSE)
            version = json.loads((dest / "package.json").read_text()).get("version")
            print(f"torchmetal build: {package} {version} -> {dest.relative_to(self.build_lib)} ({len(files)} files)")


setup(cmdclass={"build_py": BuildPyWithNpm})
