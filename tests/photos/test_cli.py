"""The ``board`` and ``capture`` verbs: exit 0 with a summary, exit 2 with one line on bad input."""

import json

import pytest

from torchmetal.cli import main
from torchmetal.photos.board import write_board

from .conftest import FLASH


def test_cli_exit_codes(bad_set, board, tmp_path, capsys):
    good, made = bad_set
    _, meta = write_board(board, tmp_path / "board")
    out = tmp_path / "cap"
    rc = main(["capture", *map(str, good[:3]), str(made["noexif.jpg"]), str(made["othercam.jpg"]), "--board", str(meta),
               "-o", str(out), "--resolution", "24", "--flash-offset", *map(str, FLASH), "-q"])
    text = capsys.readouterr().out
    assert rc == 0 and "rejected othercam.jpg: another camera" in text and "white band (no EXIF): noexif.jpg" in text
    rep = json.loads((out / "report.json").read_text())
    assert [r["used"] for r in rep["photos"]] == [True, True, True, True, False]
    assert [r.get("exposure_source") for r in rep["photos"]] == ["exif", "exif", "exif", "white_band", None]
    rc = main(["capture", str(made["noboard.jpg"]), str(made["small.jpg"]), "--board", str(meta), "-o", str(tmp_path / "x"), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "usable photos" in err
    assert not (tmp_path / "x").exists()
    rc = main(["capture", str(good[0]), "--board", str(tmp_path / "nothing.json"), "-o", str(tmp_path / "y")])
    assert rc == 2 and "board.json" in capsys.readouterr().err


def test_board_verb(tmp_path, capsys):
    assert main(["board", "-o", str(tmp_path / "b"), "--paper", "letter", "--window", "40", "30", "--dpi", "100"]) == 0
    d = json.loads((tmp_path / "b" / "board.json").read_text())
    assert d["window_mm"][2] - d["window_mm"][0] == pytest.approx(40) and (tmp_path / "b" / "board.png").is_file()
    capsys.readouterr()
    assert main(["board", "-o", str(tmp_path / "c"), "--window", "300", "300"]) == 2
    err = capsys.readouterr().err
    assert "window" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "c").exists()
