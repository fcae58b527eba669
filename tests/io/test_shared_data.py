"""One setting finds the shared development captures (torchmetal.io.shared_data)."""

import os
from pathlib import Path

from torchmetal.io import shared_data


def test_environment_variable_wins(tmp_path, monkeypatch):
    (tmp_path / "cards_blue").mkdir()
    (tmp_path / "cards_blue" / "capture.json").write_text("{}")
    monkeypatch.setenv(shared_data.ENV, str(tmp_path))
    assert shared_data.shared_data_dir() == tmp_path
    assert shared_data.shared_capture("cards_blue") == tmp_path / "cards_blue"
    assert shared_data.shared_capture("yellow_box") is None


def test_default_is_beside_the_repository(monkeypatch):
    monkeypatch.delenv(shared_data.ENV, raising=False)
    repo = Path(shared_data.__file__).resolve().parents[2]
    assert shared_data.shared_data_dir() == (repo.parent / "shared" / "data").resolve()


#: what the project's own files are: code, notebooks, docs and scripts
TEXT_SUFFIXES = {".py", ".ipynb", ".md", ".sh", ".cjs", ".js", ".toml", ".cfg"}
SKIP_DIRS = {".git", ".venv", "node_modules", ".pytest_cache", "__pycache__", "build", "dist"}


def _project_files(repo: Path):
    for top, dirs, files in os.walk(repo):
        dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS)
        for name in sorted(files):
            if Path(name).suffix in TEXT_SUFFIXES:
                yield Path(top) / name


def test_no_absolute_machine_paths_in_the_project():
    """No path of one machine (the team's /work checkout and its shared folder): the shared data is
    found through TORCHMETAL_SHARED_DATA (or its default beside the checkout) wherever it is."""
    repo = Path(shared_data.__file__).resolve().parents[2]
    marker = "/" + "work" + "/"  # spelled apart so this file does not match itself
    hits = [str(p.relative_to(repo)) for p in _project_files(repo) if marker in p.read_text(errors="replace")]
    assert hits == []


def test_every_reader_goes_through_shared_data():
    """Only torchmetal/io/shared_data.py builds the default path or reads the variable; everything
    else (bench, tests, notebooks, scripts) asks shared_data_dir() / shared_capture()."""
    import re

    repo = Path(shared_data.__file__).resolve().parents[2]
    own = re.compile(r"""["'](\.\./)+shared/data|Path\(["'][^"']*shared/data|["']shared["']\s*/\s*["']data["']|environ[^\n]*""" + shared_data.ENV)
    hits = [str(p.relative_to(repo)) for p in _project_files(repo)
            if p.suffix in {".py", ".ipynb", ".sh"} and p.name not in {"shared_data.py", "test_shared_data.py"}
            and own.search(p.read_text(errors="replace"))]
    assert hits == []
