"""The window of one photo resampled onto the capture grid (docs/design.md §2.1 pixel geometry), area-correct.

Every capture pixel is a square on the sample plane; it is split into ``ss × ss`` sub-squares
whose centres are projected into the photo through the calibrated camera (pose + lens
distortion — the undistortion and the plane homography in one exact mapping, so the photo is
resampled only once), read bilinearly in *linear* light (sRGB decoded first) and averaged.
``ss`` follows the photo's own sampling: at least one sub-sample per photo pixel the capture
pixel covers, so the average is the photo's area mean over the pixel's footprint.

Beside the image: which channels were clipped (255 anywhere in the footprint), which pixels the
photo saw, and the values of the white paper band just outside the window (the colour and
exposure reference, :mod:`torchmetal.photos.white`), clipped points flagged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchmetal.photos.board import BLANK_MARGIN_MM, Board
from torchmetal.photos.calibrate import Intrinsics, project
from torchmetal.photos.detect import Observation, decode_photo

__all__ = ["Rectified", "window_points", "photo_map", "photo_scale", "rectify", "MAX_SUPERSAMPLE"]

MAX_SUPERSAMPLE = 8
MAP_STEP = 4  # sub-pixels between exactly projected points of the rectification map
RING_MM = (1.0, BLANK_MARGIN_MM - 1.0)  # the paper band (outside the window) used as white reference


@dataclass
class Rectified:
    """One photo on the capture grid: image (3, H, W) float32 linear RGB (photo units),
    saturated (3, H, W) bool, seen (H, W) bool; the paper band's points (n, 3) board mm, their
    linear RGB (n, 3) (0 where unseen), clipped (n,) bool (some channel 255 in the footprint) and
    seen (n,) bool (inside the photo); the photo pixels per capture pixel (worst direction), ``ss``."""

    image: np.ndarray
    saturated: np.ndarray
    seen: np.ndarray
    paper_points: np.ndarray
    paper_values: np.ndarray
    paper_clipped: np.ndarray
    paper_seen: np.ndarray
    px_per_cell: float
    supersample: int


def window_points(board: Board, h: int, w: int, ss: int = 1) -> np.ndarray:
    """Board coordinates (h·ss·w·ss, 3) mm of the sub-pixel centres of the capture grid, row-major
    over the (h·ss, w·ss) grid (docs/design.md §2.1: row 0 is +y, the sheet's top)."""
    ww, wh = board.window_size_mm
    cx, cy = board.window_centre_board
    u = (np.arange(w * ss) + 0.5) / (w * ss)
    v = (np.arange(h * ss) + 0.5) / (h * ss)
    x = (u - 0.5) * ww  # capture x (mm)
    y = (0.5 - v) * wh  # capture y (mm)
    gx, gy = np.meshgrid(cx + x, cy - y)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)


def _plane_points(board: Board, rows: np.ndarray, cols: np.ndarray, h: int, w: int) -> np.ndarray:
    """Board coordinates (len(rows)·len(cols), 3) mm of fractional sub-pixel indices on the
    (h, w) grid (index i ↔ centre (i + 0.5) / h of the window's height, row 0 at the top)."""
    ww, wh = board.window_size_mm
    cx, cy = board.window_centre_board
    gx, gy = np.meshgrid(cx + ((cols + 0.5) / w - 0.5) * ww, cy - (0.5 - (rows + 0.5) / h) * wh)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)


