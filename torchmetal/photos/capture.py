"""Phone photos of a sample in the board's window → a capture directory (docs/design.md §2.1, 2.6).

``capture_from_photos`` runs, in order:

1. per photo (in threads): EXIF, decode, ChArUco corners, edge width, the window's crop
   (:func:`~torchmetal.photos.detect.inspect_photo`);
2. the set's camera: the most common (resolution, camera) wins, the others are rejected;
3. intrinsics calibrated from the usable photos (or given), outliers by reprojection error
   rejected and the calibration redone once without them;
4. per photo: pose, camera and flash positions, elevation, how much of the window it sees and
   how blurred it is at the capture's scale;
5. rectification onto the N-pixel grid; the white reference from the unclipped part of the paper
   band around the window (:mod:`~torchmetal.photos.white`);
6. exposure from EXIF, or else from the band's level; white balance from the band, or else the
   set's median gains (:func:`_exposures`). A photo is rejected for its exposure only when neither
   EXIF nor its band can set it.

Every rejected photo gets a one-line reason in the report; too few usable photos raise a
:class:`~torchmetal.errors.CaptureError` that lists them. Nothing is written until everything
succeeded, and then atomically (:func:`save_photo_capture`).
"""

from __future__ import annotations

import collections
import math
import os
import re
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.errors import CaptureError
from torchmetal.photos.board import Board
from torchmetal.photos.calibrate import Intrinsics, calibrate, camera_position, flash_position, project, solve_pose
from torchmetal.photos.detect import Observation, inspect_photo
from torchmetal.photos.rectify import Rectified, photo_scale, rectify, window_points
from torchmetal.photos.report import contact_sheet as sheet
from torchmetal.photos.white import WhiteReference, white_reference

if TYPE_CHECKING:  # annotations only: a real import would load torch (this module imports numpy only)
    from torchmetal.io.capture import Capture

__all__ = ["PhotoCapture", "capture_from_photos", "save_photo_capture", "MIN_PHOTOS", "MIN_ELEVATION_DEG"]

MIN_PHOTOS = 3
MIN_ELEVATION_DEG = 20.0
MIN_VISIBLE = 0.9  # fraction of the window a photo must see
MAX_BLUR_PX = 4.0  # edge width (photo px) beyond which a photo counts as blurred …
MAX_BLUR_CELLS = 1.5  # … when the blur also spans this many capture pixels
REPROJ_FLOOR_PX = 1.5  # reprojection RMS always tolerated (outliers: above max(this, 3·median))
REPORT_FORMAT = "torchmetal-photo-report"


@dataclass
class PhotoCapture:
    """The capture built from photos, with everything the report and contact sheet show."""

    capture: Capture
    board: Board
    report: dict
    intrinsics: Intrinsics
    observations: list[Observation]
    rectified: dict[int, Rectified] = field(default_factory=dict)  # photo index → rectified
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    whites: dict[int, WhiteReference] = field(default_factory=dict)  # photo index → its band's white level


def _stems(paths: list[Path]) -> list[str]:
    stems = [re.sub(r"[^A-Za-z0-9_.\-]", "_", p.stem) or "photo" for p in paths]
    stems = [s if re.match(r"[A-Za-z0-9_]", s) else "_" + s for s in stems]
    if len(set(stems)) != len(stems):
        stems = [f"{k:03d}_{s}" for k, s in enumerate(stems)]
    return stems


def _camera(o: Observation) -> str | None:
    """The photo's camera and lens, None when its EXIF names no make or model (stripped)."""
    return None if o.exif.make is None and o.exif.model is None else o.exif.camera


