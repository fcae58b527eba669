"""One setting finds the shared development captures (torchmetal.io.shared_data)."""

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


def test_no_absolute_machine_paths_in_the_project():
    repo = Path(shared_data.__file__).resolve().parents[2]
    hits = [p for d in ("torchmetal", "tests", "notebooks") for p in (repo / d).rglob("*")
            if p.suffix in {".py", ".ipynb"} and "/work/shared" in p.read_text(errors="replace")
            and p.name != "test_shared_data.py"]
    assert hits == []
