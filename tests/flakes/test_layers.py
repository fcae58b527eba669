"""torchmetal.flakes by layer (torchmetal/flakes/__init__.py): the render model (flakes.model) below the
estimation (flakes.estimate), both below the stage and the choices at the package's top; each imports
only the layers below it, at module level or in a function (the graph of tests/test_import_graph.py)."""

from __future__ import annotations

from tests.test_import_graph import import_graph

FLAKES = "torchmetal.flakes"
#: what the render model may not import: the layers above it, and the modules that import it
ABOVE_MODEL = (f"{FLAKES}.estimate", f"{FLAKES}.stage", f"{FLAKES}.choice", f"{FLAKES}.density_choice", f"{FLAKES}.run",
               "torchmetal.renderer", "torchmetal.material", "torchmetal.metrics", "torchmetal.pipeline", "torchmetal.fit")
#: what the estimation may not import: the stage and the choices, and what they need that it does not
ABOVE_ESTIMATE = (f"{FLAKES}.stage", f"{FLAKES}.choice", f"{FLAKES}.density_choice", f"{FLAKES}.run", "torchmetal.renderer",
                  "torchmetal.metrics", "torchmetal.pipeline")


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _violations(prefix: str, forbidden: tuple[str, ...]) -> list[str]:
    _, every = import_graph()
    return sorted(f"{m} imports {t}" for m, ts in every.items() if _within(m, (prefix,))
                  for t in ts if _within(t, forbidden))


def test_render_model_imports_nothing_above_it():
    assert _violations(f"{FLAKES}.model", ABOVE_MODEL) == []


def test_estimation_imports_nothing_above_it():
    assert _violations(f"{FLAKES}.estimate", ABOVE_ESTIMATE) == []


def test_package_exports_the_render_model_only():
    """``import torchmetal.flakes`` (which every flakes import runs first) loads the render model alone, so the
    renderer and the metrics can import it without a circle."""
    _, every = import_graph()
    assert every[FLAKES] and all(_within(t, (f"{FLAKES}.model",)) for t in every[FLAKES]), every[FLAKES]


def test_every_flakes_module_is_in_a_layer():
    top, _ = import_graph()
    top_level = {m for m in top if m.startswith(FLAKES + ".") and not _within(m, (f"{FLAKES}.model", f"{FLAKES}.estimate"))}
    assert top_level == {f"{FLAKES}.stage", f"{FLAKES}.choice", f"{FLAKES}.density_choice", f"{FLAKES}.run"}, top_level