def _consistency(obs: list[Observation], ok: list[int], intrinsics: Intrinsics | None) -> None:
    """Reject photos from another camera or with another resolution than the set's (in place).
    A photo whose EXIF names no camera is taken as the set's when its resolution matches."""
    if intrinsics is not None:
        want = tuple(intrinsics.image_size)
        for i in ok:
            if obs[i].size != want:
                obs[i].reason = (f"resolution {obs[i].size[0]}x{obs[i].size[1]}, the intrinsics are for "
                                 f"{want[0]}x{want[1]}")
    ok = [i for i in ok if obs[i].reason is None]
    named = [i for i in ok if _camera(obs[i]) is not None] or ok  # photos without a camera follow the rest
    keys = collections.Counter((obs[i].size, _camera(obs[i])) for i in named)
    if not keys:
        return
    best = max(keys.values())
    (size, cam) = next(k for k in ((obs[i].size, _camera(obs[i])) for i in named) if keys[k] == best)
    for i in ok:
        if obs[i].size != size:
            obs[i].reason = f"mixed resolutions: {obs[i].size[0]}x{obs[i].size[1]}, the set is {size[0]}x{size[1]}"
        elif _camera(obs[i]) is not None and _camera(obs[i]) != cam:
            obs[i].reason = f"another camera or lens: {obs[i].exif.camera!r}, the set is {cam!r}"


def _too_few(obs: list[Observation], used: int, what: str) -> CaptureError:
    reasons = "; ".join(f"{o.name}: {o.reason}" for o in obs if o.reason)[:600]
    return CaptureError(f"expected at least {MIN_PHOTOS} usable photos {what}, found {used} of {len(obs)}"
                        + (f" ({reasons})" if reasons else ""))


def _views(obs: list[Observation], idx: list[int], board: Board) -> list[tuple[np.ndarray, np.ndarray]]:
    pts = board.corner_points()
    return [(pts[obs[i].ids], obs[i].corners) for i in idx]


def _self_calibrate(obs: list[Observation], ok: list[int], board: Board) -> Intrinsics:
    """Calibrate from the usable photos; photos whose reprojection error is an outlier are rejected
    and the calibration redone once without them."""
    if len(ok) < MIN_PHOTOS:
        raise _too_few(obs, len(ok), "to calibrate the camera")
    size = obs[ok[0]].size
    intr, _ = calibrate(_views(obs, ok, board), size)
    rms = {}
    for i in ok:
        try:
            rms[i] = solve_pose(board.corner_points()[obs[i].ids], obs[i].corners, intr)[2]
        except CaptureError as e:
            rms[i] = math.inf
            obs[i].extra["pose_error"] = str(e)
    finite = [v for v in rms.values() if math.isfinite(v)]
    limit = max(REPROJ_FLOOR_PX, 3.0 * float(np.median(finite))) if finite else REPROJ_FLOOR_PX
    bad = [i for i in ok if rms[i] > limit]
    for i in bad:
        obs[i].reason = obs[i].extra.get("pose_error") or (
            f"reprojection error {rms[i]:.2f} px (limit {limit:.2f}): the sheet is not flat, or the photo moved")
    if bad:
        ok = [i for i in ok if i not in bad]
        if len(ok) < MIN_PHOTOS:
            raise _too_few(obs, len(ok), "to calibrate the camera")
        intr, _ = calibrate(_views(obs, ok, board), size)
    w, h = size
    f, cx, cy = intr.matrix[0, 0], intr.matrix[0, 2], intr.matrix[1, 2]
    if not (0.3 * w < f < 5 * w and abs(cx - w / 2) < 0.2 * w and abs(cy - h / 2) < 0.2 * h):
        raise CaptureError(f"camera calibration failed: expected a plausible lens, found f = {f:.0f} px and principal point "
                           f"({cx:.0f}, {cy:.0f}) for {w}x{h} (photos from more varied angles, or --intrinsics FILE)")
    intr.source = f"calibrated from {len(ok)} photos"
    intr.camera = next((_camera(obs[i]) for i in ok if _camera(obs[i]) is not None), obs[ok[0]].exif.camera)
    return intr


