"""Image files ↔ float arrays, and the sRGB transfer function (IEC 61966-2-1).

This is the only place where file encodings are handled: BGR channel order, uint8/uint16
quantisation and alpha channels are converted here, once. Everything past this module sees
float RGB ``(H, W, 3)`` arrays (or ``(…, 3, H, W)`` tensors).

Supported files:

========  =====================================  ============================
suffix    read                                   write
========  =====================================  ============================
.png      8-/16-bit RGB or RGBA (alpha dropped)  8- or 16-bit RGB
.npy      float (H, W, 3) (or (H, W, 4))          float32 (H, W, 3)
.exr      float RGB(A) (OpenCV, else OpenEXR)    –
========  =====================================  ============================
"""

from __future__ import annotations

import functools
import io
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import CaptureError, InputError

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # read by OpenCV when it loads; cv2 itself loads lazily

__all__ = [
    "srgb_to_linear", "linear_to_srgb", "read_image", "read_raw", "decode_planes", "code_table", "write_image",
    "encode_image", "quantize", "atomic_write_bytes", "have_exr", "PNG_MAX",
]


@functools.cache
def _cv2():
    """OpenCV, imported on first use, with OpenEXR decoding enabled."""
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the cv2 import
    import cv2

    return cv2

# IEC 61966-2-1 constants
_A = 0.055
_GAMMA = 2.4
_LIN_SLOPE = 12.92
_SRGB_KNEE = 0.04045  # encoded value where the linear segment ends
_LIN_KNEE = 0.0031308  # linear value where the linear segment ends

PNG_MAX = {8: 255, 16: 65535}
_LOOKUP_PIXELS = 1 << 16  # pixels per table lookup in decode_planes (a 512 KiB index temporary)
_PNG_DTYPE = {8: np.uint8, 16: np.uint16}


def srgb_to_linear(x: Tensor) -> Tensor:
    """Decode sRGB values to linear, exact IEC 61966-2-1 piecewise curve.

    x ≤ 0.04045: x / 12.92; otherwise ((x + 0.055) / 1.055)^2.4. Values above 1 follow the
    power branch (extended range). Gradients are finite everywhere (double ``where``).

    Args:
        x: tensor of any shape, dtype and device.

    Returns:
        tensor like ``x``.
    """
    power = x > _SRGB_KNEE
    base = torch.where(power, x, torch.full_like(x, 1.0))
    high = ((base + _A) / (1.0 + _A)) ** _GAMMA
    return torch.where(power, high, x / _LIN_SLOPE)


@functools.cache
def code_table(bits: int, srgb: bool) -> np.ndarray:
    """Float32 value of every integer code of a ``bits``-bit file (8: 256 entries, 16: 65 536).

    ``srgb=False``: code / (2^bits − 1), correctly rounded in float32 (what ``np.divide`` in
    float32 gives). ``srgb=True``: :func:`srgb_to_linear` of code / (2^bits − 1), computed in
    float64 and rounded once to float32. Built once per (bits, srgb) and read-only.
    """
    if bits not in PNG_MAX:
        raise InputError(f"bits: expected 8 or 16, found {bits!r}")
    top = PNG_MAX[bits]
    if srgb:
        table = srgb_to_linear(torch.arange(top + 1, dtype=torch.float64) / top).to(torch.float32).numpy()
    else:
        table = np.arange(top + 1, dtype=np.float32) / np.float32(top)
    table.setflags(write=False)
    return table


def linear_to_srgb(x: Tensor) -> Tensor:
    """Encode linear values to sRGB, exact IEC 61966-2-1 piecewise curve.

    x ≤ 0.0031308: 12.92·x; otherwise 1.055·x^(1/2.4) − 0.055.

    Args:
        x: tensor of any shape, dtype and device.

    Returns:
        tensor like ``x``.
    """
    power = x > _LIN_KNEE
    base = torch.where(power, x, torch.full_like(x, 1.0))
    high = (1.0 + _A) * base ** (1.0 / _GAMMA) - _A
    return torch.where(power, high, x * _LIN_SLOPE)


# ---------------------------------------------------------------------------------------- read


