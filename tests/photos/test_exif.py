import numpy as np
from PIL import Image

from torchmetal.photos.exif import PhotoExif, exif_bytes, read_exif


def _jpeg(path, exif: bytes | None):
    im = Image.fromarray(np.zeros((8, 8, 3), np.uint8))
    im.save(path, "JPEG", **({"exif": exif} if exif else {}))


def test_round_trip(tmp_path):
    e = PhotoExif(exposure_time=1 / 60, f_number=1.8, iso=200, make="Acme", model="P1", focal_mm=4.2)
    _jpeg(tmp_path / "a.jpg", exif_bytes(e))
    r = read_exif(tmp_path / "a.jpg")
    assert abs(r.exposure - 1 / 60 * 200 / 1.8**2) < 1e-9
    assert r.camera == "Acme P1 4.2 mm" and r.missing == []


def test_missing_tags(tmp_path):
    _jpeg(tmp_path / "b.jpg", None)
    r = read_exif(tmp_path / "b.jpg")
    assert r.exposure is None and r.missing == ["ExposureTime", "ISOSpeedRatings", "FNumber"]
    (tmp_path / "c.jpg").write_bytes(b"not an image")
    assert read_exif(tmp_path / "c.jpg").exposure is None


def test_zoom_changes_the_camera():
    a = PhotoExif(make="A", model="B", focal_mm=4.2)
    b = PhotoExif(make="A", model="B", focal_mm=4.2, zoom=2.0)
    assert a.camera != b.camera