def _visible(board: Board, pose, intr: Intrinsics, size: tuple[int, int]) -> float:
    """Fraction of the window (24 x 24 samples) in front of the camera and inside the photo."""
    import cv2

    pts = window_points(board, 24, 24)
    r = cv2.Rodrigues(np.asarray(pose[0], np.float64).reshape(3, 1))[0]
    front = (pts @ r[2] + float(np.ravel(pose[1])[2])) > 0
    p = project(pts, *pose, intr)
    w, h = size
    return float((front & (p[:, 0] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= h - 1)).mean())


def _bar(items, total: int, desc: str, on: bool):
    if not on:
        return items
    from tqdm.auto import tqdm

    return tqdm(items, total=total, desc=desc, unit="photo", leave=False)


def mirror_point(light: np.ndarray, camera: np.ndarray) -> np.ndarray | None:
    """Where the flash's mirror highlight falls on the plane z = 0 (capture frame, same units)."""
    if light[2] <= 0 or camera[2] <= 0:
        return None
    t = light[2] / (light[2] + camera[2])
    mirrored = np.array([camera[0], camera[1], -camera[2]])
    return (light + t * (mirrored - light))[:2]


def _exposures(obs: list[Observation], used: list[int], whites: dict[int, WhiteReference]):
    """Exposure, white balance and the intensity unit of the used photos, and which reference set each.

    Exposure: EXIF (t · ISO / N²) where the photo has it; else the band's green level divided by
    the set's paper level per unit EXIF exposure (the median over photos with both), so both kinds
    share one scale; relative to the first used photo. White balance: the band's gains (green kept),
    else the median gains of the photos with a band. The unit: photo value per unit irradiance of
    the white paper at relative exposure 1 (paper albedo 1), the median over the photos with a band.
    Photos exposed by EXIF alone whose scale no photo with both can relate to the band's get a
    reason (in place); no band in any photo is an error.

    Returns:
        rel {i: float}, gains {i: (3,) float64}, unit float, sources {i: (exposure, white balance)}.
    """
    band = {i: whites[i].level for i in used if whites[i].level is not None}
    exif = {i: obs[i].exif.exposure for i in used if obs[i].exif.exposure is not None}
    if not band:
        raise CaptureError(f"expected the white paper band unclipped in at least one photo, found it clipped or hidden "
                           f"in all {len(used)} usable photos: nothing sets the colours and the intensity unit")
    both = [i for i in band if i in exif]
    if not both:
        for i in used:
            if i not in band:
                obs[i].reason = ("exposure: expected a photo with both EXIF exposure and the white band to relate this "
                                 "photo's EXIF to the others' band, found none")
        used = [i for i in used if i in band]
    per_exif = float(np.median([band[i][1] / exif[i] for i in both])) if both else 1.0
    expo = {i: exif[i] if (both and i in exif) else float(band[i][1]) / per_exif for i in used}
    rel = {i: expo[i] / expo[used[0]] for i in used}
    unit = float(np.median([band[i][1] / rel[i] for i in used if i in band]))
    own = {i: band[i][1] / band[i] for i in used if i in band}
    median_gains = np.median(np.stack(list(own.values())), axis=0)
    gains = {i: own.get(i, median_gains) for i in used}
    sources = {i: ("exif" if both and i in exif else "white_band", "white_band" if i in band else "set_median")
               for i in used}
    return rel, gains, unit, sources


def _check_request(paths: list[Path], resolution: int, flash_offset_mm) -> np.ndarray:
    """The flash offset (3,) in mm, after checking there are photos and the resolution is an integer in [8, 8192]."""
    if not paths:
        raise CaptureError("expected at least one photo, found none")
    if isinstance(resolution, bool) or not isinstance(resolution, int) or not 8 <= resolution <= 8192:
        raise CaptureError(f"resolution: expected an integer in [8, 8192], found {resolution!r}")
    offset = np.asarray(flash_offset_mm, np.float64)
    if offset.shape != (3,) or not np.isfinite(offset).all():
        raise CaptureError(f"flash offset: expected 3 finite numbers (mm), found {list(np.ravel(offset))}")
    return offset


