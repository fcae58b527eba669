import json

import numpy as np
import pytest

from torchmetal.errors import CaptureError
from torchmetal.photos import simulate as S
from torchmetal.photos.calibrate import Intrinsics, calibrate, camera_position, flash_position, project, solve_pose
from torchmetal.photos.capture import mirror_point


def test_calibration_recovers_the_camera_from_exact_corners(board):
    cam = S.phone_camera((800, 600))
    poses = S.hand_held_poses(board, 8, seed=4)
    pts = board.corner_points()[board.corner_ids()]
    views = []
    for rvec, tvec in poses:
        px = project(pts, rvec, tvec, cam)
        inside = (px[:, 0] > 0) & (px[:, 0] < 799) & (px[:, 1] > 0) & (px[:, 1] < 599)
        views.append((pts[inside], px[inside]))
    intr, _ = calibrate(views, (800, 600))
    assert np.allclose(intr.matrix, cam.matrix, rtol=1e-6, atol=1e-4) and intr.rms_px < 1e-4
    assert np.allclose(intr.distortion, cam.distortion, atol=1e-6)
    rvec, tvec, rms = solve_pose(*views[0], intr)
    assert rms < 1e-4
    assert np.allclose(camera_position(board, rvec, tvec), camera_position(board, *poses[0]), atol=1e-9)


def test_flash_offset_is_in_the_camera_frame(board):
    rvec, tvec = S.hand_held_poses(board, 1, seed=0, overhead=0)[0]
    c = camera_position(board, rvec, tvec)
    f = flash_position(board, rvec, tvec, (0.0, 0.0, 100.0))  # 100 mm forward, along the view
    view = -c / np.linalg.norm(c)  # the camera looks at (about) the window centre
    assert np.linalg.norm(f - c) == pytest.approx(0.1) and ((f - c) / 0.1) @ view > 0.99


def test_mirror_point_is_where_the_highlight_peaks():
    light, camera = np.array([0.05, -0.02, 0.3]), np.array([-0.04, 0.03, 0.25])
    p = np.array([*mirror_point(light, camera), 0.0])
    to_l, to_c = light - p, camera - p
    to_l, to_c = to_l / np.linalg.norm(to_l), to_c / np.linalg.norm(to_c)
    mirrored = np.array([-to_l[0], -to_l[1], to_l[2]])  # reflect about the normal (0, 0, 1)
    assert np.allclose(mirrored, to_c, atol=1e-12)


def test_intrinsics_file_round_trip_and_errors(tmp_path):
    cam = S.phone_camera((640, 480))
    cam.save(tmp_path / "i.json")
    back = Intrinsics.load(tmp_path / "i.json")
    assert np.allclose(back.matrix, cam.matrix) and np.allclose(back.distortion, cam.distortion)
    assert back.image_size == (640, 480)
    with pytest.raises(CaptureError, match="intrinsics.json"):
        Intrinsics.load(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text(json.dumps({"format": "torchmetal-intrinsics", "fx": 1}))
    with pytest.raises(CaptureError, match="expected image_size"):
        Intrinsics.load(tmp_path / "bad.json")
    (tmp_path / "other.json").write_text(json.dumps({"format": "torchmetal-board"}))
    with pytest.raises(CaptureError, match="torchmetal-intrinsics"):
        Intrinsics.load(tmp_path / "other.json")


def test_degenerate_corners_are_a_one_line_error():
    cam = S.phone_camera((640, 480))
    line = np.stack([np.arange(6.0) * 20, np.zeros(6), np.zeros(6)], 1)
    with pytest.raises(CaptureError, match="no pose"):
        solve_pose(line, np.stack([np.arange(6.0) * 10 + 100, np.full(6, 200.0)], 1), cam)
