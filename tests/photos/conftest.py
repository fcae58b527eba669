"""Generated phone photos shared by the photos tests (made once per session, small and quick)."""

import pytest
import torch

from torchmetal.photos import simulate as S
from torchmetal.photos.board import make_board, render_sheet

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
