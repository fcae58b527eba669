"""Each bad photo gets its one-line reason, the good ones still make a capture; an unusable set is
a clear error (CaptureError; the CLI exits 2 with one line)."""

import json
import math

import cv2
import numpy as np
import pytest
from PIL import Image

from torchmetal.errors import CaptureError
from torchmetal.photos import simulate as S
from torchmetal.photos.board import write_board
from torchmetal.photos.capture import capture_from_photos
from torchmetal.photos.exif import PhotoExif, exif_bytes

from .conftest import FLASH


def _pose(board, el, az, d, target):
    e, a = math.radians(el), math.radians(az)
    centre = d * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    return S._look_at(board, centre, np.asarray(target, np.float64), 0.0)


def _resave(src, dst, *, exif: PhotoExif | None, transform=None):
    img = np.asarray(Image.open(src).convert("RGB"))
    if transform is not None:
        img = transform(img)
    Image.fromarray(img).save(dst, "JPEG", quality=95, **({"exif": exif_bytes(exif)} if exif else {}))
    return dst


def _bend(a):
    """The right half of the photo moved 6 px down: no single pose fits all the corners."""
    a = a.copy()
    w = a.shape[1]
    a[:, w // 2:] = np.roll(a[:, w // 2:], 6, axis=0)
    return a


@pytest.fixture(scope="module")
def bad_set(tmp_path_factory, photo_set, board, sheet, sample):
    out = tmp_path_factory.mktemp("bad")
    good = photo_set.paths[:5]
    ex = photo_set.exif[0]
    rendered = S.phone_photos(out, board, sample, poses=[_pose(board, 15, 90, 0.18, [0, 0.02, 0]),  # grazing
                                                         _pose(board, 55, 30, 0.3, [0.14, 0, 0])],  # window half out
                              flash_offset_mm=FLASH, sheet=sheet, supersample=1, names=["grazing.jpg", "cutoff.jpg"])
    p = photo_set.paths
    made = {
        "noboard.jpg": _resave(p[5], out / "noboard.jpg", exif=ex, transform=lambda a: np.full_like(a, 128)),
        "blurred.jpg": _resave(p[5], out / "blurred.jpg", exif=photo_set.exif[5],
                               transform=lambda a: cv2.GaussianBlur(a, (0, 0), 2.0)),
        "veryblurred.jpg": _resave(p[9], out / "veryblurred.jpg", exif=photo_set.exif[9],
                                   transform=lambda a: cv2.GaussianBlur(a, (0, 0), 6.0)),
        "small.jpg": _resave(p[6], out / "small.jpg", exif=photo_set.exif[6],
                             transform=lambda a: cv2.resize(a, (640, 480), interpolation=cv2.INTER_AREA)),
        "othercam.jpg": _resave(p[7], out / "othercam.jpg", exif=PhotoExif(1 / 60, 1.8, 100, "Other", "Cam", 5.1)),
        "noexif.jpg": _resave(p[8], out / "noexif.jpg", exif=None),
        "bent.jpg": _resave(p[10], out / "bent.jpg", exif=photo_set.exif[10], transform=_bend),
        "notaphoto.jpg": out / "notaphoto.jpg",
    }
    made["notaphoto.jpg"].write_bytes(b"this is text")
    made["grazing.jpg"], made["cutoff.jpg"] = rendered.paths
    return good, made


EXPECT = {
    "noboard.jpg": "no board found (no markers detected)", "blurred.jpg": "blurred: edges",
    "veryblurred.jpg": "no board found (no markers detected): the photo is blurred", "small.jpg": "mixed resolutions",
    "othercam.jpg": "another camera", "noexif.jpg": "missing EXIF", "notaphoto.jpg": "expected a JPEG",
    "grazing.jpg": "below 20 deg", "cutoff.jpg": "board cut off", "bent.jpg": "reprojection error",
}


def test_each_bad_photo_gets_its_reason(bad_set, board):
    good, made = bad_set
    paths = [good[0], *made.values(), *good[1:]]
    result = capture_from_photos(paths, board, flash_offset_mm=FLASH, resolution=64)
    rows = {r["file"]: r for r in result.report["photos"]}
    for name, text in EXPECT.items():
        assert not rows[name]["used"] and rows[name]["shot"] is None, name
        assert text in rows[name]["reason"], (name, rows[name]["reason"])
        assert "\n" not in rows[name]["reason"]
    used = [r for r in result.report["photos"] if r["used"]]
    assert [r["file"] for r in used] == [p.name for p in good] and [r["shot"] for r in used] == list(range(len(good)))
    assert result.capture.num_shots == len(good)


def test_too_few_usable_photos_is_one_clear_error(bad_set, board):
    _, made = bad_set
    with pytest.raises(CaptureError, match=r"expected at least 3 usable photos .* found 0 of 3 \(noboard.jpg: no board"):
        capture_from_photos([made["noboard.jpg"], made["notaphoto.jpg"], made["noexif.jpg"]], board, resolution=16)


def test_cli_exit_codes(bad_set, board, tmp_path, capsys):
    from torchmetal.cli import main

    good, made = bad_set
    _, meta = write_board(board, tmp_path / "board")
    out = tmp_path / "cap"
    rc = main(["capture", *map(str, good[:3]), str(made["noexif.jpg"]), "--board", str(meta), "-o", str(out),
               "--resolution", "24", "--flash-offset", *map(str, FLASH)])
    text = capsys.readouterr().out
    assert rc == 0 and "rejected noexif.jpg: missing EXIF" in text
    rep = json.loads((out / "report.json").read_text())
    assert [r["used"] for r in rep["photos"]] == [True, True, True, False]
    rc = main(["capture", str(made["noboard.jpg"]), str(made["small.jpg"]), "--board", str(meta), "-o", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "usable photos" in err
    assert not (tmp_path / "x").exists()
    rc = main(["capture", str(good[0]), "--board", str(tmp_path / "nothing.json"), "-o", str(tmp_path / "y")])
    assert rc == 2 and "board.json" in capsys.readouterr().err


def test_board_verb(tmp_path, capsys):
    from torchmetal.cli import main

    assert main(["board", "-o", str(tmp_path / "b"), "--paper", "letter", "--window", "40", "30", "--dpi", "100"]) == 0
    d = json.loads((tmp_path / "b" / "board.json").read_text())
    assert d["window_mm"][2] - d["window_mm"][0] == pytest.approx(40) and (tmp_path / "b" / "board.png").is_file()
    capsys.readouterr()
    assert main(["board", "-o", str(tmp_path / "c"), "--window", "300", "300"]) == 2
    err = capsys.readouterr().err
    assert "window" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "c").exists()
