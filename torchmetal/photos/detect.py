"""Find the board in one photo: decode, ChArUco corners (sub-pixel), blur, the window's crop.

:func:`inspect_photo` does everything that needs the full-resolution pixels once, so a photo is
decoded a single time: markers are found on a copy reduced to at most :data:`DETECT_SIDE` pixels
(fast; ArUco needs only a few pixels per marker bit), the ChArUco corners are then refined on the
full-resolution image, and the part of the photo around the window (where the sample and the
paper reference are) is kept as a crop for the rectification, next to a thumbnail for the
contact sheet. Pixel coordinates follow OpenCV (pixel centres at integers).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchmetal.photos.board import BLANK_MARGIN_MM, Board
from torchmetal.photos.exif import PhotoExif, read_exif

__all__ = ["Observation", "inspect_photo", "decode_photo", "detect_corners", "edge_width", "MIN_CORNERS"]

DETECT_SIDE = 1600  # markers are searched on a copy at most this long (pixels): >= 3 px per marker bit at 30 cm
MIN_CORNERS = 12  # fewer usable corners: the board is cut off or hidden
THUMB_SIDE = 360
BLURRED_PX = 4.0  # a photo without markers whose sharpest edges are this wide is called blurred
SUBPIX_FRACTION = 0.1  # cornerSubPix half-window over the (foreshortened) square: inside the white margin
CROP_MARGIN_MM = BLANK_MARGIN_MM + 4.0  # kept around the window: sample + paper reference band


@dataclass
class Observation:
    """One photo after :func:`inspect_photo`. ``reason`` is None while the photo is usable."""

    path: Path
    exif: PhotoExif
    size: tuple[int, int] | None = None  # (width, height)
    ids: np.ndarray | None = None  # (K,) ChArUco corner ids
    corners: np.ndarray | None = None  # (K, 2) float64 pixels
    markers: int = 0
    blur_px: float | None = None  # edge width (px) in the blurriest direction
    crop: np.ndarray | None = None  # (h, w, 3) uint8 BGR around the window
    crop_origin: tuple[int, int] = (0, 0)  # (x, y) of the crop's top-left pixel
    thumb: np.ndarray | None = None  # (h, w, 3) uint8 BGR, long side THUMB_SIDE
    thumb_scale: float = 1.0
    reason: str | None = None
    extra: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.path.name


def decode_photo(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 BGR, in the sensor's orientation (EXIF rotation ignored, so every photo of
    one camera shares one set of intrinsics). Raises ValueError with the reason."""
    import cv2

    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION) if data.size else None
    if img is None:
        kind = "HEIC (export as JPEG)" if path.suffix.lower() in (".heic", ".heif") else "undecodable data"
        raise ValueError(f"expected a JPEG/PNG photo, found {kind}")
    if img.dtype != np.uint8:
        raise ValueError(f"expected an 8-bit photo, found {img.dtype}")
    if img.ndim == 2 or img.shape[2] not in (3, 4):
        raise ValueError(f"expected a colour photo, found {1 if img.ndim == 2 else img.shape[2]} channel(s)")
    return img[:, :, :3] if img.shape[2] == 4 else img


def _detector(board: Board):
    import cv2

    cp = cv2.aruco.CharucoParameters()
    dp = cv2.aruco.DetectorParameters()
    return cv2.aruco.CharucoDetector(board.charuco(), cp, dp)


def detect_corners(gray: np.ndarray, board: Board, small: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """ChArUco corners of ``board`` in a full-resolution (H, W) uint8 image (markers searched on
    ``small``, a reduced copy, when given; else on one made here).

    Returns:
        ids (K,) of the usable corners (all four squares printed), corners (K, 2) float64 pixels
        refined with ``cornerSubPix`` at full resolution, marker quads (M of (4, 2)) in pixels.
    """
    import cv2

    h, w = gray.shape
    if small is None:
        small = _reduce(gray)
    fx, fy = w / small.shape[1], h / small.shape[0]
    ch_c, ch_ids, m_c, m_ids = _detector(board).detectBoard(small)
    up = lambda p: np.stack([(p[:, 0] + 0.5) * fx - 0.5, (p[:, 1] + 0.5) * fy - 0.5], 1)  # noqa: E731
    quads = [up(np.asarray(q, np.float64).reshape(4, 2)) for q in (m_c or ())]
    if ch_ids is None or len(ch_ids) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), quads
    ids = np.asarray(ch_ids, np.int64).ravel()
    pts = up(np.asarray(ch_c, np.float64).reshape(-1, 2))
    keep = np.isin(ids, board.corner_ids())
    ids, pts = ids[keep], pts[keep]
    if len(ids) == 0:
        return ids, pts, quads
    # refine at full resolution, with a window a fifth of the local square size
    square_px = _square_px(ids, pts, board)
    half = int(np.clip(round(SUBPIX_FRACTION * square_px), 2, 15))
    p32 = pts.astype(np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 1e-3)
    cv2.cornerSubPix(gray, p32, (half, half), (-1, -1), crit)
    refined = p32.reshape(-1, 2).astype(np.float64)
    moved = np.linalg.norm(refined - pts, axis=1) < max(2.0, 0.5 * half) * max(fx, 1.0)
    return ids[moved], refined[moved], quads


def _reduce(img: np.ndarray) -> np.ndarray:
    """``img`` area-reduced so that its longer side is at most DETECT_SIDE (itself when smaller)."""
    import cv2

    h, w = img.shape[:2]
    f = max(h, w) / DETECT_SIDE
    return img if f <= 1.0 else cv2.resize(img, (round(w / f), round(h / f)), interpolation=cv2.INTER_AREA)