def photo_map(board: Board, pose, intr: Intrinsics, h: int, w: int, ss: int, step: int = MAP_STEP) -> np.ndarray:
    """Photo pixel (n, 2) of every sub-pixel centre of the capture grid, row-major over (h·ss, w·ss).

    Projected exactly on every ``step``-th sub-pixel (and the last) and interpolated bilinearly in
    between: the plane → photo mapping is smooth (perspective + lens), so at a step of a few photo
    pixels the interpolation is off by ~1e-3 px, and it costs ~step² less than projecting all.
    """
    import torch
    import torch.nn.functional as F

    ny, nx = h * ss, w * ss
    my, mx = max(2, -(-(ny - 1) // step) + 1), max(2, -(-(nx - 1) // step) + 1)
    rows = np.linspace(0, ny - 1, my)
    cols = np.linspace(0, nx - 1, mx)
    coarse = project(_plane_points(board, rows, cols, ny, nx), *pose, intr).reshape(my, mx, 2)
    if (my, mx) == (ny, nx):
        return coarse.reshape(-1, 2)
    t = torch.from_numpy(np.ascontiguousarray(coarse.transpose(2, 0, 1)))[None]
    fine = F.interpolate(t, size=(ny, nx), mode="bilinear", align_corners=True)[0]
    return fine.permute(1, 2, 0).reshape(-1, 2).numpy()


def photo_scale(board: Board, pose, intr: Intrinsics, h: int, w: int) -> float:
    """Photo pixels spanned by one capture pixel, in the worst direction (max over the grid)."""
    k = 17
    hh, ww = max(2, min(h, k)), max(2, min(w, k))
    p = project(window_points(board, hh, ww), *pose, intr).reshape(hh, ww, 2)
    dx = np.linalg.norm(np.diff(p, axis=1), axis=2).max() * (ww / w)
    dy = np.linalg.norm(np.diff(p, axis=0), axis=2).max() * (hh / h)
    return float(max(dx, dy))


def _ring_points(board: Board, step: float = 0.5) -> np.ndarray:
    cx, cy = board.window_centre_board
    ww, wh = board.window_size_mm
    a0, a1 = RING_MM
    xs = np.arange(-ww / 2 - a1, ww / 2 + a1 + 1e-9, step)
    ys = np.arange(-wh / 2 - a1, wh / 2 + a1 + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    inner = (np.abs(gx) < ww / 2 + a0) & (np.abs(gy) < wh / 2 + a0)
    gx, gy = gx[~inner], gy[~inner]
    return np.stack([cx + gx, cy - gy, np.zeros(gx.size)], 1)


def _block_mean(a: np.ndarray, ss: int) -> np.ndarray:
    """(h·ss, w·ss[, C]) float32 → (h, w[, C]): the mean of each ss × ss block (OpenCV's integer-factor
    area reduction, faster than numpy's strided mean: docs/measurements.md; equal to it to float32 rounding)."""
    import cv2

    if ss == 1:
        return a
    return cv2.resize(a, (a.shape[1] // ss, a.shape[0] // ss), interpolation=cv2.INTER_AREA)


def _sample(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear lookup (any number of points, reshaped to fit cv2.remap's size limits)."""
    import cv2

    n = mx.size
    cols = 4096
    rows = -(-n // cols)
    pad = rows * cols - n
    fx = np.concatenate([mx.ravel(), np.full(pad, -10.0)]).astype(np.float32).reshape(rows, cols)
    fy = np.concatenate([my.ravel(), np.full(pad, -10.0)]).astype(np.float32).reshape(rows, cols)
    out = cv2.remap(img, fx, fy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * cols, *img.shape[2:])[:n]


def rectify(obs: Observation, board: Board, intr: Intrinsics, pose, h: int, w: int, *, ss: int | None = None) -> Rectified:
    """Resample the window of ``obs`` onto the (h, w) capture grid with camera ``intr`` and ``pose``."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.images import code_table

    scale = photo_scale(board, pose, intr, h, w)
    ss = int(np.clip(np.ceil(scale), 1, MAX_SUPERSAMPLE)) if ss is None else int(ss)
    pts = photo_map(board, pose, intr, h, w, ss)
    ring = _ring_points(board)
    rpx = project(ring, *pose, intr)
    W, H = obs.size
    allpx = np.concatenate([pts, rpx])
    in_img = (allpx[:, 0] >= 0) & (allpx[:, 0] <= W - 1) & (allpx[:, 1] >= 0) & (allpx[:, 1] <= H - 1)
    crop, (x0, y0) = obs.crop, obs.crop_origin
    ch, cw = (0, 0) if crop is None else crop.shape[:2]
    in_crop = (allpx[:, 0] >= x0) & (allpx[:, 0] <= x0 + cw - 1) & (allpx[:, 1] >= y0) & (allpx[:, 1] <= y0 + ch - 1)
    if crop is None or bool((in_img & ~in_crop).any()):  # the crop was too tight: decode again
        crop, (x0, y0) = decode_photo(obs.path), (0, 0)
    lut = code_table(8, True)
    linear = lut[crop]  # (h, w, 3) float32, BGR
    clipped = (crop == 255).astype(np.float32)
    n = len(pts)
    mx, my = allpx[:, 0] - x0, allpx[:, 1] - y0
    vals = _sample(linear, mx, my)
    sats = _sample(clipped, mx, my)
    img = _block_mean(vals[:n].reshape(h * ss, w * ss, 3), ss)
    sat = _block_mean(sats[:n].reshape(h * ss, w * ss, 3), ss) > 0  # bilinear reads of 0/1 are >= 0: mean > 0 iff any
    seen = _block_mean(in_img[:n].reshape(h * ss, w * ss).astype(np.float32), ss) == 1.0
    ring_seen = in_img[n:]
    ring_vals = np.where(ring_seen[:, None], vals[n:][:, ::-1], 0.0).astype(np.float32)
    return Rectified(
        image=np.ascontiguousarray(img[:, :, ::-1].transpose(2, 0, 1)), saturated=np.ascontiguousarray(sat[:, :, ::-1].transpose(2, 0, 1)),
        seen=seen, paper_points=ring, paper_values=ring_vals, paper_clipped=ring_seen & (sats[n:] > 0).any(1),
        paper_seen=ring_seen, px_per_cell=scale, supersample=ss,
    )
