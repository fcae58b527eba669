"""Captures read region by region: the tiled capture format and its converter.

A **tiled capture** is an ordinary capture directory (docs/design.md §2.1, so ``load_capture`` reads it
too) whose per-pixel files are all ``.npy`` arrays, which numpy memory-maps: any rectangle or
strided grid of pixels is read without loading the rest.

    capture.json      color_space "linear" (any allowed), shots → images/<stem>.npy
    images/*.npy      (H, W, 3) float32 linear RGB (any dtype the loader takes works)
    saturated.npy     optional (N, H, W, 3) bool: clipped values of the source images
    normals.npy       optional (H, W, 3) float unit normals
    mask.npy          optional (H, W) bool

:func:`convert_capture` writes one from any capture (PNG/EXR images, PNG mask), one image at
a time: the decoded values are exactly those :func:`~torchmetal.io.capture.load_capture` gives.

:class:`TiledCapture` is the read side: it has the attributes of a
:class:`~torchmetal.io.capture.Capture` that the fit's observation builder reads, but its
``images``, ``saturated``, ``mask`` and ``normals`` are :class:`Planes` that decode only the
pixels indexed (``capture.images[..., rows, cols]``), with the same decoding, checks and
normalisation as the loader. Memory is that of the region read, never of the capture.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import CaptureError
from torchmetal.io.capture import UNIT_TOL, Capture, check_pixels, load_mask, parse_meta, read_meta
from torchmetal.io.capture_save import replace_dir
from torchmetal.io.images import decode_planes, read_raw, srgb_to_linear


def _npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise CaptureError(f"{path}: expected a numpy .npy array, found unreadable data ({e})") from None


def _spatial(key) -> tuple[slice, slice]:
    """(rows, cols) of an index ``[..., rows, cols]`` or ``[:, rows, cols]``."""
    if not isinstance(key, tuple) or len(key) < 2 or not all(isinstance(k, slice) for k in key[-2:]):
        raise TypeError(f"tiled capture planes: expected an index [..., rows, cols] with slices, found {key!r}")
    lead = key[:-2]
    if not all(k is Ellipsis or k == slice(None) for k in lead):
        raise TypeError(f"tiled capture planes: expected all leading dimensions, found {key!r}")
    return key[-2], key[-1]


class Planes:
    """A lazily read (C…, H, W) array: ``shape``, ``dtype``, ``device`` and ``[..., rows, cols]``."""

    def __init__(self, shape: tuple[int, ...], dtype: torch.dtype, read: Callable[[slice, slice], Tensor]) -> None:
        self.shape = torch.Size(shape)
        self.dtype = dtype
        self.device = torch.device("cpu")
        self._read = read

    def __getitem__(self, key) -> Tensor:
        rows, cols = _spatial(key)
        return self._read(rows, cols)

    def dim(self) -> int:
        return len(self.shape)

    def is_floating_point(self) -> bool:
        return self.dtype.is_floating_point


class TiledCapture:
    """A capture directory whose images are ``.npy`` files, read region by region.

    Attributes as :class:`~torchmetal.io.capture.Capture`: ``images`` (N, 3, H, W), ``saturated``
    (N, 3, H, W), ``mask`` (1, H, W), ``normals`` (3, H, W) as :class:`Planes`; ``lights``,
    ``intensities``, ``cameras``, ``size``, ``names``, ``color_space``; plus ``root``,
    ``flat_normals`` (no normals file) and :meth:`region` (a real Capture of a rectangle, for tests).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        root = Path(path)
        meta_file = root if root.suffix.lower() == ".json" and not root.is_dir() else root / "capture.json"
        self.root = root = meta_file.parent
        cs, size, normals_name, mask_name, sat_name, shots = parse_meta(read_meta(meta_file), str(meta_file))
        not_npy = [s.image for s in shots if Path(s.image).suffix.lower() != ".npy"]
        if not_npy or (mask_name and Path(mask_name).suffix.lower() != ".npy"):
            raise CaptureError(f"{meta_file}: expected .npy images and mask for a tiled read, found "
                               f"{(not_npy or [mask_name])[0]!r} (convert it with torchmetal.scale.tiles.convert_capture)")
        self._files = [root / s.image for s in shots]
        first = _npy(self._files[0])
        if first.ndim != 3 or first.shape[2] not in (3, 4):
            raise CaptureError(f"{self._files[0]}: expected an (H, W, 3) image array, found shape {first.shape}")
        h, w = first.shape[:2]
        for f in self._files[1:]:
            shape = _npy(f).shape
            if shape[:2] != (h, w):
                raise CaptureError(f"{f}: expected size {w}x{h} (width x height, as {shots[0].image}), found "
                                   f"{shape[1] if len(shape) > 1 else '?'}x{shape[0]}")
        n = len(shots)
        self.height, self.width, self.num_shots = h, w, n
        self.color_space, self.size, self.names = cs, size, [s.image for s in shots]
        f32 = lambda rows: torch.tensor(rows, dtype=torch.float64).to(torch.float32)  # noqa: E731 — as load_capture
        self.lights = f32([s.light for s in shots])
        self.intensities = f32([s.intensity for s in shots])
        self.cameras = f32([s.camera for s in shots])
        self._sat_file = root / sat_name if sat_name else None
        self._normals_file = root / normals_name if normals_name else None
        self._mask_file = root / mask_name if mask_name else None
        self.flat_normals = self._normals_file is None
        self._cache: tuple | None = None
        self.images = Planes((n, 3, h, w), torch.float32, lambda r, c: self._pixels(r, c)[0])
        self.saturated = Planes((n, 3, h, w), torch.bool, lambda r, c: self._pixels(r, c)[1])
        self.mask = Planes((1, h, w), torch.bool, self._read_mask)
        self.normals = Planes((3, h, w), torch.float32, self._read_normals)

    # -- region reads (decoding exactly as load_capture) ------------------------------------------

    def _pixels(self, rows: slice, cols: slice) -> tuple[Tensor, Tensor]:
        key = (rows.indices(self.height), cols.indices(self.width))
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        self._cache = None
        srgb = self.color_space == "srgb"
        parts, sats = [], []
        for f in self._files:
            raw = np.asarray(_npy(f)[rows, cols, :3])
            img = np.empty((3, *raw.shape[:2]), np.float32)
            sat = np.empty((3, *raw.shape[:2]), bool)
            is_float = raw.dtype.kind == "f"
            if not is_float and raw.dtype not in (np.uint8, np.uint16):
                raise CaptureError(f"{f}: expected uint8, uint16 or float pixels, found dtype {raw.dtype}")
            decode_planes(raw, img, sat, srgb=srgb and not is_float)
            t = torch.from_numpy(img)
            if is_float:
                check_pixels(t, str(f))
                if srgb:
                    t = srgb_to_linear(t)
            parts.append(t)
            sats.append(torch.from_numpy(sat))
        images, saturated = torch.stack(parts), torch.stack(sats)
        if self._sat_file is not None:
            arr = _npy(self._sat_file)
            if arr.shape != (self.num_shots, self.height, self.width, 3) or arr.dtype != np.bool_:
                raise CaptureError(f"{self._sat_file}: expected a bool array of shape "
                                   f"{(self.num_shots, self.height, self.width, 3)}, found {arr.dtype} {arr.shape}")
            saturated |= torch.from_numpy(np.ascontiguousarray(arr[:, rows, cols].transpose(0, 3, 1, 2)))
        self._cache = (key, images, saturated)
        return images, saturated

    def _read_mask(self, rows: slice, cols: slice) -> Tensor:
        if self._mask_file is None:
            r, c = len(range(*rows.indices(self.height))), len(range(*cols.indices(self.width)))
            return torch.ones(1, r, c, dtype=torch.bool)
        arr = _npy(self._mask_file)
        if arr.ndim == 3:
            arr = arr[:, :, :3]
        if arr.shape[:2] != (self.height, self.width) or arr.ndim not in (2, 3):
            raise CaptureError(f"{self._mask_file}: expected a mask of size {self.width}x{self.height}, found shape {arr.shape}")
        part = np.asarray(arr[rows, cols])
        part = (part != 0).any(axis=2) if part.ndim == 3 else part != 0
        return torch.from_numpy(np.ascontiguousarray(part)).unsqueeze(0)

    def _read_normals(self, rows: slice, cols: slice) -> Tensor:
        r, c = len(range(*rows.indices(self.height))), len(range(*cols.indices(self.width)))
        if self._normals_file is None:
            n = torch.zeros(3, r, c, dtype=torch.float32)
            n[2] = 1.0
            return n
        f = self._normals_file
        arr = _npy(f)
        if arr.shape != (self.height, self.width, 3) or not np.issubdtype(arr.dtype, np.floating):
            raise CaptureError(f"{f}: expected float normals of shape {(self.height, self.width, 3)}, found {arr.dtype} {arr.shape}")
        n = np.asarray(arr[rows, cols], dtype=np.float64)  # the loader's normalisation, pixel by pixel
        if not np.isfinite(n).all():
            raise CaptureError(f"{f}: expected finite normals, found non-finite values")
        length = np.sqrt((n * n).sum(axis=2, keepdims=True))
        if (length[..., 0] < 1e-12).any():
            raise CaptureError(f"{f}: expected non-zero normals, found zero-length ones")
        out = np.where(np.abs(length - 1.0) > UNIT_TOL, n / length, n).astype(np.float32)
        return torch.from_numpy(np.ascontiguousarray(out.transpose(2, 0, 1)))

    def region(self, rows: slice, cols: slice) -> Capture:
        """The pixels ``rows`` × ``cols`` as an in-memory Capture (its own, smaller, surface)."""
        images, saturated = self._pixels(rows, cols)
        return Capture(images=images, normals=self._read_normals(rows, cols), mask=self._read_mask(rows, cols),
                       lights=self.lights, intensities=self.intensities, cameras=self.cameras, size=self.size,
                       saturated=saturated, names=self.names, color_space=self.color_space)