def _square_px(ids: np.ndarray, pts: np.ndarray, board: Board) -> float:
    """The board's squares in pixels, in the more foreshortened direction: the smaller of the median
    image distances between horizontally and vertically adjacent corners."""
    n = board.squares[0] - 1
    pos = {int(i): p for i, p in zip(ids, pts)}
    horiz = [np.linalg.norm(pos[i + 1] - p) for i, p in pos.items() if (i + 1) in pos and (i + 1) % n != 0]
    vert = [np.linalg.norm(pos[i + n] - p) for i, p in pos.items() if (i + n) in pos]
    meds = [float(np.median(d)) for d in (horiz, vert) if d]
    return min(meds) if meds else 20.0


def edge_width(gray: np.ndarray, quads: list[np.ndarray], max_patches: int = 12) -> float | None:
    """Width (px) of the marker edges in the blurriest of 4 directions: contrast / steepest slope.

    A sharp, anti-aliased edge measures about 1–2 px; defocus or shake of σ px widens it to about
    2.5·σ in the direction it acts. Measured on patches around the detected markers, in linear light.
    """
    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.images import code_table

    if not quads:
        return None
    lut = code_table(8, True)
    h, w = gray.shape
    per_dir: list[list[float]] = [[], [], [], []]
    step = max(1, len(quads) // max_patches)
    for q in quads[::step][:max_patches]:
        x0, y0 = np.floor(q.min(0)).astype(int)
        x1, y1 = np.ceil(q.max(0)).astype(int)
        gx, gy = (x1 - x0) // 5 + 2, (y1 - y0) // 5 + 2
        x0, y0, x1, y1 = max(0, x0 - gx), max(0, y0 - gy), min(w, x1 + gx), min(h, y1 + gy)
        if x1 - x0 < 8 or y1 - y0 < 8:
            continue
        p = lut[gray[y0:y1, x0:x1]]
        lo, hi = np.percentile(p, [3, 97])
        contrast = hi - lo
        if contrast <= 0.05:
            continue
        diffs = (p[:, 1:] - p[:, :-1], p[1:, :] - p[:-1, :],
                 (p[1:, 1:] - p[:-1, :-1]) / np.sqrt(2), (p[1:, :-1] - p[:-1, 1:]) / np.sqrt(2))
        for k, d in enumerate(diffs):
            slope = np.percentile(np.abs(d), 99.5)
            per_dir[k].append(contrast / max(slope, 1e-6))
    if not per_dir[0]:
        return None
    return float(max(np.median(v) for v in per_dir))


def _window_polygon(board: Board, grow_mm: float) -> np.ndarray:
    """(4, 2) board-frame corners (mm) of the window grown by ``grow_mm``."""
    cx, cy = board.window_centre_board
    ww, wh = board.window_size_mm
    a, b = ww / 2 + grow_mm, wh / 2 + grow_mm
    return np.array([[cx - a, cy - b], [cx + a, cy - b], [cx + a, cy + b], [cx - a, cy + b]], np.float64)


def inspect_photo(path: str | os.PathLike, board: Board) -> Observation:
    """Decode one photo, find the board, keep what the capture needs; never raises for a bad photo
    (the reason is set instead)."""
    import cv2

    path = Path(path)
    obs = Observation(path=path, exif=read_exif(path))
    try:
        img = decode_photo(path)
    except (ValueError, OSError) as e:
        obs.reason = str(e)
        return obs
    h, w = img.shape[:2]
    obs.size = (w, h)
    small = _reduce(img)  # one pass over the full colour image: detection copy and thumbnail
    f = THUMB_SIDE / max(h, w)
    obs.thumb_scale = f
    obs.thumb = cv2.resize(small, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    ids, pts, quads = detect_corners(gray, board, cv2.cvtColor(small, cv2.COLOR_BGR2GRAY))
    obs.ids, obs.corners, obs.markers = ids, pts, len(quads)
    if not quads:
        h2, w2 = min(h, 1024), min(w, 1024)
        y0, x0 = (h - h2) // 2, (w - w2) // 2
        whole = [np.array([[x0, y0], [x0 + w2, y0], [x0 + w2, y0 + h2], [x0, y0 + h2]], np.float64)]
        width = edge_width(gray, whole)
        blurred = f": the photo is blurred (edges {width:.1f} px wide)" if width is not None and width > BLURRED_PX else ""
        obs.reason = f"no board found (no markers detected){blurred}"
        return obs
    obs.blur_px = edge_width(gray, quads)
    if len(ids) < MIN_CORNERS:
        blurred = (f"; the photo is blurred (edges {obs.blur_px:.1f} px wide)"
                   if obs.blur_px is not None and obs.blur_px > BLURRED_PX else "")
        obs.reason = f"board cut off or hidden: {len(ids)} usable corners found (need {MIN_CORNERS}){blurred}"
        return obs
    # the window's neighbourhood, located by a homography from the corners (no intrinsics yet)
    obj = board.corner_points()[ids][:, :2]
    hom, _ = cv2.findHomography(obj, pts, 0)
    if hom is None:
        obs.reason = "board corners found but degenerate (all on one line?)"
        return obs
    poly = cv2.perspectiveTransform(_window_polygon(board, CROP_MARGIN_MM).reshape(-1, 1, 2), hom).reshape(-1, 2)
    pad = 0.08 * np.ptp(poly, axis=0).max() + 8
    x0, y0 = np.floor(poly.min(0) - pad).astype(int)
    x1, y1 = np.ceil(poly.max(0) + pad).astype(int)
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(w, x1), min(h, y1)
    if x1 - x0 < 4 or y1 - y0 < 4:
        obs.reason = "board cut off: the window is outside the photo"
        return obs
    obs.crop = np.ascontiguousarray(img[y0:y1, x0:x1])
    obs.crop_origin = (int(x0), int(y0))
    return obs
