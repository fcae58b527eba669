"""Writing a capture directory (docs/design.md §2.1): :func:`save_capture`, atomically (written under a
temporary sibling name and renamed into place: an interrupted save never leaves a half-written
capture), and its parts
(:func:`write_capture_files`, :func:`prepare_target`, :func:`replace_dir`) for writers that add
files of their own (the tiled capture, the phone-photo capture, material directories)."""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from pathlib import Path, PurePosixPath

import numpy as np
from torch import Tensor

__all__ = ["save_capture", "write_capture_files", "prepare_target", "replace_dir"]

from torchmetal.errors import CaptureError
from torchmetal.io.capture import COLOR_SPACES, FORMAT, VERSION, Capture
from torchmetal.io.images import PNG_MAX, _cv2, encode_image, linear_to_srgb, quantize

_SAFE_STEM = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")  # image stems kept as they are


def _file_names(names: list[str], suffix: str) -> list[str]:
    """images/<stem><suffix>, keeping the source stems when they are safe and unique."""
    stems = [PurePosixPath(str(nm).replace("\\", "/")).stem for nm in names]
    if len(set(stems)) != len(stems) or not all(_SAFE_STEM.match(s) for s in stems):
        stems = [f"{k:03d}" for k in range(len(names))]
    return [f"images/{s}{suffix}" for s in stems]


def _hwc(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().permute(1, 2, 0).numpy())


def _row(t: Tensor) -> list[float]:
    return [float(v) for v in t.detach().cpu().tolist()]


def write_capture_files(
    capture: Capture, root: str | os.PathLike, *, bits: int | str = "npy", color_space: str | None = None
) -> dict:
    """Write the files of ``capture`` into the existing, empty directory ``root`` (not atomic:
    :func:`save_capture` wraps it). Returns the capture.json dictionary written."""
    if bits not in (8, 16, "npy"):
        raise CaptureError(f"bits: expected 8, 16 or 'npy', found {bits!r}")
    cs = color_space or ("linear" if bits == "npy" else capture.color_space)
    if cs not in COLOR_SPACES:
        raise CaptureError(f"color_space: expected one of {list(COLOR_SPACES)}, found {cs!r}")
    capture.validate()
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    suffix = ".npy" if bits == "npy" else ".png"
    names = _file_names(capture.names, suffix)
    need_sat_file = False
    for k, name in enumerate(names):
        img = capture.images[k].detach().cpu().double()  # one shot at a time, encoded in float64
        if cs == "srgb":
            img = linear_to_srgb(img)
        arr = _hwc(img)
        (root / name).write_bytes(encode_image(arr, suffix, 8 if bits == "npy" else int(bits)))
        sat = _hwc(capture.saturated[k])
        if bits == "npy":
            need_sat_file |= bool(sat.any())
        else:
            need_sat_file |= bool((sat & (quantize(arr, int(bits)) != PNG_MAX[int(bits)])).any())
    meta: dict = {
        "format": FORMAT,
        "version": VERSION,
        "color_space": cs,
        "surface": {"width": float(capture.size[0]), "height": float(capture.size[1])},
    }
    if capture.normals_given or not capture.flat:  # a given map is kept, flat or not
        np.save(root / "normals.npy", _hwc(capture.normals.float()), allow_pickle=False)
        meta["normals"] = "normals.npy"
    if not bool(capture.mask.all()):
        m = capture.mask[0].detach().cpu().numpy().astype(np.uint8) * 255
        ok, buf = _cv2().imencode(".png", m)
        if not ok:
            raise CaptureError(f"mask: expected a PNG-encodable mask, found shape {m.shape}")
        (root / "mask.png").write_bytes(buf.tobytes())
        meta["mask"] = "mask.png"
    if need_sat_file:
        np.save(root / "saturated.npy", capture.saturated.detach().cpu().permute(0, 2, 3, 1).numpy(), allow_pickle=False)
        meta["saturated"] = "saturated.npy"
    meta["shots"] = [
        {"image": name, "light": _row(capture.lights[k]), "light_intensity": _row(capture.intensities[k]),
         "camera": _row(capture.cameras[k])}
        for k, name in enumerate(names)
    ]
    (root / "capture.json").write_text(json.dumps(meta, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return meta


def replace_dir(tmp: Path, path: Path) -> None:
    """Move the finished directory ``tmp`` to ``path``; an existing capture there is swapped out."""
    if path.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old.", dir=path.parent))
        os.replace(path, old / path.name)
        try:
            os.replace(tmp, path)
        except BaseException:
            os.replace(old / path.name, path)  # put the old capture back
            raise
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)


def prepare_target(path: str | os.PathLike) -> tuple[Path, Path]:
    """Check that ``path`` may be (re)written as a capture; returns (path, fresh temp sibling dir)."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise CaptureError(f"{path}: expected a directory (or nothing) to write the capture to, found a file")
        if any(path.iterdir()) and not (path / "capture.json").is_file():
            raise CaptureError(f"{path}: expected an empty directory or an existing capture, found other files (not overwritten)")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path, Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp.", dir=path.parent))


def save_capture(
    capture: Capture, path: str | os.PathLike, *, bits: int | str = "npy", color_space: str | None = None
) -> Path:
    """Write ``capture`` as a capture directory, atomically; returns the path.

    Args:
        bits: "npy" (float32 images, bit-exact round trip, the default), 16 or 8 (PNG).
        color_space: file encoding, "linear" or "srgb"; default "linear" for npy and the
            capture's own ``color_space`` for PNG (so a PNG capture re-saved with the bit depth
            it was loaded with reproduces its values exactly).

    Writes capture.json, images/<stem>.png|.npy (source stems kept when safe and unique, else
    NNN), normals.npy when given or not flat, mask.png when not all True, saturated.npy when the
    clipping flags can't be recovered from the image values. An existing capture at ``path`` is
    replaced in one rename; a directory holding anything else is refused.
    """
    path, tmp = prepare_target(path)
    try:
        write_capture_files(capture, tmp, bits=bits, color_space=color_space)
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path
