"""The contact sheet: every photo as a thumbnail with what the capture made of it.

Per tile: the photo (sensor orientation) with the detected corners (green), the window as the
pose projects it (green: used, red: rejected), the flash's mirror point (yellow cross), the
rectified window in the corner, and below it the file name, used / rejected with the reason,
reprojection error, corners, saturation, elevation, and which reference set the exposure (EXIF or
the white band) and the white balance (the band, or the set's median gains), with the share of the
band that was unclipped. With the capture plan's suggestion (``torchmetal capture`` makes one), a last tile:
where the highlight has not been seen and where to hold the phone next (:func:`plan_tile`). One PNG, the
check to look at after a capture (docs/capture.md).
"""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import numpy as np

from torchmetal.photos.calibrate import project

__all__ = ["contact_sheet", "contact_image", "plan_tile"]

COLUMNS = 4
TEXT_ROWS = 4
ROW_PX = 16


_SOURCE = {"exif": "EXIF", "white_band": "white band", "set_median": "set median"}


def references_line(row: dict) -> str:
    """Which reference set a used photo's exposure and white balance (WB), and how much of the
    paper band was unclipped, e.g. ``exposure EXIF, WB white band, band 90 % unclipped``."""
    band = row.get("white_band_unclipped")
    share = "" if band is None else f", band {100 * band:.0f} % unclipped"
    return (f"exposure {_SOURCE.get(row.get('exposure_source'), '?')}, "
            f"WB {_SOURCE.get(row.get('white_balance_source'), '?')}{share}")


def _text_lines(row: dict) -> list[str]:
    first = f"{row['file']}: " + (f"shot {row['shot']}" if row["used"] else "REJECTED")
    if row["used"]:
        second = (f"reproj {row['reprojection_px']:.2f} px, {row['corners']} corners, sat {row.get('saturated_pct', 0):.1f} %")
        third = f"elev {row.get('elevation_deg', 0):.0f} deg, highlight {row.get('highlight', 'none')}"
        return [first, second, third, references_line(row)]
    lines = textwrap.wrap(row["reason"] or "", 58) + ["", "", ""]
    rest = " ".join(lines[2:]).strip()
    return [first, lines[0], lines[1], rest if len(rest) <= 58 else rest[:55] + "..."]


def _tile(result, i: int, width: int) -> np.ndarray:
    import cv2
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.images import linear_to_srgb

    obs = result.observations[i]
    row = result.report["photos"][i]
    thumb_h = round(width * 3 / 4)
    canvas = np.full((thumb_h + TEXT_ROWS * ROW_PX + 6, width, 3), 255, np.uint8)
    if obs.thumb is not None:
        th, tw = obs.thumb.shape[:2]
        f = min(width / tw, thumb_h / th)
        img = cv2.resize(obs.thumb, (max(1, round(tw * f)), max(1, round(th * f))), interpolation=cv2.INTER_AREA)
        canvas[: img.shape[0], : img.shape[1]] = img
        s = obs.thumb_scale * f
        to_px = lambda p: np.round((p + 0.5) * s - 0.5).astype(np.int32)  # noqa: E731
        if obs.corners is not None:
            for p in to_px(obs.corners):
                cv2.circle(canvas, tuple(int(v) for v in p), 1, (0, 200, 0), -1)
        pose = result.poses.get(i)
        if pose is not None:
            board = result.board
            ww, wh = board.window_size_mm
            cx, cy = board.window_centre_board
            corners = np.array([[cx - ww / 2, cy - wh / 2, 0], [cx + ww / 2, cy - wh / 2, 0],
                                [cx + ww / 2, cy + wh / 2, 0], [cx - ww / 2, cy + wh / 2, 0]])
            poly = to_px(project(corners, *pose, result.intrinsics)).reshape(-1, 1, 2)
            colour = (0, 180, 0) if row["used"] else (0, 0, 230)
            cv2.polylines(canvas, [poly], True, colour, 1, cv2.LINE_AA)
            hl = row.get("highlight_mm")
            if hl is not None:
                p = board.capture_to_board(np.array([[hl[0] / 1000, hl[1] / 1000, 0.0]]))
                q = to_px(project(p, *pose, result.intrinsics))[0]
                if 0 <= q[0] < width and 0 <= q[1] < thumb_h:
                    cv2.drawMarker(canvas, (int(q[0]), int(q[1])), (0, 220, 255), cv2.MARKER_CROSS, 10, 2)
    r = result.rectified.get(i)
    if r is not None:
        side = width // 4
        h, w = r.image.shape[1:]
        f = side / max(h, w)
        # reduced in linear light first (area-correct, and the sRGB curve then runs on ~1/30 of the pixels)
        lin = cv2.resize(np.ascontiguousarray(r.image.transpose(1, 2, 0)), (max(1, round(w * f)), max(1, round(h * f))),
                         interpolation=cv2.INTER_AREA)
        lin = torch.from_numpy(np.clip(lin / max(float(np.percentile(r.image, 99.5)), 1e-6), 0, 1))
        small = (linear_to_srgb(lin).numpy() * 255).round().astype(np.uint8)[:, :, ::-1]
        canvas[2: 2 + small.shape[0], width - 2 - small.shape[1]: width - 2] = small
    for k, line in enumerate(_text_lines(row)):
        colour = (0, 0, 0) if row["used"] or k == 0 else (0, 0, 200)
        cv2.putText(canvas, line, (4, thumb_h + (k + 1) * ROW_PX), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)
    return canvas


