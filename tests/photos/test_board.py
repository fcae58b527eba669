import dataclasses
import json

import numpy as np
import pytest

from torchmetal.photos.board import BLANK_MARGIN_MM, BoardError, load_board, make_board, render_sheet, write_board


def test_geometry_follows_the_dpi_and_fits_the_sheet():
    for paper, dpi in (("a4", 300), ("letter", 200)):
        b = make_board(paper, (50, 40), dpi)
        img = render_sheet(b)
        assert np.allclose(b.sheet_mm, (img.shape[1] * 25.4 / dpi, img.shape[0] * 25.4 / dpi))
        ox, oy = b.origin_mm
        bw, bh = b.board_mm
        assert ox > 0 and oy > 0 and ox + bw < b.sheet_mm[0] and oy + bh < b.sheet_mm[1]
        assert b.window_size_mm == pytest.approx((50, 40))


def test_raster_is_opencvs_board_outside_the_blank_squares():
    # integer pixels per marker cell (14 mm / 7 cells = 2 mm = 20 px at 254 dpi): OpenCV's image is exact there
    b = dataclasses.replace(make_board("a4", (50, 50), 254), marker_mm=14.0)
    img = render_sheet(b)
    nx, ny = b.squares
    ref = b.charuco().generateImage((nx * 200, ny * 200), marginSize=0, borderBits=1) / 255.0
    ox, oy = (round(v * 10) for v in b.origin_mm)
    sub = img[oy: oy + ny * 200, ox: ox + nx * 200]
    blank = np.kron(b.blank_squares(), np.ones((200, 200))) > 0
    assert np.abs(sub - ref)[~blank].max() < 1e-9
    # blank squares are paper except for the window's cut line
    x0, y0, x1, y1 = (round(v * 10) for v in b.window_mm)
    inside = img[y0 + 5: y1 - 5, x0 + 5: x1 - 5]
    assert inside.min() > 1 - 1e-9
    band = img[y0 - round(BLANK_MARGIN_MM * 10) + 1: y0 - 4, x0:x1]
    assert band.min() > 1 - 1e-9


def test_raster_is_area_exact():
    b = make_board("a4", (50, 50), 100)
    fine = render_sheet(b, dpi=200)
    coarse = render_sheet(b, dpi=100)
    h, w = coarse.shape
    pooled = fine[: 2 * h, : 2 * w].reshape(h, 2, w, 2).mean((1, 3))
    assert np.abs(pooled - coarse)[:-1, :-1].max() < 1e-9


def test_usable_corners_avoid_the_window():
    b = make_board()
    ids = b.corner_ids()
    pts = b.corner_points()[ids]
    cx, cy = b.window_centre_board
    ww, wh = b.window_size_mm
    outside = (np.abs(pts[:, 0] - cx) > ww / 2 + BLANK_MARGIN_MM) | (np.abs(pts[:, 1] - cy) > wh / 2 + BLANK_MARGIN_MM)
    assert outside.all() and len(ids) >= 60


def test_capture_frame_round_trip_and_axes():
    b = make_board()
    cx, cy = b.window_centre_board
    q = b.board_to_capture(np.array([[cx + 10, cy - 5, -300.0]]))[0]
    assert q == pytest.approx([0.010, 0.005, 0.300])  # x right, y to the sheet's top, z out of the print
    p = np.random.default_rng(0).normal(size=(5, 3)) * 100
    assert np.allclose(b.capture_to_board(b.board_to_capture(p)), p)


def test_write_and_load(tmp_path):
    b = make_board("letter", (60, 45), 100)
    png, meta = write_board(b, tmp_path / "b")
    assert load_board(meta) == b and load_board(tmp_path / "b") == b
    d = json.loads(meta.read_text())
    assert d["format"] == "torchmetal-board" and d["version"] == 1 and d["image"] == "board.png"
    assert set(d["charuco"]) == {"dictionary", "squares", "square_mm", "marker_mm", "legacy_pattern", "origin_mm"}
    from PIL import Image

    with Image.open(png) as im:
        assert im.info["dpi"][0] == pytest.approx(100, abs=0.01)
        assert im.size == (round(d["sheet_mm"][0] * 100 / 25.4), round(d["sheet_mm"][1] * 100 / 25.4))


@pytest.mark.parametrize("kwargs, match", [
    (dict(paper="a3"), "paper"), (dict(window=(170, 50)), "ring of printed squares"),
    (dict(window=(0, 50)), "window"), (dict(dpi=20), "dpi"),
])
def test_bad_options(kwargs, match):
    with pytest.raises(BoardError, match=match):
        make_board(**kwargs)


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(format="x"), "format"),
    (lambda d: d["charuco"].update(dictionary="DICT_NOPE"), "dictionary"),
    (lambda d: d.update(window_mm=[0, 0, 1]), "window_mm"),
    (lambda d: d.update(window_mm=[1, 1, 400, 400]), "inside the board"),
    (lambda d: d["charuco"].update(marker_mm=30), "marker_mm"),
])
def test_bad_board_json(tmp_path, edit, match):
    d = make_board().to_json()
    edit(d)
    (tmp_path / "board.json").write_text(json.dumps(d))
    with pytest.raises(BoardError, match=match):
        load_board(tmp_path)


def test_missing_board_json(tmp_path):
    with pytest.raises(BoardError, match="board.json"):
        load_board(tmp_path / "nope.json")