def _locate(o: Observation, e: dict, board: Board, intr: Intrinsics, offset: np.ndarray, given=None):
    """The photo's pose (rvec, tvec) board → camera (``given`` instead of the solved one when not None),
    the flash position and the camera's elevation (degrees); its geometry is noted in the report entry
    ``e``. None when no pose is found (``o.reason`` says why)."""
    obj = board.corner_points()[o.ids]
    try:
        rvec, tvec, rms = solve_pose(obj, o.corners, intr)
    except CaptureError as err:
        o.reason = str(err)
        return None
    if given is not None:
        rvec, tvec = (np.asarray(v, np.float64).ravel() for v in given)
        rms = float(np.sqrt(((project(obj, rvec, tvec, intr) - o.corners) ** 2).sum(1).mean()))
    e["reprojection_px"] = round(rms, 4)
    cam = camera_position(board, rvec, tvec)
    light = flash_position(board, rvec, tvec, offset)
    elev = math.degrees(math.asin(np.clip(cam[2] / np.linalg.norm(cam), -1, 1)))
    e.update(camera_mm=[round(float(v) * 1000, 3) for v in cam], flash_mm=[round(float(v) * 1000, 3) for v in light],
             elevation_deg=round(elev, 2), distance_mm=round(float(np.linalg.norm(cam)) * 1000, 2))
    hl = mirror_point(light, cam)
    if hl is not None:
        ww, wh = board.window_size_mm
        inside = abs(hl[0]) * 1000 < ww / 2 and abs(hl[1]) * 1000 < wh / 2
        e["highlight_mm"] = [round(float(v) * 1000, 2) for v in hl]
        e["highlight"] = "in the window" if inside else "outside the window"
    return (rvec, tvec), light, elev


def _rectify_photo(o: Observation, e: dict, board: Board, intr: Intrinsics, pose, light: np.ndarray, elev: float,
                   grid: tuple[int, int], resolution: int) -> tuple[Rectified | None, WhiteReference | None]:
    """The photo rectified onto the capture ``grid`` (h, w) and its white reference, measurements noted in ``e``.
    The rectified photo is None when the photo is rejected (``o.reason`` says why: too grazing, board cut off,
    blurred, no exposure reference), and so is the white reference unless the photo got that far."""
    if elev < MIN_ELEVATION_DEG:
        o.reason = f"taken from {elev:.0f} deg elevation, below {MIN_ELEVATION_DEG:.0f} deg (too grazing)"
        return None, None
    vis = _visible(board, pose, intr, o.size)
    if vis < MIN_VISIBLE:
        o.reason = f"board cut off: the photo sees {vis:.0%} of the window (need {MIN_VISIBLE:.0%})"
        return None, None
    h, w = grid
    scale = photo_scale(board, pose, intr, h, w)
    e["photo_px_per_cell"] = round(scale, 3)
    if o.blur_px is not None:
        cells = o.blur_px / max(scale, 1e-9)
        e["blur_cells"] = round(cells, 3)
        if o.blur_px > MAX_BLUR_PX and cells > MAX_BLUR_CELLS:
            o.reason = (f"blurred: edges {o.blur_px:.1f} px wide (sharp: ~1-2 px), {cells:.1f} capture pixels at "
                        f"resolution {resolution}")
            return None, None
    r = rectify(o, board, intr, pose, h, w)
    ww, wh = board.window_size_mm
    white = white_reference(board.board_to_capture(r.paper_points), r.paper_values, r.paper_clipped,
                            r.paper_seen, light, (ww / 2000.0, wh / 2000.0))
    e["white_band_unclipped"] = round(white.unclipped, 4)
    if white.level is None and o.exif.exposure is None:
        o.reason = (f"no exposure reference: expected EXIF {', '.join(o.exif.missing)} or the white paper band "
                    f"around the window, found neither ({white.reason})")
        return None, white
    return r, white