def _rgb_channels(arr: np.ndarray, path: Path) -> np.ndarray:
    """(H, W, 3|4) → (H, W, 3); anything else is rejected with the channel count found."""
    if arr.ndim == 2:
        raise CaptureError(f"{path}: expected 3 colour channels (RGB), found 1 (grayscale)")
    if arr.ndim != 3:
        raise CaptureError(f"{path}: expected an (H, W, 3) image, found shape {arr.shape}")
    c = arr.shape[2]
    if c == 4:
        return arr[:, :, :3]
    if c != 3:
        raise CaptureError(f"{path}: expected 3 colour channels (RGB), found {c}")
    return arr


@functools.cache
def have_exr() -> bool:
    """Whether this OpenCV build can decode OpenEXR files."""
    for line in _cv2().getBuildInformation().splitlines():
        if line.strip().startswith("OpenEXR:"):
            return line.split(":", 1)[1].strip().upper() not in ("NO", "")
    return False


def _read_openexr(path: Path) -> np.ndarray:
    """An EXR file through the OpenEXR package (a dependency: pip's OpenCV builds have no OpenEXR)."""
    try:
        import OpenEXR
    except ImportError:
        raise CaptureError(f"{path}: expected a readable EXR file, found that neither this OpenCV build nor the OpenEXR "
                           "package can read it (pip install openexr, or convert the images to 16-bit PNG or float .npy)"
                           ) from None
    try:
        with OpenEXR.File(str(path)) as f:
            channels = {name: np.asarray(c.pixels) for name, c in f.channels().items()}
    except Exception as e:  # noqa: BLE001 - OpenEXR raises RuntimeError/ValueError on bad files
        raise CaptureError(f"{path}: expected a readable EXR image, found undecodable data "
                           f"({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
    for name in ("RGB", "RGBA"):
        if name in channels:
            arr = channels[name]
            break
    else:
        if not {"R", "G", "B"} <= set(channels):
            raise CaptureError(f"{path}: expected R, G and B channels, found {sorted(channels)}")
        arr = np.stack([channels[c] for c in "RGB"], axis=-1)
    return arr.astype(np.float32) if arr.dtype == np.float16 else arr


def _read_cv2(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".exr" and not have_exr():
        return _read_openexr(path)
    data = np.fromfile(path, dtype=np.uint8)  # handles non-ASCII paths, unlike cv2.imread
    cv2 = _cv2()
    arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if arr is None:
        raise CaptureError(f"{path}: expected a readable {path.suffix.lstrip('.').upper()} image, found undecodable data")
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = arr[:, :, 2::-1] if arr.shape[2] == 3 else arr[:, :, [2, 1, 0, 3]]  # BGR(A) → RGB(A), once
    return arr


def _read_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise CaptureError(f"{path}: expected a numpy .npy array, found unreadable data ({e})") from None


def read_raw(path: str | os.PathLike) -> np.ndarray:
    """The stored RGB values of an image file, undecoded: (H, W, 3) uint8, uint16 or float.

    BGR files are returned as an RGB view (no copy); a 4th alpha channel is dropped.

    Raises:
        CaptureError: missing/unreadable file, unsupported type or dtype, not 3 channels, no pixels.
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: expected an image file, found nothing")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        arr = _read_npy(path)
    elif suffix in (".png", ".exr", ".tif", ".tiff"):
        arr = _read_cv2(path)
    else:
        raise CaptureError(f"{path}: expected a .png, .npy or .exr image, found suffix {path.suffix!r}")
    arr = _rgb_channels(arr, path)
    if arr.shape[0] < 1 or arr.shape[1] < 1:
        raise CaptureError(f"{path}: expected an image of at least 1x1 pixels, found {arr.shape[1]}x{arr.shape[0]}")
    if arr.dtype not in (np.uint8, np.uint16) and not np.issubdtype(arr.dtype, np.floating):
        raise CaptureError(f"{path}: expected uint8, uint16 or float pixels, found dtype {arr.dtype}")
    return arr


def decode_planes(raw: np.ndarray, out: np.ndarray, saturated: np.ndarray, *, srgb: bool = False) -> None:
    """Write raw (H, W, 3) values as float32 planes into ``out`` (3, H, W) and clipping flags
    into ``saturated`` (3, H, W) bool, without full-size temporaries.

    Integers (uint8 / uint16): looked up in :func:`code_table` — v / 255 or v / 65535 correctly
    rounded in float32, or with ``srgb`` their linear value (the sRGB curve in float64, rounded
    once to float32); flagged where v is the maximum.
    Floats: copied as float32 (with ``srgb``, decoded by :func:`srgb_to_linear` in float32);
    never flagged.
    """
    planes = raw.transpose(2, 0, 1)  # (3, H, W) view
    if raw.dtype in (np.uint8, np.uint16):
        bits = 8 if raw.dtype == np.uint8 else 16
        table = code_table(bits, srgb)
        h, w = raw.shape[:2]
        rows = max(1, _LOOKUP_PIXELS // max(w, 1))
        for c in range(3):
            for r in range(0, h, rows):  # np.take copies its indices to intp: bound that copy
                if out.dtype == table.dtype:
                    np.take(table, raw[r:r + rows, :, c], out=out[c, r:r + rows], mode="clip")  # "clip": unbuffered
                else:
                    out[c, r:r + rows] = table[raw[r:r + rows, :, c]]
        np.equal(planes, PNG_MAX[bits], out=saturated)
    else:
        np.copyto(out, planes, casting="unsafe")
        if srgb:
            t = torch.from_numpy(out)
            t.copy_(srgb_to_linear(t))
        saturated[...] = False


def read_image(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an RGB image file as stored (no colour decoding).

    Integer files are scaled to [0, 1] (v / 255 or v / 65535, correctly rounded in float32);
    float files are returned as float32 unchanged (they may exceed 1; non-finite and negative
    values are reported by the capture loader, not here).

    Args:
        path: .png (8/16-bit), .npy (float (H, W, 3)) or .exr.

    Returns:
        image: (H, W, 3) float32, C-contiguous.
        saturated: (H, W, 3) bool, True where the stored value is the encoding maximum
        (255 / 65535); all False for float files.

    Raises:
        CaptureError: missing/unreadable file, unsupported type, not 3 channels (a 4th alpha
        channel is dropped).
    """
    raw = read_raw(path)
    h, w = raw.shape[:2]
    image = np.empty((3, h, w), np.float32)
    saturated = np.empty((3, h, w), bool)
    decode_planes(raw, image, saturated)
    return np.ascontiguousarray(image.transpose(1, 2, 0)), np.ascontiguousarray(saturated.transpose(1, 2, 0))


# --------------------------------------------------------------------------------------- write


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same directory + ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def quantize(image: np.ndarray, bits: int) -> np.ndarray:
    """Float [0, 1] → uint8/uint16 with clipping and round-half-even (``np.rint``).

    Computed in float64 so that ``quantize(v / 65535) == v`` for every stored value v.
    """
    top = PNG_MAX[bits]
    q = np.rint(np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0) * top)
    return q.astype(_PNG_DTYPE[bits])


def _check_array(array: np.ndarray) -> np.ndarray:
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().numpy()
    array = np.asarray(array)
    if array.ndim != 3 or array.shape[2] != 3:
        raise InputError(f"image: expected an (H, W, 3) array, found shape {array.shape}")
    if not np.issubdtype(array.dtype, np.floating):
        raise InputError(f"image: expected a float array, found dtype {array.dtype}")
    return array


def encode_image(array: np.ndarray, suffix: str, bits: int = 8) -> bytes:
    """File bytes of an (H, W, 3) float RGB array for ``suffix`` ".png" or ".npy"."""
    array = _check_array(array)
    suffix = suffix.lower()
    if suffix == ".png":
        if bits not in PNG_MAX:
            raise InputError(f"bits: expected 8 or 16 for PNG, found {bits!r}")
        q = quantize(array, bits)
        ok, buf = _cv2().imencode(".png", np.ascontiguousarray(q[:, :, ::-1]))  # RGB → BGR, once
        if not ok:
            raise InputError(f"image: expected a PNG-encodable array, found shape {q.shape} dtype {q.dtype}")
        return buf.tobytes()
    if suffix == ".npy":
        out = io.BytesIO()
        np.save(out, np.ascontiguousarray(array, dtype=np.float32), allow_pickle=False)
        return out.getvalue()
    raise InputError(f"image: expected a .png or .npy file name, found suffix {suffix!r}")


def write_image(path: str | os.PathLike, array: np.ndarray, bits: int = 8) -> Path:
    """Write an (H, W, 3) float RGB array atomically; returns the path.

    .png: clipped to [0, 1], rounded to ``bits`` (8 or 16); .npy: float32 as is (``bits``
    ignored). Values are written as given (no colour encoding; see :func:`linear_to_srgb`).
    """
    path = Path(path)
    atomic_write_bytes(path, encode_image(array, path.suffix, bits))
    return path
