"""three.js for the viewer's 3D preview and the engine-parity client, taken from npm (offline).

The repository's package.json pins ``three`` (``npm ci`` installs it into ``node_modules``). The
page and the parity page load it as ES modules through an import map
(``"three": "three/three.module.js"``); :data:`FILES` lists the few files they need, under the
names they are served as. Nothing is fetched from a CDN: when three.js is not found the viewer
runs without its 3D preview (and says so), and the parity check is skipped.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

THREE_ENV = "TORCHMETAL_THREE"
THREE_VERSION = "0.187."
# served name -> path inside the npm package
FILES = {
    "three/three.module.js": "build/three.module.js",
    "three/three.core.js": "build/three.core.js",
    "three/addons/loaders/GLTFLoader.js": "examples/jsm/loaders/GLTFLoader.js",
    "three/addons/utils/BufferGeometryUtils.js": "examples/jsm/utils/BufferGeometryUtils.js",
    "three/addons/utils/SkeletonUtils.js": "examples/jsm/utils/SkeletonUtils.js",
    "three/LICENSE": "LICENSE",
}
IMPORT_MAP = {"imports": {"three": "./three/three.module.js", "three/addons/": "./three/addons/"}}


def _candidates(three_dir: str | os.PathLike | None) -> list[Path]:
    if three_dir is not None:
        return [Path(three_dir)]
    if os.environ.get(THREE_ENV):
        return [Path(os.environ[THREE_ENV])]
    here = Path(__file__).resolve()
    wheel = here.parents[1] / "_npm" / "three"  # where a wheel's build hook would put a copy (as for ORT)
    return list(dict.fromkeys([wheel, here.parents[2] / "node_modules" / "three", Path.cwd() / "node_modules" / "three"]))


def find_three(three_dir: str | os.PathLike | None = None) -> tuple[Path, str] | None:
    """The npm package folder of three.js 0.187.x and its version, or None when there is none.

    ``three_dir`` (or ``$TORCHMETAL_THREE``) names the package folder (the one holding
    ``package.json``, ``build/`` and ``examples/``); else ``torchmetal/_npm/three`` (a wheel's copy),
    else ``node_modules/three`` of the repository or of the working directory.
    """
    for c in _candidates(three_dir):
        if not all((c / rel).is_file() for rel in FILES.values()):
            continue
        try:
            version = str(json.loads((c / "package.json").read_text()).get("version", "unknown"))
        except (OSError, ValueError):
            version = "unknown"
        if version.startswith(THREE_VERSION):
            return c, version
    return None


def three_files(three_dir: str | os.PathLike | None = None) -> dict[str, Path] | None:
    """{served name: file} of three.js (see :data:`FILES`), or None when it is not installed."""
    found = find_three(three_dir)
    if found is None:
        return None
    root, _ = found
    return {name: root / rel for name, rel in FILES.items()}


def copy_three(dest: str | os.PathLike, three_dir: str | os.PathLike | None = None) -> str | None:
    """Copy three.js's files under ``dest`` (``dest/three/…``); returns its version, None when absent."""
    import shutil

    found = find_three(three_dir)
    if found is None:
        return None
    root, version = found
    for name, rel in FILES.items():
        out = Path(dest) / name
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(root / rel, out)
    return version
