"""What the phone-photo capture must show, on generated phone photos: intrinsics, camera positions, rectified
images against the direct renders, the report, the capture directory."""

import json

import numpy as np
import pytest
import torch

from torchmetal.io.capture import load_capture
from torchmetal.metrics import psnr
from torchmetal.photos.capture import save_photo_capture
from torchmetal.photos.simulate import direct_render

from .conftest import FLASH, SHOTS, N


def inner_mask(board, h, w, inset_mm=1.0):
    """(H, W) bool: capture pixels whose whole square lies at least ``inset_mm`` inside the window."""
    ww, wh = board.window_size_mm
    j, i = np.arange(w), np.arange(h)
    okx = (j * ww / w >= inset_mm) & ((j + 1) * ww / w <= ww - inset_mm)
    oky = (i * wh / h >= inset_mm) & ((i + 1) * wh / h <= wh - inset_mm)
    return torch.from_numpy(oky[:, None] & okx[None, :])


def test_intrinsics_within_one_percent(captured, photo_set):
    k, kt = captured.intrinsics.matrix, photo_set.intrinsics.matrix
    w, h = photo_set.intrinsics.image_size
    assert abs(k[0, 0] / kt[0, 0] - 1) < 0.01 and abs(k[1, 1] / kt[1, 1] - 1) < 0.01
    assert abs(k[0, 2] - kt[0, 2]) < 0.01 * w and abs(k[1, 2] - kt[1, 2]) < 0.01 * h
    # the distortion as it acts: where the image corners land, within 1 % of the corner radius
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64)
    import cv2

    moved = [cv2.undistortPoints(corners.reshape(-1, 1, 2), i.matrix, i.distortion).reshape(-1, 2)
             for i in (captured.intrinsics, photo_set.intrinsics)]
    radius = np.linalg.norm(moved[1], axis=1)
    assert (np.linalg.norm(moved[0] - moved[1], axis=1) / radius).max() < 0.01


def test_camera_and_flash_positions_within_a_millimetre(captured, photo_set):
    cap = captured.capture
    assert cap.num_shots == SHOTS
    cams = cap.cameras[:, :3].double().numpy()
    lights = cap.lights[:, :3].double().numpy()
    assert (cap.cameras[:, 3] == 1).all() and (cap.lights[:, 3] == 1).all()
    assert np.linalg.norm(cams - photo_set.cameras, axis=1).max() < 1e-3
    assert np.linalg.norm(lights - photo_set.lights, axis=1).max() < 1e-3
    dist = np.linalg.norm(photo_set.cameras, axis=1)
    assert dist.min() > 0.25 and dist.max() < 0.35


def test_rectified_images_match_the_direct_renders(captured, photo_set):
    cap = captured.capture
    ref = direct_render(photo_set)
    mask = inner_mask(photo_set.board, N, N)[None].expand(3, -1, -1)
    worst = min(psnr(cap.images[k], ref[k], mask=mask) for k in range(SHOTS))
    assert worst >= 35.0
    # the edge itself mixes in paper: the full window is measurably worse than its inside
    assert psnr(cap.images, ref) < min(psnr(cap.images[k], ref[k], mask=mask) for k in range(SHOTS))


def test_some_highlights_land_in_the_window(captured):
    rows = captured.report["photos"]
    assert sum(r["highlight"] == "in the window" for r in rows) >= 2
    assert all(25 - 2.5 <= r["elevation_deg"] <= 90 for r in rows)


def test_exposure_and_white_balance(captured, photo_set):
    cap = captured.capture
    e = np.array([x.exposure for x in photo_set.exif])
    rel = cap.intensities[:, 0].double().numpy()
    assert np.allclose(rel / rel[0], e / e[0], rtol=1e-6)  # light_intensity follows EXIF exactly
    assert (cap.intensities[:, 0] == cap.intensities[:, 1]).all()
    # the unit is the same for every shot: photo units per unit intensity are off by one global factor
    ratio = photo_set.intensity / rel
    assert ratio.std() / ratio.mean() < 1e-6
    # white balance: the paper-based gains undo every photo's tint, and the sample's colours come out neutral
    gains = np.array([r["white_balance"] for r in captured.report["photos"]])
    undone = gains * photo_set.tints
    assert np.abs(undone / undone[:, 1:2] - 1).max() < 0.01
    ref = direct_render(photo_set)
    mask = inner_mask(photo_set.board, N, N)
    for k in range(SHOTS):
        got = cap.images[k][:, mask].mean(1) / ref[k][:, mask].mean(1)
        assert (got / got[1] - 1).abs().max() < 0.015


def test_report_and_directory(captured, photo_set, tmp_path):
    out = save_photo_capture(captured, tmp_path / "cap")
    rep = json.loads((out / "report.json").read_text())
    assert [r["file"] for r in rep["photos"]] == [p.name for p in photo_set.paths]
    for k, r in enumerate(rep["photos"]):
        assert r["used"] and r["shot"] == k and r["reason"] is None
        assert 0 < r["reprojection_px"] < 1.0 and r["corners"] >= 40
        assert r["saturated_pct"] >= 0 and "highlight" in r
    assert rep["intrinsics"]["fx"] == pytest.approx(captured.intrinsics.matrix[0, 0])
    meta = json.loads((out / "capture.json").read_text())
    assert [p.stem in s["image"] for p, s in zip(photo_set.paths, meta["shots"])] == [True] * SHOTS
    assert meta["surface"] == {"width": 0.05, "height": 0.05}
    cap = load_capture(out)
    assert torch.equal(cap.images, captured.capture.images) and cap.mask.all()
    assert (out / "contact.png").stat().st_size > 10_000 and (out / "intrinsics.json").is_file()
    # the saved intrinsics are reusable: the same poses come back
    from torchmetal.photos.calibrate import Intrinsics
    from torchmetal.photos.capture import capture_from_photos

    again = capture_from_photos(photo_set.paths[:4], photo_set.board, flash_offset_mm=FLASH, resolution=N,
                                intrinsics=Intrinsics.load(out / "intrinsics.json"))
    assert torch.allclose(again.capture.cameras, captured.capture.cameras[:4], atol=1e-6)
    assert again.report["intrinsics"]["source"].startswith("read from")


def test_true_pose_capture_is_the_truth_geometry(captured_true, photo_set):
    cams = captured_true.capture.cameras[:, :3].double().numpy()
    assert np.abs(cams - photo_set.cameras).max() < 1e-6
