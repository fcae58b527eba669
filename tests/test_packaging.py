"""What `pip install torchmetal` brings: every third-party import of the package is declared, in the right place.

Walks every module of torchmetal/ (imports at any depth, lazy ones included) and maps each top-level
import to the distribution that provides it in this environment; core code needs a core dependency,
code that only an extra reaches needs that extra. Also: the wheel's build hook (setup.py) copies the
onnxruntime-web files that formats/web.py needs.
"""

import ast
import importlib.metadata as md
import re
import sys
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

# imports that only optional code reaches: module -> (extra that must declare it, where)
OPTIONAL = {
    "ray": ("ray", "scale/engines.py: fit-many --engine ray (one-line error without it)"),
    "scipy": ("bench", "bench/baselines.py: the numpy/scipy paper baseline (bench says so without it)"),
    "skimage": ("bench", "synth photo textures and the zoo's photo scenes (synth falls back to procedural)"),
    "playwright": ("test", "viewer/fps.py: the browser frame-rate measurement, a developer tool"),
}
# imported only as a fallback that is never needed on Linux: not declared on purpose
UNDECLARED_OK = {"psutil": "bench/memory.py reads /proc first; psutil only where /proc is missing"}
LOCAL = {"torchmetal", "torchmetal_runtime"}


def _name(req: str) -> str:
    return re.split(r"[\s<>=!~\[;(]", req, maxsplit=1)[0].lower().replace("_", "-")


def _providers() -> dict[str, set[str]]:
    """import name -> distributions, extension modules included (packages_distributions misses OpenEXR's .so)."""
    out: dict[str, set[str]] = {k: {d.lower().replace("_", "-") for d in v} for k, v in md.packages_distributions().items()}
    for dist in md.distributions():
        for f in dist.files or ():
            if len(f.parts) == 1 and f.name.endswith((".so", ".pyd")):
                out.setdefault(f.name.split(".")[0], set()).add(dist.metadata["Name"].lower().replace("_", "-"))
    return out


def _imports() -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for path in sorted((ROOT / "torchmetal").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for n in names:
                top = n.split(".")[0]
                if top not in sys.stdlib_module_names and top not in LOCAL:
                    out.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return out


def test_every_third_party_import_is_declared():
    core = {_name(r) for r in PYPROJECT["project"]["dependencies"]}
    extras = {k: {_name(r) for r in v} for k, v in PYPROJECT["project"]["optional-dependencies"].items()}
    dists = _providers()
    problems = []
    for module, files in sorted(_imports().items()):
        if module in UNDECLARED_OK:
            continue
        provided = dists.get(module, set())
        assert provided, f"{module} (imported in {sorted(files)}) is not installed here"
        if module in OPTIONAL:
            extra, _ = OPTIONAL[module]
            if not provided & extras.get(extra, set()):
                problems.append(f"{module}: expected in the [{extra}] extra ({sorted(provided)})")
        elif not provided & core:
            problems.append(f"{module} ({sorted(provided)}), imported in {sorted(files)[:3]}: not a core dependency")
    assert not problems, problems


def test_test_extra_covers_the_other_extras():
    extras = {k: {_name(r) for r in v} for k, v in PYPROJECT["project"]["optional-dependencies"].items()}
    for name, reqs in extras.items():
        assert reqs <= extras["test"], f"[{name}] has {sorted(reqs - extras['test'])} that [test] lacks"


def test_exporters_need_no_scipy():
    """`export` (every format) runs on a plain install: scipy is only for the bench baseline."""
    for path in (ROOT / "torchmetal" / "formats").glob("*.py"):
        assert "import scipy" not in path.read_text() and "from scipy" not in path.read_text(), path


def test_wheel_build_hook_copies_what_web_needs(monkeypatch):
    """setup.py's hook takes the file list from formats/web.py: a wheel carries exactly what write() copies."""
    from torchmetal.formats import web

    src = (ROOT / "setup.py").read_text()
    tree = ast.parse(src)
    ns: dict = {"__file__": str(ROOT / "setup.py")}
    keep = [n for n in tree.body if not (isinstance(n, ast.Expr) and isinstance(n.value, ast.Call))]  # not setup()
    exec(compile(ast.Module(keep, type_ignores=[]), "setup.py", "exec"), ns)
    packages = {p: (src_dir, files, required) for p, src_dir, files, required in ns["npm_files"]()}
    _, files, required = packages["onnxruntime-web"]
    assert required
    assert {f"dist/{n}" for n in web.WASM_FILES + web.WEBGPU_FILES} | {"package.json"} == set(files)
    wheel_dir = Path(web.__file__).resolve().parents[1] / "_npm" / "onnxruntime-web"
    assert wheel_dir in web._candidates(None)


@pytest.mark.parametrize("module", sorted(OPTIONAL))
def test_optional_imports_are_lazy(module):
    """Optional packages are imported inside the functions that need them, never at module level."""
    for path in (ROOT / "torchmetal").rglob("*.py"):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                assert not any(n.split(".")[0] == module for n in names), f"{path}: top-level import of {module}"
