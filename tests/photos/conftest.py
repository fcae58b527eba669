"""Generated phone photos shared by the photos tests (made once per session, small and quick)."""

import math

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from torchmetal.photos import simulate as S
from torchmetal.photos.board import make_board, render_sheet
from torchmetal.photos.exif import PhotoExif, exif_bytes

N = 64  # capture resolution = the texture's grid
FLASH = (12.0, -4.0, 0.0)  # mm, camera frame
SHOTS = 12


@pytest.fixture(scope="session")
def board():
    return make_board("a4", (50.0, 50.0), dpi=150)


@pytest.fixture(scope="session")
def sheet(board):
    return render_sheet(board)


@pytest.fixture(scope="session")
def sample():
    return S.Sample(S.smooth_texture(N, N, seed=3), torch.tensor([0.45, 0.5, 0.55]), torch.tensor([50.0, 60.0, 70.0]))


@pytest.fixture(scope="session")
def photo_set(tmp_path_factory, board, sheet, sample):
    """12 photos, 800x600, poses 25-70 deg plus 3 near-overhead, flash 12 mm off the lens, JPEG q92, 1 % noise."""
    out = tmp_path_factory.mktemp("photos")
    return S.phone_photos(out, board, sample, n=SHOTS, seed=0, flash_offset_mm=FLASH, sheet=sheet, supersample=1)


@pytest.fixture(scope="session")
def captured(photo_set):
    from torchmetal.photos.capture import capture_from_photos

    return capture_from_photos(photo_set.paths, photo_set.board, flash_offset_mm=FLASH, resolution=N)


@pytest.fixture(scope="session")
def captured_true(photo_set):
    """The same photos rectified with the true intrinsics and poses."""
    from torchmetal.photos.capture import capture_from_photos

    poses = dict(enumerate(photo_set.poses))
    return capture_from_photos(photo_set.paths, photo_set.board, flash_offset_mm=FLASH, resolution=N,
                               intrinsics=photo_set.intrinsics, poses=poses)


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
                                                         _pose(board, 55, 30, 0.3, [0.14, 0, 0]),  # window half out
                                                         _pose(board, 55, 30, 0.3, [0.12, 0, 0])],  # ~4 % out
                              flash_offset_mm=FLASH, sheet=sheet, supersample=1,
                              names=["grazing.jpg", "cutoff.jpg", "partial.jpg"])
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
    made["grazing.jpg"], made["cutoff.jpg"], made["partial.jpg"] = rendered.paths
    return good, made
