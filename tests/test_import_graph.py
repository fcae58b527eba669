"""The torchmetal package's own import graph has no circles, and every import points down the layers.

Every module of the package is parsed with :mod:`ast` (nothing is imported). Each ``import`` and
``from … import`` of a torchmetal module becomes an edge: relative imports are resolved against the
importing module's package, and ``from torchmetal.x import y`` points at ``torchmetal.x.y`` when
``y`` is a submodule, else at ``torchmetal.x``. Imports under ``if TYPE_CHECKING:`` never run and
are left out; imports named by a string (``importlib.import_module``) are not seen.

An import is *module-level* when it runs while the module itself is imported (at the top, or in a
class body or an ``if``/``try`` there), and *function-local* when it sits in a function body and
runs only when that function is called. A circle is a strongly connected component of more than
one module.

* Module-level imports: no circle at all (a circle there makes the import order matter).
* All imports, function-local included: no circle among the modules outside
  :data:`PENDING` (a function-local import that closes a circle hides a layering problem).
  Circles that reach into :data:`PENDING` are counted and may not grow beyond
  :data:`PENDING_CYCLES`; run this file as a script to list them.
* All imports, function-local included: a module imports only modules of its own layer or of a
  layer below it (:data:`LAYERS`, lowest first). Each module belongs to the most specific entry
  that names it or a package above it; a module no entry names fails the test (place it).
  Upward imports that cannot be fixed yet are listed, counted, in :data:`ALLOWED_UPWARD` (none
  now); the list may only shrink.

The layers, lowest first (derived from the graph; a layer may import itself and anything below):

1. core: the package itself (exceptions, lazily resolved names), errors, memory, checks,
   geometry, lbfgs, phong, lobes: numerics on tensors, nothing about files or flakes; and the selection's
   rule and shot plan (torchmetal.select, .rule, .plan), which the fit's own choices use; the fit's options
   (torchmetal.config).
2. io: captures and images on disk (:mod:`torchmetal.io`).
3. model: the forward model and its scores: the flake model and its field
   (flakes.model, field, observed, placement, filters, md), material, renderer, metrics, and
   synth (synthetic captures rendered with it).
4. fit: the Phong fit (:mod:`torchmetal.fit`; ``torchmetal.normals``, the normal estimation
   that is leaving fit/, keeps its place; ``torchmetal.lightcal`` and ``torchmetal.clipping``, the capture's
   nuisances chosen with fits).
5. select: the selection harness, its screens and the choices made before the fit (select.harness, .screens, .choices),
   which fit candidates with the fit.
6. flakes: flake estimation (the rest of :mod:`torchmetal.flakes`: detection, statistics,
   choice, stage); it may use the fit, not the other way round.
7. pipeline: fit + flakes → material.
8. outputs: what a fitted material is turned into: onnx_export, formats, report, and the web
   page's parts that formats.web writes and formats.parity drives (viewer.site, viewer.three,
   viewer.browser).
9. tools: bench, scale, photos, demo and the rest of viewer (server, view verb, fps).
10. entry: the command line (cli, __main__).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = "torchmetal"
ROOT = Path(__file__).resolve().parents[1] / PACKAGE

#: modules still being reworked elsewhere: their function-local circles are counted, not forbidden
PENDING = ("torchmetal.fit", "torchmetal.pipeline")

#: circles (with function-local imports) that reach into PENDING; lower the count and drop the
#: circle as they are broken, never add one (the last, fit.normals <-> fit.normals_choice, went with
#: the torchmetal.normals package)
PENDING_CYCLES = 0
KNOWN_PENDING_CYCLES: list[set[str]] = []

#: the package's layers, lowest first: (name, entries). An entry names a module and everything under
#: it, except the package itself, which names only its own ``__init__``; the most specific entry wins.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("core", ("torchmetal", "torchmetal.errors", "torchmetal.memory", "torchmetal.checks", "torchmetal.geometry",
              "torchmetal.lbfgs", "torchmetal.phong", "torchmetal.lobes", "torchmetal.select", "torchmetal.select.rule",
              "torchmetal.select.plan", "torchmetal.config")),
    ("io", ("torchmetal.io",)),
    ("model", ("torchmetal.flakes.model", "torchmetal.material", "torchmetal.renderer", "torchmetal.metrics", "torchmetal.synth")),
    ("fit", ("torchmetal.fit", "torchmetal.normals", "torchmetal.lightcal", "torchmetal.clipping", "torchmetal.registration")),
    ("select", ("torchmetal.select.harness", "torchmetal.select.choices", "torchmetal.select.screens")),
    ("flakes", ("torchmetal.flakes",)),
    ("pipeline", ("torchmetal.pipeline",)),
    ("outputs", ("torchmetal.onnx_export", "torchmetal.formats", "torchmetal.report", "torchmetal.viewer.site",
                 "torchmetal.viewer.three", "torchmetal.viewer.browser")),
    ("tools", ("torchmetal.bench", "torchmetal.scale", "torchmetal.photos", "torchmetal.demo", "torchmetal.viewer",
               "torchmetal.plan")),
    ("entry", ("torchmetal.cli", "torchmetal.__main__")),
]

#: upward imports (importer, imported) that cannot be fixed yet, e.g. inside PENDING: counted, may only
#: shrink (none now)
ALLOWED_UPWARD: list[tuple[str, str]] = []


def module_files(root: Path = ROOT, package: str = PACKAGE) -> dict[str, Path]:
    """Dotted module name → source file, for every ``.py`` file under ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = [package, *path.relative_to(root).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """(import node, function-local?) for every import that can run (not under TYPE_CHECKING)."""
    stack = [(tree, False)]
    while stack:
        node, local = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node, local
            continue
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            children = node.orelse  # the body runs only under a type checker
        else:
            children = list(ast.iter_child_nodes(node))
        inner = local or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        stack.extend((c, inner) for c in children)


def _targets(node: ast.Import | ast.ImportFrom, name: str, is_package: bool, modules: dict) -> set[str]:
    """The torchmetal modules one import statement of module ``name`` loads directly."""
    if isinstance(node, ast.Import):
        found = set()
        for alias in node.names:
            mod = alias.name
            while mod and mod not in modules:  # ``import torchmetal.x.attr`` cannot happen, but be safe
                mod = mod.rpartition(".")[0]
            if mod:
                found.add(mod)
        return found
    if node.level:
        base = name.split(".") if is_package else name.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        mod = ".".join(base + ([node.module] if node.module else []))
    else:
        mod = node.module or ""
    if mod not in modules:
        return set()
    found = set()
    for alias in node.names:
        sub = f"{mod}.{alias.name}"
        found.add(sub if sub in modules else mod)
    return found


def import_graph(root: Path = ROOT, package: str = PACKAGE) -> tuple[dict, dict]:
    """(module-level edges, all edges): module name → set of torchmetal modules it imports."""
    modules = module_files(root, package)
    top: dict[str, set] = {m: set() for m in modules}
    every: dict[str, set] = {m: set() for m in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node, local in _imports(tree):
            targets = _targets(node, name, path.name == "__init__.py", modules) - {name}
            every[name] |= targets
            if not local:
                top[name] |= targets
    return top, every


def cycles(graph: dict[str, set]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted, sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set = set()
    stack: list = []
    out = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return sorted(out)


def _pending(module: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in PENDING)


def pending_cycles(graph: dict[str, set]) -> list[list[str]]:
    """The circles of ``graph`` that reach into :data:`PENDING`."""
    return [c for c in cycles(graph) if any(_pending(m) for m in c)]


def outside_graph(graph: dict[str, set]) -> dict[str, set]:
    """``graph`` restricted to the modules outside :data:`PENDING`."""
    return {m: {t for t in ts if not _pending(t)} for m, ts in graph.items() if not _pending(m)}


def layer_of(module: str, layers: list = LAYERS, package: str = PACKAGE) -> int | None:
    """Index in ``layers`` of the most specific entry naming ``module`` (None: no entry does)."""
    best, found = -1, None
    for i, (_, entries) in enumerate(layers):
        for e in entries:
            covers = module == e or (e != package and module.startswith(e + "."))
            if covers and len(e) > best:
                best, found = len(e), i
    return found


def upward_imports(graph: dict[str, set], layers: list = LAYERS, package: str = PACKAGE) -> list[tuple[str, str]]:
    """(importer, imported) for every edge of ``graph`` into a higher layer, sorted (modules without a
    layer are left to :func:`test_every_module_has_a_layer`)."""
    out = []
    for m, ts in graph.items():
        here = layer_of(m, layers, package)
        for t in ts:
            there = layer_of(t, layers, package)
            if here is not None and there is not None and there > here:
                out.append((m, t))
    return sorted(out)


# ----------------------------------------------------------------------------- tests


def test_graph_sees_the_package():
    top, every = import_graph()
    assert "torchmetal.bench.tasks" in top and "torchmetal.formats.engine" in top
    # an edge of each kind the parser must resolve
    assert "torchmetal.bench.memory" in top["torchmetal.bench.tasks"]  # absolute, module-level
    assert "torchmetal.phong" in every["torchmetal.bench.scoring"] - top["torchmetal.bench.scoring"]  # in a function


def test_no_module_level_cycle():
    top, _ = import_graph()
    assert cycles(top) == []


def test_no_cycle_outside_pending_counting_function_local_imports():
    _, every = import_graph()
    assert cycles(outside_graph(every)) == []


def test_pending_cycles_do_not_grow():
    """No more circles through PENDING than measured, and none wider than a known one (a new import
    that joins a known circle makes it wider without adding a circle)."""
    _, every = import_graph()
    found = pending_cycles(every)
    listing = "\n".join(" <-> ".join(c) for c in found)
    assert len(found) <= PENDING_CYCLES, f"new import circle(s) through {', '.join(PENDING)}:\n{listing}"
    assert all(any(set(c) <= known for known in KNOWN_PENDING_CYCLES) for c in found), (
        f"import circle(s) through {', '.join(PENDING)} beyond the known ones:\n{listing}")


def test_every_module_has_a_layer():
    unplaced = sorted(m for m in module_files() if layer_of(m) is None)
    assert not unplaced, f"place these modules in a layer of LAYERS: {', '.join(unplaced)}"


def test_no_upward_import():
    """No import, at module level or in a function, reaches a higher layer, beyond the counted allowance."""
    _, every = import_graph()
    names = [name for name, _ in LAYERS]
    found = upward_imports(every)
    listing = "\n".join(f"{m} ({names[layer_of(m)]}) imports {t} ({names[layer_of(t)]})" for m, t in found)
    new = [e for e in found if e not in ALLOWED_UPWARD]
    assert not new, f"upward import(s): move the shared code down, or the importer up:\n{listing}"
    assert len(found) == len(ALLOWED_UPWARD), "an allowed upward import is gone: drop it from ALLOWED_UPWARD"


def test_layers_catch_an_upward_import(tmp_path):
    """Layer lookup (the package itself, most specific entry) and the upward check on a made-up package."""
    pkg = tmp_path / "pkg"
    (pkg / "high").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "low.py").write_text("def f():\n    from pkg.high import top\n")
    (pkg / "high" / "__init__.py").write_text("")
    (pkg / "high" / "top.py").write_text("from pkg import low\n")
    (pkg / "high" / "base.py").write_text("from pkg.high import top\n")
    layers = [("low", ("pkg", "pkg.low", "pkg.high.base")), ("high", ("pkg.high",))]
    assert [layer_of(m, layers, "pkg") for m in ("pkg", "pkg.low", "pkg.high", "pkg.high.top", "pkg.high.base")] == [
        0, 0, 1, 1, 0]
    assert layer_of("other", layers, "pkg") is None
    _, every = import_graph(pkg, "pkg")
    assert upward_imports(every, layers, "pkg") == [("pkg.high.base", "pkg.high.top"), ("pkg.low", "pkg.high.top")]


def test_checks_catch_a_cycle(tmp_path):
    """The parser and the circle search on a made-up package: relative, submodule and local imports."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from . import b\n")
    (pkg / "a.py").write_text("from pkg.sub import b\nfrom typing import TYPE_CHECKING\n"
                              "if TYPE_CHECKING:\n    from pkg import c\n")
    (pkg / "sub" / "b.py").write_text("from ..a import x\n")
    (pkg / "c.py").write_text("def f():\n    from pkg import d\n")
    (pkg / "d.py").write_text("import pkg.c\n")
    top, every = import_graph(pkg, "pkg")
    assert top["pkg.a"] == {"pkg.sub.b"} and top["pkg.sub.b"] == {"pkg.a"} and top["pkg.sub"] == {"pkg.sub.b"}
    assert cycles(top) == [["pkg.a", "pkg.sub.b"]]
    assert cycles(every) == [["pkg.a", "pkg.sub.b"], ["pkg.c", "pkg.d"]]


if __name__ == "__main__":
    top_, every_ = import_graph()
    for title, found in (("module-level", cycles(top_)), ("with function-local imports", cycles(every_))):
        print(f"{title}: {len(found)} circle(s)")
        for c in found:
            print("  " + " <-> ".join(c))
    print(f"upward imports: {len(upward_imports(every_))}")
    for m_, t_ in upward_imports(every_):
        print(f"  {m_} -> {t_}")