def _rectify_all(obs: list[Observation], ok: list[int], entries: dict[int, dict], board: Board, intr: Intrinsics,
                 offset: np.ndarray, poses: dict | None, resolution: int, progress: bool):
    """Pose, checks, rectification and white reference of the photos ``ok`` (:func:`_locate`,
    :func:`_rectify_photo`). Returns {i: pose} of the located photos, {i: Rectified} and {i: WhiteReference}
    of those not rejected before rectification (the rectified ones only for photos still usable)."""
    grid = board.capture_grid(resolution)
    found_poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    rect: dict[int, Rectified] = {}
    whites: dict[int, WhiteReference] = {}
    for i in _bar(ok, len(ok), "rectify", progress):
        located = _locate(obs[i], entries[i], board, intr, offset, poses[i] if poses is not None and i in poses else None)
        if located is None:
            continue
        found_poses[i], light, elev = located
        r, white = _rectify_photo(obs[i], entries[i], board, intr, found_poses[i], light, elev, grid, resolution)
        if white is not None:
            whites[i] = white
        if r is not None:
            rect[i] = r
    return found_poses, rect, whites


def _to_capture(used: list[int], rect: dict[int, Rectified], poses: dict, gains: dict, rel: dict, unit: float,
                board: Board, offset: np.ndarray, stems: list[str]) -> Capture:
    """The Capture of the used photos: their rectified images white-balanced (in place), the mask where every
    one saw the sample, flash and camera positions, intensities ``unit`` × relative exposure."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.capture import Capture

    lights, cams = {}, {}
    for i in used:
        r, (rvec, tvec) = rect[i], poses[i]
        r.image *= gains[i][:, None, None].astype(np.float32)
        lights[i], cams[i] = flash_position(board, rvec, tvec, offset), camera_position(board, rvec, tvec)
    ww, wh = board.window_size_mm
    return Capture(
        images=torch.from_numpy(np.stack([rect[i].image for i in used])),
        mask=torch.from_numpy(np.stack([rect[i].seen for i in used]).all(0))[None],
        saturated=torch.from_numpy(np.stack([rect[i].saturated for i in used])),
        lights=torch.tensor([[*lights[i], 1.0] for i in used], dtype=torch.float64).float(),
        intensities=torch.tensor([[unit * rel[i]] * 3 for i in used], dtype=torch.float64).float(),
        cameras=torch.tensor([[*cams[i], 1.0] for i in used], dtype=torch.float64).float(),
        size=(ww / 1000.0, wh / 1000.0), names=[f"images/{s}.npy" for s in stems], color_space="srgb",
    )


def _photo_rows(obs: list[Observation], entries: dict[int, dict], used: list[int], rect: dict[int, Rectified],
                rel: dict) -> list[dict]:
    """``report.json``'s ``photos``: per photo, its shot or why it was not used, and what was measured."""
    shot_of = {i: k for k, i in enumerate(used)}
    rows = []
    for i, o in enumerate(obs):
        e = entries[i]
        row = {"file": o.name, "used": i in shot_of, "shot": shot_of.get(i), "reason": o.reason,
               "reprojection_px": e.pop("reprojection_px", None), "corners": 0 if o.ids is None else int(len(o.ids)),
               "markers": o.markers, "blur_px": None if o.blur_px is None else round(o.blur_px, 3)}
        if i in shot_of:
            sat = rect[i].saturated.any(0)
            row["saturated_pct"] = round(100.0 * float(sat.mean()), 3)
            row["exposure"] = round(rel[i], 6)
        row.update(e)
        rows.append(row)
    return rows