def _plan_lines(plan) -> list[str]:
    from torchmetal.plan.run import hand_held

    lines = [f"NEXT PHOTO (plan): highlight seen on {plan.seen():.0%} so far"]
    for k, cam in enumerate(plan.cameras.tolist()[: TEXT_ROWS - 2]):
        lines.append(f"{k + 1}: {hand_held(cam)}")
    lines.append("red: never lit; o past cameras; top view")
    return lines


def plan_tile(result, plan, width: int) -> np.ndarray:
    """The plan's suggestion as one more tile: left, the sample (the photos' mean) with red where no photo put the
    highlight and the planned shots' hotspots numbered; right, a top view of the past cameras (grey) and the
    planned ones (numbered, best first) around the window; below, where to hold the phone."""
    import cv2

    from torchmetal.io.images import linear_to_srgb
    from torchmetal.plan.run import _free_offsets

    thumb_h = round(width * 3 / 4)
    canvas = np.full((thumb_h + TEXT_ROWS * ROW_PX + 6, width, 3), 255, np.uint8)
    cap = result.capture
    side = min(width // 2 - 8, thumb_h - 8)
    img = cap.images.mean(0).clamp_min(0)
    img = (linear_to_srgb((img / max(float(img.quantile(0.995)), 1e-6)).clamp(0, 1)).permute(1, 2, 0).numpy() * 255)
    h, w = img.shape[:2]
    f = side / max(h, w)
    ph, pw = max(1, round(h * f)), max(1, round(w * f))
    panel = cv2.resize(np.ascontiguousarray(img.astype(np.uint8)[:, :, ::-1]), (pw, ph), interpolation=cv2.INTER_AREA)
    never = ~plan.coverage if plan.inside is None else ~plan.coverage & plan.inside
    unseen = cv2.resize(never.numpy().astype(np.uint8), (pw, ph), interpolation=cv2.INTER_NEAREST) > 0
    panel[unseen] = (0.55 * panel[unseen] + 0.45 * np.array([40, 40, 230])).astype(np.uint8)
    colours = [(200, 120, 0), (0, 140, 255), (60, 170, 60), (180, 60, 180)]
    for k, m in enumerate(plan.planned_cover.numpy()):
        if not m.any():
            continue
        mk = cv2.resize(m.astype(np.uint8), (pw, ph), interpolation=cv2.INTER_NEAREST)
        cs, _ = cv2.findContours(mk, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(panel, cs, -1, colours[k % len(colours)], 2)
        yy, xx = np.nonzero(mk)
        cv2.putText(panel, str(k + 1), (int(xx.mean()) - 4, int(yy.mean()) + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (255, 255, 255), 2, cv2.LINE_AA)
    y0 = (thumb_h - ph) // 2
    canvas[y0: y0 + ph, 4: 4 + pw] = panel
    # top view: capture frame x right, y to the sheet's top (up in the tile)
    cams = [c for c in cap.cameras.tolist() if c[3] == 1]
    pts = np.array([c[:2] for c in cams] + [c[:2] for c in plan.cameras.tolist()] + [[cap.size[0] / 2, cap.size[1] / 2]])
    reach = float(np.abs(pts).max()) * 1.15
    x0, tw = width // 2 + 4, width // 2 - 8
    scale = min(tw, thumb_h - 8) / (2 * reach)
    cx, cy = x0 + tw // 2, thumb_h // 2
    to_px = lambda p: (int(round(cx + p[0] * scale)), int(round(cy - p[1] * scale)))  # noqa: E731
    ww, wh = cap.size
    cv2.rectangle(canvas, to_px((-ww / 2, wh / 2)), to_px((ww / 2, -wh / 2)), (0, 0, 0), 1)
    for c in cams:
        cv2.circle(canvas, to_px(c), 3, (150, 150, 150), -1, cv2.LINE_AA)
    qs = [to_px(c) for c in plan.cameras.tolist()]
    for k, q in enumerate(qs):
        cv2.circle(canvas, q, 6, colours[k % len(colours)], -1, cv2.LINE_AA)
    placed = [(q[0] - 6, q[1] - 6, q[0] + 6, q[1] + 6) for q in qs]  # labels clear of every marker and each other
    for k, (dx, dy) in enumerate(_free_offsets([(q[0], q[1]) for q in qs], placed, size=(10.0, 12.0))):
        cv2.putText(canvas, str(k + 1), (qs[k][0] + dx, qs[k][1] + dy + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    colours[k % len(colours)], 1, cv2.LINE_AA)
    for k, line in enumerate(_plan_lines(plan)):
        cv2.putText(canvas, line, (4, thumb_h + (k + 1) * ROW_PX), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def contact_image(result, width: int = 360, plan=None) -> np.ndarray:
    """(H, W, 3) uint8 BGR: the tiles of every photo, COLUMNS per row; with a ``plan``
    (:class:`torchmetal.plan.core.Plan` of ``result.capture``) its suggestion as the last tile."""
    tiles = [_tile(result, i, width) for i in range(len(result.observations))]
    if plan is not None:
        tiles.append(plan_tile(result, plan, width))
    th, tw = tiles[0].shape[:2]
    rows = -(-len(tiles) // COLUMNS)
    cols = min(COLUMNS, len(tiles))
    sheet = np.full((rows * (th + 4), cols * (tw + 4), 3), 230, np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, COLUMNS)
        sheet[r * (th + 4): r * (th + 4) + th, c * (tw + 4): c * (tw + 4) + tw] = t
    return sheet


def contact_sheet(result, path: str | os.PathLike, plan=None) -> Path:
    """Write the contact sheet PNG (atomically); with a ``plan``, its suggestion as the last tile."""
    import cv2

    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.images import atomic_write_bytes

    ok, buf = cv2.imencode(".png", contact_image(result, plan=plan))
    if not ok:
        raise ValueError("contact sheet: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())
    return Path(path)
