"""Each bad photo gets its one-line reason, the good ones still make a capture; an unusable set is
a clear error (CaptureError; the CLI exits 2 with one line). A photo without EXIF is not bad: its
white band sets its exposure."""

import pytest

from torchmetal.errors import CaptureError
from torchmetal.photos.capture import capture_from_photos

from .conftest import FLASH

EXPECT = {
    "noboard.jpg": "no board found (no markers detected)", "blurred.jpg": "blurred: edges",
    "veryblurred.jpg": "no board found (no markers detected): the photo is blurred", "small.jpg": "mixed resolutions",
    "othercam.jpg": "another camera", "notaphoto.jpg": "expected a JPEG",
    "grazing.jpg": "below 20 deg", "cutoff.jpg": "board cut off", "bent.jpg": "reprojection error",
}


def test_each_bad_photo_gets_its_reason(bad_set, board):
    good, made = bad_set
    bad = {k: v for k, v in made.items() if k not in ("partial.jpg", "noexif.jpg")}
    paths = [good[0], *bad.values(), *good[1:], made["noexif.jpg"], made["partial.jpg"]]  # partial: sees ~96 %
    result = capture_from_photos(paths, board, flash_offset_mm=FLASH, resolution=64)
    rows = {r["file"]: r for r in result.report["photos"]}
    for name, text in EXPECT.items():
        assert not rows[name]["used"] and rows[name]["shot"] is None, name
        assert text in rows[name]["reason"], (name, rows[name]["reason"])
        assert "\n" not in rows[name]["reason"]
    used = [r for r in result.report["photos"] if r["used"]]
    names = [p.name for p in good] + ["noexif.jpg", "partial.jpg"]
    assert [r["file"] for r in used] == names and [r["shot"] for r in used] == list(range(len(names)))
    assert result.capture.num_shots == len(names)
    assert rows["noexif.jpg"]["exposure_source"] == "white_band" and rows[good[0].name]["exposure_source"] == "exif"
    seen = result.capture.mask.float().mean()
    assert 0.85 < seen < 0.995  # the mask keeps the pixels every photo saw
    assert result.report["mask_pct"] == pytest.approx(100 * float(seen), abs=1e-3)


def test_too_few_usable_photos_is_one_clear_error(bad_set, board):
    _, made = bad_set
    with pytest.raises(CaptureError, match=r"expected at least 3 usable photos .* found 1 of 3 \(noboard.jpg: no board"):
        capture_from_photos([made["noboard.jpg"], made["notaphoto.jpg"], made["noexif.jpg"]], board, resolution=16)


def test_intrinsics_for_another_resolution(photo_set, board):
    from torchmetal.photos.simulate import phone_camera

    with pytest.raises(CaptureError, match=r"found 0 of 3 \(IMG_0001.jpg: resolution 800x600, the intrinsics are for 640x480"):
        capture_from_photos(photo_set.paths[:3], board, intrinsics=phone_camera((640, 480)), resolution=16)
