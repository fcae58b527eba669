"""Camera intrinsics from the photo set itself, per-photo poses, and where camera and flash were.

Intrinsics: OpenCV's pinhole model with square pixels (fx = fy) and radial distortion k1, k2
(phones correct most of their distortion themselves; tangential terms and k3 would only fit
noise), calibrated from every usable photo's ChArUco corners (Zhang's method,
``cv2.calibrateCamera``). Poses: ``solvePnP`` (IPPE, for planar targets) refined by
Levenberg–Marquardt. Positions are converted from the board frame (mm) into the capture frame
(metres, :meth:`Board.board_to_capture`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchmetal.errors import CaptureError
from torchmetal.photos.board import Board

__all__ = ["Intrinsics", "calibrate", "solve_pose", "camera_position", "flash_position", "project", "FLAGS"]

INTRINSICS_FORMAT = "torchmetal-intrinsics"


def _flags():
    import cv2

    return cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3


FLAGS = "fx = fy, k1 k2 radial (no tangential, no k3)"


@dataclass
class Intrinsics:
    """Pinhole camera: matrix (3, 3), distortion (k1, k2, p1, p2, k3), for ``image_size`` (w, h)."""

    image_size: tuple[int, int]
    matrix: np.ndarray
    distortion: np.ndarray
    rms_px: float | None = None
    source: str = "calibrated"
    camera: str | None = None

    def to_json(self) -> dict:
        k = self.matrix
        return {"format": INTRINSICS_FORMAT, "version": 1, "image_size": list(self.image_size),
                "fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
                "distortion": [float(v) for v in self.distortion], "model": FLAGS, "rms_px": self.rms_px,
                "source": self.source, "camera": self.camera}

    @classmethod
    def from_json(cls, meta: object, label: str) -> "Intrinsics":
        if not isinstance(meta, dict) or meta.get("format") != INTRINSICS_FORMAT:
            found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
            raise CaptureError(f"{label}: expected format {INTRINSICS_FORMAT!r} (a capture's intrinsics.json), found {found!r}")
        try:
            size = tuple(int(v) for v in meta["image_size"])
            fx, fy, cx, cy = (float(meta[k]) for k in ("fx", "fy", "cx", "cy"))
            dist = np.asarray([float(v) for v in meta["distortion"]], np.float64)
        except (KeyError, TypeError, ValueError) as e:
            raise CaptureError(f"{label}: expected image_size, fx, fy, cx, cy and distortion, found a problem with {e}") from None
        if len(size) != 2 or dist.shape != (5,) or not np.isfinite([fx, fy, cx, cy, *dist]).all() or fx <= 0 or fy <= 0:
            raise CaptureError(f"{label}: expected 2 sizes, finite fx, fy > 0 and 5 distortion terms, found {meta!r}"[:200])
        k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
        return cls(size, k, dist, meta.get("rms_px"), f"read from {label}", meta.get("camera"))

    def save(self, path: str | os.PathLike) -> Path:
        # on use: loads torch (this module imports numpy only)
        from torchmetal.io.images import atomic_write_bytes

        atomic_write_bytes(path, (json.dumps(self.to_json(), indent=1) + "\n").encode())
        return Path(path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Intrinsics":
        p = Path(path)
        if not p.is_file():
            raise CaptureError(f"{p}: expected an intrinsics.json (written by `torchmetal capture`), found nothing")
        try:
            meta = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CaptureError(f"{p}: expected valid JSON, found {type(e).__name__}") from None
        return cls.from_json(meta, str(p))


def calibrate(views: list[tuple[np.ndarray, np.ndarray]], image_size: tuple[int, int]) -> tuple[Intrinsics, list]:
    """Intrinsics from planar views: each (object points (K, 3) mm, image points (K, 2) px).

    Returns:
        the intrinsics (``rms_px`` over all corners) and per view (rvec, tvec).
    """
    import cv2

    obj = [o.astype(np.float32).reshape(-1, 1, 3) for o, _ in views]
    img = [p.astype(np.float32).reshape(-1, 1, 2) for _, p in views]
    k0 = np.eye(3)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(image_size), k0, None, flags=_flags(), criteria=crit)
    except cv2.error as e:
        msg = str(e).strip().splitlines()[-1][:120]
        raise CaptureError(f"camera calibration failed: expected views of the board from varied angles, found OpenCV "
                           f"refusing them ({msg}); take photos from more directions or pass --intrinsics") from None
    dist = np.asarray(dist, np.float64).ravel()
    dist = np.concatenate([dist, np.zeros(max(0, 5 - dist.size))])[:5]
    intr = Intrinsics(tuple(image_size), np.asarray(k, np.float64), dist, float(rms))
    return intr, [(np.asarray(r, np.float64).ravel(), np.asarray(t, np.float64).ravel()) for r, t in zip(rvecs, tvecs)]


def project(points: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Board points (n, 3) mm → (n, 2) float64 pixels (with distortion): OpenCV's model
    (``cv2.projectPoints``, slower on large grids: docs/measurements.md), written out column by column."""
    r = _rotation(rvec)
    t = np.asarray(tvec, np.float64).ravel()
    p = np.asarray(points, np.float64).reshape(-1, 3)
    x, y, z = (p[:, 0] * r[k, 0] + p[:, 1] * r[k, 1] + p[:, 2] * r[k, 2] + t[k] for k in range(3))
    x, y = x / z, y / z
    k1, k2, p1, p2, k3 = intr.distortion
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    k = intr.matrix
    return np.stack([k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]], 1)


def solve_pose(obj: np.ndarray, img: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray, float]:
    """Pose of the board in one photo: (rvec, tvec) board → camera (mm), and the RMS reprojection error (px)."""
    import cv2

    o = obj.astype(np.float64).reshape(-1, 1, 3)
    p = img.astype(np.float64).reshape(-1, 1, 2)
    try:
        ok, rvec, tvec = cv2.solvePnP(o, p, intr.matrix, intr.distortion, flags=cv2.SOLVEPNP_IPPE)
        if ok:
            crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            rvec, tvec = cv2.solvePnPRefineLM(o, p, intr.matrix, intr.distortion, rvec, tvec, crit)
    except cv2.error:
        ok = False
    if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        raise CaptureError("no pose fits the corners found (are they all on one line?)")
    rvec, tvec = rvec.ravel(), tvec.ravel()
    err = project(obj, rvec, tvec, intr) - img
    return rvec, tvec, float(np.sqrt((err**2).sum(1).mean()))


def _rotation(rvec: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]


def camera_position(board: Board, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """The camera centre (3,) in the capture frame, metres."""
    r = _rotation(rvec)
    return board.board_to_capture(-r.T @ np.asarray(tvec, np.float64))


def flash_position(board: Board, rvec: np.ndarray, tvec: np.ndarray, offset_mm) -> np.ndarray:
    """The flash (3,) in the capture frame, metres: the camera centre plus ``offset_mm`` in the
    camera frame (OpenCV: x right, y down, z forward)."""
    r = _rotation(rvec)
    centre = -r.T @ np.asarray(tvec, np.float64)
    return board.board_to_capture(centre + r.T @ np.asarray(offset_mm, np.float64))