def capture_from_photos(
    photos, board: Board, *, flash_offset_mm=(0.0, 0.0, 0.0), intrinsics: Intrinsics | None = None,
    resolution: int = 512, poses: dict | None = None, workers: int | None = None, progress: bool = False,
) -> PhotoCapture:
    """Build a capture from phone photos of the board (docs/design.md §2.6).

    Args:
        photos: image paths (JPEG/PNG, 8-bit), in shot order.
        board: the printed board's geometry (:func:`~torchmetal.photos.board.load_board`).
        flash_offset_mm: the flash in the camera frame (OpenCV: x right, y down, z forward), mm.
        intrinsics: use these instead of calibrating from the photos.
        resolution: N, the capture's longer side in pixels (square pixels).
        poses: {photo index: (rvec, tvec)} board → camera (mm) to use instead of the estimated
            ones (for checks against known geometry).
        workers: threads for decoding and detection (default: up to 4).
        progress: show tqdm bars (detection, rectification).

    Raises:
        CaptureError: fewer than MIN_PHOTOS usable photos, or a failed calibration.
    """
    t0 = time.perf_counter()
    paths = [Path(p) for p in photos]
    offset = _check_request(paths, resolution, flash_offset_mm)
    workers = workers or max(1, min(4, os.cpu_count() or 1))
    with ThreadPoolExecutor(workers) as pool:
        obs = list(_bar(pool.map(lambda p: inspect_photo(p, board), paths), len(paths), "detect", progress))
    stages = {"inspect": time.perf_counter() - t0}
    ok = [i for i, o in enumerate(obs) if o.reason is None]
    _consistency(obs, ok, intrinsics)
    ok = [i for i in ok if obs[i].reason is None]
    intr = intrinsics if intrinsics is not None else _self_calibrate(obs, ok, board)
    ok = [i for i in ok if obs[i].reason is None]
    stages["calibrate"] = time.perf_counter() - t0 - sum(stages.values())

    h, w = board.capture_grid(resolution)
    entries: dict[int, dict] = {i: {} for i in range(len(obs))}
    found_poses, rect, whites = _rectify_all(obs, ok, entries, board, intr, offset, poses, resolution, progress)
    used = [i for i in ok if obs[i].reason is None]
    if len(used) >= MIN_PHOTOS:
        rel, gains, unit, sources = _exposures(obs, used, whites)
        used = [i for i in used if obs[i].reason is None]
    if len(used) < MIN_PHOTOS:
        raise _too_few(obs, len(used), "for a capture")
    stages["poses_rectify"] = time.perf_counter() - t0 - sum(stages.values())

    for i in used:
        entries[i]["white_balance"] = [round(float(g), 4) for g in gains[i]]
        entries[i]["exposure_source"], entries[i]["white_balance_source"] = sources[i]
    capture = _to_capture(used, rect, found_poses, gains, rel, unit, board, offset, _stems([paths[i] for i in used]))
    ww, wh = board.window_size_mm
    n = len(used)
    report = {
        "format": REPORT_FORMAT, "version": 1, "photos": _photo_rows(obs, entries, used, rect, rel),
        "intrinsics": intr.to_json(), "board": board.to_json(), "resolution": [h, w], "surface_m": [ww / 1000.0, wh / 1000.0],
        "flash_offset_mm": [float(v) for v in offset], "intensity_unit": unit,
        "used": n, "rejected": len(obs) - n, "seconds": round(time.perf_counter() - t0, 3),
        "stage_seconds": {k: round(v, 3) for k, v in stages.items()},
        "mask_pct": round(100.0 * float(capture.mask.float().mean()), 3),
    }
    return PhotoCapture(capture, board, report, intr, obs, {i: rect[i] for i in used}, found_poses, whites)


def save_photo_capture(result: PhotoCapture, out: str | os.PathLike, *, contact_sheet: bool = True, plan=None) -> Path:
    """Write the capture directory plus ``report.json``, ``intrinsics.json`` and ``contact.png``, atomically; with a
    ``plan`` (:func:`torchmetal.plan.run.plan_capture` of ``result.capture``) the contact sheet shows it."""
    import json
    import shutil

    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.capture_save import prepare_target, replace_dir, write_capture_files

    path, tmp = prepare_target(out)
    try:
        write_capture_files(result.capture, tmp, bits="npy")
        result.intrinsics.save(tmp / "intrinsics.json")
        if contact_sheet:
            sheet(result, tmp / "contact.png", plan=plan)
        (tmp / "report.json").write_text(json.dumps(result.report, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path