def is_tiled(path: str | os.PathLike) -> bool:
    """True when the capture's images (and mask) are .npy files, readable region by region."""
    try:
        TiledCapture(path)
    except CaptureError:
        return False
    return True


def convert_capture(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Write the capture ``src`` as a tiled capture at ``dst`` (atomically), one image at a time.

    Images become (H, W, 3) float32 linear ``.npy`` (decoded exactly as ``load_capture`` does:
    lookup tables for 8/16-bit codes, the sRGB curve), clipped values go to ``saturated.npy``,
    a PNG mask to ``mask.npy``; normals are copied. Peak memory: one decoded image.
    """
    src = Path(src)
    meta_file = src if src.suffix.lower() == ".json" and not src.is_dir() else src / "capture.json"
    root = meta_file.parent
    meta = read_meta(meta_file)
    cs, size, normals_name, mask_name, sat_name, shots = parse_meta(meta, str(meta_file))
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", dir=dst.parent))
    try:
        (tmp / "images").mkdir()
        new_shots, h, w = _convert_images(root, shots, cs, sat_name, tmp)
        out_meta = {"format": meta["format"], "version": meta["version"], "color_space": "linear",
                    "surface": {"width": size[0], "height": size[1]}, "shots": new_shots}
        if (tmp / "saturated.npy").exists():
            out_meta["saturated"] = "saturated.npy"
        if normals_name:
            shutil.copyfile(root / normals_name, tmp / "normals.npy")
            out_meta["normals"] = "normals.npy"
        if mask_name:
            np.save(tmp / "mask.npy", load_mask(root / mask_name, h, w)[0].numpy())
            out_meta["mask"] = "mask.npy"
        (tmp / "capture.json").write_text(json.dumps(out_meta, indent=1))
        replace_dir(tmp, dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dst


def _convert_images(root: Path, shots: list, cs: str, sat_name: str | None, tmp: Path) -> tuple[list[dict], int, int]:
    """Decode the shots' images one at a time into ``tmp/images/*.npy`` (and ``tmp/saturated.npy`` when anything
    clips or the source has a saturated.npy, merged in). Returns (the new shots' metadata, h, w)."""
    n = len(shots)
    sat_out = None
    h = w = None
    new_shots = []
    for k, shot in enumerate(shots):
        f = root / shot.image
        raw = read_raw(f)
        if h is None:
            h, w = raw.shape[:2]
        elif raw.shape[:2] != (h, w):
            raise CaptureError(f"{f}: expected size {w}x{h} (width x height, as {shots[0].image}), found "
                               f"{raw.shape[1]}x{raw.shape[0]}")
        img, sat = _decode(raw, f, cs, h, w)
        del raw
        name = f"images/{k:03d}.npy"
        np.save(tmp / name, np.ascontiguousarray(img.transpose(1, 2, 0)))
        if sat.any() or sat_name:
            if sat_out is None:
                sat_out = np.lib.format.open_memmap(tmp / "saturated.npy", mode="w+", dtype=bool, shape=(n, h, w, 3))
            sat_out[k] = sat.transpose(1, 2, 0)
        new_shots.append({"image": name, "light": shot.light, "light_intensity": shot.intensity, "camera": shot.camera})
        del img, sat
    if sat_out is not None:
        if sat_name:
            _merge_saturated(sat_out, root / sat_name, n, h, w)
        sat_out.flush()
        del sat_out
    return new_shots, h, w


def _decode(raw: np.ndarray, f: Path, cs: str, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """(image (3, H, W) float32 linear, saturated (3, H, W) bool) of a raw image, decoded as ``load_capture`` does."""
    img = np.empty((3, h, w), np.float32)
    sat = np.empty((3, h, w), bool)
    is_float = raw.dtype.kind == "f"
    decode_planes(raw, img, sat, srgb=cs == "srgb" and not is_float)
    t = torch.from_numpy(img)
    if is_float:
        check_pixels(t, str(f))
        if cs == "srgb":
            t.copy_(srgb_to_linear(t))
    return img, sat


def _merge_saturated(sat_out: np.ndarray, f: Path, n: int, h: int, w: int) -> None:
    """OR the source capture's saturated.npy ``f`` into ``sat_out`` (N, H, W, 3)."""
    extra = _npy(f)
    if extra.shape != (n, h, w, 3) or extra.dtype != np.bool_:
        raise CaptureError(f"{f}: expected a bool array of shape {(n, h, w, 3)}, found "
                           f"{extra.dtype} {extra.shape}")
    for k in range(n):
        sat_out[k] |= extra[k]
