"""The white reference: the level of the plain paper band around the window, from its unclipped part.

The band (:data:`~torchmetal.photos.rectify.RING_MM` outside the window) is Lambertian paper lit by
the flash, so once each point's value is divided by the flash's irradiance there (cos / d²) it is
one colour everywhere — except where the photo clipped it (a flash hotspot on glossy paper, an
exposure set for a dark sample), where the clip's unclipped halo is still too bright, and where
ink, the sample or a shadow bleeds in (darker). :func:`white_reference` therefore

1. drops points that are outside the photo or clipped in any channel, and every point within
   :data:`HOTSPOT_GUARD_MM` of a clipped one (the hotspot's halo);
2. splits the band into :data:`SEGMENTS` angular segments around the window and takes in each the
   per-channel median of its brighter half (ink and sample are darker than paper) — a segment
   with too few usable points is left out;
3. leaves out segments whose luminance is an outlier among the segments (an unclipped hotspot, a
   shadow), and returns the per-channel median over the rest.

A photo's band gives no reference when fewer than :data:`MIN_SEGMENTS` segments remain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["WhiteReference", "white_reference", "band_segments", "SEGMENTS", "MIN_SEGMENTS", "HOTSPOT_GUARD_MM"]

SEGMENTS = 16  # angular segments of the band around the window
MIN_SEGMENTS = 2  # fewer usable segments: the band gives no reference
MIN_SEGMENT_POINTS = 8  # a segment needs this many usable points …
MIN_SEGMENT_SHARE = 0.25  # … and this share of its points usable
HOTSPOT_GUARD_MM = 3.0  # points this close to a clipped point are left out (the hotspot's halo)
SEGMENT_TOL = 0.04  # segments within this relative luminance of the median always count …
SEGMENT_MADS = 4.0  # … and beyond it, those within this many robust deviations


@dataclass(frozen=True)
class WhiteReference:
    """The paper band's white level in one photo.

    ``level``: (3,) linear RGB, photo value per unit flash irradiance (intensity 1, cos/d² in m⁻²)
    of the paper, or None when the band gives no reference (``reason`` says why). ``unclipped``:
    the fraction of the band's points (0–1) the level was taken from; ``segments``: how many of
    the :data:`SEGMENTS` segments it used.
    """

    level: np.ndarray | None
    unclipped: float
    segments: int
    reason: str | None = None


def band_segments(xy: np.ndarray, half: tuple[float, float], n: int = SEGMENTS) -> np.ndarray:
    """(k,) int segment index in [0, n) of band points ``xy`` (k, 2) relative to the window centre,
    by their angle in the frame where the window (half sizes ``half``, same units) is a square."""
    ang = np.arctan2(xy[:, 1] / half[1], xy[:, 0] / half[0])
    return np.floor((ang + math.pi) / (2 * math.pi) * n).astype(np.int64) % n


def _near(points: np.ndarray, targets: np.ndarray, radius: float, chunk: int = 2048) -> np.ndarray:
    """(k,) bool: points (k, 2) within ``radius`` of any of ``targets`` (m, 2)."""
    out = np.zeros(len(points), bool)
    if len(targets) == 0:
        return out
    r2 = radius * radius
    for a in range(0, len(points), chunk):
        p = points[a: a + chunk]
        d2 = ((p[:, None, :] - targets[None, :, :]) ** 2).sum(-1)
        out[a: a + chunk] = (d2 <= r2).any(1)
    return out


def white_reference(points: np.ndarray, values: np.ndarray, clipped: np.ndarray, seen: np.ndarray,
                    light: np.ndarray, half: tuple[float, float]) -> WhiteReference:
    """The paper's white level from the band's unclipped part.

    Args:
        points: (k, 3) band points in the capture frame (m, on z = 0, window centre at the origin).
        values: (k, 3) linear RGB photo values there (ignored where not ``seen``).
        clipped: (k,) bool, some channel clipped (255) in the point's footprint.
        seen: (k,) bool, the point lies inside the photo.
        light: (3,) the flash in the capture frame (m).
        half: the window's half sizes (m), x and y.
    """
    points = np.asarray(points, np.float64)
    k = len(points)
    if k == 0:
        return WhiteReference(None, 0.0, 0, "no band points")
    lv = np.asarray(light, np.float64)[None] - points
    d2 = (lv * lv).sum(1)
    irr = np.clip(lv[:, 2], 0, None) / (d2 * np.sqrt(d2))
    bad = clipped & seen
    guard = _near(points[:, :2], points[bad, :2], HOTSPOT_GUARD_MM / 1000.0)
    usable = seen & ~clipped & ~guard & (irr > 0)
    seg = band_segments(points[:, :2], half)
    norm = np.where(usable[:, None], np.asarray(values, np.float64) / np.where(irr > 0, irr, 1.0)[:, None], 0.0)
    levels, counts = [], []
    for s in range(SEGMENTS):
        inside = seg == s
        ok = inside & usable
        m = int(ok.sum())
        if m < MIN_SEGMENT_POINTS or m < MIN_SEGMENT_SHARE * int(inside.sum()):
            continue
        v = norm[ok]
        lum = v.mean(1)  # selecting on one channel would bias it by its own noise
        levels.append(np.median(v[lum >= np.median(lum)], axis=0))
        counts.append(m)
    if levels:
        lev = np.array(levels)
        lum = lev.mean(1)
        med = float(np.median(lum))
        dev = np.abs(lum / med - 1.0) if med > 0 else np.full(len(lum), np.inf)
        mad = 1.4826 * float(np.median(dev))
        keep = dev <= max(SEGMENT_TOL, SEGMENT_MADS * mad)
        lev, used_pts = lev[keep], int(np.array(counts)[keep].sum())
    else:
        lev, used_pts = np.zeros((0, 3)), 0
    frac = used_pts / k
    if len(lev) < MIN_SEGMENTS or not np.all(np.median(lev, 0) > 0):
        share = float((seen & ~clipped).sum()) / k
        return WhiteReference(None, frac, len(lev), f"{len(lev)} of {SEGMENTS} band segments usable (need {MIN_SEGMENTS}), "
                                                    f"{share:.0%} of the band unclipped and in the photo")
    return WhiteReference(np.median(lev, axis=0), frac, len(lev))
