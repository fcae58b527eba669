"""``torchmetal capture``'s contact sheet and printout show the capture plan's next photos."""

from __future__ import annotations

import numpy as np
import pytest

from torchmetal.cli import main
from torchmetal.photos.board import write_board
from torchmetal.photos.report import COLUMNS, contact_image, plan_tile
from torchmetal.plan.run import hand_held, plan_capture

from .conftest import FLASH, SHOTS


@pytest.fixture(scope="module")
def plan(captured):
    return plan_capture(captured.capture, 2)


def test_hand_held_words():
    assert hand_held([0.1, -0.05, 0.3, 1.0]) == "30 cm up, 10 cm right, 5 cm to the bottom, tilt 20 deg"
    assert hand_held([0.0, 0.0, 0.25]) == "25 cm up, tilt 0 deg"
    assert hand_held([-0.02, 0.07, 0.2]) == "20 cm up, 2 cm left, 7 cm to the top, tilt 20 deg"


def test_sheet_gets_the_plan_tile(captured, plan):
    plain = contact_image(captured)
    withplan = contact_image(captured, plan=plan)
    tiles = SHOTS + 1
    rows = -(-tiles // COLUMNS)
    th = plain.shape[0] // (-(-SHOTS // COLUMNS))
    assert withplan.shape[0] == rows * th and withplan.shape[1] == plain.shape[1]
    tile = plan_tile(captured, plan, 360)
    # the planned cameras are drawn (first: its colour) and the text lines are written below the panels
    assert (np.abs(tile.astype(int) - np.array([200, 120, 0])).sum(-1) == 0).sum() > 20
    thumb_h = 270
    assert (tile[thumb_h:] < 128).any()
    # the unseen part of the sample is tinted red where the plan says no photo put the highlight
    if not bool(plan.coverage.all()):
        left = tile[:thumb_h, : 360 // 2]
        assert ((left[..., 2].astype(int) - left[..., 0]) > 60).any()


def test_capture_verb_prints_the_next_photos(photo_set, board, tmp_path, capsys):
    _, meta = write_board(board, tmp_path / "board")
    out = tmp_path / "cap"
    rc = main(["capture", *map(str, photo_set.paths[:5]), "--board", str(meta), "-o", str(out), "--resolution", "32",
               "--flash-offset", *map(str, FLASH), "--plan", "1", "-q"])
    text = capsys.readouterr().out
    assert rc == 0
    lines = [ln for ln in text.splitlines() if "next photo" in ln]
    assert len(lines) == 1 and lines[0].strip().startswith("next photo 1: phone ") and "cm up" in lines[0]
    assert (out / "contact.png").stat().st_size > 10_000
    rc = main(["capture", *map(str, photo_set.paths[:5]), "--board", str(meta), "-o", str(tmp_path / "c0"),
               "--resolution", "32", "--flash-offset", *map(str, FLASH), "--plan", "0", "-q"])
    assert rc == 0 and "next photo" not in capsys.readouterr().out
