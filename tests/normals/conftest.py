"""The normals tests run fits on tiny images like the fit tests: the same one intra-op thread."""

from tests.fit.conftest import _one_thread  # noqa: F401 (an autouse fixture: imported, it applies here too)
