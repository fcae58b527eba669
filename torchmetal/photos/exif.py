"""EXIF of phone photos: exposure (time × ISO / f-number²) and which camera took them (Pillow).

Only the header is read, never the pixels. :func:`exif_bytes` writes the same tags (for the
generated test photos).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["PhotoExif", "read_exif", "exif_bytes"]

_IFD_EXIF = 0x8769
_MAKE, _MODEL = 0x010F, 0x0110
_EXPOSURE_TIME, _F_NUMBER, _ISO, _FOCAL, _ZOOM = 0x829A, 0x829D, 0x8827, 0x920A, 0xA404


def _number(v: object) -> float | None:
    if isinstance(v, (tuple, list)):
        v = v[0] if v else None
    try:
        x = float(v)  # type: ignore[arg-type]  (IFDRational, int, float)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) and x > 0 else None


def _text(v: object) -> str | None:
    if isinstance(v, bytes):
        v = v.decode("utf-8", "replace")
    return v.strip("\x00 ").strip() or None if isinstance(v, str) else None


@dataclass(frozen=True)
class PhotoExif:
    """What the capture needs from a photo's EXIF (None where the tag is missing)."""

    exposure_time: float | None = None  # seconds
    f_number: float | None = None
    iso: float | None = None
    make: str | None = None
    model: str | None = None
    focal_mm: float | None = None
    zoom: float | None = None

    @property
    def exposure(self) -> float | None:
        """Relative exposure t · ISO / N² (None without all three tags)."""
        if self.exposure_time is None or self.f_number is None or self.iso is None:
            return None
        return self.exposure_time * self.iso / self.f_number**2

    @property
    def missing(self) -> list[str]:
        names = {"ExposureTime": self.exposure_time, "ISOSpeedRatings": self.iso, "FNumber": self.f_number}
        return [k for k, v in names.items() if v is None]

    @property
    def camera(self) -> str:
        """Which camera and lens: make, model, focal length and digital zoom (what fixes the intrinsics)."""
        parts = [self.make or "?", self.model or "?"]
        if self.focal_mm is not None:
            parts.append(f"{self.focal_mm:.3g} mm")
        if self.zoom is not None and abs(self.zoom - 1.0) > 1e-3:
            parts.append(f"zoom {self.zoom:.3g}")
        return " ".join(parts)

    def to_json(self) -> dict:
        return {"exposure_time": self.exposure_time, "f_number": self.f_number, "iso": self.iso,
                "camera": self.camera, "exposure": self.exposure}


def read_exif(path: str | os.PathLike) -> PhotoExif:
    """The EXIF tags of an image file; an unreadable header gives an empty :class:`PhotoExif`."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(Path(path)) as im:
            top = im.getexif()
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return PhotoExif()
    sub = top.get_ifd(_IFD_EXIF) if _IFD_EXIF in top else {}

    def tag(key: int):
        return sub.get(key, top.get(key))

    return PhotoExif(
        exposure_time=_number(tag(_EXPOSURE_TIME)), f_number=_number(tag(_F_NUMBER)), iso=_number(tag(_ISO)),
        make=_text(top.get(_MAKE)), model=_text(top.get(_MODEL)), focal_mm=_number(tag(_FOCAL)),
        zoom=_number(tag(_ZOOM)),
    )


def exif_bytes(exif: PhotoExif) -> bytes:
    """An EXIF block with ``exif``'s tags (those that are not None), for ``Image.save(exif=…)``."""
    from PIL import Image

    e = Image.Exif()
    if exif.make:
        e[_MAKE] = exif.make
    if exif.model:
        e[_MODEL] = exif.model
    ifd = e.get_ifd(_IFD_EXIF)
    for key, value in ((_EXPOSURE_TIME, exif.exposure_time), (_F_NUMBER, exif.f_number), (_ISO, exif.iso),
                       (_FOCAL, exif.focal_mm), (_ZOOM, exif.zoom)):
        if value is not None:
            ifd[key] = int(value) if key == _ISO else float(value)
    return e.tobytes()
